"""Where a hybrid's learned residual is trusted, and how uncertain the hybrid is: training coverage and residual levels.

Per learned joint j the training data's occupancy of (q_j, q'_j, q''_j) is counted on a grid (bins
between the 0.5 and 99.5 percentiles).  The learned residual is weighted by

  w_j = min(1, count / min_count) * min(1, |q'_j| / stick_speed)

so a query outside the training data's coverage (an empty or thin cell, or outside the grid) falls
back to the physics part, and so does a joint in its sticking regime: at rest the friction torque is
anything within the static band, set by the motion's history, not by the state, and a residual
learned there memorises the training runs' particular rests (on the UR10e logs the joint-1 residual
learned at rest was -4 N m where the joint-wise runs held +1 to +6.5 N m).

The uncertainty (one standard deviation of the torque error, N m) comes from the residual levels
measured on held-out training segments, binned by joint speed: the hybrid's where w = 1, the physics
part's where w = 0, and in between sqrt(w s_h^2 + (1 - w) s_p^2) (a hybrid that does not blend, H2
or H3, keeps its own level s_h).  In the sticking regime it is at
least the static band's spread, f_c / sqrt(3) (a torque anywhere within +-f_c).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.configio import join, require

SPEED_EDGES = np.array([0.0, 0.002, 0.01, 0.03, 0.1, 0.3, 1.0, np.inf])  # |q'| bins [rad/s] of the levels


def speed_bin(speed: np.ndarray) -> np.ndarray:
    """The level bin of each |q'| in `speed` [rad/s] (0 .. len(SPEED_EDGES) - 2)."""
    # (Array methods rather than numpy's dispatching functions: one sample's arithmetic costs less than them.)
    return np.minimum(np.maximum(SPEED_EDGES.searchsorted(speed, side="right") - 1, 0), len(SPEED_EDGES) - 2)


