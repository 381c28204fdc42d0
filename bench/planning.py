"""`main.py bench planning`: four planners on the named and on random collision-free paths, each plan run on the plant.

Planners (cell/planning/planner.py, cell/planning/ppo_planner.py): `uniform` (the pendant knob: a trapezoid
scaled until the model's torques fit), `kinematic` (TOPP-RA with speed and acceleration limits only, the accelerations
calibrated once per arm on the plant: bench/planning_calibration.py), `ppo` (the paper's method: a PPO
policy trained on the hybrid model), `model` (ours: TOPP-RA under the hybrid model's torque limits).
Each planner has one setting per arm, calibrated on the plant on one reference set of paths (the named
ones and five random ones): the kinematic baseline its accelerations, the three torque-aware planners the
share of their planning limit (`model_trust`).  Then each plan is executed once as planned (no per-path
correction) and the plant's joint torques are measured: a run whose peak reaches the safety monitor's share
of a motor limit (or that the monitor stops for torque) is a torque violation.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from bench.planning_calibration import (
    CALIBRATION_SEED,
    EXERCISED_SHARE,
    calibrate,
    calibrate_trust,
    kinematic_calibration_key,
    load_or_calibrate,
)
from cell.collision.geometry import CollisionChecker
from cell.control.signals import raise_if_interrupted
from cell.model.robot import RobotModel
from cell.planning.averaging import BLEND_S
from cell.planning.baselines import KinematicPlanner, UniformScalingPlanner
from cell.planning.config import PlannerConfig
from cell.planning.constraints import ToppraTerms
from cell.planning.planner import GeometricPath, Planner, PlanningError, TimedTrajectory, ToppraPlanner, TorqueFn
from cell.planning.ppo import load_snapshots
from cell.planning.ppo_planner import PpoPlanner, PpoSettings, load_or_train
from cell.planning.speed_env import WORKSPACE_DEG, obs_dim, random_waypoints

log = logging.getLogger(__name__)
PLANNER_NAMES = ("uniform", "kinematic", "ppo", "model")
PAPER_IMPROVEMENT_PCT = {"trajectory_1": 24.7, "trajectory_2": 15.3, "trajectory_3": 21.3}
CALIBRATION_PATHS = 5  # random reference paths besides the named ones
# Torque-bound reference moves for the model trust alone (the torque class's draw, same seed): the per-joint
# shares let joints 1 and 3 use more of their bound, and these moves are where joint 1's start peaks are
# highest on the plant (docs/planning.md).
TRUST_TORQUE_PATHS = 3
MAX_ROUNDS = 4  # runs per planner and path: the first, then tightened re-runs after a torque violation
# The random paths' class: `speed` (3-5 waypoints across the workspace: mostly at the joint-speed limits),
# `torque` (one move of joints 1-3, short or medium, wrist held: the motors' torque shapes the timing), or
# `mixed` (the two alternately).
PATH_CLASSES = ("speed", "torque", "mixed")
TORQUE_MOVES_DEG = ((20.0, 70.0), (70.0, 120.0))  # per joint 1-3: a short and a medium move
# One more reference path for the model trust alone: joint 2 accelerates at its torque bound up to its speed
# cap while joint 1 swings through a reversal.  There the plant's joint-2 torque runs about 0.1 of the motor
# limit over the model's (a speed-dependent error, which a lower trust shrinks only in part), more than on
# any other reference path; without it every reference run stayed within the limit at full trust while such
# moves elsewhere reached the safety stop (docs/notes/planning-history.md).
TRUST_REFERENCE_DEG = {"reference_j2_fast": [[-2.0, -39.0, 64.0, 40.0, 40.0, -7.0],
                                             [-63.0, -32.0, 43.0, 56.0, 92.0, -22.0],
                                             [-26.0, 13.0, 96.0, 75.0, 113.0, -3.0]]}


@dataclass
class PlanningSetup:
    """What the bench needs from the application: the arm, its model, the paths, and a plant to run on."""

    robot: RobotModel
    torque_fn: TorqueFn
    terms: ToppraTerms | None
    model_name: str
    pcfg: PlannerConfig
    named: dict[str, list[list[float]]]  # degrees
    collisions: CollisionChecker
    run: Callable[[TimedTrajectory], dict[str, Any]]  # execute -> {"outcome", "peak_ratio" (n,), ...}
    calibration_run: Callable[[TimedTrajectory], dict[str, Any]]
    safety_fraction: float  # of the motor limit: the safety monitor's stop
    workspace: tuple[np.ndarray, np.ndarray]  # the safety monitor's TCP box (min, max), m
    artefacts: Path
    arm_identity: dict[str, Any]


def inside_box(checker: ToppraPlanner, w: np.ndarray, box: tuple[np.ndarray, np.ndarray], margin: float = 0.05) -> bool:
    """Whether the TCP stays `margin` inside the cell's workspace box (the safety monitor's) along the path."""
    qs = checker.check_waypoints(w).eval(np.linspace(0.0, 1.0, 60))[0]
    tcp = np.array([checker.robot.tcp_pose(q).translation for q in qs])
    return bool(np.all(tcp >= box[0] + margin) and np.all(tcp <= box[1] - margin))


def torque_move(rng: np.random.Generator, medium: bool) -> np.ndarray:
    """Two waypoints (rad): a start drawn in the workspace, and a move of joints 1-3 by a short (20-70 deg) or
    medium (70-120 deg) step each, towards the side with more room (shortened to the room there); the wrist
    holds.  Large inertia, little distance: the torque limits, not the speed limits, set the time."""
    lo, hi = np.radians(WORKSPACE_DEG[:, 0]), np.radians(WORKSPACE_DEG[:, 1])
    start = rng.uniform(lo, hi)
    end = start.copy()
    a, b = TORQUE_MOVES_DEG[int(medium)]
    for j in range(3):
        up, down = hi[j] - start[j], start[j] - lo[j]
        step = min(np.radians(rng.uniform(a, b)), max(up, down))
        end[j] = start[j] + (step if up >= down else -step)
    return np.array([start, end])


def draw_path(rng: np.random.Generator, path_class: str, k: int) -> tuple[str, np.ndarray]:
    """The k-th random path's name prefix and waypoints for the class (`mixed`: speed, torque, speed...)."""
    kind = path_class if path_class != "mixed" else ("speed", "torque")[k % 2]
    if kind == "torque":
        return "torque", torque_move(rng, medium=bool(rng.integers(0, 2)))
    return "random", random_waypoints(rng, int(rng.integers(3, 6)))


