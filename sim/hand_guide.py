"""A simulated operator's hand for hand guiding: a spring-damper that pulls the tool toward a target moving
along a path, applied every physics step as the plant's external wrench (world frame, at the TCP).  Then it
lets go, and at the end pushes hard (above the guiding limit) to check that the arm stops."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cell.control.trajectory import PathProfile
from sim.plant import Plant


@dataclass
class HandScript:
    """What the hand does, in plant time [s] from when it grabs the tool."""

    path: list[list[float]]  # polyline offsets from the tool's position at the grab [m]
    speed_mps: float = 0.1
    accel_mps2: float = 0.5
    pause_s: float = 0.0  # rest at each inner vertex (an operator placing the tool: what --teach records)
    settle_s: float = 1.5  # after the path: hold the end point this long, then let go
    release_s: float = 10.0  # let go this long
    push_n: float | None = None  # then push this hard along `push_dir` (None: no push)
    push_dir: list[float] = field(default_factory=lambda: [0.0, 0.0, -1.0])
    push_ramp_s: float = 0.3
    push_hold_s: float = 1.0


class SimHand:
    """F = K (target - tcp) + D (v_target - v_tcp) on the tool while it holds it; nothing when released.

    The defaults are a relaxed human arm holding a tool: endpoint stiffness is a few hundred to about 1000 N/m
    and damping a few tens of N s/m (measured arm impedance); 800 N/m and 40 N s/m sit in that range, so the
    hand follows its path within a centimetre at the 8-12 N a guided arm asks.  It is not a position servo: a
    stiffer hand would hide the admittance loop's errors in the path figures.  Left out: the hand's own mass
    (about 1-2 kg), which the tool would carry and the virtual sensor would read as inertia."""

    def __init__(self, plant: Plant, script: HandScript, grab_at_s: float, stiffness: float = 800.0,
                 damping: float = 40.0) -> None:
        self.plant = plant
        self.script = script
        self.grab_at = grab_at_s
        self.k = stiffness
        self.d = damping
        pts = np.asarray(script.path, float)
        # The path as legs between pauses: one trapezoid profile per leg.
        self.legs = [PathProfile(pts[i:i + 2], script.speed_mps, script.accel_mps2) for i in range(len(pts) - 1)] \
            if script.pause_s > 0 else [PathProfile(pts, script.speed_mps, script.accel_mps2)]
        self.leg_starts = np.cumsum([0.0] + [leg.duration + script.pause_s for leg in self.legs])
        self.path_end_s = float(self.leg_starts[-1] - script.pause_s)
        self.release_at = self.path_end_s + script.settle_s
        self.push_at = self.release_at + script.release_s
        self.end_s = self.push_at + (script.push_ramp_s + script.push_hold_s if script.push_n else 0.0)
        self.origin: np.ndarray | None = None
        self._prev_tcp: np.ndarray | None = None
        self.samples: list[tuple[float, str, np.ndarray, np.ndarray, np.ndarray]] = []  # t, phase, tcp, target, F

    def offset_at(self, t: float) -> np.ndarray:
        """The target's offset from the grab point, `t` s after the grab."""
        for leg, t0 in zip(self.legs, self.leg_starts, strict=False):
            if t < t0 + leg.duration + self.script.pause_s or leg is self.legs[-1]:
                return leg.at(max(0.0, t - t0))[0]
        return np.asarray(self.script.path[-1], float)

    def update(self) -> None:
        """Called after every physics step (Plant.after_physics_step): sets the next step's wrench."""
        p = self.plant
        t = p.t - self.grab_at
        tcp, _ = p.tool_pose()
        h = p.dt / p.substeps
        v = (tcp - self._prev_tcp) / h if self._prev_tcp is not None else np.zeros(3)
        self._prev_tcp = tcp
        if t < 0:
            return
        if self.origin is None:
            self.origin = tcp.copy()
        s = self.script
        if t < self.release_at:
            target = self.origin + self.offset_at(t)
            v_target = (self.offset_at(t + 1e-3) - self.offset_at(t)) / 1e-3
            force = self.k * (target - tcp) + self.d * (v_target - v)
            phase = "guide" if t < self.path_end_s else "settle"
        elif t < self.push_at or not s.push_n:
            target, force, phase = tcp, np.zeros(3), "released"
        else:
            a = min(1.0, (t - self.push_at) / s.push_ramp_s)
            u = np.asarray(s.push_dir, float) / np.linalg.norm(s.push_dir)
            target, force, phase = tcp, a * s.push_n * u, "push"
        p.external_wrench = np.concatenate([force, np.zeros(3)]) if np.any(force) else None
        self.samples.append((t, phase, tcp, target, force))

    def path_error(self, point: np.ndarray) -> float:
        """Distance from `point` to the hand's path (the polyline, placed at the grab point) [m]."""
        assert self.origin is not None
        pts = self.origin + np.asarray(self.script.path, float)
        best = np.inf
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            ab = b - a
            u = float(np.clip((point - a) @ ab / (ab @ ab), 0.0, 1.0))
            best = min(best, float(np.linalg.norm(point - (a + u * ab))))
        return best
