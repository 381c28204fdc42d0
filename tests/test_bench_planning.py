"""`main.py bench planning`: its figures from per-path rows, the kinematic calibration, its CLI errors, a small run."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bench.planning as bench_planning
from bench.planning import (
    PLANNER_NAMES,
    TRUST_REFERENCE_DEG,
    draw_path,
    gap_closed,
    random_paths,
    summarise,
    torque_move,
    trust_reference_set,
)
from bench.planning_calibration import calibrate, calibrate_trust
from cell.planning.baselines import KinematicPlanner
from cell.planning.config import PlannerConfig
from cell.planning.planner import ToppraPlanner
from cell.planning.speed_env import WORKSPACE_DEG
from main import main

PATH = np.radians([[0, -30, 90, 0, 90, 0], [60, 10, 60, -30, 90, 30], [120, 30, 30, 0, 90, 0]])
KEYS = {"median_time_ratio", "median_gap_closed", "gap_closed", "ppo_curve", "paths_class", "torque_violations",
        "plan_time_s_p95", "ppo_training_s", "model_vs_ppo",
        "collision_stops", "kinematic_acceleration_limits", "per_path", "reduction_vs_uniform_median_pct",
        "paper_setting", "unvalidated_paths", "median_time_ratio_first_run", "model_trust"}


def row(path: str, times: dict[str, float], violation: str | None = None, speed_limit: float = np.nan) -> dict:
    return {"path": path, "speed_limit_only_s": speed_limit,
            **{p: {"duration_s": t, "plan_time_s": 0.01 * t, "outcome": "done", "peak_ratio": 0.5,
                   "torque_violation": p == violation, "rounds": 1 + (p == violation),
                   "speed_bound_share": 0.5, "validated_s": t * (1.1 if p == violation else 1.0)}
               for p, t in times.items()}}


def test_the_summary_takes_medians_over_the_kinematic_baseline_and_counts_violations():
    rows = [row("trajectory_1", {"uniform": 2.0, "kinematic": 1.0, "ppo": 0.9, "model": 0.8}, violation="ppo"),
            row("random_00", {"uniform": 3.0, "kinematic": 2.0, "ppo": 1.5, "model": 1.6}),
            row("random_01", {"uniform": 4.0, "kinematic": 2.0, "ppo": 1.8, "model": 1.2})]
    out = summarise(rows)
    assert set(out["median_time_ratio"]) == set(PLANNER_NAMES)
    assert out["median_time_ratio"]["model"] == pytest.approx(0.8)  # of 0.8, 0.8, 0.6
    assert out["median_time_ratio"]["ppo"] == pytest.approx(0.9)  # of 0.99 (validated after a re-run), 0.75, 0.9
    assert out["median_time_ratio_first_run"]["ppo"] == pytest.approx(0.9)
    assert out["runs"]["ppo"] == 4 and out["unvalidated_paths"]["ppo"] == 0
    assert out["median_time_ratio"]["kinematic"] == 1.0
    assert out["torque_violations"] == {"uniform": 0, "kinematic": 0, "ppo": 1, "model": 0}
    assert out["model_vs_ppo"]["paths_model_not_slower"] == 2 and out["model_vs_ppo"]["paths"] == 3
    assert out["model_vs_ppo"]["min_saving_pct"] == pytest.approx(100 * (1 - 1.6 / 1.5))
    assert out["named_paths"]["trajectory_1"]["ppo_reduction_pct"] == pytest.approx(100 * (1 - 0.99 / 2.0))
    assert out["named_paths"]["trajectory_1"]["paper_reduction_pct"] == 24.7
    assert out["plan_time_s_p95"]["uniform"] == pytest.approx(np.percentile([0.02, 0.03, 0.04], 95))


def test_gap_closed_is_the_share_of_the_kinematic_excess_over_the_speed_limit_bound_that_ours_removes():
    assert gap_closed(3.0, 2.8, 2.6) == pytest.approx(0.5)
    assert gap_closed(3.0, 2.6, 2.6) == pytest.approx(1.0)  # at the bound
    assert gap_closed(3.0, 3.0, 2.6) == pytest.approx(0.0)  # no faster than kinematic
    assert gap_closed(3.0, 3.1, 2.6) == pytest.approx(-0.25)  # slower
    assert np.isnan(gap_closed(2.6, 2.6, 2.6))  # kinematic already at the bound: nothing to close
    assert np.isnan(gap_closed(np.nan, 2.6, 2.0))  # not validated
    rows = [row("trajectory_1", {"uniform": 2.0, "kinematic": 1.0, "ppo": 0.9, "model": 0.9}, speed_limit=0.8),
            row("trajectory_2", {"uniform": 2.0, "kinematic": 1.0, "ppo": 0.9, "model": 0.8}, speed_limit=0.8),
            row("random_00", {"uniform": 3.0, "kinematic": 2.0, "ppo": 1.5, "model": 1.6}, speed_limit=1.0),
            row("random_01", {"uniform": 4.0, "kinematic": 2.0, "ppo": 1.8, "model": 1.9}, speed_limit=1.5),
            row("random_02", {"uniform": 4.0, "kinematic": 2.0, "ppo": 1.8, "model": 1.2})]  # no bound: left out
    out = summarise(rows)
    assert out["gap_closed"]["random_00"] == pytest.approx(0.4) and out["gap_closed"]["random_02"] is None
    assert out["median_gap_closed"]["random"] == pytest.approx(0.3)  # of 0.4, 0.2
    assert out["median_gap_closed"]["named"] == pytest.approx(0.75)  # of 0.5, 1.0
    assert out["median_time_ratio_by_group"]["named"]["model"] == pytest.approx(0.85)
    assert out["median_time_ratio_by_group"]["random"]["model"] == pytest.approx(0.8)  # of 0.8, 0.95, 0.6
    assert out["median_time_ratio_by_group"]["random"]["speed_limit_only"] == pytest.approx(0.625)  # 0.5, 0.75


@pytest.mark.parametrize("medium", [False, True])
def test_a_torque_bound_path_moves_joints_1_to_3_by_short_or_medium_steps_and_holds_the_wrist(medium):
    rng = np.random.default_rng(3)
    lo, hi = np.radians(WORKSPACE_DEG[:, 0]), np.radians(WORKSPACE_DEG[:, 1])
    for _ in range(50):
        w = torque_move(rng, medium)
        assert w.shape == (2, 6)
        assert np.all(w >= lo - 1e-12) and np.all(w <= hi + 1e-12)
        assert np.array_equal(w[0, 3:], w[1, 3:])
        step = np.degrees(np.abs(w[1, :3] - w[0, :3]))
        room = np.degrees(np.maximum(hi - w[0], w[0] - lo))[:3]  # a step is shortened to the room there
        low, high = (70.0, 120.0) if medium else (20.0, 70.0)
        assert np.all(step <= high + 1e-9)
        assert np.all((step >= low - 1e-9) | np.isclose(step, room))


def test_the_path_classes_draw_their_kind_and_name_it(robot):
    rng = np.random.default_rng(0)
    assert [draw_path(rng, "mixed", k)[0] for k in range(4)] == ["random", "torque", "random", "torque"]
    assert draw_path(rng, "torque", 0)[1].shape == (2, 6) and draw_path(rng, "speed", 0)[1].shape[0] >= 3
    checker = ToppraPlanner(robot, robot.rnea, PlannerConfig())
    box = (np.full(3, -5.0), np.full(3, 5.0))
    paths = random_paths(checker, 4, 1, box, path_class="torque")
    assert [n for n, _ in paths] == ["torque_00", "torque_01", "torque_02", "torque_03"]
    assert all(w.shape == (2, 6) for _, w in paths)
    names = [n for n, _ in random_paths(checker, 4, 1, box, path_class="mixed")]
    assert names == ["random_00", "torque_01", "random_02", "torque_03"]
    # the default (speed) draw is the one the bench has always made: the same paths for the same seed
    assert [n for n, _ in random_paths(checker, 2, 1, box)] == ["random_00", "random_01"]


def test_the_trusts_extra_reference_drives_joint_2_to_its_speed_cap_while_joint_1_reverses(robot, monkeypatch):
    """The move the model under-predicts most on the plant is what the model trust is calibrated on first; the
    kinematic baseline keeps the shared reference set."""
    monkeypatch.setattr(bench_planning, "reference_set", lambda s: [("shared", PATH)])
    monkeypatch.setattr(bench_planning, "torque_references", lambda s: [("reference_torque_00", PATH)])
    names = [n for n, _ in trust_reference_set(None)]  # type: ignore[arg-type]
    assert names == ["reference_j2_fast", "reference_torque_00", "shared"]
    cfg = PlannerConfig(velocity_fraction=0.75, acceleration_limits=[150.0] * 6, torque_margin=0.15)
    def rigid(q, dq, ddq):
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    planner = ToppraPlanner(robot, rigid, cfg)
    traj = planner.plan(np.radians(TRUST_REFERENCE_DEG["reference_j2_fast"]))
    assert np.max(np.abs(traj.dq[:, 1])) >= 0.97 * planner.vlim[1]
    assert np.min(traj.dq[:, 0]) < -0.3 and np.max(traj.dq[:, 0]) > 0.3  # joint 1 swings through a reversal


def test_the_calibration_finds_the_largest_acceleration_fraction_within_the_limit(robot):
    """A stand-in plant whose peak torque ratio grows with the largest joint acceleration of the plan."""
    def run(traj):
        peak = float(np.max(np.abs(traj.ddq) / shape_ref)) * 0.5
        return {"outcome": "done" if peak < 0.9 else "safety_stop", "peak_ratio": np.full(6, peak)}

    def make(acc):
        return KinematicPlanner(robot, robot.rnea, PlannerConfig(acceleration_limits=list(acc), velocity_fraction=0.75))

    from bench.planning_calibration import acceleration_shape

    qs = make(np.ones(6)).check_waypoints(PATH).eval(np.linspace(0, 1, 50))[0]
    shape_ref = acceleration_shape(robot, qs)
    out = calibrate(make, robot, [("p", PATH)], run, limit_fraction=0.85, steps=8)
    # peak = 0.5 x (fraction, where the acceleration limit is reached): the answer is just below 1.7 -> 1.0 cap
    assert out["fraction"] == 1.0
    out = calibrate(make, robot, [("p", PATH)], run, limit_fraction=0.3, steps=8)
    # the limit is reached where the largest acceleration is 0.6 of the shape: at a fraction of 0.6, or a little
    # above where the speed limit keeps the plan from using all of it
    assert 0.45 <= out["fraction"] <= 0.75
    kept = [c for c in out["checks"] if c["fraction"] == out["fraction"]]
    assert kept and kept[0]["ok"] and all(r["peak_ratio"] <= 0.3 for r in kept[0]["runs"])
    assert any(not c["ok"] and out["fraction"] < c["fraction"] < out["fraction"] * 1.1 for c in out["checks"])
    assert out["executions"] == len(out["checks"])
    assert np.allclose(out["acceleration_limits"], np.array(out["shape"]) * out["fraction"], rtol=1e-2)


def test_the_trust_holds_the_joint_that_exceeded_and_lets_the_tested_others_use_more(robot):
    """A stand-in plant that under-predicts joint 2 by 20 % and joint 1 by 5 %: the shared share stops where
    joint 2 reaches the limit; joint 2 keeps it, the joints the reference plan loads (here to half their bound:
    1 and 4) rise as far as joint 1's error allows, and the joints it never loads keep the shared share."""
    cfg = PlannerConfig(velocity_fraction=0.75, acceleration_limits=[150.0] * 6, torque_margin=0.15)

    def rigid(q, dq, ddq):
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    planner = ToppraPlanner(robot, rigid, cfg)
    error = np.array([1.05, 1.2, 1.0, 1.0, 1.0, 1.0])

    def run(traj):
        peak = np.max(np.abs(rigid(traj.q, traj.dq, traj.ddq)), axis=0) * error / robot.limits.effort
        return {"outcome": "done", "peak_ratio": peak}

    ref = [("p", np.radians([[0, -30, 90, 0, 90, 0], [30, 10, 60, -30, 90, 30]]))]
    out = calibrate_trust(planner, ref, run, limit_fraction=0.85, steps=6, joint_steps=6, exercised_share=0.5)
    assert out["binding_joints"] == [2] and out["exercised_joints"] == [1, 2, 4]
    per_joint = np.array(out["per_joint"])
    assert out["fraction"] < 1.0
    assert per_joint[[1, 2, 4, 5]] == pytest.approx(np.full(4, out["fraction"]), abs=1e-4)
    assert np.all(per_joint[[0, 3]] > out["fraction"]) and per_joint[0] == per_joint[3]  # one share for both
    for c in out["checks"] + out["joint_checks"]:  # every kept setting ran within the limit
        assert not c["ok"] or all(r["peak_ratio"] <= 0.85 for r in c["runs"])
    assert out["executions"] == len(out["checks"]) + len(out["joint_checks"])


