"""The peg's geometry in the hole frame: its bottom rim's lowest and highest points, tilted entry poses, the
wall pivot, tilts, and reference paths along straight segments."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from cell.control.trajectory import TOOL_DOWN
from tasks.peg.config import PegConfig

EZ = np.array([0.0, 0.0, 1.0])
DOWN = -EZ

Segment = tuple[pin.SE3, pin.SE3, float]  # (from, to, duration [s])


def rim_points(pose: pin.SE3, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest points of the peg's bottom rim (the TCP is the face centre, tool z along the peg)."""
    z = pose.rotation[:, 2]
    # World down, projected onto the face plane (down . z is -z_z; sqrt(w.w) is numpy's norm of a vector).
    w = DOWN - float(-z[2]) * z
    n = math.sqrt(w.dot(w))
    if n < 1e-9:  # upright: every rim point is as low as the centre
        return pose.translation.copy(), pose.translation.copy()
    w /= n
    return pose.translation + radius * w, pose.translation - radius * w


def entry_pose(cfg: PegConfig, hole_top: float, lead: np.ndarray, low_xy: np.ndarray,
               height: float | None = None) -> pin.SE3:
    """Tilted pose, lowest rim point over `low_xy` and `height` (default `approach_height_m`) above the
    mouth at `hole_top`, leading along `lead`."""
    a = math.radians(cfg.entry_tilt_deg)
    # Tilt the downward peg axis away from the lead: the rim point on the lead side is then the lowest.
    axis = np.cross(EZ, lead)
    axis /= np.linalg.norm(axis)
    pose = pin.SE3(pin.exp3(axis * a) @ TOOL_DOWN, np.zeros(3))
    low, _ = rim_points(pose, cfg.peg_diameter_m / 2)
    h = cfg.approach_height_m if height is None else height
    pose.translation = np.array([*low_xy, hole_top + h]) - low
    return pose


def wall_pivot(tip: pin.SE3, radius: float, hole_top: float) -> np.ndarray:
    """The point at the mouth's height on the peg's lead-side generator (through its lowest rim point): leaning
    on the wall, the peg rotates upright about it."""
    low, _ = rim_points(tip, radius)
    up = -tip.rotation[:, 2]
    s = (hole_top - low[2]) / max(up[2], 1e-6)
    return low + s * up


def tilt_angle(R: np.ndarray) -> float:
    """Angle of the peg axis from vertical [rad]."""
    return math.acos(float(np.clip(-R[2, 2], -1.0, 1.0)))


def tilt_of(R: np.ndarray) -> np.ndarray:
    """Tilt of the peg axis from vertical as small rotations about base x and y [rad]."""
    z = R[:, 2]  # peg axis, pointing down when vertical
    return np.array([math.atan2(z[1], -z[2]), math.atan2(-z[0], -z[2])])


def on_segments(segments: list[Segment], t: float) -> tuple[pin.SE3, bool]:
    """The pose at time t along `segments` (smoothstep on each), and whether t is past their end."""
    for start, end, duration in segments:
        if t < duration:
            s = t / duration
            return pin.SE3.Interpolate(start, end, s * s * (3 - 2 * s)), False
        t -= duration
    return segments[-1][1].copy(), True
