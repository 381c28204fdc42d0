"""A compact PPO (clipped surrogate, GAE, Gaussian policy) on jax + optax, for the path-speed planner.

Why not sbx or stable-baselines3: `pip install sbx-rl` resolves to stable-baselines3 -> torch 2.14 with
15 nvidia-* CUDA 13 wheels and triton (several GB) on a plain Linux install, which CI (fresh machine, 20 min,
2 cores) cannot afford, and the CPU-only torch index cannot be named from pyproject for a plain
`pip install -e .[test]`.  jax and optax are already dependencies (the model lab's learners); the algorithm is
the standard one (Schulman et al. 2017, with the usual defaults of the maintained implementations:
advantage normalisation, value-loss weight 0.5, gradient clipping 0.5) and fits in this module.
The trained policy is numpy arrays in an .npz artefact, served without jax.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import ConfigError

log = logging.getLogger(__name__)
Params = dict[str, np.ndarray]
FORMAT = "tmcell-ppo-policy"


@dataclass
class PPOConfig:
    updates: int = 150  # rollouts of n_envs whole episodes
    n_envs: int = 32
    epochs: int = 8
    minibatches: int = 4
    learning_rate: float = 3e-4
    clip: float = 0.2
    gae_lambda: float = 0.95
    gamma: float = 1.0  # episodic and short: the whole path's time counts
    entropy: float = 0.0
    hidden: int = 64
    init_log_std: float = -0.5
    seed: int = 0


def init_params(rng: np.random.Generator, n_obs: int, hidden: int, init_log_std: float) -> Params:
    """Two tanh MLPs (actor mean, critic), orthogonal-style scaled Gaussian init."""
    def dense(n_in: int, n_out: int, gain: float) -> np.ndarray:
        return (rng.standard_normal((n_in, n_out)) * gain / np.sqrt(n_in)).astype(np.float32)

    p: Params = {}
    for head, out_gain in (("pi", 0.01), ("v", 1.0)):
        p[f"{head}_w1"], p[f"{head}_b1"] = dense(n_obs, hidden, 1.0), np.zeros(hidden, np.float32)
        p[f"{head}_w2"], p[f"{head}_b2"] = dense(hidden, hidden, 1.0), np.zeros(hidden, np.float32)
        p[f"{head}_w3"], p[f"{head}_b3"] = dense(hidden, 1, out_gain), np.zeros(1, np.float32)
    p["log_std"] = np.full(1, init_log_std, np.float32)
    return p


def mlp(p: Any, head: str, x: Any, xp: Any = np) -> Any:
    h = xp.tanh(x @ p[f"{head}_w1"] + p[f"{head}_b1"])
    h = xp.tanh(h @ p[f"{head}_w2"] + p[f"{head}_b2"])
    return (h @ p[f"{head}_w3"] + p[f"{head}_b3"])[..., 0]


def act_deterministic(p: Params, obs: np.ndarray) -> np.ndarray:
    """The policy's mean action (numpy, no jax): what the planner uses."""
    return np.clip(mlp(p, "pi", np.asarray(obs, np.float32)), -1.0, 1.0)


def _make_update(pc: PPOConfig) -> tuple[Callable[..., Any], Any]:
    import jax
    import jax.numpy as jnp
    import optax

    opt = optax.chain(optax.clip_by_global_norm(0.5), optax.adam(pc.learning_rate))

    def loss(p: Any, obs: Any, act: Any, logp_old: Any, adv: Any, ret: Any) -> Any:
        mean = mlp(p, "pi", obs, jnp)
        log_std = p["log_std"][0]
        logp = -0.5 * ((act - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi)
        ratio = jnp.exp(logp - logp_old)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg = -jnp.mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - pc.clip, 1 + pc.clip) * adv))
        v = mlp(p, "v", obs, jnp)
        entropy = log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e)
        return pg + 0.5 * jnp.mean((v - ret) ** 2) - pc.entropy * entropy

    @jax.jit
    def update(p: Any, state: Any, obs: Any, act: Any, logp: Any, adv: Any, ret: Any) -> tuple[Any, Any]:
        grads = jax.grad(loss)(p, obs, act, logp, adv, ret)
        updates, state = opt.update(grads, state, p)
        return optax.apply_updates(p, updates), state

    return update, opt