@pytest.mark.parametrize("argv, message", [
    (["bench", "planning", "--paths", "0"], "--paths"),
    (["bench", "planning", "--paths", "x"], "--paths"),
    (["bench", "planning", "--ppo-updates", "-3"], "--ppo-updates"),
    (["bench", "planning", "--paths-class", "heavy"], "--paths-class"),
])
def test_bad_arguments_give_one_line_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code != 0
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("main.py")]
    assert len(err) == 1 and message in err[0]


def test_a_missing_model_artefact_is_one_line(capsys):
    assert main(["bench", "planning", "--model", "/nonexistent/model", "--paths", "1"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "/nonexistent/model" in err[0]


@pytest.mark.slow
def test_a_small_bench_runs_every_planner_on_the_plant_and_reports_its_keys(monkeypatch, capsys):
    """Two random paths and the three named ones on the nominal model, a 2-update policy; the calibrations are
    replaced by fixed settings (tested above; on the plant they take a minute or two)."""
    monkeypatch.setattr("bench.planning.kinematic_limits", lambda s: {
        "acceleration_limits": [4.0, 4.0, 6.0, 10.0, 10.0, 10.0], "fraction": 0.3, "executions": 0, "loaded": True})
    monkeypatch.setattr("bench.planning.model_trust", lambda s: {
        "fraction": 0.8, "per_joint": [0.8] * 6, "executions": 0, "loaded": True})
    code = main(["-q", "bench", "planning", "--paths", "2", "--ppo-updates", "2", "--model", "nominal",
                 "--seed", "1", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == (0 if out["torque_violations"]["model"] == 0 else 1)
    assert set(out) >= KEYS
    assert out["paths"] == 5 and len(out["per_path"]) == 5
    for key in ("median_time_ratio", "torque_violations", "plan_time_s_p95"):
        assert set(out[key]) == set(PLANNER_NAMES)
    assert out["ppo_trained_now"] and out["ppo_training_s"] > 0
    assert out["median_time_ratio"]["kinematic"] == 1.0
    assert out["ppo_curve"][-1]["updates"] == 2 and out["paths_class"] == "speed"
    assert set(out["paper_setting"]) == {"trajectory_1", "trajectory_2", "trajectory_3"}
    assert all(r[p]["outcome"] in ("done", "safety_stop", "collision", "plan_failed") for r in out["per_path"]
               for p in PLANNER_NAMES)
