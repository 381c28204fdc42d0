"""The peg's search phases: the ring of entry points tried when stuck outside the hole, and, with the lead
edge in the hole, the search for the wall and the chord across the hole that centres the peg on it."""

from __future__ import annotations

import collections
import logging
import math
from typing import Literal

import numpy as np
import pinocchio as pin

from tasks.peg.config import PegConfig
from tasks.peg.geometry import Segment, entry_pose
from tasks.peg.touch import stalling

log = logging.getLogger(__name__)

SearchStep = Literal["searching", "on_wall", "lost"]


def plan_back_off(cfg: PegConfig, probes: int, ref: pin.SE3, tip: pin.SE3, hole_xy: np.ndarray,
                  hole_top: float) -> tuple[list[Segment], np.ndarray]:
    """Stuck outside after `probes` probes: lift, then put the lowest rim point on the next point of a ring
    around the nominal centre, leading toward the centre (a bounded search for a hole further off than
    expected).  The reference's path there, and the new lead direction."""
    c = cfg
    k = probes
    ang = math.radians(c.lead_direction_deg) + k * 2.0  # ~115 deg apart: spread over the ring
    radius = min(c.max_offset_m, c.search_step_m * (1 + k // 3))
    out = np.array([math.cos(ang), math.sin(ang), 0.0])
    target = entry_pose(cfg, hole_top, -out, hole_xy + radius * out[:2])
    lifted = ref.copy()
    lifted.translation[2] = tip.translation[2] + c.backoff_m  # above the contact, not the pressed-in ref
    target.translation[2] = max(target.translation[2], lifted.translation[2])
    v = c.backoff_speed_mps
    segments = [
        (ref.copy(), lifted, max(0.03, 1.5 * c.backoff_m / v)),
        (lifted, target, max(0.05, 1.5 * float(np.linalg.norm(target.translation - lifted.translation)) / v)),
    ]
    return segments, -out


class WallSearch:
    """The slide's search phases, stuck inside with the lead edge in the hole.

    The face just lifted off the far rim, moving in free space, the little of the peg below the mouth meets
    the wall.  Find the wall along the lead, then the chord across the lead a little back from it (its
    midpoint centres the peg across the lead), then the wall along the lead again on the centred line: the
    peg then leans on the wall at the hole's diameter, ready to be rotated upright.  Each step moves the
    task's reference (hole frame) in place from the measured tip and the tool moment.
    """

    def __init__(self, cfg: PegConfig, dt: float) -> None:
        self.cfg = cfg
        self.dt = dt
        self.phase = 0
        self.phase_clear = False  # the previous phase's wall moment has dropped off
        self.phase_time = 0.0
        # The tip's position along the current search move, the last stall_cycles + 1 cycles (the stall test)
        self.tip_track: collections.deque[float] = collections.deque(maxlen=cfg.stall_cycles + 1)
        self.stalled = 0
        self.phase_from = np.zeros(3)
        self.slide_from = np.zeros(3)
        self.settled = False
        self.slid = 0.0
        self.chord_a = np.zeros(3)
        self.chord_mid = 0.0
        self.chord_free = 0.0  # how far the chord measurement travelled before meeting the wall
        self.chord_retries = 0
        self.reason = ""  # why the search was lost
        self.z_return: float | None = None  # the height the reference goes back down to after a climb

    def begin(self, ref: pin.SE3, tip: pin.SE3) -> None:
        """Start from the measured tip: the reference moves there first (it drops the approach's wound-up push)."""
        self.chord_retries = 0
        self.chord_free = 0.0
        self.z_return = None
        self.phase = 0
        self.phase_clear = False
        self.phase_time = 0.0
        self.tip_track.clear()
        self.stalled = 0
        self.phase_from = tip.translation.copy()
        self.slide_from = tip.translation.copy()
        self.settled = False  # the reference has reached slide_from
        self.slid = 0.0

    def step(self, ref: pin.SE3, tip: pin.SE3, lead: np.ndarray, mx: float, my: float) -> SearchStep:
        """One control step: "searching", "on_wall" (leaning on the wall on the centred line) or "lost"
        (no wall within max_slide_m; `reason` says so)."""
        c = self.cfg
        # The reference goes to where the probe left the tip at the lift's speed, not in one period: a contact
        # can push the tip 0.7 mm off its held reference while probing, and that jump in one period swung
        # joint 1 past its torque limit (the servo's wound-up integral and damping).
        if not self.settled:
            gap = self.slide_from - ref.translation
            step = c.backoff_speed_mps * self.dt
            left = float(np.linalg.norm(gap))
            ref.translation += gap if left <= step else gap / left * step
            self.settled = left <= step
            return "searching"
        if ref.translation[2] < self.slide_from[2] + c.slide_lift_m:
            ref.translation[2] += c.backoff_speed_mps * self.dt
            return "searching"
        if self.z_return is not None:  # back down after a climb, slowly, while the next move goes on
            ref.translation[2] = max(self.z_return, ref.translation[2] - c.climb_return_speed_mps * self.dt)
            if ref.translation[2] <= self.z_return:
                self.z_return = None
        perp = np.array([-lead[1], lead[0], 0.0])
        # (direction, speed, distance for a fixed move or None to move until blocked, fast distance)
        # The way back across the chord is free as far as where its measurement started (the peg was there).
        phases = [(lead, c.slide_speed_mps, None, c.slide_fast_m),
                  (-lead, c.slide_speed_mps, c.chord_backoff_m, 0.0),
                  (perp, c.chord_speed_mps, None, 0.0),
                  (-perp, c.slide_speed_mps, None, max(0.0, self.chord_free - c.chord_free_margin_m)),
                  (perp, c.slide_speed_mps, 0.0, 0.0),  # to the chord's midpoint (distance set below)
                  (lead, c.chord_speed_mps, None, 0.0)]
        d, v, dist, fast = phases[self.phase]
        if self.phase == 4:
            dist = self.chord_mid
        if dist is None and self.slid >= fast:
            v = c.slide_slow_speed_mps if self.phase == 0 else c.chord_speed_mps
        step = v * self.dt if dist is None else min(v * self.dt, dist - self.slid)
        ref.translation += d * step
        self.slid += step
        moved = float((tip.translation - self.phase_from) @ d)
        lag = self.slid - moved
        self.tip_track.append(float(tip.translation @ d))
        k = c.stall_cycles
        if (dist is None and self.phase_time > c.stall_after_s and len(self.tip_track) > k
                and stalling(self.tip_track[-1] - self.tip_track[-1 - k], v, c, self.dt)):
            self.stalled += 1
        else:
            self.stalled = 0
        m = math.hypot(mx, my)
        # The previous phase's wall contact rings on for a while (the tip springs back, the moment decays):
        # a lag blocks this phase only once the tip has really moved its way, a moment only after it has
        # once dropped off (else a chord can end before it starts).
        if np.isfinite(m) and m < c.block_moment_nm / 2:
            self.phase_clear = True
        done = False
        if dist is not None:
            done = self.slid >= dist - 1e-9 and self.phase_time > 0.1
        elif self.slid > max(fast, c.min_probe_travel_m) and (
                (moved > c.min_probe_travel_m and lag > c.slide_block_m)
                or tip.translation[2] - ref.translation[2] > c.slide_climb_m
                or (moved > c.min_probe_travel_m and self.stalled >= 1)
                or (self.phase_clear and np.isfinite(m) and m > c.block_moment_nm)):
            done = True
        elif self.slid > c.max_slide_m:
            self.reason = (f"moved {self.slid * 1e3:.1f} mm (search phase {self.phase}) without "
                           "meeting the hole's wall")
            return "lost"
        if not done:
            self.phase_time += self.dt
            return "searching"
        log.info("peg-in-hole: search phase %d ended after %.2f mm (lag %.2f mm, lifted %.2f mm, |M| %.2f N·m)",
                 self.phase, self.slid * 1e3, lag * 1e3, (tip.translation[2] - ref.translation[2]) * 1e3, m)
        if dist is None:  # blocked: drop the wound-up reference so the wall is not pushed
            ref.translation[:2] = tip.translation[:2]
            if tip.translation[2] > ref.translation[2] and self.phase < len(phases) - 1:
                # Nor dropped on: a tip that climbed the mouth's edge falls by the whole climb within a period
                # as the next move takes it off the edge, so the reference starts from the tip and goes back
                # down at climb_return_speed_mps (why: docs/peg.md, "The slide").
                self.z_return = float(ref.translation[2])
                ref.translation[2] = tip.translation[2]
        if self.phase == 2:
            self.chord_a = tip.translation.copy()
            self.chord_free = max(0.0, moved)
        if self.phase == 3:
            chord = float((self.chord_a - tip.translation) @ perp)
            self.chord_mid = chord / 2
            if chord < c.min_chord_m and self.chord_retries < c.max_chord_retries:
                # Too short to be the free play across the hole: the peg is still too near the lead wall
                # for its submerged arc to move.  Back off further, again.
                self.chord_retries += 1
                log.info("peg-in-hole: chord %.2f mm too short: measuring again further back", chord * 1e3)
                self.phase = 0  # +1 below: back off along the lead again
        if self.phase == 4:
            self.chord_retries = 0
        if self.phase == len(phases) - 1:
            return "on_wall"
        self.phase += 1
        self.phase_clear = False
        self.phase_from = tip.translation.copy()
        self.slid = 0.0
        self.phase_time = 0.0
        self.tip_track.clear()
        self.stalled = 0
        return "searching"