def train(
    env: Any, sample_paths: Callable[[np.random.Generator, int], list[Any]], n_obs: int, knots: int, pc: PPOConfig,
    snapshots: tuple[int, ...] = (),
) -> tuple[Params, dict[str, Any]]:
    """PPO on `env` (a `SpeedEnvBatch`): each update rolls out `n_envs` fresh paths from start to end.  The
    policy after each update count in `snapshots` is kept (`info["snapshots"]`), so what the training budget
    buys can be measured afterwards."""
    import jax.numpy as jnp

    rng = np.random.default_rng(pc.seed)
    params = init_params(rng, n_obs, pc.hidden, pc.init_log_std)
    update, opt = _make_update(pc)
    jp = {k: jnp.asarray(v) for k, v in params.items()}
    state = opt.init(jp)
    t0 = time.perf_counter()
    history: list[float] = []
    kept: dict[int, Params] = {}
    B, K = pc.n_envs, knots
    for u in range(pc.updates):
        p_np = {k: np.asarray(v) for k, v in jp.items()}
        obs = env.reset(sample_paths(rng, B))
        O, A, LP, R, V = [], [], [], [], []
        for _ in range(K):
            mean = mlp(p_np, "pi", obs)
            std = float(np.exp(p_np["log_std"][0]))
            act = mean + std * rng.standard_normal(B).astype(np.float32)
            logp = -0.5 * ((act - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)
            O.append(obs)
            A.append(act)
            LP.append(logp)
            V.append(mlp(p_np, "v", obs))
            obs, reward, _, _ = env.step(np.clip(act, -1.0, 1.0))
            R.append(reward)
        rew, val = np.stack(R, 1), np.stack(V, 1)  # (B, K)
        adv = np.zeros_like(rew)
        last = np.zeros(B)
        for k in reversed(range(K)):  # GAE; the episode ends after the last knot
            nxt = val[:, k + 1] if k + 1 < K else 0.0
            delta = rew[:, k] + pc.gamma * nxt - val[:, k]
            last = delta + pc.gamma * pc.gae_lambda * last
            adv[:, k] = last
        ret = adv + val
        flat = [np.stack(O, 1).reshape(B * K, -1), np.stack(A, 1).ravel(), np.stack(LP, 1).ravel(),
                adv.ravel(), ret.ravel()]
        n = B * K
        mb = n // pc.minibatches
        for _ in range(pc.epochs):
            order = rng.permutation(n)
            for i in range(pc.minibatches):
                idx = order[i * mb:(i + 1) * mb]
                jp, state = update(jp, state, *(jnp.asarray(a[idx], jnp.float32) for a in flat))
        history.append(float(rew.sum(1).mean()))
        if u + 1 in snapshots:
            kept[u + 1] = {k: np.asarray(v, np.float32) for k, v in jp.items()}
        if u % 25 == 0 or u == pc.updates - 1:
            log.info("ppo update %d/%d: mean episode return %.3f", u + 1, pc.updates, history[-1])
    params = {k: np.asarray(v, np.float32) for k, v in jp.items()}
    info = {"training_s": time.perf_counter() - t0, "env_steps": pc.updates * B * K,
            "final_return": float(np.mean(history[-10:])), "first_return": history[0],
            "returns": np.round(history, 3).tolist(), "snapshots": kept}
    return params, info


def save_policy(path: Path, params: Params, meta: dict[str, Any]) -> None:
    path.mkdir(parents=True, exist_ok=True)
    with open(path / "policy.npz", "wb") as f:
        np.savez(f, **params)  # type: ignore[arg-type]  # numpy's stub takes the keywords for allow_pickle
    (path / "policy.json").write_text(json.dumps({"format": FORMAT, **meta}, indent=1), encoding="utf-8")


def save_snapshot(path: Path, updates: int, params: Params) -> None:
    """The policy as it was after `updates` updates, beside the final one."""
    with open(path / f"policy-{updates:05d}.npz", "wb") as f:
        np.savez(f, **params)  # type: ignore[arg-type]  # as in save_policy


def load_snapshots(path: Path, n_obs: int, hidden: int) -> dict[int, Params]:
    """The saved snapshots by update count (those whose shapes fit; none when training kept none)."""
    want = {k: v.shape for k, v in init_params(np.random.default_rng(0), n_obs, hidden, 0.0).items()}
    out: dict[int, Params] = {}
    for f in sorted(path.glob("policy-*.npz")):
        with np.load(f) as z:
            params = {k: z[k] for k in z.files}
        if {k: v.shape for k, v in params.items()} == want:
            out[int(f.stem.split("-")[1])] = params
    return out


def load_policy(path: Path, n_obs: int, hidden: int) -> tuple[Params, dict[str, Any]]:
    """The saved policy, refused (ConfigError) when its format or shapes do not match what is asked."""
    try:
        meta = json.loads((path / "policy.json").read_text(encoding="utf-8"))
        with np.load(path / "policy.npz") as z:
            params = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read the PPO policy ({exc})") from None
    want = {k: v.shape for k, v in init_params(np.random.default_rng(0), n_obs, hidden, 0.0).items()}
    got = {k: v.shape for k, v in params.items()}
    if meta.get("format") != FORMAT or got != want:
        raise ConfigError(f"{path}: PPO policy has format {meta.get('format')!r} and shapes {got}, expected "
                          f"{FORMAT!r} with {want}: retrain it (delete the directory)")
    return params, meta


def config_dict(pc: PPOConfig) -> dict[str, Any]:
    return asdict(pc)
