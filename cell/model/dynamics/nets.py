"""Neural learners (the paper's DNN and LSTM): one network per feature group, trained in JAX, served in numpy."""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.data.samples import Samples, holdout_segments
from cell.model.dynamics.features import FeatureSpec, Group, group_matrices, groups
from drivers.configio import join, require

log = logging.getLogger(__name__)

NET_LEARNERS = ("dnn", "lstm")
ACTIVATIONS = ("tanh", "relu")


@dataclass
class NetParams:
    """Settings of a DNN or LSTM learner (the paper tunes width, depth, dropout and the optimiser's rate).

    lstm: one LSTM layer over the group's window (oldest sample first) with `dropout` on its inputs and
    `recurrent_dropout` on the state fed back (one mask per sequence, as Keras draws them), its last
    state joined with the group's derived inputs, then `layers - 1` dense layers and a linear head.
    dnn: `layers` dense layers of `hidden` units with dropout after each, then a linear head.
    """

    learner: str = "dnn"
    hidden: int = 64
    layers: int = 2
    activation: str = "tanh"
    dropout: float = 0.05
    recurrent_dropout: float = 0.05
    learning_rate: float = 3e-3
    weight_decay: float = 1e-5
    batch_size: int = 256
    epochs: int = 40
    patience: int = 8  # epochs without a better validation score before stopping
    validation_fraction: float = 0.2  # whole segments held out for early stopping (0: none)
    nthread: int = 2
    seed: int = 0

    def validate(self, where: str) -> None:
        require(self.learner in NET_LEARNERS, join(where, "learner"), f"must be one of {', '.join(NET_LEARNERS)}")
        require(1 <= self.hidden <= 1024, join(where, "hidden"), "must lie in 1..1024")
        require(1 <= self.layers <= 8, join(where, "layers"), "must lie in 1..8")
        require(self.activation in ACTIVATIONS, join(where, "activation"), f"must be one of {', '.join(ACTIVATIONS)}")
        require(0 <= self.dropout < 1, join(where, "dropout"), "must lie in [0, 1)")
        require(0 <= self.recurrent_dropout < 1, join(where, "recurrent_dropout"), "must lie in [0, 1)")
        require(0 < self.learning_rate <= 1, join(where, "learning_rate"), "must lie in (0, 1]")
        require(self.weight_decay >= 0, join(where, "weight_decay"), "must be >= 0")
        require(self.batch_size >= 1, join(where, "batch_size"), "must be >= 1")
        require(self.epochs >= 1, join(where, "epochs"), "must be >= 1")
        require(0 <= self.validation_fraction < 0.9, join(where, "validation_fraction"), "must lie in [0, 0.9)")

    def to_dict(self) -> dict[str, Any]:
        return dict(vars(self))


def _act(name: str, xp: Any) -> Callable[[Any], Any]:
    return xp.tanh if name == "tanh" else (lambda v: xp.maximum(v, 0))


def _sigmoid(v: np.ndarray) -> np.ndarray:
    return 0.5 * (np.tanh(0.5 * v) + 1.0)  # no overflow warning for large |v|


def forward_np(p: dict[str, np.ndarray], x: np.ndarray, params: NetParams, window: int, width: int) -> np.ndarray:
    """The network on standardised inputs (N, d) in numpy, float32: the served path (same maths as `forward_jax`)."""
    act = _act(params.activation, np)
    h = x
    dense_from = 0
    if params.learner == "lstm":
        N = x.shape[0]
        seq = x[:, :window * width].reshape(N, window, width)
        H = p["Wh"].shape[0]
        hs = np.zeros((N, H), np.float32)
        cs = np.zeros((N, H), np.float32)
        for t in range(window - 1, -1, -1):  # columns are newest first; run oldest to newest
            z = seq[:, t] @ p["Wi"] + hs @ p["Wh"] + p["b"]
            i, f, g, o = z[:, :H], z[:, H:2 * H], z[:, 2 * H:3 * H], z[:, 3 * H:]
            cs = _sigmoid(f) * cs + _sigmoid(i) * np.tanh(g)
            hs = _sigmoid(o) * np.tanh(cs)
        h = np.concatenate([hs, x[:, window * width:]], axis=1)
        dense_from = 1
    for k in range(dense_from, params.layers):
        h = act(h @ p[f"W{k}"] + p[f"b{k}"])
    out: np.ndarray = h @ p["Wout"] + p["bout"]
    return out


