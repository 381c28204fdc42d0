"""The kinematic baseline's joint accelerations, chosen on the plant the way a careful integrator would.

A kinematic time-optimal parameterisation (TOTG, ruckig, toppra without torque) knows only joint speed
and acceleration limits, and an integrator sets the accelerations once per arm, low enough that no
motion exceeds a motor's torque.  Here: the per-joint *shape* is what each motor could give its joint
alone at the joint's worst inertia on the reference paths (`effort_j / max M_jj(q)`, nominal URDF: what
a datasheet gives), and one *fraction* of it is bisected (in log space) on the plant: the largest for
which every reference path, planned kinematically, executes with every measured joint torque within
`limit_fraction` of the motor limit (the same share the torque-aware planners plan to).

The torque-aware planners get the same treatment (`calibrate_trust`): one share of their planning limit per
arm, bisected on the same reference paths, since the model under-predicts the plant at the fastest motions.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cell.control.signals import raise_if_interrupted
from cell.data.atomic import write_atomic
from cell.model.robot import RobotModel
from cell.planning.baselines import KinematicPlanner
from cell.planning.config import PlannerConfig
from cell.planning.planner import PlanningError, TimedTrajectory, ToppraPlanner

log = logging.getLogger(__name__)
# The reference paths' random draw and the plant's noise in the calibration runs: fixed, apart from any bench
# seed, so a stored setting is the same whichever bench made it (the measured peaks move by about 0.01 of a
# motor limit with the noise, and a bisection step is that fine).
CALIBRATION_SEED = 1000
Run = Callable[[TimedTrajectory], dict[str, Any]]  # execute on the plant -> {"outcome", "peak_ratio", ...}
# A joint counts as tested by the trust's reference runs when some reference plan loads it to this share of its
# planning limit: only such joints may use more than the shared trust.
EXERCISED_SHARE = 0.9


def kinematic_calibration_key(arm: dict[str, Any], pcfg: PlannerConfig) -> dict[str, Any]:
    """What a stored calibration of the kinematic baseline's accelerations was made for: the arm (its identity
    without the run's noise seed), the planner settings its bisection depends on and the noise seed of its own
    runs.  `bench planning` stores the calibration under it and `plan` reads it back only when it matches."""
    return {"arm": arm, "limit_fraction": 1.0 - pcfg.torque_margin, "velocity_fraction": pcfg.velocity_fraction,
            "guards": list(pcfg.acceleration_limits), "smoothing_s": pcfg.smoothing_s, "noise_seed": CALIBRATION_SEED}


def acceleration_shape(robot: RobotModel, qs: np.ndarray) -> np.ndarray:
    """Per joint: effort / the largest diagonal inertia M_jj(q) over the configurations qs (rad/s^2)."""
    n = robot.n
    zero = np.zeros(n)
    worst = np.zeros(n)
    for q in qs:
        g = robot.rnea(q, zero, zero)
        for j in range(n):
            e = np.zeros(n)
            e[j] = 1.0
            worst[j] = max(worst[j], float(robot.rnea(q, zero, e)[j] - g[j]))
    return robot.limits.effort / np.maximum(worst, 1e-6)


def reference_ok(plan: Callable[[np.ndarray], TimedTrajectory], ref: list[tuple[str, np.ndarray]], run: Run,
                 limit_fraction: float) -> tuple[bool, list[dict[str, Any]]]:
    """Plan and execute every reference path; stop at the first one over the limit."""
    rows: list[dict[str, Any]] = []
    for name, w in ref:
        try:
            traj = plan(w)
        except PlanningError as exc:
            rows.append({"path": name, "outcome": f"plan_failed: {exc}"})
            return False, rows
        res = run(traj)
        # An interrupted reference run looks like one over the limit: bisecting on would store a low fraction.
        raise_if_interrupted(res["outcome"])
        per_joint = np.asarray(res["peak_ratio"], float)
        peak = float(np.nanmax(per_joint))
        rows.append({"path": name, "duration_s": traj.duration, "outcome": res["outcome"], "peak_ratio": peak,
                     "joint": int(np.nanargmax(per_joint)) if per_joint.size > 1 else None})
        if res["outcome"] != "done" or not peak <= limit_fraction:
            return False, rows
    return True, rows


def bisect_fraction(plan_at: Callable[[float], Callable[[np.ndarray], TimedTrajectory]],
                    ref: list[tuple[str, np.ndarray]], run: Run, limit_fraction: float, steps: int, lo: float,
                    hi: float, what: str, lo_known_ok: bool = False) -> tuple[float, list[dict[str, Any]]]:
    """The largest fraction in (0, hi] (to `steps` log-bisections) whose plans `plan_at(f)` keep every reference run
    within the limit; `lo` is halved until it does (or taken as within it: `lo_known_ok`)."""
    checks: list[dict[str, Any]] = []
    bar = tqdm(total=steps + 2, desc=f"{what} calibration", unit="check")  # hi, lo, then the bisections

    def ok(f: float) -> bool:
        good, rows = reference_ok(plan_at(f), ref, run, limit_fraction)
        checks.append({"fraction": f, "ok": good, "runs": rows})
        if len(checks) > bar.total:
            bar.total = len(checks)
        bar.update()
        log.info("%s calibration: fraction %.4f -> %s", what, f, "within the limits" if good else rows[-1])
        return good

    if ok(hi):
        bar.close()
        return hi, checks
    while not lo_known_ok and not ok(lo):
        hi, lo = lo, lo / 2
        if lo < 1e-3:
            raise PlanningError(f"{what} calibration: even a fraction of 0.001 exceeds a limit")
    for _ in range(steps):
        mid = float(np.sqrt(lo * hi))
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    bar.close()
    return lo, checks


def calibrate(make: Callable[[np.ndarray], KinematicPlanner], robot: RobotModel, ref: list[tuple[str, np.ndarray]],
              run: Run, limit_fraction: float, steps: int = 6, lo: float = 0.05, hi: float = 1.0) -> dict[str, Any]:
    """Bisect the fraction of `acceleration_shape` (see the module docstring); `make(acc)` builds the planner."""
    qs = np.concatenate([make(np.ones(robot.n)).check_waypoints(w).eval(np.linspace(0, 1, 50))[0] for _, w in ref])
    shape = acceleration_shape(robot, qs)
    best, checks = bisect_fraction(lambda f: make(shape * f).plan, ref, run, limit_fraction, steps, lo, hi,
                                   "kinematic")
    return {"fraction": best, "shape": shape.round(3).tolist(), "acceleration_limits": (shape * best).round(3).tolist(),
            "limit_fraction": limit_fraction, "reference_paths": [n for n, _ in ref], "checks": checks,
            "executions": sum(len(c["runs"]) for c in checks)}


def exercised_joints(planner: ToppraPlanner, ref: list[tuple[str, np.ndarray]], scale: np.ndarray,
                     share: float = EXERCISED_SHARE) -> list[int]:
    """The joints (0-based) whose planned torque reaches `share` of their planning limit on some reference path
    planned at `scale`: those whose bound the reference runs have tested on the plant."""
    peak = np.zeros(len(scale))
    for _, w in ref:
        try:
            peak = np.maximum(peak, planner.excess(planner.plan(w, scale), scale))
        except PlanningError:
            continue
    return [int(j) for j in np.nonzero(peak >= share)[0]]


def calibrate_trust(planner: ToppraPlanner, ref: list[tuple[str, np.ndarray]], run: Run, limit_fraction: float,
                    steps: int = 5, lo: float = 0.7, hi: float = 1.0, joint_steps: int = 4,
                    exercised_share: float = EXERCISED_SHARE) -> dict[str, Any]:
    """The torque-aware planners' one setting per arm, found the same way on the same paths: the share of the
    planning limit (`torque_scale`) the model may use so that the plant's torques stay within the limit.  A
    model fitted on gentler motions under-predicts the torques of the fastest ones, and not on every joint
    alike: first one share for all joints is bisected (`fraction`); then the joints whose measured torque
    ended a failing check keep it, and one share for the joints the reference plans load to their bound
    (`exercised_joints`) is bisected between it and `hi` with the rest held (`per_joint`: what the planners
    use).  A joint that never limited a reference run is not held back by another joint's error; a joint the
    references never loaded keeps the shared share, since nothing measured it there."""
    n = planner.plan(ref[0][1]).q.shape[1]
    best, checks = bisect_fraction(lambda f: lambda w: planner.plan(w, np.full(n, f)), ref, run, limit_fraction,
                                   steps, lo, hi, "model trust")
    binding = sorted({c["runs"][-1]["joint"] for c in checks if not c["ok"] and c["runs"][-1].get("joint") is not None})
    per_joint = np.full(n, best)
    exercised = exercised_joints(planner, ref, per_joint, exercised_share) if binding and best < hi else []
    rise = sorted(set(exercised) - set(binding))  # the joints whose share is bisected further
    joint_checks: list[dict[str, Any]] = []
    if rise and joint_steps > 0:
        held = ~np.isin(np.arange(n), rise)

        def scale(f: float) -> np.ndarray:
            return np.where(held, best, f)

        others, joint_checks = bisect_fraction(lambda f: lambda w: planner.plan(w, scale(f)), ref, run,
                                               limit_fraction, joint_steps, best, hi, "model trust (other joints)",
                                               lo_known_ok=True)
        per_joint = scale(max(others, best))
    return {"fraction": best, "per_joint": per_joint.round(4).tolist(), "binding_joints": [j + 1 for j in binding],
            "exercised_joints": [j + 1 for j in exercised],
            "limit_fraction": limit_fraction, "reference_paths": [n for n, _ in ref], "checks": checks,
            "joint_checks": joint_checks,
            "executions": sum(len(c["runs"]) for c in checks + joint_checks)}


def load_or_calibrate(path: Path, key: dict[str, Any], calibrate_now: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """The stored calibration when it was made for `key` (arm, model, limits), else a new one, stored only once it
    completed (an interrupt raises out of `calibrate_now` first), in one atomic write."""
    if path.exists():
        stored = json.loads(path.read_text(encoding="utf-8"))
        if stored.get("key") == key:
            stored["loaded"] = True
            return stored
        log.warning("%s: calibrated for another arm or settings; calibrating again", path)
    log.info("calibrating on the plant (once per arm and model; stored in %s)", path)
    out = {"key": key, **calibrate_now()}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(out, indent=1))
    out["loaded"] = False
    return out