def random_paths(checker: ToppraPlanner, count: int, seed: int, box: tuple[np.ndarray, np.ndarray],
                 prefix: str = "random", path_class: str = "speed") -> list[tuple[str, np.ndarray]]:
    """`count` paths of the class (`draw_path`) whose spline stays in the joint limits and the cell's workspace
    box, and collides with nothing; named `prefix_NN` (speed class) or `torque_NN`."""
    rng = np.random.default_rng(seed)
    out: list[tuple[str, np.ndarray]] = []
    tries = 0
    while len(out) < count:
        tries += 1
        if tries > 200 * count:
            raise PlanningError(f"bench planning: found only {len(out)} collision-free paths in {tries} draws")
        kind, w = draw_path(rng, path_class, len(out))
        try:
            if not inside_box(checker, w, box):
                continue
        except PlanningError:
            continue
        out.append((f"{prefix if kind == 'random' else kind}_{len(out):02d}", w))
    return out


def reference_set(s: PlanningSetup) -> list[tuple[str, np.ndarray]]:
    """The paths every per-arm setting is calibrated on: the named ones and a fixed random draw."""
    checker = ToppraPlanner(s.robot, s.torque_fn, s.pcfg, s.collisions, s.terms)
    ref = [(n, np.radians(w)) for n, w in s.named.items()]
    return ref + random_paths(checker, CALIBRATION_PATHS, CALIBRATION_SEED, s.workspace, "reference")


