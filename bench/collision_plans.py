"""The planned free motion of `bench collision`'s false-alarm run: time-optimal moves between random poses, and
the plans `bench planning` makes (time-optimal on the model, kinematic, PPO) on its own kind of paths."""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.planning import random_paths
from cell.collision.geometry import CollisionChecker
from cell.config import CONFIG_DIR, CellConfig
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.moves import random_moves
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from cell.planning.baselines import KinematicPlanner
from cell.planning.constraints import toppra_terms
from cell.planning.planner import Planner, PlanningError, ToppraPlanner
from cell.planning.ppo import load_policy
from cell.planning.ppo_planner import PpoPlanner, PpoSettings, load_or_train
from cell.planning.speed_env import obs_dim
from tasks.setup.plan import load_plan_file

REST_S = 0.25  # at rest between moves: each move starts from standstill, the hardest start
log = logging.getLogger(__name__)

TORQUE_SCALE = 0.8  # of the planning limit: the scale `plan` validates its first run at
# Without a stored `bench planning` policy the bench trains a small one of its own (about 10 s on a core):
# fewer updates than `bench planning`'s 300, so its plans are slower and nearer the model's middle ground.
FAST_PPO_UPDATES = 30


def max_tcp_speed() -> float:
    """The TCP speed limit `plan` runs its moves under (config/plans.yaml)."""
    return load_plan_file(CONFIG_DIR / "plans.yaml").max_tcp_speed


def time_optimal_stream(robot: RobotModel, cfg: CellConfig, model: LearnedModel, seconds: float,
                        seed: int) -> np.ndarray:
    """(K, n) joint targets at the control period: time-optimal moves between random poses, each
    from rest, until `seconds` are filled (the last move may be cut)."""
    dt = cfg.loop.period_s
    plans = load_plan_file(CONFIG_DIR / "plans.yaml")
    planner = ToppraPlanner(robot, model.predict, plans.planner, None, toppra_terms(model))
    # The excitation's random test moves give collision-free poses whose straight joint lines are free.
    moves = random_moves(robot, cfg, ExcitationConfig(), dt, 1, max(2, int(seconds / 1.0)), [1.0], seed=seed)
    poses = [moves.start] + [s.q[-1] for s in moves.segments]
    rest = int(round(REST_S / dt))
    stream = [np.repeat(poses[0][None, :], rest, axis=0)]
    total = rest
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        if total * dt >= seconds:
            break
        try:
            traj = planner.plan(np.vstack([a, b]), np.full(robot.n, TORQUE_SCALE))
        except PlanningError as exc:
            # The stream must stay continuous: the moves after this one start from b, so stop here (the
            # caller counts the seconds actually played).
            log.warning("time-optimal free motion: stopped at an infeasible move (%s)", exc)
            break
        stream += [traj.q, np.repeat(b[None, :], rest, axis=0)]
        total += len(traj.q) + rest
    return np.vstack(stream)[: int(round(seconds / dt))]


@dataclass
class BenchPlanners:
    """The three planners `bench planning` runs with the guard, each with its torque scale, and where their
    settings came from (its stored calibrations and policy, or this bench's fallbacks)."""

    planners: dict[str, tuple[Planner, np.ndarray]]
    sources: dict[str, str]
    checker: ToppraPlanner  # draws the paths (joint and workspace limits, collision-free)


def _stored(path: Path, key: str) -> Any:
    """`key` of a `bench planning` calibration file, or None when there is none."""
    try:
        return json.loads(path.read_text(encoding="utf-8")).get(key)
    except (OSError, ValueError):
        return None


