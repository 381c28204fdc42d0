"""Sensorless peg-in-hole (paper 6.2): the task's state machine, from the survey to the retract."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from cell.control.impedance import DiscreteImpedance
from cell.control.loop import Command, Observation
from cell.control.trajectory import JointMove
from cell.model.robot import RobotModel
from tasks.base import MachineTask
from tasks.peg.bore import BoreCentring
from tasks.peg.compliance import comply, regulate, relieve, rotate_upright
from tasks.peg.config import PegConfig
from tasks.peg.contact import Contact, believed, classify
from tasks.peg.geometry import Segment, entry_pose, on_segments, rim_points, tilt_angle, tilt_of, wall_pivot
from tasks.peg.search import WallSearch, plan_back_off
from tasks.peg.states import INSERTION_STATES, TRANSITIONS, PegState, PegTriggers
from tasks.peg.survey import Survey, fit_face, hole_frame
from tasks.peg.touch import GuardedDescent

log = logging.getLogger(__name__)


class PegInHoleTask(MachineTask, PegTriggers):
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
    # Scored over the insertion (as the bench scores a trial); touched on the survey's points and the approach.
    working_states = INSERTION_STATES
    touch_states = (PegState.SURVEY.value, PegState.APPROACH.value, PegState.PROBE.value)

    def __init__(self, cfg: PegConfig, robot: RobotModel, hole_xy: np.ndarray, hole_top: float, dt: float,
                 q_home: np.ndarray) -> None:
        self.cfg = cfg
        self.robot = robot
        self.dt = dt
        self.hole_xy = np.asarray(cfg.hole_xy if cfg.hole_xy is not None else hole_xy, float)
        self.hole_top = hole_top
        self.radius = cfg.peg_diameter_m / 2
        super().__init__(PegState.MOVE_TO_START, TRANSITIONS)
        self.lead = np.array([math.cos(math.radians(cfg.lead_direction_deg)),
                              math.sin(math.radians(cfg.lead_direction_deg)), 0.0])
        # The hole frame: base-frame coordinates of a fixture whose face is level at `hole_top` through the
        # nominal centre.  Identity until the survey has measured the face; then a world pose is
        # world_from_hole * (the same pose in the hole frame).
        self.world_from_hole = pin.SE3.Identity()
        self.hole_from_world = pin.SE3.Identity()
        self.hole_tilt_deg: float | None = None
        self.start = entry_pose(cfg, hole_top, self.lead, self.hole_xy)  # approach start, hole frame
        self.survey = Survey(cfg, dt, self.hole_xy, hole_top, self.lead)
        self.guard = GuardedDescent(cfg, dt)  # the survey's and the approach's touches
        self.search = WallSearch(cfg, dt)  # the slide's search phases
        self.rc = (cfg.hole_diameter_m - cfg.peg_diameter_m) / 2  # nominal radial clearance
        self.bore = BoreCentring(cfg, dt, self.rc)  # tight fits: the upright peg centred on the bore
        first = self.survey.poses[0] if self.survey.poses else self.start
        q_start, ok = robot.ik(first, q_home)
        if not ok:
            raise ValueError(f"peg start pose {first.translation.round(3).tolist()} is not reachable")
        for pose in self.survey.poses[1:]:
            if not robot.ik(pose, q_start)[1]:
                raise ValueError(f"peg survey pose {pose.translation.round(3).tolist()} is not reachable")
        self.q_start = q_start
        self.move: JointMove | None = None
        self.ref = first.copy()  # TCP (peg face centre) reference, hole frame
        self._first = first
        self._feeding = False
        self._retared = False
        self._pull_t = 0.0
        self.law = DiscreteImpedance(cfg.impedance, dt)
        self.contact = Contact.FREE
        self.depth = -cfg.approach_height_m
        self.low_depth = self.high_depth = self.depth
        self.tilt = np.zeros(2)
        self.probes = 0
        self.realigns = 0
        self._approach_from = float(self.start.translation[2])
        self._samples: list[np.ndarray] = []
        self._segments: list[Segment] = []  # the back-off's path
        self._depth_hist: list[float] = []
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

    # ------------------------------------------------------------------------- the step
    def step(self, obs: Observation) -> Command:
        self.t = obs.t
        w = obs.wrench
        fz, mx, my = float(w.force[2]), float(w.torque[0]), float(w.torque[1])
        # The measured pose in the hole frame: where the peg really is.
        tip = self.hole_from_world * self.robot.tcp_pose(obs.state.q)
        self._tip = tip
        low, high = rim_points(tip, self.radius)
        self.depth = self.hole_top - float(tip.translation[2])
        self.low_depth = self.hole_top - float(low[2])
        self.high_depth = self.hole_top - float(high[2])
        self.tilt = tilt_of(tip.rotation)
        if self.state not in (PegState.MOVE_TO_START, PegState.TARE):
            self.max_depth = max(self.max_depth, self.depth)
            if math.isfinite(fz):
                self.peak_force = max(self.peak_force, abs(fz))
            if math.isfinite(mx) and math.isfinite(my):
                self.peak_moment = max(self.peak_moment, math.hypot(mx, my))
        contact = classify(fz, mx, my, self.low_depth, self.high_depth, self.cfg)
        if contact != self.contact:
            self.contact_log.append(f"{obs.t:.2f}s {contact.value}")
        self.contact = contact
        if self.state not in (PegState.MOVE_TO_START, PegState.TARE, PegState.DONE, PegState.FAILED):
            self._check_limits(fz, mx, my)
        rebias = not self.done and bool(getattr(self, f"_{self.state.value}")(obs, fz, mx, my))
        q = obs.q_cmd if self.done else self._command(obs)
        self.t_state += self.dt
        return Command(
            q=q,
            log={"contact": self.contact.value, "contact_state": believed(self.state.value, contact,
                                                                            self.high_depth, self.cfg).value,
                 "depth": self.depth, "low_depth": self.low_depth, "high_depth": self.high_depth,
                 "fz_setpoint": self._setpoint,
                 "tip_x": float(tip.translation[0]), "tip_y": float(tip.translation[1]),
                 "tip_z": float(tip.translation[2]), "tilt_x": float(self.tilt[0]), "tilt_y": float(self.tilt[1]),
                 "ref_x": float(self.ref.translation[0]), "ref_y": float(self.ref.translation[1]),
                 "ref_z": float(self.ref.translation[2])},
            rebias_force=rebias,
        )

    def _command(self, obs: Observation) -> np.ndarray:
        if self.state == PegState.MOVE_TO_START:
            assert self.move is not None
            return self.move.at(self.t_state)
        if self.state == PegState.TARE:
            return self.q_start
        q, _ = self.robot.ik(self.world_from_hole * self.ref, obs.q_cmd, iters=3, tol=1e-7)
        return q

    def _check_limits(self, fz: float, mx: float, my: float) -> None:
        c = self.cfg
        m = math.hypot(mx, my)
        tilt = math.degrees(math.sqrt(self.tilt.dot(self.tilt)))  # numpy's norm of a vector, without its checks
        if math.isfinite(fz) and fz > c.max_force_n:
            self.fail_because(f"push force {fz:.1f} N exceeded the task limit {c.max_force_n:.1f} N "
                              f"({self.state.value}, depth {self.depth * 1e3:.1f} mm)")
        elif math.isfinite(m) and m > c.max_moment_nm:
            self.fail_because(f"tool moment {m:.2f} N·m exceeded the task limit {c.max_moment_nm:.2f} N·m "
                              f"({self.state.value}, depth {self.depth * 1e3:.1f} mm)")
        elif tilt > c.max_tilt_deg:
            self.fail_because(f"peg tilted {tilt:.1f} deg, beyond the {c.max_tilt_deg:.1f} deg limit")
        elif self.state in (PegState.APPROACH, PegState.PROBE, PegState.BACK_OFF) and \
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
            self.survey.k = 0
            self.guard.touching = 0
            self._segments = []
            self.tared()
            return True
        return False

    def _survey(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        self._setpoint = 0.0
        self.ref, status = self.survey.step(fz, self.ref, self._tip, self.guard, self.t)
        if status == "failed":
            self.fail_because(self.survey.reason)
        elif status == "at_point":
            self._approach_from = float(self.ref.translation[2])
        elif status == "touched_all" and self._fit_face():
            # The mouth is now known to about 0.1 mm: start the approach just above it.
            self.start = entry_pose(self.cfg, self.hole_top, self.lead, self.hole_xy,
                                    self.cfg.surveyed_approach_height_m)
            self.survey.lift_to(self.start.copy(), self._tip)
        elif status == "surveyed":
            self.ref = self.start.copy()
            self._approach_from = float(self.ref.translation[2])
            self.surveyed()
        return False

    def _fit_face(self) -> bool:
        """Fit the plane through the surveyed points; from then on, work in the hole frame it defines."""
        n, tilt, z0 = fit_face(self.survey.points, self.hole_xy)
        self.hole_tilt_deg = tilt
        if tilt > self.cfg.max_hole_tilt_deg:
            self.fail_because(f"fixture face tilted {tilt:.1f} deg, beyond the {self.cfg.max_hole_tilt_deg:.1f} "
                              "deg the task accepts")
            return False
        ref_world, tip_world = self.world_from_hole * self.ref, self.world_from_hole * self._tip
        self.world_from_hole = hole_frame(n, self.hole_xy, z0, self.hole_top)
        self.hole_from_world = self.world_from_hole.inverse()
        self.ref = self.hole_from_world * ref_world
        self._tip = self.hole_from_world * tip_world
        log.info("peg-in-hole: fixture face tilted %.2f deg (normal %s), mouth at %.2f mm (nominal %.2f)", tilt,
                 np.round(n, 4).tolist(), z0 * 1e3, self.hole_top * 1e3)
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
        touch = self.guard.touch(fz, c.contact_cycles, self.ref, self._tip)
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
        self.guard.descend(c.slow_speed_mps if slow else c.approach_speed_mps, self.t, self.ref, self._tip)
        if self._approach_from - self.ref.translation[2] > c.max_approach_m:
            self.fail_because(f"no contact within {c.max_approach_m * 1e3:.0f} mm of approach")
        return False

    def _probe(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        # Hold the touching pose (no force loop: contacts are far stiffer than the servo is fast),
        # let the impact ring out, average the wrench and classify with the kinematic depths.
        c = self.cfg
        self._setpoint = 0.0
        if self.t_state >= c.probe_settle_s and math.isfinite(fz):
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
                self._segments, self.lead = plan_back_off(c, self.probes, self.ref, self._tip, self.hole_xy,
                                                          self.hole_top)
                self.outside()
            elif kind == Contact.STUCK_INSIDE:
                self._begin_slide()
                self.inside()
            else:
                self._begin_insert("aligned while probing")
        return False

    def _back_off(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        self._setpoint = 0.0
        self.ref, arrived = on_segments(self._segments, self.t_state)
        if not arrived:
            return False
        self._approach_from = float(self.ref.translation[2])
        self.backed_off()
        return False

    def _slide(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        self._setpoint = 0.0
        status = self.search.step(self.ref, self._tip, self.lead, mx, my)
        if status == "lost":
            self.fail_because(self.search.reason)
        elif status == "on_wall":
            self._begin_rotate("leaning on the wall on the centred line")
        return False

    def _rotate(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        c = self.cfg
        self._setpoint = 0.0
        tilt = math.degrees(float(np.linalg.norm(self.tilt)))
        ref_tilt = tilt_angle(self.ref.rotation)
        if ref_tilt <= 1e-4:
            # Upright with the lead side on the wall: step off it onto the hole's axis (wall_clearance_m),
            # at centre_speed_mps as the insertion starts (a step in one period jerked the arm sideways into
            # the rim, 90-100 N spikes).
            self._centre_left = c.wall_clearance_m if c.wall_clearance_m is not None else \
                (c.hole_diameter_m - c.peg_diameter_m) / 2
            self._begin_insert(f"upright (measured tilt {tilt:.2f} deg)")
            return False
        # Rotate toward upright about the wall contact, and comply to the side load as in the insertion.
        push = rotate_upright(self.ref, self._pivot, ref_tilt, fz, c, self.dt)
        if push > 1.0:  # reflex: take back the servo's wound-up travel along the peg
            relieve(self.ref, self._tip, self.law)
        comply(self.ref, mx, my, self.cfg, self.dt)
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
            if self._centre_left <= 0 and self.rc <= c.bore_centring_below_m:
                self.bore.begin(self.ref, self._tip)
            return False
        if self.bore.active:
            self.bore.step(self.ref, self._tip)
            return False
        axis = self.ref.rotation[:, 2]
        m = math.hypot(mx, my) if math.isfinite(mx) and math.isfinite(my) else 0.0
        if not (math.isfinite(fz) and fz >= c.contact_force_n):
            # Nothing pushes back: feed at a fixed speed (not through the law), slowing as a side load
            # builds (the hole's axis is not the peg's: a wedge ahead is far stiffer than the servo is fast).
            # Slowly near the mouth, and after a stall (a wedge ahead) unless the fit is tight (bore re-measured).
            slow = self.depth <= c.entry_depth_m or (self.realigns > 0 and self.rc > c.bore_centring_below_m)
            fast = c.free_insert_speed_mps if self.rc > c.bore_centring_below_m else c.tight_feed_speed(self.rc)
            v = min(c.entry_speed_mps, fast) if slow else c.feed_speed(self.depth, fast)
            side = max(0.0, m - c.comply_deadband_nm) / (c.side_moment_nm - c.comply_deadband_nm)
            self.ref.translation += axis * v * max(0.0, 1.0 - side) * self.dt
            self.law.reset()
            self._feeding = True
        else:
            if self._feeding:
                # First push back after a free feed: the servo's lag (v x its time constant) would go on
                # pressing into a contact far stiffer than the law; start the law from the measured tip.
                relieve(self.ref, self._tip, self.law)
                self._feeding = False
            regulate(self.ref, self.law, fz, c.insert_force_n, axis, c.insert_speed_limit_mps * self.dt)
        if m > c.side_moment_nm or (math.isfinite(fz) and fz > c.max_force_n * 0.6):
            # reflex: a wedge ahead; stop pushing into it before the law catches up
            relieve(self.ref, self._tip, self.law)
        comply(self.ref, mx, my, self.cfg, self.dt)
        self.bore.hold(self.ref, self._tip)
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
        comply(self.ref, mx, my, self.cfg, self.dt, scale=2.0)
        self.bore.hold(self.ref, self._tip)
        if self.t_state >= c.realign_time_s:
            self.law.reset()
            self._depth_hist = []
            if self.rc <= c.bore_centring_below_m:
                self.bore.begin(self.ref, self._tip)  # measure the bore again where the peg now is
            self.realigned()
        return False

    def _release(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        a = min(1.0, self.t_state / self.cfg.release_time_s)
        self._setpoint = (1 - a) * self._release_from
        regulate(self.ref, self.law, fz, self._setpoint, self.ref.rotation[:, 2],
                 self.cfg.insert_speed_limit_mps * self.dt)
        if a >= 1.0:
            self.released()
        return False

    def _retract(self, obs: Observation, fz: float, mx: float, my: float) -> bool:
        self._setpoint = 0.0
        # Starting from rest the arm sticks (joint stiction; measured: the F/T sensor winds to -30..-80 N
        # for ~0.1-0.2 s before it breaks free, in free air as in the hole): a pull is a stuck peg only
        # when it lasts.
        self._pull_t = self._pull_t + self.dt if (math.isfinite(fz) and -fz > self.cfg.max_pull_n) else 0.0
        if self._pull_t > self.cfg.max_pull_s:
            self.fail_because(f"peg stuck while retracting (pull {-fz:.1f} N for {self._pull_t:.2f} s)")
            return False
        # Out along the peg's own axis, which the insertion has aligned with the hole's.
        v = self.cfg.retract_speed(self.depth, self.rc)  # slowly while in the hole or near it
        self.ref.translation -= self.ref.rotation[:, 2] * v * self.dt
        if self.depth > 0:
            comply(self.ref, mx, my, self.cfg, self.dt)  # still in the hole: follow its axis rather than pull on a wall
            self.bore.hold(self.ref, self._tip)
        if self.depth <= -self.cfg.retract_height_m:
            self.retracted()
        return False

    # ------------------------------------------------------------------------- helpers
    def _begin_slide(self) -> None:
        self.search.begin(self.ref, self._tip)
        self.law.reset()

    def _begin_rotate(self, why: str) -> None:
        log.info("peg-in-hole: %s (lowest point %.2f mm, highest %.2f mm below the mouth)", why,
                 self.low_depth * 1e3, self.high_depth * 1e3)
        # Drop the slide's wound-up lateral reference, and pivot about the lead-side generator at the mouth.
        self.ref.translation[:] = self._tip.translation
        self.ref.rotation[:] = self._tip.rotation
        self._pivot = wall_pivot(self._tip, self.radius, self.hole_top)
        self.law.reset()
        self.blocked()

    def _begin_insert(self, why: str) -> None:
        log.info("peg-in-hole: %s (depth %.1f mm)", why, self.depth * 1e3)
        self.law.reset()
        self._depth_hist = []
        if self.state == PegState.ROTATE:
            self.upright()
        else:
            self.aligned()

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
            "hole_axis": (self.world_from_hole.rotation[:, 2].round(6).tolist()
                          if self.hole_tilt_deg is not None else None),
            "realignments": self.realigns,
            "peak_force_n": self.peak_force,
            "peak_moment_nm": self.peak_moment,
            "contact_changes": len(self.contact_log),
        }

    # The runner's hook for the figure (its virtual-vs-measured figures come from the runner's own tap).
    @staticmethod
    def plot_run(table: Any, path: Path, title: str, limits: dict[str, list[tuple[str, float]]] | None = None) -> Path:
        from cell.view.report import plot_peg_run

        return plot_peg_run(table, path, title, limits)