def torque_references(s: PlanningSetup) -> list[tuple[str, np.ndarray]]:
    """The model trust's torque-bound reference moves: a fixed draw of the torque class."""
    checker = ToppraPlanner(s.robot, s.torque_fn, s.pcfg, s.collisions, s.terms)
    torque = random_paths(checker, TRUST_TORQUE_PATHS, CALIBRATION_SEED, s.workspace, path_class="torque")
    return [(f"reference_{n}", w) for n, w in torque]


def trust_reference_set(s: PlanningSetup) -> list[tuple[str, np.ndarray]]:
    """The model trust's reference paths: the joint-2 move the model under-predicts most first (a failing
    check ends there), then the torque-bound moves, then the shared reference set."""
    return [(n, np.radians(w)) for n, w in TRUST_REFERENCE_DEG.items()] + torque_references(s) + reference_set(s)


def model_trust(s: PlanningSetup) -> dict[str, Any]:
    """The share of the planning limit the torque-aware planners use on this arm, per joint (calibrate_trust;
    stored)."""
    limit = 1.0 - s.pcfg.torque_margin
    planner = ToppraPlanner(s.robot, s.torque_fn, s.pcfg, s.collisions, s.terms)
    key = {"arm": s.arm_identity, "model": s.model_name, "limit_fraction": limit,
           "velocity_fraction": s.pcfg.velocity_fraction, "smoothing_s": s.pcfg.smoothing_s,
           "torque_discretization": s.pcfg.torque_discretization, "start_margin": s.pcfg.start_margin,
           "start_margin_s": s.pcfg.start_margin_s, "retiming": s.pcfg.retiming,
           "exact_smoothing_s": s.pcfg.exact_smoothing_s, "residual": s.pcfg.residual,
           "tcp_speed_limit": s.pcfg.tcp_speed_limit, "extra_reference_deg": TRUST_REFERENCE_DEG,
           "exact_smoothing_start_s": s.pcfg.exact_smoothing_start_s, "exact_smoothing_blend_s": BLEND_S,
           "exact_smoothing_stop_s": s.pcfg.exact_smoothing_stop_s,
           "torque_references": TRUST_TORQUE_PATHS, "toppra_gridpoints": s.pcfg.toppra_gridpoints,
           "exact_step": "rest-to-rest average, one sample at rest",
           "per_joint": True, "noise_seed": CALIBRATION_SEED, "exercised_share": EXERCISED_SHARE}
    return load_or_calibrate(s.artefacts / "model_trust.json", key,
                             lambda: calibrate_trust(planner, trust_reference_set(s), s.calibration_run, limit))


def kinematic_limits(s: PlanningSetup) -> dict[str, Any]:
    """The calibrated kinematic accelerations for this arm (stored under the artefacts, made if missing)."""
    ref = reference_set(s)
    limit = 1.0 - s.pcfg.torque_margin

    def make(acc: np.ndarray) -> KinematicPlanner:
        acc = np.minimum(acc, s.pcfg.acceleration_limits)  # the configured guards stay the ceiling
        return KinematicPlanner(s.robot, s.torque_fn, replace(s.pcfg, acceleration_limits=acc.tolist()), s.collisions)

    out = load_or_calibrate(s.artefacts / "kinematic.json", kinematic_calibration_key(s.arm_identity, s.pcfg),
                            lambda: calibrate(make, s.robot, ref, s.calibration_run, limit))
    out["acceleration_limits"] = np.minimum(out["acceleration_limits"], s.pcfg.acceleration_limits).tolist()
    return out


def planners(s: PlanningSetup, kin_acc: list[float], policy: Any, settings: PpoSettings) -> dict[str, Planner]:
    return {
        "uniform": UniformScalingPlanner(s.robot, s.torque_fn, s.pcfg, s.collisions, s.terms),
        "kinematic": KinematicPlanner(s.robot, s.torque_fn, replace(s.pcfg, acceleration_limits=kin_acc), s.collisions),
        "ppo": PpoPlanner(s.robot, s.torque_fn, s.pcfg, policy, settings, s.collisions, s.terms),
        "model": ToppraPlanner(s.robot, s.torque_fn, s.pcfg, s.collisions, s.terms),
    }


