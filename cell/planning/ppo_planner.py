"""The paper's planner: a PPO policy sets the path speed knot by knot on the torque model; train, store, load, plan.

The policy is trained once on random paths of the workspace (`cell/planning/speed_env.py`), not per path as in
the paper: a plan must come in well under a second, and the bench plans paths the policy has never seen.
At plan time the policy's mean action is rolled out on the path, the knot speeds are timed by the same
code as the time-optimal planner (constant path acceleration between knots, smoothed, speed and
acceleration guards), and the full model checks the result: if a torque exceeds its limit anyway, the
whole profile is slowed uniformly until it fits (`iterations` > 1 says how often that was needed).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell.collision.geometry import CollisionChecker
from cell.model.robot import RobotModel
from cell.planning.config import PlannerConfig
from cell.planning.constraints import ToppraTerms
from cell.planning.planner import GeometricPath, PlanningError, TimedTrajectory, ToppraPlanner, TorqueFn
from cell.planning.ppo import Params, PPOConfig, act_deterministic, load_policy, save_policy, save_snapshot, train
from cell.planning.speed_env import EnvConfig, PathData, SpeedEnvBatch, obs_dim, path_data, random_waypoints

log = logging.getLogger(__name__)
# Update counts whose policy is kept beside the final one: PPO's time against its training budget.
SNAPSHOTS = (10, 20, 30, 60, 100, 150, 200, 300, 500, 1000)
SLOWDOWN_STEP = 0.97  # per fallback iteration, of every knot speed
MAX_SLOWDOWNS = 80  # 0.97^80 ~ 0.09


@dataclass
class PpoSettings:
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    waypoints: tuple[int, int] = (3, 5)  # training paths have this many waypoints (inclusive)


class PpoPlanner(ToppraPlanner):
    name = "ppo"

    def __init__(self, robot: RobotModel, torque_fn: TorqueFn, cfg: PlannerConfig, policy: Params,
                 settings: PpoSettings, collisions: CollisionChecker | None = None,
                 terms: ToppraTerms | None = None) -> None:
        super().__init__(robot, torque_fn, cfg, collisions, terms)
        self.policy = policy
        self.ec = settings.env

    def rollout(self, path: GeometricPath, limit: np.ndarray) -> np.ndarray:
        """The policy's knot speeds along the path (K+1,)."""
        env = SpeedEnvBatch(self.torque_fn, limit, self.ec)
        obs = env.reset([path_data(path.spline, self.vlim, limit, self.terms.inv_dyn, self.ec)])
        done = False
        while not done:
            obs, _, done, _ = env.step(act_deterministic(self.policy, obs))
        return np.stack(env.speeds, axis=1)[0]

    def plan(self, waypoints: np.ndarray, torque_scale: np.ndarray | None = None) -> TimedTrajectory:
        t0 = time.perf_counter()
        path = self.check_waypoints(waypoints)
        scale = np.ones(self.robot.n) if torque_scale is None else np.array(torque_scale, float)
        sd = self.rollout(path, self.torque_limit(scale))
        grid = np.linspace(0.0, 1.0, self.ec.knots + 1)
        for it in range(1, MAX_SLOWDOWNS + 1):
            traj = self.timed_smoothed(path, grid, sd)  # the step it was trained and compared with
            ratio = self.excess(traj, scale)
            if np.all(ratio <= 1.0 + 1e-3):
                return self.stamp(traj, t0, it, scale)
            sd = sd * SLOWDOWN_STEP
        raise PlanningError(f"ppo: the policy's profile still exceeds a torque limit after slowing it to "
                            f"{SLOWDOWN_STEP ** MAX_SLOWDOWNS:.2f} x (worst ratio {float(np.max(ratio)):.3f})")


def training_paths(robot: RobotModel, vlim: np.ndarray, limit: np.ndarray, terms: ToppraTerms,
                   settings: PpoSettings, only: np.ndarray | None = None) -> Any:
    """(rng, count) -> PathData of random workspace paths, the ones the policy learns on; with `only`, that
    one path every time (the paper's setting: one policy per trajectory)."""
    lo, hi = settings.waypoints
    fixed = None if only is None else path_data(GeometricPath(only).spline, vlim, limit, terms.inv_dyn, settings.env)

    def sample(rng: np.random.Generator, count: int) -> list[PathData]:
        if fixed is not None:
            return [fixed] * count
        out = []
        for _ in range(count):
            w = random_waypoints(rng, int(rng.integers(lo, hi + 1)))
            out.append(path_data(GeometricPath(w).spline, vlim, limit, terms.inv_dyn, settings.env))
        return out

    return sample


def train_policy(robot: RobotModel, torque_fn: TorqueFn, cfg: PlannerConfig, terms: ToppraTerms | None,
                 settings: PpoSettings, out: Path | None, model_name: str,
                 only: np.ndarray | None = None) -> tuple[Params, dict[str, Any]]:
    """Train on the model (at the planning limit, torque_scale 1) and store the policy under `out`."""
    base = PpoPlanner(robot, torque_fn, cfg, {}, settings, None, terms)
    limit = base.torque_limit()
    env = SpeedEnvBatch(torque_fn, limit, settings.env)
    sample = training_paths(robot, base.vlim, limit, base.terms, settings, only)
    log.info("training the PPO planner on %s: %d updates x %d paths x %d knots", model_name,
             settings.ppo.updates, settings.ppo.n_envs, settings.env.knots)
    params, info = train(env, sample, obs_dim(settings.env, robot.n), settings.env.knots, settings.ppo,
                         tuple(u for u in SNAPSHOTS if u < settings.ppo.updates))
    snapshots = info.pop("snapshots")
    meta = {"model": model_name, "env": asdict(settings.env), "ppo": asdict(settings.ppo),
            "planner": asdict(cfg), "only": None if only is None else np.asarray(only).round(6).tolist(), **info}
    if out is not None:
        for old in out.glob("policy-*.npz"):
            old.unlink()  # a previous training's snapshots would mix into this one's curve
        save_policy(out, params, meta)
        for u, snap in snapshots.items():
            save_snapshot(out, u, snap)
        log.info("PPO policy saved to %s (%.1f s of training)", out, info["training_s"])
    return params, meta


def load_or_train(path: Path, robot: RobotModel, torque_fn: TorqueFn, cfg: PlannerConfig,
                  terms: ToppraTerms | None, settings: PpoSettings, model_name: str,
                  only: np.ndarray | None = None) -> tuple[Params, dict[str, Any]]:
    """The stored policy if it was trained for this model, environment, training budget and path set, else a
    new one."""
    if (path / "policy.json").exists():
        params, meta = load_policy(path, obs_dim(settings.env, robot.n), settings.ppo.hidden)
        want_only = None if only is None else np.asarray(only).round(6).tolist()
        if (meta.get("model") == model_name and meta.get("env") == asdict(settings.env)
                and meta.get("ppo") == asdict(settings.ppo) and meta.get("only") == want_only):
            meta["loaded"] = True
            return params, meta
        log.warning("%s: the stored policy was trained for another model or settings; retraining", path)
    return train_policy(robot, torque_fn, cfg, terms, settings, path, model_name, only)
