"""Trajectories stacked for fitting (`Samples`), with their derivatives, and subsampled by whole moves."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cell.data.dataset import Trajectory
from cell.sensing.derivatives import CausalDerivatives, DerivativeMode, FilterConfig, zero_phase_derivatives
from drivers.errors import DataError


def derivatives(
    traj: Trajectory, mode: DerivativeMode = "zero_phase", cfg: FilterConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(dq, ddq) for one trajectory with the chosen filter."""
    if mode == "zero_phase":
        return zero_phase_derivatives(traj.t, traj.q, traj.dq, cfg)
    if mode == "causal":
        dt = float(np.median(np.diff(traj.t)))
        return CausalDerivatives(traj.n, dt, cfg).run(traj.q, traj.dq)
    raise ValueError(f"unknown derivative mode {mode!r} (zero_phase or causal)")


@dataclass
class Samples:
    """Trajectories stacked for fitting: (N, n) arrays and the row where each trajectory starts."""

    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    tau: np.ndarray
    starts: np.ndarray  # first row of each trajectory (windows never reach across one)
    names: list[str]
    segment: np.ndarray  # global segment id per row (trajectory-unique), for subsampling by whole moves
    mode: DerivativeMode = "zero_phase"
    period_s: float | None = None  # the trajectories' median sample period (windows and derivatives depend on it)

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def trajectory_slices(self) -> list[slice]:
        ends = np.concatenate([self.starts[1:], [len(self)]])
        return [slice(int(a), int(b)) for a, b in zip(self.starts, ends, strict=True)]

    def take_rows(self, rows: np.ndarray) -> Samples:
        """Rows (sorted) as a new Samples; a jump in row index starts a new trajectory."""
        rows = np.sort(np.asarray(rows, np.int64))
        new_start = np.ones(len(rows), bool)
        new_start[1:] = np.diff(rows) != 1
        starts_set = np.zeros(len(self), bool)
        starts_set[self.starts] = True
        new_start |= starts_set[rows]
        return Samples(
            q=self.q[rows], dq=self.dq[rows], ddq=self.ddq[rows], tau=self.tau[rows],
            starts=np.flatnonzero(new_start), names=self.names, segment=self.segment[rows], mode=self.mode,
            period_s=self.period_s,
        )


def stack(trajs: Sequence[Trajectory], mode: DerivativeMode = "zero_phase", cfg: FilterConfig | None = None) -> Samples:
    if not trajs:
        raise DataError("no trajectories to stack (empty dataset split)")
    qs, vs, accs, taus, segs, starts = [], [], [], [], [], []
    row = 0
    seg_base = 0
    for tr in trajs:
        v, a = derivatives(tr, mode, cfg)
        qs.append(tr.q)
        vs.append(v)
        accs.append(a)
        taus.append(tr.tau)
        seg = tr.segment if tr.segment is not None else np.zeros(len(tr), np.int64)
        _, inv = np.unique(seg, return_inverse=True)
        segs.append(inv + seg_base)
        seg_base += int(inv.max()) + 1
        starts.append(row)
        row += len(tr)
    return Samples(
        q=np.concatenate(qs), dq=np.concatenate(vs), ddq=np.concatenate(accs), tau=np.concatenate(taus),
        starts=np.asarray(starts, np.int64), names=[t.name for t in trajs], segment=np.concatenate(segs), mode=mode,
        period_s=float(np.median(np.concatenate([np.diff(tr.t) for tr in trajs]))) if row > len(trajs) else None,
    )


def subsample_segments(s: Samples, n_samples: int, seed: int = 0) -> Samples:
    """About `n_samples` rows made of whole segments (moves) drawn at random: a shorter collection
    of the same family, not a random scatter of rows (which would flatter small training sets)."""
    if n_samples >= len(s):
        return s
    rng = np.random.default_rng(seed)
    ids, counts = np.unique(s.segment, return_counts=True)
    order = rng.permutation(len(ids))
    total = np.cumsum(counts[order])
    k = int(np.searchsorted(total, n_samples)) + 1
    chosen = ids[order[:k]]
    rows = np.flatnonzero(np.isin(s.segment, chosen))
    return s.take_rows(rows[:n_samples])  # the last segment is cut so the count is never exceeded


def holdout_segments(s: Samples, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """(training rows, validation rows): whole segments (moves) held out for early stopping, since
    neighbouring rows are nearly identical and a row-wise split would validate on the training data.
    No validation rows (None) for fraction 0 or fewer than 5 segments."""
    if fraction <= 0:
        return np.arange(len(s)), None
    ids = np.unique(s.segment)
    if len(ids) < 5:
        return np.arange(len(s)), None
    rng = np.random.default_rng(seed)
    val_ids = rng.choice(ids, max(1, int(round(fraction * len(ids)))), replace=False)
    val = np.isin(s.segment, val_ids)
    return np.flatnonzero(~val), np.flatnonzero(val)