def run_once(planner: Planner, w: np.ndarray, s: PlanningSetup, scale: np.ndarray) -> dict[str, Any]:
    try:
        traj = planner.plan(w, scale)
    except PlanningError as exc:
        return {"outcome": "plan_failed", "reason": str(exc), "torque_violation": False}
    res = s.run(traj)
    raise_if_interrupted(res["outcome"])  # Ctrl+C / SIGTERM ends the bench, not just this plan's run
    peak = np.asarray(res["peak_ratio"], float)
    vlim = s.robot.limits.velocity * s.pcfg.velocity_fraction
    # the share of the motion some joint spends near (within 10 % of) its speed limit: little to gain there
    at_speed = float(np.mean(np.max(np.abs(traj.dq) / vlim, axis=1) >= 0.9))
    return {"duration_s": traj.duration, "plan_time_s": traj.plan_time_s, "iterations": traj.iterations,
            "speed_bound_share": at_speed,
            "outcome": res["outcome"], "elapsed_s": res.get("elapsed_s"), "reason": res.get("reason"),
            "peak_ratio": float(np.nanmax(peak)), "peak_ratio_per_joint": peak.round(3).tolist(),
            "torque_violation": bool(np.nanmax(peak) >= s.safety_fraction or res["outcome"] == "safety_stop"
                                     and "torque" in str(res.get("reason"))),
            "run_dir": res.get("run_dir")}


def run_planner(planner: Planner, w: np.ndarray, s: PlanningSetup, scale: np.ndarray) -> dict[str, Any]:
    """The first run at the planner's per-arm setting (the single-shot figures), then, while the plant shows a
    torque violation, the setting tightened by the excess and run again (up to MAX_ROUNDS): the first run
    within the limits is the plan one would deploy (`validated_s`).  A stop for another reason (the collision
    guard) ends the path unvalidated: re-running would not tell more about torques."""
    first = last = run_once(planner, w, s, scale)
    rounds = 1
    while last["torque_violation"] and rounds < MAX_ROUNDS:
        scale = scale * min(0.95, (1.0 - s.pcfg.torque_margin) / last["peak_ratio"])
        last = run_once(planner, w, s, scale)
        rounds += 1
    ok = last["outcome"] == "done" and not last["torque_violation"]
    return {**first, "rounds": rounds, "validated_s": last["duration_s"] if ok else None,
            "final_outcome": last["outcome"], "final_peak_ratio": last.get("peak_ratio"),
            "final_scale": float(np.min(scale)), "final_run_dir": last.get("run_dir")}


def speed_limit_time(path: GeometricPath, vlim: np.ndarray, samples: int = 2000) -> float:
    """The path's duration at its joint-speed cap everywhere (infinite accelerations): no timing that keeps the
    speed limits is shorter."""
    s = np.linspace(0.0, 1.0, samples + 1)
    cap = np.min(vlim[None, :] / np.maximum(np.abs(path.eval(s)[1]), 1e-9), axis=1)
    return float(np.sum(np.diff(s) / (0.5 * (cap[:-1] + cap[1:]))))


def gap_closed(t_kinematic: float, t_model: float, t_speed_limit: float) -> float:
    """(T_kinematic - T_model) / (T_kinematic - T_speed_limit): the share of the kinematic plan's time above the
    speed-limit bound that ours removes (1 at the bound, 0 no faster than kinematic, < 0 slower); NaN where a
    time is missing or the kinematic plan is already at the bound."""
    span = t_kinematic - t_speed_limit
    if not (np.isfinite(t_kinematic) and np.isfinite(t_model) and np.isfinite(t_speed_limit)) or span <= 1e-9:
        return float("nan")
    return (t_kinematic - t_model) / span


