"""Hand guiding on the simulated cell: the simulated hand pulls the tool along a 0.4 m path at 0.1 m/s, lets
go for 10 s, then pushes above the guiding limit.  Figures: the TCP's largest distance from the hand's path
and the hand's largest force while guiding, the drift after release, and whether the push stopped the arm."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from cell.collision.config import TaskContactSafety
from cell.config import CellConfig
from cell.control.loop import Command, Observation, OpenCell
from cell.model.robot import RobotModel
from sim.cell import make_sim_cell
from sim.hand_guide import HandScript, SimHand
from tasks.hand_guide import HandGuideTask, load_hand_guide_config
from tasks.runner import run_task

log = logging.getLogger(__name__)

# 0.25 m along +y, then 0.15 m along +x: a level 0.4 m path with one right-angle corner, from the grab point.
BENCH_PATH = [[0.0, 0.0, 0.0], [0.0, 0.25, 0.0], [0.15, 0.25, 0.0]]
GRAB_DELAY_S = 0.2  # the hand takes the tool this long after the guiding starts
# The bench's pass marks: the tool within this of the hand's path and the hand's force within this while
# guiding, and the drift over the 10 s after release; the push above the limit must stop the arm besides.
TARGETS = {"path_error_mm_max": 15.0, "hand_force_n_max": 15.0, "release_drift_mm": 2.0}


class HandOnTask:
    """The task, with the simulated hand starting to guide once the task guides (delegates the rest)."""

    def __init__(self, task: HandGuideTask, hand: SimHand) -> None:
        self._task = task
        self._hand = hand

    def step(self, obs: Observation) -> Command:
        if self._task.state_name == "guide" and self._hand.grab_at == np.inf:
            self._hand.grab_at = self._hand.plant.t + GRAB_DELAY_S
        return self._task.step(obs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._task, name)


def guided_run(cfg: CellConfig, robot: RobotModel, script: HandScript, seed: int | None,
               wrap: Callable[[OpenCell], OpenCell], record: bool = False,
               inertia: Callable[[np.ndarray], np.ndarray] | None = None,
               readback: bool = True) -> tuple[dict[str, Any], SimHand, Any]:
    """Hand guiding on the free simulated scene (the wiping tool) with the scripted hand; the run's summary,
    the hand (its samples) and the task.  `inertia`: the arm's Cartesian inertia the task predicts the
    observer's read-back with (`tasks.hand_guide.model_inertia`); `readback` False: no read-back to predict
    (a force source other than the virtual sensor)."""
    hcfg = load_hand_guide_config(cfg.tasks.get("hand_guide"), f"{cfg.source}: tasks.hand_guide")
    if not readback:
        hcfg.inertia_readback = 0.0
    task = HandGuideTask(hcfg, robot, cfg.loop.period_s, np.asarray(cfg.robot.home, float), inertia=inertia)
    # Guiding is contact: the guard reads the hand's force as a tool force (held to the cell's limit), not a collision.
    cfg.collision.tasks[task.name] = TaskContactSafety(contact_states=["guide"])
    holder = make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="free", tool="wipe")
    hand = SimHand(holder.plant, script, grab_at_s=np.inf)
    holder.plant.after_physics_step = hand.update
    try:
        cell = wrap(holder.open())
        start_s = 30.0  # the move to the start and the tare take well under this
        hcfg.duration_s = min(hcfg.duration_s, GRAB_DELAY_S + hand.end_s + 0.5)
        summary = run_task(HandOnTask(task, hand), cell, cfg, robot, start_s + hand.end_s + 2.0, record=record,
                           extra_summary={"seed": seed})
    finally:
        holder.close()
    return summary, hand, task


def hand_guide_figures(hand: SimHand, task: HandGuideTask, summary: dict[str, Any]) -> dict[str, Any]:
    phases = np.array([s[1] for s in hand.samples])
    tcp = np.array([s[2] for s in hand.samples])
    force = np.array([np.linalg.norm(s[4]) for s in hand.samples])
    out: dict[str, Any] = {"outcome": summary.get("outcome"), "reason": summary.get("reason")}
    guiding = np.isin(phases, ["guide", "settle"])
    if guiding.any():
        err = np.array([hand.path_error(p) for p in tcp[guiding]])
        out.update(path_length_m=float(sum(np.linalg.norm(np.diff(np.asarray(hand.script.path), axis=0), axis=1))),
                   path_speed_mps=hand.script.speed_mps, path_error_mm_max=float(err.max() * 1e3),
                   path_error_mm_mean=float(err.mean() * 1e3), hand_force_n_max=float(force[guiding].max()),
                   hand_force_n_mean=float(force[phases == "guide"].mean()))
    released = phases == "released"
    if released.any():
        p = tcp[released]
        drift = np.linalg.norm(p - p[0], axis=1)
        out.update(release_s=float(np.ptp([s[0] for s, r in zip(hand.samples, released, strict=True) if r])),
                   release_drift_mm=float(drift.max() * 1e3), release_drift_end_mm=float(drift[-1] * 1e3))
    pushing = phases == "push"
    if pushing.any():
        p = tcp[pushing]
        out.update(push_force_n=float(hand.script.push_n or 0.0), push_stopped=bool(
            summary.get("outcome") == "failed" and task.stop_force_n is not None),
            push_stop_force_n=task.stop_force_n, push_travel_mm=float(np.linalg.norm(p[-1] - p[0]) * 1e3))
    else:
        out["push_stopped"] = False
    # The task's own peak (the run's summary keeps another source's): it includes the reading that stopped it.
    out.update(peak_virtual_force_n=float(task.peak_force), sim_time_s=summary.get("sim_time_s"),
               force_source=summary.get("force_source"), collision=summary.get("collision"))
    return out


def bench_hand_guide(cfg: CellConfig, robot: RobotModel, seed: int | None, wrap: Callable[[OpenCell], OpenCell],
                     inertia: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, Any]:
    hcfg = load_hand_guide_config(cfg.tasks.get("hand_guide"), f"{cfg.source}: tasks.hand_guide")
    script = HandScript(path=BENCH_PATH, speed_mps=0.1, settle_s=1.5, release_s=10.0,
                        push_n=1.5 * hcfg.max_force_n)
    summary, hand, task = guided_run(cfg, robot, script, seed, wrap, inertia=inertia)
    out = hand_guide_figures(hand, task, summary)
    # Every figure the verdict rests on is reported, null when the run stopped before its phase (a stop
    # while guiding leaves no release to measure): a missing key would read as "not measured", not "failed".
    for key in ("path_error_mm_max", "hand_force_n_max", "release_drift_mm"):
        out.setdefault(key, None)
    out["targets"] = dict(TARGETS)
    out["passed"] = bool(all(out[k] is not None and out[k] <= v for k, v in TARGETS.items()) and out["push_stopped"])
    return out
