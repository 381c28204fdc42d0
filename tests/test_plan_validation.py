"""Validation of plans on the simulated plant: a model that under-predicts is corrected by measurement."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from cell.config import CONFIG_DIR
from sim.cell import make_sim_cell
from tasks.setup.plan import load_plan_file, plan_and_validate


def test_an_under_predicting_model_is_corrected_by_the_measured_torques(cfg, robot):
    """The planner trusts a model with 40 % too little inertial torque; the first (conservative) run
    shows the plant needs more, and the final kept run stays within every joint's limit."""
    plans = load_plan_file(CONFIG_DIR / "plans.yaml")
    cfg.safety = replace(cfg.safety, max_tcp_speed=plans.max_tcp_speed)

    def weak(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        full = np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])
        still = np.array([robot.gravity(a) for a in q])
        return still + 0.6 * (full - still)

    def opener():
        holder = make_sim_cell(cfg, robot.limits, seed=3, scene_kind="free")
        return holder.open(), holder

    ex = plan_and_validate("trajectory_2", plans.paths["trajectory_2"], "toppra", cfg, robot, weak, plans.planner,
                           opener, None, rounds=5, first_scale=1.0)
    effort = robot.limits.effort
    assert ex.outcome == "done"
    assert ex.rounds > 1  # the first plan, trusted at face value, did not hold
    assert np.all(ex.peak_tau <= effort), ex.peak_tau / effort
    assert np.max(ex.peak_tau / effort) > 0.5  # and it is still a fast plan, not a crawl
    assert Path(ex.run_dir or "").exists()