def nanmedian(x: Any) -> float | None:
    """The median of the finite values, None when there are none (JSON has no NaN)."""
    a = np.asarray(x, float)
    return float(np.median(a[np.isfinite(a)])) if np.any(np.isfinite(a)) else None


def pct(a: float, b: float) -> float:
    """How much shorter a is than b, in percent of b."""
    return 100.0 * (1.0 - a / b)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The bench's figures from its per-path rows (every planner planned and ran on every path)."""
    first = {p: np.array([r[p].get("duration_s", np.nan) for r in rows]) for p in PLANNER_NAMES}
    dur = {p: np.array([r[p].get("validated_s") or np.nan for r in rows]) for p in PLANNER_NAMES}
    out: dict[str, Any] = {
        # over the paths where both ran within the limits, each with its first such run
        "median_time_ratio": {p: nanmedian(dur[p] / dur["kinematic"]) for p in PLANNER_NAMES},
        "median_time_ratio_first_run": {p: nanmedian(first[p] / first["kinematic"]) for p in PLANNER_NAMES},
        "median_time_ratio_speed_limit_only": nanmedian(
            np.array([r.get("speed_limit_only_s", np.nan) for r in rows]) / dur["kinematic"]),
        # first runs (single shot at the per-arm setting) over a torque limit
        "torque_violations": {p: sum(bool(r[p].get("torque_violation")) for r in rows) for p in PLANNER_NAMES},
        "unvalidated_paths": {p: sum(r[p].get("validated_s") is None for r in rows) for p in PLANNER_NAMES},
        "runs": {p: sum(r[p].get("rounds", 1) for r in rows) for p in PLANNER_NAMES},
        "collision_stops": {p: sum(r[p]["outcome"] == "collision" for r in rows) for p in PLANNER_NAMES},
        "plan_failures": {p: sum(r[p]["outcome"] == "plan_failed" for r in rows) for p in PLANNER_NAMES},
        "max_torque_ratio": {p: float(np.nanmax([r[p].get("peak_ratio", np.nan) for r in rows]))
                             for p in PLANNER_NAMES},
        "plan_time_s_p95": {p: float(np.nanpercentile([r[p].get("plan_time_s", np.nan) for r in rows], 95))
                            for p in PLANNER_NAMES},
        "speed_bound_share_median": {p: float(np.nanmedian([r[p].get("speed_bound_share", np.nan) for r in rows]))
                                     for p in PLANNER_NAMES},
    }
    speed = np.array([r.get("speed_limit_only_s", np.nan) for r in rows], float)
    gaps = np.array([gap_closed(k, m, v) for k, m, v in zip(dur["kinematic"], dur["model"], speed, strict=True)])
    named_rows = np.array([r["path"] in PAPER_IMPROVEMENT_PCT for r in rows])
    out["gap_closed"] = {r["path"]: None if not np.isfinite(g) else round(float(g), 4) for r, g in zip(rows, gaps,
                                                                                                         strict=True)}
    out["median_gap_closed"] = {"random": nanmedian(gaps[~named_rows]), "named": nanmedian(gaps[named_rows])}
    # the same medians as `median_time_ratio`, over the random paths (the chosen class) and the named ones apart
    out["median_time_ratio_by_group"] = {
        group: {p: nanmedian(dur[p][sel] / dur["kinematic"][sel]) for p in PLANNER_NAMES}
        | {"speed_limit_only": nanmedian(speed[sel] / dur["kinematic"][sel])}
        for group, sel in (("random", ~named_rows), ("named", named_rows))}
    saving = np.array([pct(m, p) for m, p in zip(dur["model"], dur["ppo"], strict=True)])
    both = np.isfinite(saving)  # the paths where both have a run within the limits
    out["model_vs_ppo"] = {"paths_model_not_slower": int(np.sum(saving[both] >= -0.05)), "paths": int(both.sum()),
                           "median_saving_pct": nanmedian(saving),
                           "min_saving_pct": float(saving[both].min()) if both.any() else None,
                           "max_saving_pct": float(saving[both].max()) if both.any() else None}
    out["reduction_vs_uniform_median_pct"] = {p: nanmedian([pct(a, u) for a, u in
                                                                zip(dur[p], dur["uniform"], strict=True)])
                                              for p in ("kinematic", "ppo", "model")}
    named = {r["path"]: r for r in rows if r["path"] in PAPER_IMPROVEMENT_PCT}
    out["named_paths"] = {n: {"uniform_s": r["uniform"]["validated_s"], "ppo_s": r["ppo"]["validated_s"],
                              "model_s": r["model"]["validated_s"],
                              "ppo_reduction_pct": pct(r["ppo"]["validated_s"], r["uniform"]["validated_s"]),
                              "model_reduction_pct": pct(r["model"]["validated_s"], r["uniform"]["validated_s"]),
                              "paper_reduction_pct": PAPER_IMPROVEMENT_PCT[n]}
                          for n, r in named.items()
                          if all(r[p].get("validated_s") for p in ("uniform", "ppo", "model"))}
    return out


