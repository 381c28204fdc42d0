"""Velocities and accelerations from logged joint positions: zero-phase (offline training and evaluation) or
causal (`CausalDerivatives`, the very class the controller runs once per sample)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import signal

from drivers.configio import join, require

DerivativeMode = Literal["zero_phase", "causal"]


@dataclass
class FilterConfig:
    """How velocities and accelerations are derived from the logged samples."""

    cutoff_hz: float = 20.0  # Butterworth low-pass corner
    order: int = 2  # filter order (zero-phase applies it twice: forward and backward)

    def validate(self, where: str) -> None:
        require(self.cutoff_hz > 0, join(where, "cutoff_hz"), f"must be > 0, got {self.cutoff_hz}")
        require(1 <= self.order <= 8, join(where, "order"), f"must lie in 1..8, got {self.order}")



def butter(cfg: FilterConfig, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The Butterworth low-pass (b, a) of `cfg` for sample period `dt`."""
    nyq = 0.5 / dt
    wn = min(cfg.cutoff_hz / nyq, 0.99)
    b, a = signal.butter(cfg.order, wn)
    return np.asarray(b), np.asarray(a)


def zero_phase_derivatives(
    t: np.ndarray, q: np.ndarray, dq: np.ndarray | None, cfg: FilterConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(dq, ddq) without phase lag, for offline use.

    dq: the measured one when given, else the central difference of the low-passed q.
    ddq: the central difference of dq, low-passed forward and backward (filtfilt).
    """
    cfg = cfg or FilterConfig()
    dt = float(np.median(np.diff(t)))
    b, a = butter(cfg, dt)
    padlen = 3 * max(len(a), len(b))
    can_filter = len(t) > padlen

    def lowpass(x: np.ndarray) -> np.ndarray:
        return signal.filtfilt(b, a, x, axis=0) if can_filter else x

    v = np.asarray(dq, float) if dq is not None else np.gradient(lowpass(q), t, axis=0)
    acc = lowpass(np.gradient(v, t, axis=0))
    return v, acc


class CausalDerivatives:
    """Per-sample velocity/acceleration estimate for online use (the controller runs exactly this).

    dq: the measured one when given, else the backward difference of q, low-passed;
    ddq: the backward difference of dq, low-passed (Butterworth, direct form II transposed).
    The first sample reports zero acceleration (and zero velocity when dq is not measured).
    """

    def __init__(self, n: int, dt: float, cfg: FilterConfig | None = None) -> None:
        self.cfg = cfg or FilterConfig()
        self.n = n
        self.dt = dt
        self.b, self.a = butter(self.cfg, dt)
        self.b = self.b / self.a[0]
        self.a = self.a / self.a[0]
        self.reset()

    def reset(self) -> None:
        order = len(self.a) - 1
        self._zv = np.zeros((order, self.n))
        self._za = np.zeros((order, self.n))
        self._q_prev: np.ndarray | None = None
        self._v_prev: np.ndarray | None = None

    def _filter(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        b, a = self.b, self.a
        y = b[0] * x + z[0]
        for i in range(len(z) - 1):
            z[i] = b[i + 1] * x + z[i + 1] - a[i + 1] * y
        z[-1] = b[-1] * x - a[-1] * y
        return y

    def _prime(self, z: np.ndarray, x: np.ndarray) -> None:
        """Start the filter in steady state at input x (no start-up transient)."""
        zi = signal.lfilter_zi(self.b, self.a)
        z[:] = zi[:, None] * x[None, :]

    def step(self, q: np.ndarray, dq: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(q, float)
        if dq is None:
            if self._q_prev is None:
                raw_v = np.zeros(self.n)
                self._prime(self._zv, raw_v)
            else:
                raw_v = (q - self._q_prev) / self.dt
            v = self._filter(raw_v, self._zv)
        else:
            v = np.asarray(dq, float)
        self._q_prev = q
        if self._v_prev is None:
            raw_a = np.zeros(self.n)
            self._prime(self._za, raw_a)
        else:
            raw_a = (v - self._v_prev) / self.dt
        self._v_prev = v
        return v, self._filter(raw_a, self._za)

    def run(self, q: np.ndarray, dq: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The same per-sample pipeline over a whole recording (N, n) -> (dq, ddq)."""
        self.reset()
        out_v = np.empty_like(q, dtype=float)
        out_a = np.empty_like(q, dtype=float)
        for k in range(q.shape[0]):
            out_v[k], out_a[k] = self.step(q[k], None if dq is None else dq[k])
        return out_v, out_a
