"""Tight fits: turn the peg to and fro about its own axis while it slides in the bore (screw insertion)."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from tasks.peg.config import PegConfig


class Twist:
    """Friction at the wall opposes the peg's sliding velocity there.  Fed straight in, all of it opposes the feed:
    with the servo's integral pressing the peg on the wall with tens of newtons (the joints' static friction holds
    the tip off its reference by more than a tight fit's clearance), that is more than the push.  Turning the peg
    about its own axis at a surface speed well above the feed's makes the sliding mostly round the bore, so the
    wall's friction mostly opposes the turn (carried by the wrist's last joint) and only the share v_feed / |v|
    opposes the feed, and the contact slides instead of sticking and slipping.  The peg is round: its turn about
    its own axis changes nothing else the task uses (the axis, the tip's position, the rim points)."""

    def __init__(self, cfg: PegConfig, dt: float) -> None:
        self.amplitude = math.radians(cfg.twist_amplitude_deg)
        self.omega = 2 * math.pi * cfg.twist_frequency_hz
        self.dt = dt
        self.t = 0.0
        self.angle = 0.0  # the twist now applied to the reference, about its own axis

    def step(self, ref: pin.SE3) -> None:
        """Advance the twist by one period: rotate `ref` about its own axis by the change in angle."""
        if self.amplitude <= 0:
            return
        self.t += self.dt
        angle = self.amplitude * math.sin(self.omega * self.t)
        ref.rotation = ref.rotation @ pin.exp3(np.array([0.0, 0.0, angle - self.angle]))
        self.angle = angle
