"""Fidelity rigs for tight peg fits: the plant's hole fixture with a free peg, measured through MuJoCo's collider."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import mujoco
import numpy as np

from cell.config import SceneConfig
from sim import mjcf
from sim.contacts import deepest_contact, failed_contact
from sim.profile import ToolProfile

PHYSICS_DT = 0.001  # the plant's physics step (sim/profile.py physics_dt_s)
PEG_FRICTION = ToolProfile().peg_friction


@dataclass(frozen=True)
class Fit:
    """A peg in a hole; clearances are diametral."""

    hole_d: float = 0.0218
    peg_d: float = 0.0217
    depth: float = 0.030
    peg_length: float = 0.048

    @property
    def clearance(self) -> float:
        return self.hole_d - self.peg_d


def predicted_jam_depth(fit: Fit, tilt_rad: float) -> float:
    """Depth of the peg's face centre below the mouth at which a peg tilted by `tilt_rad` wedges (two-point
    contact: the higher bottom corner on one wall, the opposite side on the far edge of the mouth).

    In the tilt plane the peg is a strip D/cos(tilt) wide across the bore: its far side leans on the mouth's
    edge, so its near side reaches the opposite wall at a depth (D_hole - D/cos(tilt)) / tan(tilt) -- the
    classic clearance / tan(tilt) -- measured at the higher corner; the face centre is r sin(tilt) lower."""
    c_eff = fit.hole_d - fit.peg_d / math.cos(tilt_rad)
    return c_eff / math.tan(tilt_rad) + fit.peg_d / 2 * math.sin(tilt_rad)


def _fixture(fit: Fit, segments: int, solimp: str, solref: str) -> tuple[str, str]:
    scene = SceneConfig(kind="peg", table_height=0.0, hole_center=[0.0, 0.0], hole_diameter=fit.hole_d,
                        hole_depth=fit.depth)
    return mjcf.hole_fixture(scene, PEG_FRICTION, segments=segments, solimp=solimp, solref=solref)


def _rig(fit: Fit, segments: int, solimp: str, tilt_rad: float, x0: float, z0: float, mass: float,
         damping: float = 0.0, dt: float = PHYSICS_DT, ccd_tolerance: float = mjcf.CCD_TOLERANCE) -> mujoco.MjModel:
    """The fixture (mouth at z = 0, bore along z) and a peg body on slide joints along world x and z, held at
    `tilt_rad` about y: its origin is the centre of its bottom face, its axis leaning toward +x."""
    r, half = fit.peg_d / 2, fit.peg_length / 2
    asset, fixture = _fixture(fit, segments, solimp, f"{2 * dt:.6g} 1")
    # The peg's own contact parameters, as in the plant (sim/mjcf.py _tool); the fixture's win by priority.
    peg = (f'<body name="peg" pos="{x0:.9g} 0 {z0:.9g}" euler="0 {tilt_rad:.9g} 0">'
           f'<joint name="px" type="slide" axis="1 0 0" damping="{damping:.6g}"/>'
           f'<joint name="pz" type="slide" axis="0 0 1" damping="{damping:.6g}"/>'
           f'<geom name="peg" type="cylinder" pos="0 0 {half:.9g}" size="{r:.9g} {half:.9g}" mass="{mass:.6g}"'
           ' friction="0.25 0.005 0.0001" solref="0.002 1" solimp="0.95 0.99 0.0005"/></body>')
    xml = (f'<mujoco><compiler angle="radian"/><option timestep="{dt}" integrator="implicitfast"'
           f' cone="elliptic" impratio="5" gravity="0 0 0" ccd_tolerance="{ccd_tolerance:.3g}">'
           '<flag multiccd="disable"/></option><size memory="20M"/>'
           f"<asset>{asset}</asset><worldbody>{fixture}{peg}</worldbody></mujoco>")
    return mujoco.MjModel.from_xml_string(xml)


@dataclass(frozen=True)
class Wedge:
    """A tilted peg pushed into the hole until it wedges."""

    tilt_deg: float
    predicted_depth_m: float  # face centre at the wedge (predicted_jam_depth)
    depth_m: float  # measured: where the peg came to rest
    max_penetration_m: float  # deepest peg-fixture contact over the run
    max_contact_force_n: float  # the largest single contact's normal force over the run
    wall_s_per_sim_s: float
    failed_steps: int = 0  # steps whose contacts the collider got wrong (sim/plant.py failed_contact)


def wedge(fit: Fit, tilt_deg: float, push_n: float = 15.0, side_n: float = 3.0, mass: float = 0.6,
          segments: int = mjcf.HOLE_WALL_SEGMENTS, solimp: str = mjcf.FIT_SOLIMP, feed_mps: float = 0.005,
          sim_s: float | None = None, dt: float = PHYSICS_DT, ccd_tolerance: float = mjcf.CCD_TOLERANCE) -> Wedge:
    """Push a peg held at `tilt_deg` down the hole with `push_n` (and `side_n` toward the side it leans on the
    mouth's edge) until it stops; where it stops against predicted_jam_depth, and the contacts' penetration.

    `mass` is what the contact pushes against: the peg tool's 0.6 kg is lighter than the arm's effective mass at
    the tip, and MuJoCo's penetration grows as force / mass, so this bounds the plant's from above."""
    a = math.radians(tilt_deg)
    r = fit.peg_d / 2
    # Start with the peg's +x side through the mouth's +x edge and its lower corner 0.2 mm into the hole.
    z0 = r * math.sin(a) - 0.0002  # face centre
    x_side = fit.hole_d / 2 - 1e-6  # the +x generator passes (just inside) the mouth's edge at z = 0
    # +x generator: centre + r (cos a, 0, -sin a) + s (sin a, 0, cos a); at z = 0: s = (r sin a - z0) / cos a
    s = (r * math.sin(a) - z0) / math.cos(a)
    x0 = x_side - r * math.cos(a) - s * math.sin(a)
    # Viscous slides: the push drives the peg at `feed_mps` in free motion, as the servo feeds the arm's peg
    # (a free 0.6 kg peg under 15 N would hit the wedge at metres per second).
    m = _rig(fit, segments, solimp, a, x0, z0, mass, damping=push_n / feed_mps, dt=dt, ccd_tolerance=ccd_tolerance)
    if sim_s is None:  # long enough to feed past the predicted wedge with room to settle
        sim_s = 0.4 + 1.5 * predicted_jam_depth(fit, a) / feed_mps
    d = mujoco.MjData(m)
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "peg")
    f6 = np.zeros(6)
    steps = int(round(sim_s / dt))
    pen = fmax = 0.0
    failed = 0
    t0 = time.perf_counter()
    for k in range(steps):
        ramp = min(1.0, (k + 1) / (0.1 / dt))  # load up over 0.1 s (no impact at the start)
        d.xfrc_applied[body, :3] = [side_n * ramp, 0.0, -push_n * ramp]
        mujoco.mj_step(m, d)
        failed += failed_contact(m, d) is not None
        pen = max(pen, deepest_contact(d))
        for i in range(d.ncon):
            mujoco.mj_contactForce(m, d, i, f6)
            fmax = max(fmax, float(f6[0]))
    wall = time.perf_counter() - t0
    return Wedge(tilt_deg=tilt_deg, predicted_depth_m=predicted_jam_depth(fit, a), depth_m=-float(d.xpos[body][2]),
                 max_penetration_m=pen, max_contact_force_n=fmax, wall_s_per_sim_s=wall / sim_s, failed_steps=failed)


def bore_error(fit: Fit, segments: int = mjcf.HOLE_WALL_SEGMENTS, samples: int = 9) -> float:
    """Largest error of the bore's diameter as the collider sees it: an upright peg is moved out of the centre in
    `samples` directions across one wall segment (face centre to corner) until the collider reports contact; the
    free travel there and opposite, against the nominal clearance."""
    m = _rig(fit, segments, mjcf.FIT_SOLIMP, 0.0, 0.0, -0.01, 0.6)
    d = mujoco.MjData(m)
    peg = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "peg")
    walls = [g for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
    fromto = np.zeros(6)
    worst = 0.0

    def gap(u: np.ndarray, travel: float) -> float:
        d.qpos[:] = [u[0] * travel, -0.01]  # y is not a joint: only directions in the x-z plane move it ...
        mujoco.mj_forward(m, d)
        return min(mujoco.mj_geomDistance(m, d, peg, w, 0.001, fromto) for w in walls)

    for k in range(samples):
        phi = (math.pi / segments) * k / max(1, samples - 1)  # face centre (0) to corner (pi / n)
        # ... so turn the fixture instead: the peg moves along x, the ring is rotated by -phi.
        m.body_quat[1] = [math.cos(-phi / 2), 0.0, 0.0, math.sin(-phi / 2)]
        span = 0.0
        for sign in (1.0, -1.0):
            lo, hi = 0.0, fit.clearance  # free at the centre, in contact at a whole clearance
            for _ in range(40):
                mid = (lo + hi) / 2
                if gap(np.array([sign, 0.0]), mid) > 0:
                    lo = mid
                else:
                    hi = mid
            span += lo
        worst = max(worst, abs(span - fit.clearance))
    m.body_quat[1] = [1.0, 0.0, 0.0, 0.0]
    return worst
