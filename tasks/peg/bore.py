"""Tight fits: centre the upright peg on the bore by running it once round the bore's wall, then hold it there."""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np
import pinocchio as pin

from tasks.peg.config import PegConfig
from tasks.peg.twist import Twist

log = logging.getLogger(__name__)

BoreStep = Literal["centring", "centred"]


def fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle through points (n, 2): centre and radius (algebraic fit, Kasa)."""
    a = np.column_stack([2 * xy, np.ones(len(xy))])
    b = (xy**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:2]
    return centre, float(math.sqrt(max(sol[2] + centre @ centre, 0.0)))


def arc_span(xy: np.ndarray, centre: np.ndarray) -> float:
    """The angle [rad] the points cover around `centre` (2 pi less the largest gap between them)."""
    a = np.sort(np.arctan2(xy[:, 1] - centre[1], xy[:, 0] - centre[0]))
    gaps = np.diff(np.concatenate([a, a[:1] + 2 * math.pi]))
    return float(2 * math.pi - gaps.max())


class BoreCentring:
    """With a fit of a few hundredths of a millimetre the wall search's chord, measured with the peg tilted,
    leaves the upright peg off the bore's axis by about its whole clearance: pushed in, its side presses one
    wall, the stiff arm holds it there (measured: 50-100 N of wall force, at friction 0.25 more than the 15 N
    push) and compliance on the virtual moments bangs it from wall to wall -- the 0.1 mm fit's jams.

    The bore measures itself instead.  With the peg upright and a little way in, its reference runs round a
    circle a little wider than the bore (radial clearance + `bore_orbit_press_m`) about the chord's centre: the
    wall stops the tip everywhere, so the tip traces the bore (offset by the clearance) while pressing it lightly
    and sliding round.  A circle fitted to the tip's path is the bore's centre -- kinematics only, free of the
    force source's errors.  The joints stick and slip at these few micrometres (their static friction, ~0.2 mm at
    the tip for the servo's stiffness, holds the tip until the integral breaks it free: an axis-by-axis touch was
    pinned by it), so the tip dwells where it started -- against the wall the chord left it on, itself a point of
    the bore's circle -- and then slides over an arc of it: the free fit through both is the bore's.  The fit
    counts if its radius is the radial clearance and its centre within two clearances of the start; else the peg
    stays where it was.  (Counting only paths round most of the bore, or fixing the radius on short arcs, did
    worse: 0.20 and ~0.1 success against 0.85 on the same 20 trials.)"""

    def __init__(self, cfg: PegConfig, dt: float, radial_clearance: float) -> None:
        self.cfg = cfg
        self.dt = dt
        self.rc = radial_clearance
        self.active = False
        self.centre: np.ndarray | None = None  # the bore's centre (hole-frame x, y) once measured
        self.orbits = 0
        self._c0 = np.zeros(2)  # the orbit's centre: the reference where the centring began
        self._angle = 0.0
        self._radius = 0.0
        self._path: list[np.ndarray] = []
        self._target: np.ndarray | None = None  # after the orbit: where the reference goes (the fitted centre)
        self.twist = Twist(cfg, dt)

    def begin(self, ref: pin.SE3, tip: pin.SE3) -> None:
        """Start (again) from the measured tip: the reference drops any wound-up push and lateral lead."""
        ref.translation[:] = tip.translation
        self.active = True
        self._c0 = (self.centre if self.centre is not None else tip.translation[:2]).copy()
        self._angle = 0.0
        self._radius = 0.0
        self._path = []
        self._target = None

    def step(self, ref: pin.SE3, tip: pin.SE3) -> BoreStep:
        c = self.cfg
        v = c.bore_orbit_speed_mps * self.dt
        if self._target is not None:  # to the measured centre
            left = self._target - ref.translation[:2]
            d = float(np.linalg.norm(left))
            ref.translation[:2] += left if d <= v else left * (v / d)
            if d <= v:
                self.active = False
                return "centred"
            return "centring"
        r_orbit = self.rc + c.bore_orbit_press_m
        if self._radius < r_orbit:  # out from the centre to the orbit, along its first direction
            self._radius = min(r_orbit, self._radius + v)
        else:
            self._angle += v / r_orbit
            if self._angle > math.pi / 4:  # the tip has reached the wall and settled there: record its path
                self._path.append(tip.translation[:2].copy())
        end = math.pi / 4 + math.radians(c.bore_orbit_deg)
        a = min(self._angle, end)
        ref.translation[:2] = self._c0 + self._radius * np.array([math.cos(a), math.sin(a)])
        if self._angle < end:
            return "centring"
        self.orbits += 1
        path = np.array(self._path)
        centre, radius = fit_circle(path)
        span = arc_span(path, centre)
        near = float(np.linalg.norm(centre - self._c0)) <= 2 * self.rc
        ok = abs(radius - self.rc) <= c.bore_radius_tolerance_m and near
        log.info("peg-in-hole: bore traced over %.0f deg (free radius %.1f um, nominal radial clearance %.1f), centre "
                 "%+.1f, %+.1f um from the chord's%s", math.degrees(span), radius * 1e6, self.rc * 1e6,
                 *((centre - self._c0) * 1e6), "" if ok else ": not the bore, not used")
        if ok:
            self.centre = centre
        self._target = self.centre if self.centre is not None else self._c0.copy()
        return "centring"

    def hold(self, ref: pin.SE3, tip: pin.SE3) -> None:
        """At tight fits, between orbits: keep the reference's compliant lateral shift within `bore_hold_fraction` of
        the radial clearance of the measured centre (beyond it the peg's side can only press into the wall), keep it
        within `bore_tether_fraction` of the clearance of the measured tip (the peg cannot follow it further; this
        holds when the orbit found no bore, or the peg was measured elsewhere since), and twist the peg."""
        if self.rc > self.cfg.bore_centring_below_m or self.active:
            return
        if self.centre is not None:
            off = ref.translation[:2] - self.centre
            r = float(np.linalg.norm(off))
            limit = self.cfg.bore_hold_fraction * self.rc
            if r > limit:
                ref.translation[:2] = self.centre + off * (limit / r)
        lead = ref.translation[:2] - tip.translation[:2]
        d = float(np.linalg.norm(lead))
        tether = self.cfg.bore_tether_fraction * self.rc
        if d > tether:
            ref.translation[:2] = tip.translation[:2] + lead * (tether / d)
        self.twist.step(ref)
