"""The PPO planner's environment: the agent sets the path speed along a fixed path, knot by knot, under a torque model.

The paper (section 5) trains PPO on its hybrid model as the simulator with the reward
`a |tau_limit - tau_peak|` when a torque exceeds its limit, `b T_reduction` otherwise (a < 0, b > 100).
Here the geometric path is the planners' common clamped spline (cell/planning/planner.py `GeometricPath`), cut into
`knots` equal pieces of the path parameter s.  At knot k the agent chooses the path speed at knot k+1 as a
fraction of the joint-speed cap there (the last knot is at rest); between knots the path acceleration is
constant, as in toppra's own parameterisation, so the result is timed by the same code as ours.  The
reward is the paper's, made dense: per segment `b (dt_ref - dt) / T_ref` (the time saved against a
reference profile at `reference_fraction` of the cap, normalised so that b weighs a relative reduction)
plus `a sum_j max(0, tau_peak_j / tau_limit_j - 1)`.  Unlike the paper's either-or, the time term is kept
when a limit is exceeded: withholding it would reward slow segments that also exceed.

`SpeedEnvBatch` steps many paths in lockstep so one model call serves them all (the model's per-call cost
dominates); `PathSpeedEnv` is the same thing as a single gymnasium environment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from cell.planning.constraints import InvDyn
from cell.planning.planner import TorqueFn

# Where the random paths of training and of the planning bench lie (degrees): the named paths' region
# (config/plans.yaml), in front of and beside the base, elbow up, wrist pointing down-ish.
WORKSPACE_DEG = np.array([[-120.0, 120.0], [-45.0, 35.0], [30.0, 140.0], [-90.0, 90.0], [30.0, 120.0], [-90.0, 90.0]])
OBS_MAX = 100.0  # every feature is a ratio or a log of one, >= 0; a runaway torque ratio is clipped here


@dataclass
class EnvConfig:
    knots: int = 30  # path pieces: the agent's decisions per path
    substeps: int = 3  # torque samples per piece
    min_speed_fraction: float = 0.03  # of the cap: the arm never stops between the ends
    time_weight: float = 10.0  # b: reward for the whole reference time saved
    torque_weight: float = 10.0  # |a|: penalty per unit of torque over its limit, summed over joints
    reference_fraction: float = 0.5  # the reference ("original") profile's speed, of the cap
    lookahead: int = 3  # knots ahead whose caps the agent sees


def obs_dim(ec: EnvConfig, n: int = 6) -> int:
    return 3 + ec.lookahead + 3 * n


def random_waypoints(rng: np.random.Generator, count: int, min_step_rad: float = 0.6) -> np.ndarray:
    """`count` waypoints (rad) drawn in WORKSPACE_DEG, consecutive ones at least `min_step_rad` apart."""
    lo, hi = np.radians(WORKSPACE_DEG[:, 0]), np.radians(WORKSPACE_DEG[:, 1])
    pts = [rng.uniform(lo, hi)]
    while len(pts) < count:
        q = rng.uniform(lo, hi)
        if np.linalg.norm(q - pts[-1]) >= min_step_rad:
            pts.append(q)
    return np.array(pts)


@dataclass
class PathData:
    """One path cut into knots: what the environment needs, computed once per path."""

    cap: np.ndarray  # (K+1,) path-speed cap from the joint speed limits at each knot
    q: np.ndarray  # (K, m, n) joint positions at the torque samples of each piece
    dq: np.ndarray  # (K, m, n) dq/ds there
    ddq: np.ndarray  # (K, m, n) d2q/ds2 there
    frac: np.ndarray  # (m,) where the samples lie in their piece (0..1]
    features: np.ndarray  # (K+1, 3n) per knot: gravity, acceleration and cruise torque ratios (physics)
    dt_ref: np.ndarray  # (K,) the reference profile's piece durations

    @property
    def knots(self) -> int:
        return len(self.dt_ref)


def piece_times(v: np.ndarray, ds: float) -> np.ndarray:
    """Durations of the pieces between knot speeds v (constant path acceleration)."""
    return 2.0 * ds / np.maximum(v[:-1] + v[1:], 1e-9)


def path_data(spline: Any, vlim: np.ndarray, limit: np.ndarray, inv_dyn: InvDyn, ec: EnvConfig) -> PathData:
    """Sample the spline s -> q at the knots and torque samples; the knot features come from the physics
    part of the model (cheap, per sample), the rewards from the full model (`SpeedEnvBatch`)."""
    K, m = ec.knots, ec.substeps
    grid = np.linspace(0.0, 1.0, K + 1)
    ds = 1.0 / K
    frac = np.arange(1, m + 1) / m
    s_sub = (grid[:-1, None] + frac[None, :] * ds).ravel()
    n = len(vlim)
    q_k, dq_k, ddq_k = spline(grid), spline(grid, 1), spline(grid, 2)
    cap = np.min(vlim[None, :] / np.maximum(np.abs(dq_k), 1e-9), axis=1)
    feats = np.zeros((K + 1, 3 * n))
    zero = np.zeros(n)
    for k in range(K + 1):
        g = inv_dyn(q_k[k], zero, zero)
        acc = inv_dyn(q_k[k], zero, dq_k[k]) - g  # torque per unit path acceleration
        cruise = inv_dyn(q_k[k], dq_k[k] * cap[k], ddq_k[k] * cap[k] ** 2)
        feats[k, :n] = np.abs(g) / limit
        feats[k, n:2 * n] = np.log1p(np.abs(acc) * cap[k] ** 2 / ds / limit)
        feats[k, 2 * n:] = np.log1p(np.abs(cruise) / limit)
    v_ref = ec.reference_fraction * cap
    v_ref[0] = v_ref[-1] = 0.0
    return PathData(cap=cap, q=spline(s_sub).reshape(K, m, n), dq=spline(s_sub, 1).reshape(K, m, n),
                    ddq=spline(s_sub, 2).reshape(K, m, n), frac=frac, features=feats,
                    dt_ref=piece_times(v_ref, ds))


class SpeedEnvBatch:
    """B paths stepped together; actions in [-1, 1] map to a fraction of the next knot's speed cap."""

    def __init__(self, torque_fn: TorqueFn, limit: np.ndarray, ec: EnvConfig) -> None:
        self.torque_fn = torque_fn
        self.limit = np.asarray(limit, float)
        self.ec = ec
        self.paths: list[PathData] = []
        self.k = 0
        self.v = np.zeros(0)
        self.last_peak = np.zeros(0)
        self.speeds: list[np.ndarray] = []

    def reset(self, paths: list[PathData]) -> np.ndarray:
        self.paths = paths
        self.k = 0
        self.v = np.zeros(len(paths))
        self.last_peak = np.zeros(len(paths))
        self.speeds = [self.v.copy()]
        return self.observe()

    def observe(self) -> np.ndarray:
        ec, k = self.ec, self.k
        K = ec.knots
        rows = []
        for b, p in enumerate(self.paths):
            ahead = [p.cap[k + i] / p.cap[k] if k + i <= K else 0.0 for i in range(1, ec.lookahead + 1)]
            nxt = min(k + 1, K)
            rows.append(np.concatenate([[k / K, self.v[b] / p.cap[k], self.last_peak[b]],
                                        np.minimum(ahead, 3.0), p.features[nxt]]))
        return np.clip(np.asarray(rows, np.float32), 0.0, OBS_MAX)

    def next_speed(self, action: np.ndarray) -> np.ndarray:
        ec, k = self.ec, self.k
        if k + 1 == ec.knots:
            return np.zeros(len(self.paths))  # the path ends at rest
        u = np.clip(0.5 * (np.asarray(action, float).reshape(-1) + 1.0), ec.min_speed_fraction, 1.0)
        return u * np.array([p.cap[k + 1] for p in self.paths])

    def step(self, action: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool, np.ndarray]:
        """-> observation, reward (B,), done (all paths end together), peak torque ratios (B, n)."""
        ec, k = self.ec, self.k
        ds = 1.0 / ec.knots
        v0, v1 = self.v, self.next_speed(action)
        alpha = (v1**2 - v0**2) / (2.0 * ds)
        dt = 2.0 * ds / np.maximum(v0 + v1, 1e-9)
        frac = self.paths[0].frac
        sd = np.sqrt(np.maximum(v0[:, None] ** 2 + 2.0 * alpha[:, None] * frac[None, :] * ds, 0.0))  # (B, m)
        q = np.stack([p.q[k] for p in self.paths])  # (B, m, n)
        dqs = np.stack([p.dq[k] for p in self.paths])
        ddqs = np.stack([p.ddq[k] for p in self.paths])
        dq = dqs * sd[..., None]
        ddq = ddqs * sd[..., None] ** 2 + dqs * alpha[:, None, None]
        B, m, n = q.shape
        tau = np.asarray(self.torque_fn(q.reshape(-1, n), dq.reshape(-1, n), ddq.reshape(-1, n))).reshape(B, m, n)
        peak = np.max(np.abs(tau), axis=1) / self.limit  # (B, n)
        t_ref = np.array([p.dt_ref.sum() for p in self.paths])
        dt_ref = np.array([p.dt_ref[k] for p in self.paths])
        reward = ec.time_weight * (dt_ref - dt) / t_ref - ec.torque_weight * np.sum(np.maximum(peak - 1.0, 0.0), axis=1)
        self.v = v1
        self.k += 1
        self.last_peak = np.max(peak, axis=1)
        self.speeds.append(v1.copy())
        done = self.k >= ec.knots
        return self.observe(), reward, done, peak

    def durations(self) -> np.ndarray:
        v = np.stack(self.speeds, axis=1)  # (B, k+1)
        return np.sum(2.0 / self.ec.knots / np.maximum(v[:, :-1] + v[:, 1:], 1e-9), axis=1)


class PathSpeedEnv(gym.Env[np.ndarray, np.ndarray]):
    """One path per episode, as a gymnasium environment (`path_source(rng)` gives the episode's PathData)."""

    def __init__(self, torque_fn: TorqueFn, limit: np.ndarray, ec: EnvConfig, path_source: Any) -> None:
        self.batch = SpeedEnvBatch(torque_fn, limit, ec)
        self.path_source = path_source
        n = len(limit)
        self.observation_space = gym.spaces.Box(0.0, OBS_MAX, shape=(obs_dim(ec, n),), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return self.batch.reset([self.path_source(self.np_random)])[0], {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, done, peak = self.batch.step(np.asarray(action, float).reshape(1))
        info = {"peak_ratio": peak[0], "duration_s": float(self.batch.durations()[0]) if done else None}
        return obs[0], float(reward[0]), done, False, info
