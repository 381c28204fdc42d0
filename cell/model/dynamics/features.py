"""Learned-model inputs: instant or windowed (q, dq, ddq) features in the paper's joint grouping or per joint."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from drivers.configio import join, require

Grouping = Literal["paper", "per_joint", "full", "own"]


@dataclass
class FeatureSpec:
    """Which inputs each learned output sees.

    grouping:
      * ``paper``: joints 1-3 trained together on q, dq, ddq of joints 1-3; every further joint on
        all n angles plus its own dq, ddq (the paper's Table 1, extended past joint 5 the same way);
      * ``per_joint``: every joint on all n angles plus its own dq, ddq;
      * ``full``: every joint on all n angles, speeds and accelerations;
      * ``own``: every joint on its own q, dq, ddq only (for a residual that is mostly joint friction).
    window: samples per input (1 = instant; the paper's best uses 10 = 80 ms at 8 ms), flattened
      newest first; rows before a trajectory's start reuse its first sample.
    joints: the learned outputs are joints 1..joints; None (the default): every joint of the arm (the
      paper models 1-5 of its six).
    Derived inputs (current sample, per output joint j, with s_j = tanh(dq_j / sign_eps) the
    direction of motion), the structure of gear friction:
    physics_inputs: |tau_phys_j| * s_j, where tau_phys is what the model's own physics part predicts
      (friction that grows with the load is then a function of one input, not of the whole
      configuration).  Never used by D, which has no physics part.
    friction_harmonics: H > 0 adds s_j and sin(k q_j) s_j, cos(k q_j) s_j for k = 1..H (friction
      that varies with the gear position, a few periods per revolution).
    angle_sums: sin and cos of every run of consecutive angles q_i + ... + q_j (all groups): the
      orientations of the links, of which gravity and inertia are smooth sums.  Parameter-free, so
      a purely data-driven model (D) may use them.
    """

    window: int = 10
    grouping: Grouping = "paper"
    joints: int | None = None
    physics_inputs: bool = False
    friction_harmonics: int = 0
    angle_sums: bool = False
    sign_eps: float = 0.005

    def validate(self, where: str) -> None:
        require(1 <= self.window <= 50, join(where, "window"), f"must lie in 1..50, got {self.window}")
        require(self.joints is None or self.joints >= 1, join(where, "joints"), "must be >= 1 (or null: all)")
        require(0 <= self.friction_harmonics <= 20, join(where, "friction_harmonics"), "must lie in 0..20")
        require(self.sign_eps > 0, join(where, "sign_eps"), "must be > 0")

    def learned(self, n: int) -> int:
        """How many joints (1..m) are learned on an arm of n joints."""
        return n if self.joints is None else self.joints

    def to_dict(self) -> dict[str, Any]:
        return {"window": self.window, "grouping": self.grouping, "joints": self.joints,
                "physics_inputs": self.physics_inputs, "friction_harmonics": self.friction_harmonics,
                "angle_sums": self.angle_sums, "sign_eps": self.sign_eps}


def derived_layout(spec: FeatureSpec, n: int) -> list[tuple[str, int]]:
    """Layout of the derived-input vector E as (name, joint) over all learned joints; each group
    takes the entries of its own joints (joint -1: every group).  Matches the columns of `derived`."""
    J = range(spec.learned(n))
    out: list[tuple[str, int]] = []
    if spec.physics_inputs:
        out += [(f"load{j + 1}", j) for j in J]
    if spec.friction_harmonics:
        out += [(f"dir{j + 1}", j) for j in J]
        for k in range(1, spec.friction_harmonics + 1):
            out += [(f"sin{k}q{j + 1}", j) for j in J] + [(f"cos{k}q{j + 1}", j) for j in J]
    if spec.angle_sums:
        runs = [(i, j) for i in range(n) for j in range(i, n)]
        out += [(f"sin(q{i + 1}..q{j + 1})", -1) for i, j in runs] + [(f"cos(q{i + 1}..q{j + 1})", -1) for i, j in runs]
    return out


def derived(spec: FeatureSpec, q: np.ndarray, dq: np.ndarray, physics: np.ndarray | None) -> np.ndarray:
    """E for a batch (N, n) -> (N, len(derived_layout)) float32 (computed in float64, rounded once,
    as the single-sample path `DerivedOne` does)."""
    m = spec.learned(q.shape[1])
    N = q.shape[0]
    out = np.empty((N, len(derived_layout(spec, q.shape[1]))), np.float32)
    s = np.tanh(dq[:, :m] / spec.sign_eps)
    o = 0
    if spec.physics_inputs:
        if physics is None:
            raise ValueError("these features need the physics torque as an input")
        out[:, :m] = np.abs(physics[:, :m]) * s
        o = m
    if spec.friction_harmonics:
        out[:, o:o + m] = s
        o += m
        for k in range(1, spec.friction_harmonics + 1):
            kq = k * q[:, :m]
            out[:, o:o + m] = np.sin(kq) * s
            out[:, o + m:o + 2 * m] = np.cos(kq) * s
            o += 2 * m
    if spec.angle_sums:
        n = q.shape[1]
        c = np.concatenate([np.zeros((N, 1)), np.cumsum(q, axis=1)], axis=1)
        i, j = np.triu_indices(n)
        ang = c[:, j + 1] - c[:, i]
        out[:, o:o + len(i)] = np.sin(ang)
        out[:, o + len(i):o + 2 * len(i)] = np.cos(ang)
    return out


class DerivedOne:
    """`derived` for one sample without batch overhead (the served path); same columns, same values."""

    def __init__(self, spec: FeatureSpec, n: int) -> None:
        self.m = spec.learned(n)
        self.inv_eps = 1.0 / spec.sign_eps
        self.physics = spec.physics_inputs
        self.k = np.arange(1, spec.friction_harmonics + 1, dtype=float)[:, None]  # (H, 1)
        self.sums = spec.angle_sums
        i, j = np.triu_indices(n)
        self.i, self.j1 = i, j + 1
        self.out = np.empty(len(derived_layout(spec, n)))
        self._c = np.zeros(n + 1)

    def load_columns(self) -> slice | None:
        """Where the load input's columns sit in the output (None: it has none)."""
        return slice(0, self.m) if self.physics else None

    def load_values(self, dq: np.ndarray, load: np.ndarray) -> np.ndarray:
        """Those columns' values, as `__call__` computes them."""
        return np.abs(load[:self.m]) * np.tanh(dq[:self.m] * self.inv_eps)

    def __call__(self, q: np.ndarray, dq: np.ndarray, load: np.ndarray | None) -> np.ndarray:
        m, out = self.m, self.out
        s = np.tanh(dq[:m] * self.inv_eps)
        o = 0
        if self.physics:
            assert load is not None
            out[:m] = np.abs(load[:m]) * s
            o = m
        if len(self.k):
            out[o:o + m] = s
            kq = self.k * q[:m]  # (H, m)
            h = len(self.k)
            out[o + m:o + m + 2 * h * m] = np.hstack([np.sin(kq) * s, np.cos(kq) * s]).ravel()
            o += m + 2 * h * m
        if self.sums:
            c = self._c
            np.cumsum(q, out=c[1:])
            ang = c[self.j1] - c[self.i]
            k = len(ang)
            out[o:o + k] = np.sin(ang)
            out[o + k:o + 2 * k] = np.cos(ang)
        return out


@dataclass(frozen=True)
class Group:
    """Outputs trained on one feature set: base columns index the per-sample state [q, dq, ddq] (3n),
    windowed; then `extra` columns of the derived-input vector E (current sample only)."""

    outputs: tuple[int, ...]  # joint indices (0-based)
    base: tuple[int, ...]  # columns of the per-sample state vector [q(n), dq(n), ddq(n)]
    window: int
    extra: tuple[int, ...] = ()  # indices into E
    extra_names: tuple[str, ...] = ()

    @property
    def window_width(self) -> int:
        return len(self.base) * self.window

    @property
    def width(self) -> int:
        return self.window_width + len(self.extra)

    def names(self, n: int) -> list[str]:
        labels = [f"q{i + 1}" for i in range(n)] + [f"dq{i + 1}" for i in range(n)] + [f"ddq{i + 1}" for i in range(n)]
        return [f"{labels[c]}[-{k}]" for k in range(self.window) for c in self.base] + list(self.extra_names)


def groups(spec: FeatureSpec, n: int) -> list[Group]:
    """The feature groups for an arm with n joints."""
    m = spec.learned(n)
    if m > n:
        raise ValueError(f"features.joints={spec.joints} but the arm has {n} joints")
    q = list(range(n))
    layout = derived_layout(spec, n)

    def own_q(j: int) -> tuple[int, ...]:
        return tuple(q + [n + j, 2 * n + j])

    def make(outputs: tuple[int, ...], base: tuple[int, ...]) -> Group:
        idx = tuple(i for i, (_, j) in enumerate(layout) if j in outputs or j < 0)
        return Group(outputs, base, spec.window, idx, tuple(layout[i][0] for i in idx))

    out: list[Group] = []
    if spec.grouping == "paper":
        first = list(range(min(3, m)))
        out.append(make(tuple(first), tuple(first + [n + j for j in first] + [2 * n + j for j in first])))
        out.extend(make((j,), own_q(j)) for j in range(3, m))
    elif spec.grouping == "per_joint":
        out.extend(make((j,), own_q(j)) for j in range(m))
    elif spec.grouping == "full":
        everything = tuple(range(3 * n))
        out.extend(make((j,), everything) for j in range(m))
    elif spec.grouping == "own":
        out.extend(make((j,), (j, n + j, 2 * n + j)) for j in range(m))
    else:
        raise ValueError(f"unknown grouping {spec.grouping!r} (paper, per_joint, full, own)")
    return out


def state_matrix(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
    return np.hstack([q, dq, ddq])


def history_index(n_rows: int, starts: np.ndarray | None, window: int) -> np.ndarray:
    """(n_rows, window) row indices: row i, i-1, ..., clamped at the start of i's trajectory."""
    rows = np.arange(n_rows)
    if starts is None or len(starts) == 0:
        first = np.zeros(n_rows, np.int64)
    else:
        marks = np.zeros(n_rows, np.int64)
        marks[np.asarray(starts, np.int64)] = 1
        marks[0] = 1
        seg = np.cumsum(marks) - 1
        first = np.flatnonzero(marks)[seg]
    lags = rows[:, None] - np.arange(window)[None, :]
    return np.maximum(lags, first[:, None])


def group_matrix(
    group: Group, state: np.ndarray, starts: np.ndarray | None, extras: np.ndarray | None = None,
    dtype: Any = np.float32,
) -> np.ndarray:
    """(N, width) feature matrix of one group: the window flattened newest sample first, then the
    group's columns of the derived inputs E (`derived`)."""
    out: np.ndarray = np.empty((state.shape[0], group.width), dtype)
    w = len(group.base)
    if group.window == 1:
        out[:, :w] = state[:, group.base]
    else:
        idx = history_index(state.shape[0], starts, group.window)
        base: np.ndarray = state[:, group.base].astype(dtype, copy=False)
        for k in range(group.window):
            out[:, k * w:(k + 1) * w] = base[idx[:, k]]
    if group.extra:
        if extras is None:
            raise ValueError("this feature group needs the derived inputs (see `derived`)")
        out[:, group.window_width:] = extras[:, group.extra]
    return out



def group_matrices(spec: FeatureSpec, group_list: list[Group], q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                   starts: np.ndarray | None, physics: np.ndarray | None = None,
                   ) -> Iterator[tuple[int, Group, np.ndarray]]:
    """(index, group, its feature matrix) for every group of a learner, built one at a time as asked
    for: the inputs every learner (trees or networks) fits and predicts on."""
    q, dq, ddq = np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq)
    state = state_matrix(q, dq, ddq)
    extras = derived(spec, q, dq, physics)
    for i, g in enumerate(group_list):
        yield i, g, group_matrix(g, state, starts, extras)

class WindowBuffer:
    """Per-sample history for online prediction: push one state, gather every group's window features
    at once (groups concatenated; the physics `extra` columns are not part of it).

    Equivalent to `group_matrix` on the stream seen so far (the first sample fills the history, as a
    trajectory's first rows do in batch).  The gather is one fancy index into a ring buffer.
    """

    def __init__(self, groups_: list[Group], n: int) -> None:
        self.n = n
        self.window = max(g.window for g in groups_)
        self.width = 3 * n
        self.buf = np.zeros((self.window, self.width), np.float32)
        self.flat = self.buf.reshape(-1)
        self.head = -1
        offsets = []
        for g in groups_:
            for k in range(g.window):
                for c in g.base:
                    offsets.append((k, c))
        lag = np.array([o[0] for o in offsets], np.int64)
        col = np.array([o[1] for o in offsets], np.int64)
        # For every head position, the flat indices of all features (groups concatenated).
        self.index = np.stack([((h - lag) % self.window) * self.width + col for h in range(self.window)])
        self.size = len(offsets)

    def reset(self) -> None:
        self.head = -1

    def push(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """Add the newest sample; return the concatenated feature vector (float32)."""
        n = self.n
        if self.head < 0:
            self.head = 0
            self.buf[:, :n] = q
            self.buf[:, n:2 * n] = dq
            self.buf[:, 2 * n:] = ddq
        else:
            self.head = (self.head + 1) % self.window
            row = self.buf[self.head]
            row[:n] = q
            row[n:2 * n] = dq
            row[2 * n:] = ddq
        return self.flat[self.index[self.head]]
