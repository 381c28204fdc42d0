"""Guarded moves onto stiff contacts: touch detection from Fz, and a descent whose lead is cut when the tip stalls."""

from __future__ import annotations

import collections
from typing import Literal

import numpy as np
import pinocchio as pin

from tasks.peg.config import PegConfig
from tasks.peg.geometry import rim_points

Touch = Literal["free", "hold", "touch"]


def stalling(progress: float, v: float, cfg: PegConfig, dt: float) -> bool:
    """The tip's `progress` over the last `stall_cycles` cycles is under `stall_fraction` of what a
    move at `v` commanded: something stops it (the one stall test of descents and search moves)."""
    return progress < cfg.stall_fraction * v * cfg.stall_cycles * dt


class GuardedDescent:
    """A guarded move's touch detection and descent; the task's reference and measured tip are passed in
    (hole frame), the reference is moved in place."""

    def __init__(self, cfg: PegConfig, dt: float) -> None:
        self.cfg = cfg
        self.dt = dt
        self.radius = cfg.peg_diameter_m / 2
        self.touching = 0  # Fz crossings counted since the first one
        self.touch_point = np.zeros(3)  # the lowest rim point at the first crossing
        self.touch_t = 0.0
        self.z_track: collections.deque[float] = collections.deque(maxlen=2 * cfg.stall_cycles + 1)  # tip z
        self.pressing = False  # the descent decelerated as on a contact: the lead is cut to touch_lead_m
        self.press_z = 0.0  # the tip's height when it stalled
        self.descend_t = -1.0  # the task time of the last descent step
        self.fz_window: collections.deque[float] = collections.deque(maxlen=cfg.touch_mean_cycles)  # Fz read

    def touch(self, fz: float, cycles: int, ref: pin.SE3, tip: pin.SE3) -> Touch:
        """Touch detection for a guarded move: "free", "hold" (stopped, confirming) or "touch".

        The contacts are stiff and bounce (Fz alternates 0 / 40 N from cycle to cycle), and the servo's
        tracking lag goes on pressing: stop at the first crossing (the reference to the measured tip, the
        touch point recorded) and confirm with `cycles` crossings in all within survey_confirm_s; a lone
        spike (a sensor transient) lets the move go on.  Fz is the mean of the last touch_mean_cycles
        readings (see PegConfig.touch_mean_cycles)."""
        c = self.cfg
        if np.isfinite(fz):
            self.fz_window.append(fz)
            fz = sum(self.fz_window) / len(self.fz_window)
        # A tip stalled in its descent (see descend) is kinematic evidence of a touch: the wrench need only
        # agree at touch_force_n (the lead cut to touch_lead_m presses with a few N only).
        threshold = c.touch_force_n if self.pressing else c.contact_force_n
        if np.isfinite(fz) and fz > threshold:
            if self.touching == 0:
                self.touch_point = rim_points(tip, self.radius)[0]
                self.touch_t = 0.0
                ref.translation[:] = tip.translation
            self.touching += 1
        elif self.touching:
            self.touch_t += self.dt
            if self.touch_t > c.survey_confirm_s:
                self.touching = 0
                return "free"
        if self.touching >= cycles:
            self.touching = 0
            self.pressing = False
            self.fz_window.clear()  # the next guarded move starts from its own readings
            return "touch"
        return "hold" if self.touching else "free"

    def descend(self, v: float, t: float, ref: pin.SE3, tip: pin.SE3) -> None:
        """Lower the reference at `v`, but never more than max_lead_m ahead of the measured tip: after a fast
        move the tip still trails, and that windup would press into a contact before it is seen.  A tip that
        was descending and has stalled (its last `stall_cycles` progress under stall_fraction of the
        commanded, the ones before over half of it) is on something: the reference is drawn back to
        touch_lead_m ahead until the tip moves on below where it stalled -- the force on a stiff face stays
        bounded while the wrench confirms the touch, also while the tip bounces on it."""
        c = self.cfg
        z_now = float(tip.translation[2])
        if abs(t - self.dt - self.descend_t) > 0.5 * self.dt:  # a new descent (or one resumed after a hold)
            self.z_track.clear()
            self.pressing = False
        self.descend_t = t
        self.z_track.append(z_now)
        k = c.stall_cycles
        if len(self.z_track) == self.z_track.maxlen:
            before = self.z_track[0] - self.z_track[k]
            recent = self.z_track[k] - self.z_track[-1]
            step = v * k * self.dt
            if stalling(recent, v, c, self.dt) and before > 0.5 * step:
                if not self.pressing:
                    self.press_z = z_now
                self.pressing = True
            elif recent > 0.5 * step and z_now < self.press_z - 0.5 * c.max_lead_m:
                # Moving on below where it stopped: it was a stick, not a face.  A tip that bounced off the
                # face and is falling back onto it is not below that height: the lead stays cut (given
                # back, it presses the next impact into the face: docs/peg.md, "Touches").
                self.pressing = False
        z = float(ref.translation[2]) - v * self.dt
        if self.pressing:  # take back the lead the servo had wound up: it presses into the face
            ref.translation[2] = max(z, z_now - c.touch_lead_m)
        else:
            ref.translation[2] = max(z, min(float(ref.translation[2]), z_now - c.max_lead_m))
