"""The survey of the fixture's face: touch it at a few points around the hole, fit its plane (the hole's axis
is its normal) and the frame the rest of the task works in."""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np
import pinocchio as pin

from tasks.peg.config import PegConfig
from tasks.peg.geometry import EZ, Segment, entry_pose, on_segments
from tasks.peg.touch import GuardedDescent

log = logging.getLogger(__name__)

# "moving" (lifting, descending, or on the way); "at_point" (arrived above the next touch point);
# "touched_all" (the last point touched: fit the face, then `lift_to` the approach start); "surveyed" (at the
# approach start, or no survey configured); "failed" (`reason` says why)
SurveyStep = Literal["moving", "at_point", "touched_all", "surveyed", "failed"]


def fit_face(points: list[np.ndarray], hole_xy: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares plane through the surveyed points: its upward normal, its tilt from level [deg], and its
    height over the nominal hole centre (the mouth's)."""
    p = np.array(points)
    centroid = p.mean(axis=0)
    n = np.linalg.svd(p - centroid)[2][-1]  # least-squares plane normal
    if n[2] < 0:
        n = -n
    tilt = math.degrees(math.acos(float(np.clip(n[2], -1.0, 1.0))))
    hx, hy = hole_xy
    z0 = float(centroid[2] - (n[0] * (hx - centroid[0]) + n[1] * (hy - centroid[1])) / n[2])
    return n, tilt, z0


def hole_frame(n: np.ndarray, hole_xy: np.ndarray, z0: float, hole_top: float) -> pin.SE3:
    """The hole frame T (world = T * hole frame) of a face with normal `n` through the mouth at height `z0`:
    in it, the face is level at the nominal `hole_top` through the nominal centre."""
    hx, hy = hole_xy
    ax = np.cross(EZ, n)
    s = float(np.linalg.norm(ax))
    R = pin.exp3(ax / s * math.asin(min(1.0, s))) if s > 1e-12 else np.eye(3)
    p_world, p_hole = np.array([hx, hy, z0]), np.array([hx, hy, hole_top])
    return pin.SE3(R, p_world - R @ p_hole)


class Survey:
    """The survey's touches: each step moves the task's reference (hole frame, in place or replaced: the
    returned pose is the reference) from the measured tip and Fz, with the task's guarded descent."""

    def __init__(self, cfg: PegConfig, dt: float, hole_xy: np.ndarray, hole_top: float, lead: np.ndarray) -> None:
        self.cfg = cfg
        self.dt = dt
        self.hole_top = hole_top
        self.lead = lead
        self.poses = [entry_pose(cfg, hole_top, lead, hole_xy + cfg.survey_radius_m * np.array(
            [math.cos(math.radians(a)), math.sin(math.radians(a))]), cfg.survey_height_m)
            for a in (cfg.survey_angles_deg if cfg.survey else [])]
        self.points: list[np.ndarray] = []
        self.k = 0  # the touch point surveyed next
        self.segments: list[Segment] = []
        self.seg_t = 0.0
        self.lifting = False
        self.lift_dir = EZ.copy()
        self.free_z = 0.0
        self.next_target = pin.SE3.Identity()
        self.reason = ""
        self.settle_until = 0.0  # arrived above a touch point: no descent or touch test before this time

    def step(self, fz: float, ref: pin.SE3, tip: pin.SE3, guard: GuardedDescent, t: float
             ) -> tuple[pin.SE3, SurveyStep]:
        c = self.cfg
        if self.lifting:
            # Off the touch point: raise the reference steadily until the measured tip has risen.  Stopped
            # on the face, the arm sticks (joint stiction: a small lift is held until the servo's integral
            # overcomes it, ~1 s, while the F/T sensor winds to -30 N); a steadily growing lift frees it in
            # ~0.1 s.  Only then move sideways: dragging a stuck peg loads it with a side moment.
            if tip.translation[2] >= self.free_z:
                self.lifting = False
                # Straight to the next start: it lies above the face wherever the face can be, and so does
                # every point of the straight path from here (the face is a plane).
                target = self.next_target
                d = float(np.linalg.norm(target.translation - ref.translation))
                self.segments = [(ref.copy(), target, max(0.05, 1.5 * d / c.survey_move_speed_mps))]
                self.seg_t = 0.0
                return ref, "moving"
            ref.translation += self.lift_dir * c.survey_lift_speed_mps * self.dt
            if float(ref.translation[2]) - self.free_z > c.survey_max_lift_m:
                self.reason = f"peg stuck on the fixture face at survey point {self.k - 1}"
                return ref, "failed"
            return ref, "moving"
        if self.segments:  # moving to the next touch point, or to the approach start
            self.seg_t += self.dt
            ref, arrived = on_segments(self.segments, self.seg_t)
            if not arrived:
                return ref, "moving"
            self.segments = []
            self.settle_until = t + c.survey_settle_s
            return ref, ("surveyed" if self.k >= len(self.poses) else "at_point")
        if self.k >= len(self.poses):  # no survey configured
            return ref, "surveyed"
        if t < self.settle_until:  # the stop's kick in the force reading decays (PegConfig.survey_settle_s)
            return ref, "moving"
        # Down onto the face; its height is where Fz first crossed the threshold (before the servo's lag
        # presses the point in).
        touch = guard.touch(fz, c.survey_cycles, ref, tip)
        if touch == "hold":
            return ref, "moving"
        if touch == "touch":
            guard.touching = 0
            self.points.append(guard.touch_point.copy())
            log.info("peg-in-hole: survey point %d at %s mm", self.k,
                     np.round(guard.touch_point * 1e3, 3).tolist())
            self.k += 1
            ref.translation[:] = tip.translation
            if self.k < len(self.poses):
                target = self.poses[self.k].copy()
                target.translation[2] -= self.drop(self.k)
                self.lift_to(target, tip)
                return ref, "moving"
            return ref, "touched_all"
        guard.descend(c.survey_speed_mps, t, ref, tip)
        if self.poses[self.k].translation[2] - ref.translation[2] > c.survey_depth_m:
            self.reason = (f"no fixture face within {c.survey_depth_m * 1e3:.1f} mm at survey point "
                           f"{self.k} (the hole is not where it is expected)")
            return ref, "failed"
        return ref, "moving"

    def lift_to(self, target: pin.SE3, tip: pin.SE3) -> None:
        """Lift off the touch point, then move to `target`."""
        # Up and back toward the peg's centre (straight up, the rim point stays caught longer).
        self.lift_dir = (EZ - self.lead) / math.sqrt(2.0)
        self.free_z = float(tip.translation[2]) + self.cfg.survey_lift_m
        self.next_target = target
        self.lifting = True

    def drop(self, k: int) -> float:
        """How much lower than the default start touch k can begin: a point opposite an earlier one lies
        about as far below the nominal mouth as that one lay above it (the face passes within ~0.1 mm of
        the nominal centre at the nominal height)."""
        c = self.cfg
        a = math.radians(c.survey_angles_deg[k])
        for j, p in enumerate(self.points):
            b = math.radians(c.survey_angles_deg[j])
            if abs(math.cos(a - b) + 1.0) < 0.02:  # opposite, within ~11 deg
                predicted = self.hole_top - (float(p[2]) - self.hole_top)
                start = self.hole_top + c.survey_height_m
                return max(0.0, start - (predicted + c.survey_predict_margin_m))
        return 0.0