def bench_planners(robot: RobotModel, cfg: CellConfig, model: LearnedModel, artefacts: Path | None,
                   planning_model: str | None = None) -> BenchPlanners:
    """`bench planning`'s model, kinematic and PPO planners on this arm's model, with the settings that bench
    stored under `artefacts` (its model trust, its calibrated kinematic accelerations, its PPO policy; the first
    and the last only when made for `planning_model`, the name of the model `plan` uses now); where one is
    missing: `plan`'s first-run scale, the configured acceleration guards, and a small PPO policy trained here
    (FAST_PPO_UPDATES)."""
    pcfg = load_plan_file(CONFIG_DIR / "plans.yaml").planner
    terms = toppra_terms(model)
    collisions = CollisionChecker.for_scene(robot, dataclasses.replace(cfg.scene, kind="free"))
    n = robot.n
    sources: dict[str, str] = {}
    trust = _stored(artefacts / "model_trust.json", "fraction") if artefacts else None
    made_for = (_stored(artefacts / "model_trust.json", "key") or {}).get("model") if artefacts else None
    if trust and made_for != planning_model:
        log.warning("bench collision: the stored model trust was calibrated for %s, not %s: using the first-run "
                    "scale (run `main.py bench planning` to calibrate it)", made_for, planning_model)
        trust = None
    sources["model"] = f"model trust {trust:.3f} (bench planning)" if trust else f"first-run scale {TORQUE_SCALE}"
    model_planner = ToppraPlanner(robot, model.predict, pcfg, collisions, terms)
    acc = _stored(artefacts / "kinematic.json", "acceleration_limits") if artefacts else None
    if acc is not None:
        acc = np.minimum(np.asarray(acc, float), pcfg.acceleration_limits).tolist()
        sources["kinematic"] = "calibrated accelerations (bench planning)"
    else:
        acc = list(pcfg.acceleration_limits)
        sources["kinematic"] = "configured acceleration guards (no bench planning calibration)"
    kinematic = KinematicPlanner(robot, model.predict, dataclasses.replace(pcfg, acceleration_limits=acc), collisions)
    settings = PpoSettings()
    policy = None
    if artefacts is not None and (artefacts / "ppo" / "policy.json").exists():
        try:
            policy, meta = load_policy(artefacts / "ppo", obs_dim(settings.env, n), settings.ppo.hidden)
            sources["ppo"] = (f"bench planning's policy ({meta.get('ppo', {}).get('updates')} updates, trained on "
                              f"{meta.get('model')})")
            if meta.get("model") != planning_model:
                log.warning("bench collision: the stored PPO policy was trained for %s, not %s: training a small "
                            "one instead", meta.get("model"), planning_model)
                policy = None
        except Exception as exc:  # an unreadable or other-shaped policy: train the small one instead
            log.warning("bench collision: %s; training a small PPO policy instead", exc)
    if policy is None:
        settings.ppo.updates = FAST_PPO_UPDATES
        where = (artefacts / "ppo-collision-fast") if artefacts is not None else None
        if where is not None:
            policy, meta = load_or_train(where, robot, model.predict, pcfg, terms, settings, "collision bench")
        else:
            from cell.planning.ppo_planner import train_policy

            policy, meta = train_policy(robot, model.predict, pcfg, terms, settings, None, "collision bench")
        sources["ppo"] = f"small policy trained here ({FAST_PPO_UPDATES} updates, {meta.get('training_s', 0):.0f} s)"
    ppo = PpoPlanner(robot, model.predict, pcfg, policy, settings, collisions, terms)
    model_scale = np.full(n, trust if trust else TORQUE_SCALE)
    return BenchPlanners({"model": (model_planner, model_scale), "kinematic": (kinematic, np.ones(n)),
                          "ppo": (ppo, model_scale)}, sources, model_planner)


def planning_paths(planners: BenchPlanners, cfg: CellConfig, count: int, seed: int) -> list[tuple[str, np.ndarray]]:
    """`count` paths of `bench planning`'s mixed class (multi-waypoint paths across the workspace and short or
    medium joint 1-3 moves, alternately), inside the cell's workspace box and collision-free."""
    box = (np.asarray(cfg.safety.workspace_min, float), np.asarray(cfg.safety.workspace_max, float))
    return random_paths(planners.checker, count, seed, box, path_class="mixed")


def plan_stream(planner: Planner, scale: np.ndarray, waypoints: np.ndarray, dt: float) -> np.ndarray | None:
    """One plan as joint targets at the control period, from and back to rest (None: no feasible plan)."""
    try:
        traj = planner.plan(waypoints, scale)
    except PlanningError as exc:
        log.info("bench collision: no %s plan for a path (%s)", getattr(planner, "name", "?"), exc)
        return None
    t = np.arange(0.0, traj.duration + 1e-9, dt)
    q = np.array([traj.at(x) for x in t])
    rest = int(round(REST_S / dt))
    return np.vstack([np.repeat(q[:1], rest, axis=0), q, np.repeat(q[-1:], rest, axis=0)])
