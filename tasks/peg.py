"""Sensorless peg-in-hole (paper 6.2): contact states from (Mx, My, Fz) and kinematic depth, impedance insertion."""

from __future__ import annotations

import collections
import enum
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from cell.impedance import DiscreteImpedance
from cell.loop import Command, Observation
from cell.robot import RobotModel
from cell.trajectory import TOOL_DOWN, JointMove
from tasks.base import MachineTask
from tasks.peg_config import PegConfig

log = logging.getLogger(__name__)

EZ = np.array([0.0, 0.0, 1.0])


class S(enum.Enum):
    MOVE_TO_START = "move_to_start"
    TARE = "tare"
    SURVEY = "survey"  # touch the fixture's top face at a few points: its normal is the hole's axis
    APPROACH = "approach"  # tilted peg, its lowest rim point over the nominal hole centre, down to contact
    PROBE = "probe"  # hold a light contact force and classify the contact
    BACK_OFF = "back_off"  # stuck outside: lift a little, tilt the lead another way and shift laterally
    SLIDE = "slide"  # stuck inside (lead edge in, face on the far rim): shift toward the lead side
    ROTATE = "rotate"  # stuck inside against the wall: rotate upright about the wall contact while pushing
    INSERT = "insert"  # push to the target depth under impedance control, rotating/shifting to null (Mx, My)
    REALIGN = "realign"  # stalled inside: lift a little and comply at a light force, then push again
    RELEASE = "release"
    RETRACT = "retract"
    DONE = "done"
    FAILED = "failed"


class Contact(enum.Enum):
    """The paper's contact scenarios (Fig. 13) as the task recognises them."""

    FREE = "free"
    STUCK_OUTSIDE = "stuck_outside"
    STUCK_INSIDE = "stuck_inside"
    ALIGNED = "aligned"


def classify(fz: float, mx: float, my: float, low_depth: float, high_depth: float, cfg: PegConfig) -> Contact:
    """The contact scenario from (Mx, My, Fz) and the kinematic depths of the peg's face below the mouth.

    `low_depth` / `high_depth`: how far the lowest / highest point of the peg's bottom rim is below the
    hole's mouth (forward kinematics of the measured joints).  Free: neither force nor moment.  Outside:
    touching with the whole face above the mouth (it rests on the rim or the plate).  Inside: the lead
    edge is in the hole and the peg touches with one side (its face still on the far rim, or a side
    moment).  Aligned: the whole face in the hole, pushing along the axis without a side load.
    """
    m = math.hypot(mx, my)
    if not (np.isfinite(fz) and np.isfinite(m)):  # a missing reading is never a contact outside
        return Contact.ALIGNED if high_depth >= cfg.engage_depth_m else Contact.FREE
    if fz < cfg.contact_force_n and m < cfg.contact_moment_nm:
        return Contact.FREE
    if low_depth < cfg.inside_depth_m:
        return Contact.STUCK_OUTSIDE
    if high_depth < cfg.engage_depth_m or m >= cfg.side_moment_nm:
        return Contact.STUCK_INSIDE
    return Contact.ALIGNED