@dataclass
class Coverage:
    """Coverage grid and residual levels of a hybrid's learned joints (see the module docstring)."""

    joints: np.ndarray  # (m,) learned joint indices
    lo: np.ndarray  # (m, 3) grid lower corner in (q, dq, ddq)
    width: np.ndarray  # (m, 3) cell size
    counts: np.ndarray  # (m, B, B, B) training samples per cell
    min_count: float  # a cell with fewer samples is partly trusted (0: coverage not used)
    stick_speed: float  # rad/s; below it the learned residual fades out (0: never)
    sigma_hybrid: np.ndarray  # (n, S) RMS residual of the hybrid by speed bin
    sigma_physics: np.ndarray  # (n, S) RMS residual of the physics part by speed bin
    static_band: np.ndarray  # (n,) f_c of the physics part [N m]
    # Whether predictions blend toward the physics part by the trust (H1, whose physics part is the
    # whole P2); H2 and H3 keep their learned part (it carries physics of its own) and only report.
    blend: bool = True
    # The same levels binned by the arm's fastest joint instead of the joint's own speed (None: a model saved
    # before they existed): a slow joint's error while another one is fast (coupling, velocity products).
    sigma_hybrid_arm: np.ndarray | None = None
    sigma_physics_arm: np.ndarray | None = None

    @property
    def bins(self) -> int:
        return int(self.counts.shape[1])

    @property
    def gates(self) -> bool:
        """Whether the trust can be below 1 anywhere (coverage or sticking in use)."""
        return self.min_count > 0 or self.stick_speed > 0

    # --------------------------------------------------------------------------------------- fit
    @staticmethod
    def fit(joints: list[int], q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, residual_hybrid: np.ndarray,
            residual_physics: np.ndarray, static_band: np.ndarray, bins: int = 10, min_count: float = 10.0,
            stick_speed: float = 0.0, level_rows: np.ndarray | None = None, blend: bool = True,
            own_level_rows: np.ndarray | None = None) -> Coverage:
        """Occupancy from all rows; residual levels from `level_rows` (held-out rows) when given, the levels by
        the joint's own speed from `own_level_rows` when given (the held-out rows of the regime the residual
        was fitted in: beyond it the levels by the arm's fastest joint hold the fast rows' errors)."""
        js = np.asarray(joints, np.int64)
        x = np.stack([q[:, js], dq[:, js], ddq[:, js]], axis=-1)  # (N, m, 3)
        lo = np.percentile(x, 0.5, axis=0)
        hi = np.percentile(x, 99.5, axis=0)
        width = np.maximum(hi - lo, 1e-9) / bins
        counts = np.zeros((len(js), bins, bins, bins), np.int32)
        idx = np.floor((x - lo) / width).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < bins), axis=-1)
        for k in range(len(js)):
            np.add.at(counts[k], tuple(idx[inside[:, k], k].T), 1)
        rows = np.arange(len(q)) if level_rows is None or len(level_rows) == 0 else np.asarray(level_rows)
        cov = Coverage(js, lo, width, counts, float(min_count), float(stick_speed), np.zeros(0), np.zeros(0),
                       np.asarray(static_band, float), blend)
        own = rows if own_level_rows is None or len(own_level_rows) == 0 else np.asarray(own_level_rows)
        cov.sigma_hybrid = _levels(dq[own], residual_hybrid[own])
        cov.sigma_physics = _levels(dq[own], residual_physics[own])
        arm = np.repeat(np.abs(dq[rows]).max(axis=1, keepdims=True), dq.shape[1], axis=1)
        cov.sigma_hybrid_arm = _levels(arm, residual_hybrid[rows])
        cov.sigma_physics_arm = _levels(arm, residual_physics[rows])
        return cov

    # --------------------------------------------------------------------------------------- use
    def weight(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """(N, n) trust in the learned residual, 0..1 (1 on joints that are not learned: nothing to weigh)."""
        q, dq, ddq = np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq)
        w = np.ones(q.shape)
        js = self.joints
        if self.min_count > 0:
            x = np.stack([q[:, js], dq[:, js], ddq[:, js]], axis=-1)
            idx = np.floor((x - self.lo) / self.width).astype(np.int64)
            inside = np.all((idx >= 0) & (idx < self.bins), axis=-1)
            c = np.zeros(inside.shape)
            for k in range(len(js)):
                ok = inside[:, k]
                c[ok, k] = self.counts[k][tuple(idx[ok, k].T)]
            w[:, js] = np.minimum(1.0, c / self.min_count)
        if self.stick_speed > 0:
            w[:, js] *= np.minimum(1.0, np.abs(dq[:, js]) / self.stick_speed)
        return w

    def weight_one(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, min_count: float | None = None,
                   stick: bool = True) -> np.ndarray:
        """`weight` of one sample (n,), without batch overhead (the served path); `min_count` in place of
        the model's own (the collision detector asks for coverage where the model does not gate), and
        without the sticking fade when `stick` is false."""
        js = self.joints
        w = np.ones(len(q))
        min_count = self.min_count if min_count is None else min_count
        if min_count > 0:
            # (Array methods, not numpy's functions: this runs every control period, where their dispatch costs
            # as much as the arithmetic.)
            x = np.array((q[js], dq[js], ddq[js])).T
            idx = np.floor((x - self.lo) / self.width).astype(np.int64)
            last = self.counts.shape[1] - 1
            inside = ((idx >= 0) & (idx <= last)).all(axis=-1)
            # Every joint's cell read at its index held on the grid, then zeroed where it lies outside.
            at = np.minimum(np.maximum(idx, 0), last)
            c = self.counts[np.arange(len(js)), at[:, 0], at[:, 1], at[:, 2]] * inside
            w[js] = np.minimum(1.0, c / min_count)
        if stick and self.stick_speed > 0:
            w[js] *= np.minimum(1.0, np.abs(dq[js]) / self.stick_speed)
        return w

    def sigma(self, dq: np.ndarray, w: np.ndarray) -> np.ndarray:
        """One-sigma torque uncertainty [N m] for speeds `dq` and trust `w` (see the module docstring): (n,) for
        one sample (the served path, every control period), (N, n) for N."""
        b = speed_bin(np.abs(dq))
        cols = np.arange(dq.shape[-1])
        return self._blended(self.sigma_hybrid[cols, b], self.sigma_physics[cols, b], w, dq)

    def sigma_arm(self, dq: np.ndarray, w: np.ndarray) -> np.ndarray | None:
        """The levels by the arm's fastest joint (`sigma_hybrid_arm`) at speeds `dq`, trust `w`: (n,) for one
        sample (the detector's, every control period), (N, n) for N; None for a model without them."""
        if self.sigma_hybrid_arm is None or self.sigma_physics_arm is None:
            return None
        fastest = np.abs(dq).max(axis=-1)
        b = speed_bin(fastest)
        # One bin a sample, every joint's level in it.
        return self._blended(self.sigma_hybrid_arm[:, b].T, self.sigma_physics_arm[:, b].T, w, dq)

    def _blended(self, sh: np.ndarray, sp: np.ndarray, w: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """The hybrid's level `sh` blended with the physics part's `sp` by the trust `w`, floored at the static
        band's spread where a joint sticks (its own speed `dq`)."""
        # Without blending the prediction keeps its whole learned part: its own level, the trust only reported.
        s = np.sqrt(w * sh**2 + (1.0 - w) * sp**2) if self.blend else sh
        if self.stick_speed > 0:
            sticking = np.abs(dq) < self.stick_speed
            s = np.where(sticking, np.maximum(s, self.static_band / np.sqrt(3.0)), s)
        return s

    # --------------------------------------------------------------------------------------- save
    def to_dict(self) -> dict[str, Any]:
        return {"joints": self.joints.tolist(), "lo": self.lo.tolist(), "width": self.width.tolist(),
                "counts": self.counts.tolist(), "min_count": self.min_count, "stick_speed": self.stick_speed,
                "sigma_hybrid": self.sigma_hybrid.tolist(), "sigma_physics": self.sigma_physics.tolist(),
                "static_band": self.static_band.tolist(), "blend": self.blend,
                "speed_edges": SPEED_EDGES[1:-1].tolist(),
                **({"sigma_hybrid_arm": self.sigma_hybrid_arm.tolist(),
                    "sigma_physics_arm": self.sigma_physics_arm.tolist()}
                   if self.sigma_hybrid_arm is not None and self.sigma_physics_arm is not None else {})}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Coverage:
        js = np.asarray(d["joints"], np.int64)
        cov = Coverage(js, np.asarray(d["lo"], float).reshape(len(js), 3),
                       np.asarray(d["width"], float).reshape(len(js), 3), np.asarray(d["counts"], np.int32),
                       float(d["min_count"]), float(d["stick_speed"]), np.asarray(d["sigma_hybrid"], float),
                       np.asarray(d["sigma_physics"], float), np.asarray(d["static_band"], float),
                       bool(d.get("blend", True)))
        if cov.counts.ndim != 4 or cov.counts.shape[0] != len(js) or cov.sigma_hybrid.shape[1] != len(SPEED_EDGES) - 1:
            raise ValueError("coverage arrays have inconsistent shapes")
        if "sigma_hybrid_arm" in d and "sigma_physics_arm" in d:
            cov.sigma_hybrid_arm = np.asarray(d["sigma_hybrid_arm"], float)
            cov.sigma_physics_arm = np.asarray(d["sigma_physics_arm"], float)
            if (cov.sigma_hybrid_arm.shape != cov.sigma_hybrid.shape
                    or cov.sigma_physics_arm.shape != cov.sigma_physics.shape):
                raise ValueError("coverage arrays have inconsistent shapes")
        return cov


def _levels(dq: np.ndarray, residual: np.ndarray, min_rows: int = 30) -> np.ndarray:
    """(n, S) RMS of `residual` per joint and |q'| bin; a bin with fewer than `min_rows` rows takes the
    joint's overall RMS."""
    n = dq.shape[1]
    S = len(SPEED_EDGES) - 1
    overall = np.sqrt(np.nanmean(residual**2, axis=0))
    out = np.tile(overall[:, None], (1, S))
    b = speed_bin(np.abs(dq))
    for j in range(n):
        for k in range(S):
            m = b[:, j] == k
            if m.sum() >= min_rows:
                out[j, k] = np.sqrt(np.nanmean(residual[m, j] ** 2))
    return np.nan_to_num(out, nan=0.0)


@dataclass
class CoverageConfig:
    """How a hybrid's learned residual is trusted (robot.yaml `learning`; module docstring)."""

    min_count: float = 0.0  # training samples a grid cell needs for full trust (0: coverage not used)
    stick_speed: float = 0.0  # rad/s; the learned residual fades out below it (0: never)
    bins: int = 10  # grid cells per axis of (q_j, q'_j, q''_j)
    # The motion regime a hybrid is fitted in: the moves whose fastest joint stays within fit_max_speed [rad/s]
    # and fit_max_accel [rad/s^2] (0: no limit).  The moves beyond set only its residual levels there
    # (learned.py `regime_rows`).
    fit_max_speed: float = 0.0
    fit_max_accel: float = 0.0

    def validate(self, where: str) -> None:
        require(self.fit_max_speed >= 0, join(where, "fit_max_speed"), f"must be >= 0 rad/s, got {self.fit_max_speed}")
        require(self.fit_max_accel >= 0, join(where, "fit_max_accel"),
                f"must be >= 0 rad/s^2, got {self.fit_max_accel}")
        require(0 <= self.min_count <= 1e6, join(where, "min_count"), f"must lie in [0, 1e6], got {self.min_count}")
        require(0 <= self.stick_speed <= 1.0, join(where, "stick_speed"),
                f"must lie in [0, 1] rad/s, got {self.stick_speed}")
        require(2 <= self.bins <= 50, join(where, "bins"), f"must lie in 2..50, got {self.bins}")