def paper_setting(s: PlanningSetup, settings: PpoSettings, scale: np.ndarray,
                  rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The paper's own setting: one PPO policy per named trajectory, trained on that path alone (as many updates
    as the general policy), then planned, run and validated like the others; against the same path's uniform
    and time-optimal plans."""
    out: dict[str, Any] = {}
    by_name = {r["path"]: r for r in rows}
    for name, w_deg in s.named.items():
        w = np.radians(w_deg)
        one = PpoSettings(env=settings.env, ppo=settings.ppo, waypoints=settings.waypoints)
        policy, meta = load_or_train(s.artefacts / f"ppo-{name}", s.robot, s.torque_fn, s.pcfg, s.terms, one,
                                     s.model_name, only=w)
        res = run_planner(PpoPlanner(s.robot, s.torque_fn, s.pcfg, policy, one, s.collisions, s.terms), w, s, scale)
        row = by_name[name]
        uniform, model, t = row["uniform"]["validated_s"], row["model"]["validated_s"], res["validated_s"]
        out[name] = {"ppo_s": t, "first_run": {k: res.get(k) for k in ("duration_s", "outcome", "peak_ratio")},
                     "reduction_vs_uniform_pct": pct(t, uniform) if t and uniform else None,
                     "longer_than_model_pct": -pct(t, model) if t and model else None,
                     "paper_reduction_pct": PAPER_IMPROVEMENT_PCT.get(name), "training_s": meta["training_s"]}
        log.info("paper setting, %s: one-path policy %s s (uniform %s s, ours %s s)", name, t, uniform, model)
    return out


def ppo_curve(s: PlanningSetup, settings: PpoSettings, policy_dir: Path, final_updates: int, scale: np.ndarray,
              rows: list[dict[str, Any]], paths: list[tuple[str, np.ndarray]]) -> list[dict[str, Any]]:
    """PPO's time against its training budget: the policy kept after each snapshot's update count (and the final
    one, from the rows), planned on the bench's paths at the same setting, median planned duration over the
    kinematic baseline's planned one (plans only: the plant-validated figure is the final policy's)."""
    kin = np.array([r["kinematic"].get("duration_s", np.nan) for r in rows], float)
    model = np.array([r["model"].get("duration_s", np.nan) for r in rows], float)
    out = []
    snaps = load_snapshots(policy_dir, obs_dim(settings.env, s.robot.n), settings.ppo.hidden)
    for updates, params in sorted(snaps.items()):
        planner = PpoPlanner(s.robot, s.torque_fn, s.pcfg, params, settings, None, s.terms)
        t = []
        for _, w in paths:
            try:
                t.append(planner.plan(w, scale).duration)
            except PlanningError:
                t.append(np.nan)
        out.append({"updates": updates, "median_planned_ratio": nanmedian(np.array(t) / kin)})
    final = np.array([r["ppo"].get("duration_s", np.nan) for r in rows], float)
    out.append({"updates": final_updates, "median_planned_ratio": nanmedian(final / kin)})
    for point in out:
        point["model_median_planned_ratio"] = nanmedian(model / kin)
    return out


def plot_ppo_curve(curve: list[dict[str, Any]], png: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [p["updates"] for p in curve]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(x, [p["median_planned_ratio"] for p in curve], "o-", label="PPO")
    ax.axhline(curve[-1]["model_median_planned_ratio"], color="C2", ls="--", label="ours (model)")
    ax.axhline(1.0, color="grey", ls=":", label="kinematic")
    ax.set_xscale("log")
    ax.set_xlabel("PPO updates (x 32 paths x 30 knots)")
    ax.set_ylabel("planned time / kinematic (median)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def bench_planning(s: PlanningSetup, count: int, seed: int, settings: PpoSettings,
                   path_class: str = "speed") -> dict[str, Any]:
    """Calibrate (or load) the per-arm settings, train (or load) the policy, then plan and run every path."""
    kin = kinematic_limits(s)
    trust = model_trust(s)
    # The torque-aware planners' per-arm share of the limit: ours per joint; PPO and uniform keep the one share
    # for all joints (given the others' shares they reach the TCP speed stop, which neither plans for).
    scale = np.full(s.robot.n, trust["fraction"])
    ours = np.asarray(trust["per_joint"], float)
    policy_dir = s.artefacts / "ppo"
    policy, meta = load_or_train(policy_dir, s.robot, s.torque_fn, s.pcfg, s.terms, settings, s.model_name)
    chosen = planners(s, kin["acceleration_limits"], policy, settings)
    checker = chosen["model"]
    assert isinstance(checker, ToppraPlanner)
    paths = [(n, np.radians(w)) for n, w in s.named.items()] + random_paths(checker, count, seed, s.workspace,
                                                                             path_class=path_class)
    rows = []
    vlim = s.robot.limits.velocity * s.pcfg.velocity_fraction
    for name, w in tqdm(paths, desc="bench planning", unit="path"):
        row: dict[str, Any] = {"path": name, "waypoints_deg": np.degrees(w).round(2).tolist(),
                               "speed_limit_only_s": speed_limit_time(GeometricPath(w), vlim)}
        for p in PLANNER_NAMES:
            row[p] = run_planner(chosen[p], w, s, {"kinematic": np.ones(s.robot.n), "model": ours}.get(p, scale))
        log.info("%s: %s", name, ", ".join(f"{p} {row[p].get('duration_s', float('nan')):.3f} s "
                                            f"({row[p]['outcome']}, peak {row[p].get('peak_ratio', float('nan')):.2f}"
                                            f", validated {row[p]['validated_s']} in {row[p]['rounds']})"
                                            for p in PLANNER_NAMES))
        rows.append(row)
    out = summarise(rows)
    out["paper_setting"] = paper_setting(s, settings, scale, rows)
    out["ppo_curve"] = ppo_curve(s, settings, policy_dir, settings.ppo.updates, scale, rows, paths)
    png = s.artefacts / f"ppo-curve-{path_class}-seed{seed}.png"
    plot_ppo_curve(out["ppo_curve"], png, f"PPO against its budget: {path_class} paths, seed {seed}")
    out["ppo_curve_png"] = str(png)
    out.update({
        "model": s.model_name, "seed": seed, "paths": len(rows), "random_paths": count, "paths_class": path_class,
        "ppo_training_s": meta["training_s"], "ppo_trained_now": not meta.get("loaded", False),
        "ppo_env_steps": meta["env_steps"],
        "kinematic_acceleration_limits": kin["acceleration_limits"], "kinematic_fraction": kin["fraction"],
        "kinematic_calibrated_now": not kin.get("loaded", False), "kinematic_calibration_runs": kin["executions"],
        "model_trust": trust["fraction"], "model_trust_per_joint": trust["per_joint"],
        "model_trust_calibration_runs": trust["executions"],
        "torque_violation_at": s.safety_fraction, "per_path": rows,
    })
    return out
