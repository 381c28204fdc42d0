"""Motion primitives: quintic rest-to-rest joint moves, constant-speed paths with ramps, tool-down poses."""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import pinocchio as pin

# Tool z along world -z, tool x along world x: the pose for working on a horizontal surface.
TOOL_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])

QUINTIC_PEAK_SPEED = 1.875  # max of d/ds of 10s^3 - 15s^4 + 6s^5
QUINTIC_PEAK_ACCEL = 5.7735  # max of d2/ds2 of the same

Progress = TypeVar("Progress", np.ndarray, float)


def tool_down_pose(position: np.ndarray) -> pin.SE3:
    return pin.SE3(TOOL_DOWN.copy(), np.asarray(position, float).copy())


def quintic_blend(s: Progress) -> Progress:
    """The rest-to-rest quintic 10s^3 - 15s^4 + 6s^5: 0 -> 1 over s in [0, 1], at rest at both ends."""
    return s**3 * (10 - 15 * s + 6 * s**2)


def quintic_samples(q0: np.ndarray, q1: np.ndarray, duration: float, dt: float, rest_s: float = 0.0) -> np.ndarray:
    """A quintic move from q0 to q1 in `duration`, sampled every dt (from one period after the start), then
    held at q1 for `rest_s`."""
    k = int(np.ceil(duration / dt))
    s = np.minimum(np.arange(1, k + 1) * dt / duration, 1.0)[:, None]
    q = q0 + (q1 - q0) * quintic_blend(s)
    hold = int(round(rest_s / dt))
    if hold:
        q = np.vstack([q, np.repeat(q1[None, :], hold, axis=0)])
    return q


class JointMove:
    """Quintic (rest-to-rest) joint interpolation whose peak speed respects `speed` on every joint."""

    def __init__(self, q0: np.ndarray, q1: np.ndarray, speed: np.ndarray, min_duration: float = 0.2) -> None:
        self.q0 = np.asarray(q0, float)
        self.q1 = np.asarray(q1, float)
        span = np.abs(self.q1 - self.q0)
        self.duration = max(min_duration, float(np.max(QUINTIC_PEAK_SPEED * span / np.asarray(speed, float))))

    def at(self, t: float) -> np.ndarray:
        s = min(max(t / self.duration, 0.0), 1.0)
        return self.q0 + (self.q1 - self.q0) * quintic_blend(s)


class PathProfile:
    """A polyline traversed at constant speed with acceleration ramps at both ends (trapezoid in s)."""

    def __init__(self, points: np.ndarray, speed: float, accel: float) -> None:
        self.points = np.asarray(points, float)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.cum[-1])
        t_ramp = speed / accel
        if accel * t_ramp**2 > self.length:  # too short to reach full speed: triangular profile
            t_ramp = float(np.sqrt(self.length / accel))
            speed = accel * t_ramp
        self.speed, self.accel, self.t_ramp = speed, accel, t_ramp
        self.duration = 2 * t_ramp + (self.length - accel * t_ramp**2) / speed

    def s_at(self, t: float) -> float:
        a, v, tr = self.accel, self.speed, self.t_ramp
        if t <= 0:
            return 0.0
        if t < tr:
            return 0.5 * a * t**2
        if t < self.duration - tr:
            return 0.5 * a * tr**2 + v * (t - tr)
        if t < self.duration:
            return self.length - 0.5 * a * (self.duration - t) ** 2
        return self.length

    def at(self, t: float) -> tuple[np.ndarray, bool]:
        """Point at time t and whether the path is finished."""
        s = self.s_at(t)
        i = int(np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.points) - 2))
        seg_len = self.cum[i + 1] - self.cum[i]
        u = 0.0 if seg_len == 0 else (s - self.cum[i]) / seg_len
        return self.points[i] + u * (self.points[i + 1] - self.points[i]), t >= self.duration