def forward_jax(p: dict[str, Any], x: Any, params: NetParams, window: int, width: int, key: Any, train: bool) -> Any:
    """`forward_np` in JAX, with dropout when training (inverted: nothing to rescale when serving)."""
    import jax
    import jax.numpy as jnp

    act = _act(params.activation, jnp)

    def drop(v: Any, rate: float, k: Any, shape: tuple[int, ...] | None = None) -> Any:
        if not train or rate <= 0:
            return v
        keep = jax.random.bernoulli(k, 1.0 - rate, shape or v.shape)
        return v * keep / (1.0 - rate)

    keys = jax.random.split(key, params.layers + 2)
    h = x
    dense_from = 0
    if params.learner == "lstm":
        N = x.shape[0]
        seq = x[:, :window * width].reshape(N, window, width)
        H = p["Wh"].shape[0]
        ones_in = jnp.ones((N, width))
        ones_h = jnp.ones((N, H))
        m_in = drop(ones_in, params.dropout, keys[0])  # one mask per sequence, reused at every step
        m_h = drop(ones_h, params.recurrent_dropout, keys[1])
        hs = jnp.zeros((N, H))
        cs = jnp.zeros((N, H))
        for t in range(window - 1, -1, -1):
            z = (seq[:, t] * m_in) @ p["Wi"] + (hs * m_h) @ p["Wh"] + p["b"]
            i, f, g, o = z[:, :H], z[:, H:2 * H], z[:, 2 * H:3 * H], z[:, 3 * H:]
            cs = jax.nn.sigmoid(f) * cs + jax.nn.sigmoid(i) * jnp.tanh(g)
            hs = jax.nn.sigmoid(o) * jnp.tanh(cs)
        h = jnp.concatenate([hs, x[:, window * width:]], axis=1)
        dense_from = 1
    for k in range(dense_from, params.layers):
        h = drop(act(h @ p[f"W{k}"] + p[f"b{k}"]), params.dropout, keys[k + 2])
    return h @ p["Wout"] + p["bout"]


def _init(params: NetParams, d_in: int, n_out: int, window: int, width: int, seed: int) -> dict[str, np.ndarray]:
    """Glorot-uniform kernels (flax's default for dense layers), orthogonal recurrent kernel, forget bias 1."""
    rng = np.random.default_rng(seed)

    def glorot(a: int, b: int) -> np.ndarray:
        lim = np.sqrt(6.0 / (a + b))
        return rng.uniform(-lim, lim, (a, b)).astype(np.float32)

    p: dict[str, np.ndarray] = {}
    H = params.hidden
    d = d_in
    dense_from = 0
    if params.learner == "lstm":
        p["Wi"] = glorot(width, 4 * H)
        qm, _ = np.linalg.qr(rng.normal(size=(4 * H, H)))
        p["Wh"] = qm.T.astype(np.float32)
        b = np.zeros(4 * H, np.float32)
        b[H:2 * H] = 1.0
        p["b"] = b
        d = H + (d_in - window * width)
        dense_from = 1
    for k in range(dense_from, params.layers):
        p[f"W{k}"] = glorot(d, H)
        p[f"b{k}"] = np.zeros(H, np.float32)
        d = H
    p["Wout"] = glorot(d, n_out)
    p["bout"] = np.zeros(n_out, np.float32)
    return p


@dataclass
class GroupNet:
    """One group's network with its input and output standardisation (float32)."""

    weights: dict[str, np.ndarray]
    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: np.ndarray
    y_scale: np.ndarray

    def predict(self, X: np.ndarray, params: NetParams, window: int, width: int) -> np.ndarray:
        z = ((X - self.x_mean) / self.x_scale).astype(np.float32)
        return forward_np(self.weights, z, params, window, width) * self.y_scale + self.y_mean