def rim_points(pose: pin.SE3, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest points of the peg's bottom rim (the TCP is the face centre, tool z along the peg)."""
    z = pose.rotation[:, 2]
    w = -EZ - float(-EZ @ z) * z  # world down, projected onto the face plane
    n = float(np.linalg.norm(w))
    if n < 1e-9:  # upright: every rim point is as low as the centre
        return pose.translation.copy(), pose.translation.copy()
    w /= n
    return pose.translation + radius * w, pose.translation - radius * w


class PegInHoleTask(MachineTask):
    """The peg-in-hole strategy as a `transitions` machine; the wrench comes from the loop's force source.

    Survey first: the fixture's top face is square to the hole, so touching it with the tilted peg's lowest
    rim point at three points around the nominal hole and fitting a plane gives the hole's axis (measured
    within 0.07 deg on the bench's +-2 deg fixtures) and the mouth's height.  Everything after works in
    that hole frame (`T`: world = T * hole frame; the task's poses, depths and tilts are hole-frame), so a
    tilted hole is entered, centred and pushed into along its own axis.

    Entry (a classic for chamferless tight holes): the peg is tilted so the lowest point of its bottom
    rim leads; placed over the nominal hole centre, that point drops into the hole for any lateral error
    well inside the hole's radius, and the face comes to rest on the far rim (stuck inside, told by the
    kinematic depth and Fz, not by a rim moment).  The peg then slides toward the lead side until the
    wall blocks it, rotates upright about the wall contact, and is pushed in under the impedance law with
    rotational and lateral compliance to (Mx, My).
    """

    name = "peg-in-hole"

    def __init__(self, cfg: PegConfig, robot: RobotModel, hole_xy: np.ndarray, hole_top: float, dt: float,
                 q_home: np.ndarray) -> None:
        self.cfg = cfg
        self.robot = robot
        self.dt = dt
        self.hole_xy = np.asarray(cfg.hole_xy if cfg.hole_xy is not None else hole_xy, float)
        self.hole_top = hole_top
        self.radius = cfg.peg_diameter_m / 2
        super().__init__(S.MOVE_TO_START, [
            ("arrived", S.MOVE_TO_START, S.TARE),
            ("tared", S.TARE, S.SURVEY),
            ("surveyed", S.SURVEY, S.APPROACH),
            ("touched", S.APPROACH, S.PROBE),
            ("outside", S.PROBE, S.BACK_OFF),
            ("false_alarm", S.PROBE, S.APPROACH),
            ("backed_off", S.BACK_OFF, S.APPROACH),
            ("inside", S.PROBE, S.SLIDE),
            ("blocked", S.SLIDE, S.ROTATE),
            ("upright", S.ROTATE, S.INSERT),
            ("aligned", [S.APPROACH, S.PROBE, S.SLIDE], S.INSERT),
            ("stalled", S.INSERT, S.REALIGN),
            ("realigned", S.REALIGN, S.INSERT),
            ("inserted", S.INSERT, S.RELEASE),
            ("released", S.RELEASE, S.RETRACT),
            ("retracted", S.RETRACT, S.DONE),
        ])
        self.lead = np.array([math.cos(math.radians(cfg.lead_direction_deg)),
                              math.sin(math.radians(cfg.lead_direction_deg)), 0.0])
        # The hole frame: base-frame coordinates of a fixture whose face is level at `hole_top` through the
        # nominal centre.  Identity until the survey has measured the face; then world = T * hole frame.
        self.T = pin.SE3.Identity()
        self.Ti = pin.SE3.Identity()
        self.hole_tilt_deg: float | None = None
        self.start = self._entry_pose(self.lead, self.hole_xy)  # approach start, hole frame
        self._survey_poses = [self._entry_pose(self.lead, self.hole_xy + cfg.survey_radius_m * np.array(
            [math.cos(math.radians(a)), math.sin(math.radians(a))]), cfg.survey_height_m)
            for a in (cfg.survey_angles_deg if cfg.survey else [])]
        self._survey_points: list[np.ndarray] = []
        first = self._survey_poses[0] if self._survey_poses else self.start
        q_start, ok = robot.ik(first, q_home)
        if not ok:
            raise ValueError(f"peg start pose {first.translation.round(3).tolist()} is not reachable")
        for pose in self._survey_poses[1:]:
            if not robot.ik(pose, q_start)[1]:
                raise ValueError(f"peg survey pose {pose.translation.round(3).tolist()} is not reachable")
        self.q_start = q_start
        self.move: JointMove | None = None
        self.ref = first.copy()  # TCP (peg face centre) reference, hole frame
        self._first = first
        self._seg_t = 0.0
        self._touch_point = np.zeros(3)
        self._touch_t = 0.0
        self._feeding = False
        self._phase_clear = False
        self._retared = False
        self._pull_t = 0.0
        self._chord_retries = 0
        self._lifting = False
        self._z_track: collections.deque[float] = collections.deque(maxlen=2 * cfg.stall_cycles + 1)  # tip z
        self._pressing = False  # a guarded descent decelerated as on a contact: the lead is cut to touch_lead_m
        self._press_z = 0.0  # the tip's height when it stalled
        self._descend_t = -1.0  # the task time of the last guarded-descent step
        self._lift_dir = EZ.copy()
        self._free_z = 0.0
        self._next_target = self.start.copy()
        self.law = DiscreteImpedance(cfg.impedance, dt)
        self.contact = Contact.FREE
        self.depth = -cfg.approach_height_m
        self.low_depth = self.high_depth = self.depth
        self.tilt = np.zeros(2)
        self.probes = 0
        self.realigns = 0
        self._approach_from = float(self.start.translation[2])
        self._samples: list[np.ndarray] = []
        self._segments: list[tuple[pin.SE3, pin.SE3, float]] = []
        self._depth_hist: list[float] = []
        self._slide_from = np.zeros(3)
        self._slid = 0.0
        self._touching = 0
        self._phase = 0
        self._phase_time = 0.0
        # The tip's position along the current search move, the last stall_cycles + 1 cycles (the stall test)
        self._tip_track: collections.deque[float] = collections.deque(maxlen=cfg.stall_cycles + 1)
        self._stalled = 0
        self._phase_from = np.zeros(3)
        self._chord_a = np.zeros(3)
        self._chord_mid = 0.0
        self._chord_free = 0.0  # how far the chord measurement travelled before meeting the wall
        self._centre_left = 0.0  # upright on the wall: how much of the step onto the hole's axis is left
        self._pivot = np.zeros(3)
        self._release_from = 0.0
        self._setpoint = 0.0
        self._tip = self.start.copy()
        self.t = 0.0
        self.t_approach: float | None = None
        self.t_inserted: float | None = None
        self.peak_force = 0.0
        self.peak_moment = 0.0
        self.max_depth = -math.inf
        self.contact_log: list[str] = []

    def _entry_pose(self, lead: np.ndarray, low_xy: np.ndarray, height: float | None = None) -> pin.SE3:
        """Tilted pose, lowest rim point over `low_xy` and `height` (default `approach_height_m`) above the
        mouth, leading along `lead`."""
        a = math.radians(self.cfg.entry_tilt_deg)
        # Tilt the downward peg axis away from the lead: the rim point on the lead side is then the lowest.
        axis = np.cross(EZ, lead)
        axis /= np.linalg.norm(axis)
        pose = pin.SE3(pin.exp3(axis * a) @ TOOL_DOWN, np.zeros(3))
        low, _ = rim_points(pose, self.radius)
        h = self.cfg.approach_height_m if height is None else height
        pose.translation = np.array([*low_xy, self.hole_top + h]) - low
        return pose

    # ------------------------------------------------------------------------- the step
    def step(self, obs: Observation) -> Command:
        self.t = obs.t
        w = obs.wrench
        fz, mx, my = float(w.force[2]), float(w.torque[0]), float(w.torque[1])
        tip = self.Ti * self.robot.tcp_pose(obs.state.q)  # measured pose (hole frame): where the peg really is
        self._tip = tip
        low, high = rim_points(tip, self.radius)
        self.depth = self.hole_top - float(tip.translation[2])
        self.low_depth = self.hole_top - float(low[2])
        self.high_depth = self.hole_top - float(high[2])
        self.tilt = self._tilt_of(tip.rotation)
        if self.state not in (S.MOVE_TO_START, S.TARE):
            self.max_depth = max(self.max_depth, self.depth)
            if np.isfinite(fz):
                self.peak_force = max(self.peak_force, abs(fz))
            if np.isfinite(mx) and np.isfinite(my):
                self.peak_moment = max(self.peak_moment, math.hypot(mx, my))
        contact = classify(fz, mx, my, self.low_depth, self.high_depth, self.cfg)
        if contact != self.contact:
            self.contact_log.append(f"{obs.t:.2f}s {contact.value}")
        self.contact = contact
        if self.state not in (S.MOVE_TO_START, S.TARE, S.DONE, S.FAILED):
            self._check_limits(fz, mx, my)
        rebias = False
        if not self.done:
            handler = getattr(self, f"_{self.state.value}")
            rebias = bool(handler(obs, fz, mx, my))
        q = obs.q_cmd if self.done else self._command(obs)
        self.t_state += self.dt
        return Command(
            q=q,
            log={"contact": self.contact.value, "depth": self.depth, "low_depth": self.low_depth,
                 "high_depth": self.high_depth, "fz_setpoint": self._setpoint,
                 "tip_x": float(tip.translation[0]), "tip_y": float(tip.translation[1]),
                 "tip_z": float(tip.translation[2]), "tilt_x": float(self.tilt[0]), "tilt_y": float(self.tilt[1]),
                 "ref_x": float(self.ref.translation[0]), "ref_y": float(self.ref.translation[1]),
                 "ref_z": float(self.ref.translation[2])},
            rebias_force=rebias,
        )

    def _command(self, obs: Observation) -> np.ndarray:
        if self.state == S.MOVE_TO_START:
            assert self.move is not None
            return self.move.at(self.t_state)
        if self.state == S.TARE:
            return self.q_start
        q, _ = self.robot.ik(self.T * self.ref, obs.q_cmd, iters=3, tol=1e-7)
        return q

    def _check_limits(self, fz: float, mx: float, my: float) -> None:
        c = self.cfg
        m = math.hypot(mx, my)
        tilt = math.degrees(float(np.linalg.norm(self.tilt)))
        if np.isfinite(fz) and fz > c.max_force_n:
            self.fail_because(f"push force {fz:.1f} N exceeded the task limit {c.max_force_n:.1f} N "
                              f"({self.state.value}, depth {self.depth * 1e3:.1f} mm)")
        elif np.isfinite(m) and m > c.max_moment_nm:
            self.fail_because(f"tool moment {m:.2f} N·m exceeded the task limit {c.max_moment_nm:.2f} N·m "
                              f"({self.state.value}, depth {self.depth * 1e3:.1f} mm)")
        elif tilt > c.max_tilt_deg:
            self.fail_because(f"peg tilted {tilt:.1f} deg, beyond the {c.max_tilt_deg:.1f} deg limit")
        elif self.state in (S.APPROACH, S.PROBE, S.BACK_OFF) and \
                np.linalg.norm(rim_points(self.ref, self.radius)[0][:2] - self.hole_xy) > c.max_offset_m + 1e-9:
            self.fail_because(f"no hole within {c.max_offset_m * 1e3:.1f} mm of the nominal position "
                              f"after {self.probes} probes")

    # ------------------------------------------------------------------------- states
    def _move_to_start(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        if self.move is None:
            speed = self.robot.limits.velocity * self.cfg.move_speed_fraction
            self.move = JointMove(obs.q_cmd, self.q_start, speed)
        if self.t_state >= self.move.duration:
            self.arrived()
        return False

    def _tare(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        # Hold still just above the hole so the arm settles, then re-zero the force source there.
        if self.t_state + self.dt >= self.cfg.tare_time_s:
            self.ref = self._first.copy()
            self.t_approach = obs.t
            self._approach_from = float(self.ref.translation[2])
            self._phase = 0
            self._touching = 0
            self._segments = []
            self.tared()
            return True
        return False

    def _survey(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        c = self.cfg
        self._setpoint = 0.0
        if self._lifting:
            # Off the touch point: raise the reference steadily until the measured tip has risen.  Stopped
            # on the face, the arm sticks (joint stiction: a small lift is held until the servo's integral
            # overcomes it, ~1 s, while the F/T sensor winds to -30 N); a steadily growing lift frees it in
            # ~0.1 s.  Only then move sideways: dragging a stuck peg loads it with a side moment.
            if self._tip.translation[2] >= self._free_z:
                self._lifting = False
                # Straight to the next start: it lies above the face wherever the face can be, and so does
                # every point of the straight path from here (the face is a plane).
                target = self._next_target
                d = float(np.linalg.norm(target.translation - self.ref.translation))
                self._segments = [(self.ref.copy(), target, max(0.05, 1.5 * d / c.survey_move_speed_mps))]
                self._seg_t = 0.0
                return False
            self.ref.translation += self._lift_dir * c.survey_lift_speed_mps * self.dt
            if float(self.ref.translation[2]) - self._free_z > c.survey_max_lift_m:
                self.fail_because(f"peg stuck on the fixture face at survey point {self._phase - 1}")
            return False
        if self._segments:  # moving to the next touch point, or to the approach start
            if not self._follow_segments():
                return False
            self._segments = []
            self._approach_from = float(self.ref.translation[2])
            if self._phase >= len(self._survey_poses):
                self.ref = self.start.copy()
                self._approach_from = float(self.ref.translation[2])
                self.surveyed()
            return False
        if self._phase >= len(self._survey_poses):  # no survey configured
            self.surveyed()
            return False
        # Down onto the face; its height is where Fz first crossed the threshold (before the servo's lag
        # presses the point in).
        touch = self._guarded_touch(fz, c.survey_cycles)
        if touch == "hold":
            return False
        if touch == "touch":
            self._touching = 0
            self._survey_points.append(self._touch_point.copy())
            log.info("peg-in-hole: survey point %d at %s mm", self._phase,
                     np.round(self._touch_point * 1e3, 3).tolist())
            self._phase += 1
            self.ref.translation[:] = self._tip.translation
            if self._phase < len(self._survey_poses):
                target = self._survey_poses[self._phase].copy()
                target.translation[2] -= self._survey_drop(self._phase)
            else:
                if not self._fit_face():
                    return False
                # The mouth is now known to about 0.1 mm: start the approach just above it.
                self.start = self._entry_pose(self.lead, self.hole_xy, c.surveyed_approach_height_m)
                target = self.start.copy()
            # Up and back toward the peg's centre (measured: straight up, the rim point stays caught longer).
            self._lift_dir = (EZ - self.lead) / math.sqrt(2.0)
            self._free_z = float(self._tip.translation[2]) + c.survey_lift_m
            self._next_target = target
            self._lifting = True
            return False
        self._descend(c.survey_speed_mps)
        if self._survey_poses[self._phase].translation[2] - self.ref.translation[2] > c.survey_depth_m:
            self.fail_because(f"no fixture face within {c.survey_depth_m * 1e3:.1f} mm at survey point "
                              f"{self._phase} (the hole is not where it is expected)")
        return False

    def _guarded_touch(self, fz: float, cycles: int) -> str:
        """Touch detection for a guarded move: "free", "hold" (stopped, confirming) or "touch".

        The contacts are stiff and bounce (Fz alternates 0 / 40 N from cycle to cycle), and the servo's
        tracking lag goes on pressing: stop at the first crossing (the reference to the measured tip, the
        touch point recorded) and confirm with `cycles` crossings in all within survey_confirm_s; a lone
        spike (a sensor transient) lets the move go on."""
        c = self.cfg
        # A tip stalled in its descent (see _descend) is kinematic evidence of a touch: the wrench need only
        # agree at touch_force_n (the lead cut to touch_lead_m presses with a few N only).
        threshold = c.touch_force_n if self._pressing else c.contact_force_n
        if np.isfinite(fz) and fz > threshold:
            if self._touching == 0:
                self._touch_point = rim_points(self._tip, self.radius)[0]
                self._touch_t = 0.0
                self.ref.translation[:] = self._tip.translation
            self._touching += 1
        elif self._touching:
            self._touch_t += self.dt
            if self._touch_t > c.survey_confirm_s:
                self._touching = 0
                return "free"
        if self._touching >= cycles:
            self._touching = 0
            self._pressing = False
            return "touch"
        return "hold" if self._touching else "free"

    def _descend(self, v: float) -> None:
        """Lower the reference at `v`, but never more than max_lead_m ahead of the measured tip: after a fast
        move the tip still trails, and that windup would press into a contact before it is seen.  A tip that
        was descending and has stalled (its last `stall_cycles` progress under stall_fraction of the
        commanded, the ones before over half of it) is on something: the reference is drawn back to
        touch_lead_m ahead until the tip moves on below where it stalled -- the force on a stiff face stays
        bounded while the wrench confirms the touch, also while the tip bounces on it."""
        c = self.cfg
        z_now = float(self._tip.translation[2])
        if abs(self.t - self.dt - self._descend_t) > 0.5 * self.dt:  # a new descent (or one resumed after a hold)
            self._z_track.clear()
            self._pressing = False
        self._descend_t = self.t
        self._z_track.append(z_now)
        k = c.stall_cycles
        if len(self._z_track) == self._z_track.maxlen:
            before = self._z_track[0] - self._z_track[k]
            recent = self._z_track[k] - self._z_track[-1]
            step = v * k * self.dt
            if self._stalling(recent, v) and before > 0.5 * step:
                if not self._pressing:
                    self._press_z = z_now
                self._pressing = True
            elif recent > 0.5 * step and z_now < self._press_z - 0.5 * c.max_lead_m:
                # Moving on below where it stopped: it was a stick, not a face.  A tip that bounced off the
                # face and is falling back onto it is not below that height: the lead stays cut (given
                # back there, it pressed a bench trial's next impact to 174 N).
                self._pressing = False
        z = float(self.ref.translation[2]) - v * self.dt
        if self._pressing:  # take back the lead the servo had wound up: it presses into the face
            self.ref.translation[2] = max(z, z_now - c.touch_lead_m)
        else:
            self.ref.translation[2] = max(z, min(float(self.ref.translation[2]), z_now - c.max_lead_m))

    def _stalling(self, progress: float, v: float) -> bool:
        """The tip's `progress` over the last `stall_cycles` cycles is under `stall_fraction` of what a
        move at `v` commanded: something stops it (the one stall test of descents and search moves)."""
        return progress < self.cfg.stall_fraction * v * self.cfg.stall_cycles * self.dt

    def _survey_drop(self, k: int) -> float:
        """How much lower than the default start touch k can begin: a point opposite an earlier one lies
        about as far below the nominal mouth as that one lay above it (the face passes within ~0.1 mm of
        the nominal centre at the nominal height)."""
        c = self.cfg
        a = math.radians(c.survey_angles_deg[k])
        for j, p in enumerate(self._survey_points):
            b = math.radians(c.survey_angles_deg[j])
            if abs(math.cos(a - b) + 1.0) < 0.02:  # opposite, within ~11 deg
                predicted = self.hole_top - (float(p[2]) - self.hole_top)
                start = self.hole_top + c.survey_height_m
                return max(0.0, start - (predicted + c.survey_predict_margin_m))
        return 0.0

    def _fit_face(self) -> bool:
        """Fit the plane through the surveyed points; from then on, work in the hole frame it defines."""
        p = np.array(self._survey_points)
        centroid = p.mean(axis=0)
        n = np.linalg.svd(p - centroid)[2][-1]  # least-squares plane normal
        if n[2] < 0:
            n = -n
        tilt = math.degrees(math.acos(float(np.clip(n[2], -1.0, 1.0))))
        self.hole_tilt_deg = tilt
        if tilt > self.cfg.max_hole_tilt_deg:
            self.fail_because(f"fixture face tilted {tilt:.1f} deg, beyond the {self.cfg.max_hole_tilt_deg:.1f} "
                              "deg the task accepts")
            return False
        hx, hy = self.hole_xy
        z0 = float(centroid[2] - (n[0] * (hx - centroid[0]) + n[1] * (hy - centroid[1])) / n[2])
        ax = np.cross(EZ, n)
        s = float(np.linalg.norm(ax))
        R = pin.exp3(ax / s * math.asin(min(1.0, s))) if s > 1e-12 else np.eye(3)
        p_world, p_hole = np.array([hx, hy, z0]), np.array([hx, hy, self.hole_top])
        ref_world, tip_world = self.T * self.ref, self.T * self._tip
        self.T = pin.SE3(R, p_world - R @ p_hole)
        self.Ti = self.T.inverse()
        self.ref = self.Ti * ref_world
        self._tip = self.Ti * tip_world
        log.info("peg-in-hole: fixture face tilted %.2f deg (normal %s), mouth at %.2f mm (nominal %.2f)", tilt,
                 np.round(n, 4).tolist(), z0 * 1e3, self.hole_top * 1e3)
        return True

    def _follow_segments(self) -> bool:
        """Advance the reference along self._segments (smoothstep); True when at the end."""
        self._seg_t += self.dt
        return self._ref_on_segments(self._seg_t)

    def _ref_on_segments(self, t: float) -> bool:
        """Set the reference to time t along self._segments (smoothstep); True when past the end."""
        for start, end, duration in self._segments:
            if t < duration:
                s = t / duration
                self.ref = pin.SE3.Interpolate(start, end, s * s * (3 - 2 * s))
                return False
            t -= duration
        self.ref = self._segments[-1][1].copy()
        return True

    def _approach(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        c = self.cfg
        self._setpoint = 0.0
        if c.retare_before_approach and not self._retared:
            # Just above the mouth, in free air, after the survey: hold still and re-zero the force source
            # here.  The virtual sensor's offset depends on the posture (measured +7.5 N Fz, -1 N·m My at
            # the hole after a tare 15 mm away), and every contact from now on is near this posture.
            if self.t_state + self.dt >= c.tare_time_s:
                self._retared = True
                self._approach_from = float(self.ref.translation[2])
                return True
            return False
        # Contact: Fz over the threshold on several cycles of a short window (the virtual sensor's
        # transients at the start of motion are single-cycle; its moments are too biased to call a
        # contact in free air).
        touch = self._guarded_touch(fz, c.contact_cycles)
        if touch == "hold":
            return False
        if touch == "touch":
            self.ref.translation[:] = self._tip.translation
            self.law.reset()
            self._samples = []
            self.touched()
            return False
        low_above = -(self.hole_top - float(rim_points(self.ref, self.radius)[0][2]))
        slow = low_above < c.slow_height_m
        self._descend(c.slow_speed_mps if slow else c.approach_speed_mps)
        if self._approach_from - self.ref.translation[2] > c.max_approach_m:
            self.fail_because(f"no contact within {c.max_approach_m * 1e3:.0f} mm of approach")
        return False

    def _probe(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        # Hold the touching pose (no force loop: contacts are far stiffer than the servo is fast),
        # let the impact ring out, average the wrench and classify with the kinematic depths.
        c = self.cfg
        self._setpoint = 0.0
        if self.t_state >= c.probe_settle_s and np.isfinite(fz):
            self._samples.append(np.array([fz, mx, my]))
        if self.t_state >= c.probe_settle_s + c.probe_average_s or self.t_state >= c.max_probe_s:
            if not self._samples:
                self.fail_because("no valid wrench while probing the contact")
                return False
            fz_m, mx_m, my_m = np.mean(self._samples, axis=0)
            if fz_m < c.contact_force_n / 2 and self.low_depth < c.inside_depth_m:
                log.info("probe: no contact after all (Fz %.1f N): approaching on", fz_m)
                self._approach_from = float(self.ref.translation[2])
                self.false_alarm()
                return False
            # The contact is already established: classify its place even if the held force relaxed.
            kind = classify(max(float(fz_m), c.contact_force_n), float(mx_m), float(my_m), self.low_depth,
                            self.high_depth, c)
            self.probes += 1
            log.info("probe %d: lowest point %.2f mm, highest %.2f mm below the mouth, Fz %.1f N, "
                     "M (%.3f, %.3f) N·m -> %s", self.probes, self.low_depth * 1e3, self.high_depth * 1e3,
                     fz_m, mx_m, my_m, kind.value)
            if kind == Contact.STUCK_OUTSIDE:
                if self.probes >= c.max_probes:
                    self.fail_because(f"stuck outside the hole after {self.probes} probes")
                    return False
                self._plan_back_off()
                self.outside()
            elif kind == Contact.STUCK_INSIDE:
                self._begin_slide()
                self.inside()
            else:
                self._begin_insert("aligned while probing")
        return False

    def _back_off(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        self._setpoint = 0.0
        if not self._ref_on_segments(self.t_state):
            return False
        self._approach_from = float(self.ref.translation[2])
        self.backed_off()
        return False

    def _slide(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        # The lead edge is in the hole, the face just lifted off the far rim: moving in free space, the
        # little of the peg below the mouth meets the wall.  Find the wall along the lead, then the chord
        # across the lead a little back from it (its midpoint centres the peg across the lead), then the
        # wall along the lead again on the centred line: the peg then leans on the wall at the hole's
        # diameter, ready to be rotated upright.
        c = self.cfg
        self._setpoint = 0.0
        if self.ref.translation[2] < self._slide_from[2] + c.slide_lift_m:
            self.ref.translation[2] += c.backoff_speed_mps * self.dt
            return False
        perp = np.array([-self.lead[1], self.lead[0], 0.0])
        # (direction, speed, distance for a fixed move or None to move until blocked, fast distance)
        # The way back across the chord is free as far as where its measurement started (the peg was there).
        phases = [(self.lead, c.slide_speed_mps, None, c.slide_fast_m),
                  (-self.lead, c.slide_speed_mps, c.chord_backoff_m, 0.0),
                  (perp, c.chord_speed_mps, None, 0.0),
                  (-perp, c.slide_speed_mps, None, max(0.0, self._chord_free - c.chord_free_margin_m)),
                  (perp, c.slide_speed_mps, 0.0, 0.0),  # to the chord's midpoint (distance set below)
                  (self.lead, c.chord_speed_mps, None, 0.0)]
        d, v, dist, fast = phases[self._phase]
        if self._phase == 4:
            dist = self._chord_mid
        if dist is None and self._slid >= fast:
            v = c.slide_slow_speed_mps if self._phase == 0 else c.chord_speed_mps
        step = v * self.dt if dist is None else min(v * self.dt, dist - self._slid)
        self.ref.translation += d * step
        self._slid += step
        moved = float((self._tip.translation - self._phase_from) @ d)
        lag = self._slid - moved
        self._tip_track.append(float(self._tip.translation @ d))
        k = self.cfg.stall_cycles
        if (dist is None and self._phase_t() > c.stall_after_s and len(self._tip_track) > k
                and self._stalling(self._tip_track[-1] - self._tip_track[-1 - k], v)):
            self._stalled += 1
        else:
            self._stalled = 0
        m = math.hypot(mx, my)
        # The previous phase's wall contact rings on for a while (the tip springs back, the moment decays):
        # a lag blocks this phase only once the tip has really moved its way, a moment only after it has
        # once dropped off (else a chord can end before it starts: measured 0.31 mm chords).
        if np.isfinite(m) and m < c.block_moment_nm / 2:
            self._phase_clear = True
        done = False
        if dist is not None:
            done = self._slid >= dist - 1e-9 and self._phase_t() > 0.1
        elif self._slid > max(fast, c.min_probe_travel_m) and (
                (moved > c.min_probe_travel_m and lag > c.slide_block_m)
                or (moved > c.min_probe_travel_m and self._stalled >= 1)
                or (self._phase_clear and np.isfinite(m) and m > c.block_moment_nm)):
            done = True
        elif self._slid > c.max_slide_m:
            self.fail_because(f"moved {self._slid * 1e3:.1f} mm (search phase {self._phase}) without "
                              "meeting the hole's wall")
            return False
        if not done:
            self._phase_time += self.dt
            return False
        log.info("peg-in-hole: search phase %d ended after %.2f mm (lag %.2f mm, |M| %.2f N·m)", self._phase,
                 self._slid * 1e3, lag * 1e3, m)
        if dist is None:  # blocked: drop the wound-up reference so the wall is not pushed
            self.ref.translation[:2] = self._tip.translation[:2]
        if self._phase == 2:
            self._chord_a = self._tip.translation.copy()
            self._chord_free = max(0.0, moved)
        if self._phase == 3:
            chord = float((self._chord_a - self._tip.translation) @ perp)
            self._chord_mid = chord / 2
            if chord < c.min_chord_m and self._chord_retries < c.max_chord_retries:
                # Too short to be the free play across the hole (measured 1.8-5.3 mm when sound): the peg
                # is still too near the lead wall for its submerged arc to move.  Back off further, again.
                self._chord_retries += 1
                log.info("peg-in-hole: chord %.2f mm too short: measuring again further back", chord * 1e3)
                self._phase = 0  # +1 below: back off along the lead again
        if self._phase == 4:
            self._chord_retries = 0
        if self._phase == len(phases) - 1:
            self._begin_rotate("leaning on the wall on the centred line")
            return False
        self._phase += 1
        self._phase_clear = False
        self._phase_from = self._tip.translation.copy()
        self._slid = 0.0
        self._phase_time = 0.0
        self._tip_track.clear()
        self._stalled = 0
        return False

    def _phase_t(self) -> float:
        return self._phase_time

    def _rotate(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        c = self.cfg
        self._setpoint = 0.0
        tilt = math.degrees(float(np.linalg.norm(self.tilt)))
        ref_tilt = self._tilt_angle(self.ref.rotation)
        if ref_tilt <= 1e-4:
            # Upright with the lead side on the wall: step off it onto the hole's axis (wall_clearance_m),
            # at centre_speed_mps as the insertion starts (a step in one period jerked the arm sideways into
            # the rim, 90-100 N spikes).
            self._centre_left = c.wall_clearance_m if c.wall_clearance_m is not None else \
                (c.hole_diameter_m - c.peg_diameter_m) / 2
            self._begin_insert(f"upright (measured tilt {tilt:.2f} deg)")
            return False
        # Rotate the reference toward upright about the wall contact (the pivot on the lead side).
        z = self.ref.rotation[:, 2]
        axis = np.cross(z, -EZ)
        axis /= np.linalg.norm(axis)
        # Slow the rotation as the push builds (the hole's own tilt is unknown: the far side may touch),
        # and comply to the side load as in the insertion.
        push = fz / c.rotate_max_force_n if np.isfinite(fz) else 1.0
        da = min(math.radians(c.rotate_rate_dps) * self.dt * max(0.0, 1.0 - push), ref_tilt)
        Rw = pin.exp3(axis * da)
        self.ref.translation = self._pivot + Rw @ (self.ref.translation - self._pivot)
        self.ref.rotation = Rw @ self.ref.rotation
        if push > 1.0:  # reflex: take back the servo's wound-up travel along the peg
            self._relieve()
        self._comply(mx, my)
        if push > 1.0 and self.t_state > c.rotate_give_up_s:
            self._begin_insert(f"rotation blocked at {tilt:.1f} deg: inserting with compliance")
        return False

    def _insert(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        c = self.cfg
        self._setpoint = c.insert_force_n
        if self.depth >= c.target_depth_m:
            self.t_inserted = obs.t
            self._release_from = c.insert_force_n
            self.inserted()
            return False
        if self._centre_left > 0:  # off the wall onto the hole's axis first
            d = min(self._centre_left, c.centre_speed_mps * self.dt)
            self.ref.translation -= self.lead * d
            self._centre_left -= d
            return False
        axis = self.ref.rotation[:, 2]
        m = math.hypot(mx, my) if np.isfinite(mx) and np.isfinite(my) else 0.0
        if not (np.isfinite(fz) and fz >= c.contact_force_n):
            # Nothing pushes back: feed at a fixed speed (not through the law), slowing as a side load
            # builds (the hole's axis is not the peg's: a wedge ahead is far stiffer than the servo is fast).
            # Slowly near the mouth and after a stall (something stiff is ahead).
            slow = self.depth <= c.entry_depth_m or self.realigns > 0
            v = min(c.entry_speed_mps, c.free_insert_speed_mps) if slow else c.free_insert_speed_mps
            side = max(0.0, m - c.comply_deadband_nm) / (c.side_moment_nm - c.comply_deadband_nm)
            self.ref.translation += axis * v * max(0.0, 1.0 - side) * self.dt
            self.law.reset()
            self._feeding = True
        else:
            if self._feeding:
                # First push back after a free feed: the servo's lag (v x its time constant) would go on
                # pressing into a contact far stiffer than the law; start the law from the measured tip.
                self._relieve()
                self._feeding = False
            self._regulate(fz, c.insert_force_n, axis)
        if m > c.side_moment_nm or (np.isfinite(fz) and fz > c.max_force_n * 0.6):
            self._relieve()  # reflex: a wedge ahead; stop pushing into it before the law catches up
        self._comply(mx, my)
        self._depth_hist.append(self.depth)
        n = int(round(c.stall_s / self.dt))
        if len(self._depth_hist) > n and self._depth_hist[-1] - self._depth_hist[-1 - n] < c.stall_depth_m:
            if self.realigns >= c.max_realigns:
                self.fail_because(f"jammed at depth {self.depth * 1e3:.1f} mm after {self.realigns} "
                                  f"realignments (Fz {fz:.1f} N, |M| {math.hypot(mx, my):.2f} N·m)")
                return False
            self.realigns += 1
            log.info("peg-in-hole: stalled at %.1f mm: realignment %d", self.depth * 1e3, self.realigns)
            self.ref.translation[:] = self._tip.translation  # drop the wound-up push
            self.law.reset()
            self.stalled()
        return False

    def _realign(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        c = self.cfg
        self._setpoint = c.realign_force_n
        if self.t_state < c.realign_time_s / 2:
            self.ref.translation -= self.ref.rotation[:, 2] * 2 * c.realign_lift_m * self.dt / c.realign_time_s
        self._comply(mx, my, scale=2.0)
        if self.t_state >= c.realign_time_s:
            self.law.reset()
            self._depth_hist = []
            self.realigned()
        return False

    def _release(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        a = min(1.0, self.t_state / self.cfg.release_time_s)
        self._setpoint = (1 - a) * self._release_from
        self._regulate(fz, self._setpoint, self.ref.rotation[:, 2])
        if a >= 1.0:
            self.released()
        return False

    def _retract(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        self._setpoint = 0.0
        # Starting from rest the arm sticks (joint stiction; measured: the F/T sensor winds to -30..-80 N
        # for ~0.1-0.2 s before it breaks free, in free air as in the hole): a pull is a stuck peg only
        # when it lasts.
        self._pull_t = self._pull_t + self.dt if (np.isfinite(fz) and -fz > self.cfg.max_pull_n) else 0.0
        if self._pull_t > self.cfg.max_pull_s:
            self.fail_because(f"peg stuck while retracting (pull {-fz:.1f} N for {self._pull_t:.2f} s)")
            return False
        # Out along the peg's own axis, which the insertion has aligned with the hole's.
        # Slowly while the peg is in the hole (a stiff contact at the mouth turns speed into force spikes).
        v = self.cfg.retract_speed_mps if self.depth < -0.002 else self.cfg.retract_slow_speed_mps
        self.ref.translation -= self.ref.rotation[:, 2] * v * self.dt
        if self.depth > 0:
            self._comply(mx, my)  # still in the hole: follow its axis rather than pull on a wall
        if self.depth <= -self.cfg.retract_height_m:
            self.retracted()
        return False

    # ------------------------------------------------------------------------- helpers
    def _relieve(self) -> None:
        """Move the reference back to the measured tip along the peg axis (drop the servo's lag windup)."""
        axis = self.ref.rotation[:, 2]
        ahead = float((self.ref.translation - self._tip.translation) @ axis)
        if ahead > 0:
            self.ref.translation -= axis * ahead
        self.law.reset()

    def _begin_slide(self) -> None:
        self._chord_retries = 0
        self._chord_free = 0.0
        self._phase = 0
        self._phase_clear = False
        self._phase_time = 0.0
        self._tip_track.clear()
        self._stalled = 0
        self._phase_from = self._tip.translation.copy()
        self._slide_from = self._tip.translation.copy()
        self.ref.translation[:] = self._tip.translation
        self._slid = 0.0
        self.law.reset()

    def _begin_rotate(self, why: str) -> None:
        log.info("peg-in-hole: %s (lowest point %.2f mm, highest %.2f mm below the mouth)", why,
                 self.low_depth * 1e3, self.high_depth * 1e3)
        # Drop the slide's wound-up lateral reference, and pivot about the lead-side generator at the mouth.
        self.ref.translation[:] = self._tip.translation
        self.ref.rotation[:] = self._tip.rotation
        low, _ = rim_points(self._tip, self.radius)
        up = -self._tip.rotation[:, 2]
        s = (self.hole_top - low[2]) / max(up[2], 1e-6)
        self._pivot = low + s * up
        self.law.reset()
        self.blocked()

    def _begin_insert(self, why: str) -> None:
        log.info("peg-in-hole: %s (depth %.1f mm)", why, self.depth * 1e3)
        self.law.reset()
        self._depth_hist = []
        if self.state == S.ROTATE:
            self.upright()
        else:
            self.aligned()

    def _plan_back_off(self) -> None:
        """Stuck outside: lift, then put the lowest rim point on the next point of a ring around the nominal
        centre, leading toward the centre (a bounded search for a hole further off than expected)."""
        c = self.cfg
        k = self.probes
        ang = math.radians(c.lead_direction_deg) + k * 2.0  # ~115 deg apart: spread over the ring
        radius = min(c.max_offset_m, c.search_step_m * (1 + k // 3))
        out = np.array([math.cos(ang), math.sin(ang), 0.0])
        target = self._entry_pose(-out, self.hole_xy + radius * out[:2])
        lifted = self.ref.copy()
        lifted.translation[2] = self._tip.translation[2] + c.backoff_m  # above the contact, not the pressed-in ref
        target.translation[2] = max(target.translation[2], lifted.translation[2])
        v = c.backoff_speed_mps
        self._segments = [
            (self.ref.copy(), lifted, max(0.03, 1.5 * c.backoff_m / v)),
            (lifted, target, max(0.05, 1.5 * float(np.linalg.norm(target.translation - lifted.translation)) / v)),
        ]
        self.lead = -out

    def _regulate(self, fz: float, setpoint: float, direction: np.ndarray) -> None:
        """One step of the discretised impedance law (eq. 24) along `direction` (into the hole)."""
        if not np.isfinite(fz):
            return  # hold on a missing reading; the safety monitor counts them
        dz = float(self.law.update(setpoint - fz)[0])
        vmax = self.cfg.insert_speed_limit_mps * self.dt
        dz = float(np.clip(dz, -vmax, vmax))
        self.ref.translation += direction * dz

    def _comply(self, mx: float, my: float, scale: float = 1.0) -> None:
        """Rotate about the tip and shift it so the side load goes away (the paper's rotate and shift)."""
        if not (np.isfinite(mx) and np.isfinite(my)):
            return
        c = self.cfg
        m = np.array([mx, my])
        if np.linalg.norm(m) < c.comply_deadband_nm:
            return  # inside the force source's error band: hold
        rot_tool = np.array([m[0], m[1], 0.0]) * c.rotation_gain * scale * self.dt
        shift_tool = np.array([-m[1], m[0], 0.0]) * c.shift_gain * scale * self.dt
        R = self.ref.rotation
        self.ref.translation += R @ shift_tool
        self.ref.rotation = R @ pin.exp3(rot_tool)

    @staticmethod
    def _tilt_angle(R: np.ndarray) -> float:
        return math.acos(float(np.clip(-R[2, 2], -1.0, 1.0)))

    @staticmethod
    def _tilt_of(R: np.ndarray) -> np.ndarray:
        """Tilt of the peg axis from vertical as small rotations about base x and y [rad]."""
        z = R[:, 2]  # peg axis, pointing down when vertical
        return np.array([math.atan2(z[1], -z[2]), math.atan2(-z[0], -z[2])])

    # ------------------------------------------------------------------------- results
    def summary(self) -> dict[str, Any]:
        t0 = self.t_approach
        return {
            "task": self.name,
            "outcome": self.outcome,
            "reason": self.reason,
            "final_state": self.state.value,
            "inserted": self.t_inserted is not None,
            "insertion_time_s": (self.t_inserted - t0) if (self.t_inserted is not None and t0 is not None) else None,
            "task_time_s": self.t,
            "target_depth_m": self.cfg.target_depth_m,
            "max_depth_m": self.max_depth if np.isfinite(self.max_depth) else None,
            "probes": self.probes,
            "hole_tilt_deg": self.hole_tilt_deg,
            "hole_axis": self.T.rotation[:, 2].round(6).tolist() if self.hole_tilt_deg is not None else None,
            "realignments": self.realigns,
            "peak_force_n": self.peak_force,
            "peak_moment_nm": self.peak_moment,
            "contact_changes": len(self.contact_log),
        }

    # Hooks the runner uses for peg runs (the recording has the virtual and the measured wrench).
    @staticmethod
    def log_summary(table: Any) -> dict[str, Any]:
        return wrench_errors(table)

    @staticmethod
    def plot_run(table: Any, path: Path, title: str) -> Path:
        from cell.report import plot_peg_run

        return plot_peg_run(table, path, title)


INSERTION_STATES = (S.APPROACH.value, S.PROBE.value, S.BACK_OFF.value, S.SLIDE.value, S.ROTATE.value,
                    S.INSERT.value, S.REALIGN.value)


WRENCH_AXES = ("mx", "my", "fz")  # the paper's 3-axis comparison: what the strategy reads


def wrench_abs_errors(states: Any, virtual: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """|virtual - measured| of (Mx, My, Fz), rows (n, 3), on the insertion states' samples where both
    sources read (a timed-out reading is no sample): (k, 3).  The bench and the run summary score this."""
    v, m = np.asarray(virtual, float).reshape(-1, 3), np.asarray(measured, float).reshape(-1, 3)
    rows = np.isin(np.asarray(states, dtype=object), INSERTION_STATES)
    rows &= np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(m), axis=1)
    return np.abs(v[rows] - m[rows])


def wrench_errors(table: Any) -> dict[str, Any]:
    """Virtual-vs-measured MAE of (Mx, My, Fz) over the insertion states, when the log has both."""
    d = table.to_pydict() if hasattr(table, "to_pydict") else table
    if "sensor_fz" not in d:
        return {}
    e = wrench_abs_errors(d["state"], np.column_stack([d[k] for k in WRENCH_AXES]),
                          np.column_stack([d[f"sensor_{k}"] for k in WRENCH_AXES]))
    out: dict[str, Any] = {"wrench_error_samples": len(e)}
    for i, name in enumerate(("mae_mx_nm", "mae_my_nm", "mae_fz_n")):
        out[name] = float(e[:, i].mean()) if len(e) else None
    return out