def _config_jax(nthread: int) -> None:
    """JAX on the CPU with the thread count asked for; only effective before JAX's first import."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    if "jax" not in sys.modules:
        flags = os.environ.get("XLA_FLAGS", "")
        if "intra_op_parallelism_threads" not in flags:
            os.environ["XLA_FLAGS"] = (f"{flags} --xla_cpu_multi_thread_eigen={'true' if nthread > 1 else 'false'} "
                                       f"intra_op_parallelism_threads={nthread}").strip()


Reporter = Callable[[int, float], None]
_COMPILED: dict[tuple[Any, ...], tuple[Any, Any, Any]] = {}


def _compiled(params: NetParams, window: int, width: int) -> tuple[Any, Any, Any]:
    """(optimiser, jitted epoch, jitted validation MSE) for a network shape, built once per process:
    groups of the same shape (and trials of a search with the same settings) reuse the compiled code."""
    key = (params.learner, params.hidden, params.layers, params.activation, params.dropout,
           params.recurrent_dropout, params.learning_rate, params.weight_decay, window, width)
    if key in _COMPILED:
        return _COMPILED[key]
    import jax
    import jax.numpy as jnp
    import optax

    opt = optax.adamw(params.learning_rate, weight_decay=params.weight_decay)

    def loss(p: Any, xb: Any, yb: Any, k: Any) -> Any:
        return jnp.mean((forward_jax(p, xb, params, window, width, k, True) - yb) ** 2)

    @jax.jit
    def epoch(p: Any, s: Any, xs: Any, ys: Any, k: Any) -> tuple[Any, Any]:
        def step(carry: Any, batch: Any) -> tuple[Any, None]:
            p_, s_, k_ = carry
            k_, sub = jax.random.split(k_)
            g = jax.grad(loss)(p_, batch[0], batch[1], sub)
            upd, s_ = opt.update(g, s_, p_)
            return (optax.apply_updates(p_, upd), s_, k_), None

        (p, s, _), _ = jax.lax.scan(step, (p, s, k), (xs, ys))
        return p, s

    @jax.jit
    def mse(p: Any, x: Any, y: Any) -> Any:
        return jnp.mean((forward_jax(p, x, params, window, width, jax.random.PRNGKey(0), False) - y) ** 2, axis=0)

    _COMPILED[key] = (opt, epoch, mse)
    return _COMPILED[key]


def _train_group(X: np.ndarray, Y: np.ndarray, tr: np.ndarray, va: np.ndarray | None, params: NetParams,
                 window: int, width: int, seed: int, report: Reporter | None = None) -> GroupNet:
    """Adam(W) on the mean squared error of standardised outputs, early stopping on the held-out rows."""
    _config_jax(params.nthread)
    import jax
    import jax.numpy as jnp

    Xtr = X[tr]
    x_mean = Xtr.mean(axis=0)
    x_scale = np.maximum(Xtr.std(axis=0), 1e-6)
    y_mean = Y[tr].mean(axis=0)
    y_scale = np.maximum(Y[tr].std(axis=0), 1e-6)
    Z = ((X - x_mean) / x_scale).astype(np.float32)
    T = ((Y - y_mean) / y_scale).astype(np.float32)
    p0 = {k: jnp.asarray(v) for k, v in _init(params, X.shape[1], Y.shape[1], window, width, seed).items()}
    opt, epoch, mse = _compiled(params, window, width)
    state = opt.init(p0)

    rng = np.random.default_rng(seed)
    B = min(params.batch_size, len(tr))
    steps = max(1, len(tr) // B)
    key = jax.random.PRNGKey(seed)
    Zva = jnp.asarray(Z[va]) if va is not None else None
    Tva = jnp.asarray(T[va]) if va is not None else None
    best, best_p, stale, p = np.inf, p0, 0, p0
    for e in range(params.epochs):
        order = rng.permutation(tr)[: steps * B].reshape(steps, B)
        key, sub = jax.random.split(key)
        p, state = epoch(p, state, jnp.asarray(Z[order]), jnp.asarray(T[order]), sub)
        if Zva is None:
            best_p = p
            continue
        # validation RMSE in N·m (per output, averaged): what early stopping and pruning compare
        score = float(np.mean(np.sqrt(np.asarray(mse(p, Zva, Tva))) * y_scale))
        if report is not None:
            report(e, score)
        if score < best - 1e-6:
            best, best_p, stale = score, p, 0
        else:
            stale += 1
            if stale >= params.patience:
                break
    weights = {k: np.asarray(v, np.float32) for k, v in best_p.items()}
    return GroupNet(weights, x_mean.astype(np.float32), x_scale.astype(np.float32),
                    y_mean.astype(np.float32), y_scale.astype(np.float32))


class NetLearner:
    """A DNN or LSTM per feature group, with the interface of `Forest` (fit, predict, outputs, groups)."""

    def __init__(self, spec: FeatureSpec, n: int, params: NetParams | None = None,
                 nets: dict[int, GroupNet] | None = None) -> None:
        self.spec = spec
        self.n = n
        self.params = params or NetParams()
        self.groups: list[Group] = groups(spec, n)
        self.nets: dict[int, GroupNet] = nets or {}  # by group index
        self.fit_seconds = 0.0

    @property
    def learner(self) -> str:
        return self.params.learner

    @property
    def outputs(self) -> list[int]:
        return [j for g in self.groups for j in g.outputs]

    def fit(self, s: Samples, target: np.ndarray, params: NetParams, physics: np.ndarray | None = None,
            report: Reporter | None = None) -> NetLearner:
        """target: (N, n) torque (or residual); physics: the torque the 'load' inputs are made of.
        `report(step, validation RMSE)` is called after every epoch of every group (for pruning)."""
        params.validate("net")
        self.params = params
        tr, va = holdout_segments(s, params.validation_fraction, params.seed)
        t0 = time.perf_counter()
        step = 0
        for gi, g, X in group_matrices(self.spec, self.groups, s.q, s.dq, s.ddq, s.starts, physics):
            Y = target[:, list(g.outputs)].astype(np.float32)

            def rep(e: int, v: float, base: int = step) -> None:
                if report is not None:
                    report(base + e, v)

            self.nets[gi] = _train_group(X, Y, tr, va, params, g.window, len(g.base), params.seed + gi, rep)
            step += params.epochs
        self.fit_seconds = time.perf_counter() - t0
        log.info("%s: %d group net(s) in %.1f s", params.learner, len(self.groups), self.fit_seconds)
        return self

    def predict(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, starts: np.ndarray | None,
                physics: np.ndarray | None = None) -> np.ndarray:
        """(N, n) with NaN on joints that are not learned."""
        out = np.full((np.atleast_2d(q).shape[0], self.n), np.nan)
        for gi, g, X in group_matrices(self.spec, self.groups, q, dq, ddq, starts, physics):
            out[:, list(g.outputs)] = self.nets[gi].predict(X, self.params, g.window, len(g.base))
        return out

    def trees(self) -> int:
        return 0

    def weights(self) -> int:
        """Trainable numbers in all networks."""
        return sum(int(v.size) for net in self.nets.values() for v in net.weights.values())


def flatten_nets(nets: dict[int, GroupNet]) -> dict[str, np.ndarray]:
    """The arrays of every group net under 'g<i>/<name>' (an .npz archive's keys)."""
    out: dict[str, np.ndarray] = {}
    for gi, net in nets.items():
        for k, v in net.weights.items():
            out[f"g{gi}/w/{k}"] = v
        for k in ("x_mean", "x_scale", "y_mean", "y_scale"):
            out[f"g{gi}/{k}"] = getattr(net, k)
    return out


def unflatten_nets(arrays: dict[str, np.ndarray], n_groups: int) -> dict[int, GroupNet]:
    """Inverse of `flatten_nets`; KeyError when a group's arrays are missing."""
    nets: dict[int, GroupNet] = {}
    for gi in range(n_groups):
        pre = f"g{gi}/"
        w = {k[len(pre) + 2:]: np.asarray(v, np.float32) for k, v in arrays.items() if k.startswith(pre + "w/")}
        if not w:
            raise KeyError(f"group {gi}: no weights")
        nets[gi] = GroupNet(w, *(np.asarray(arrays[pre + k], np.float32)
                                 for k in ("x_mean", "x_scale", "y_mean", "y_scale")))
    return nets
