"""Builds the plant's MuJoCo model (MJCF) from the same URDF, bent by the plant profile, plus a scene."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from cell.config import TOOLS, SceneConfig
from sim.profile import LINKS, PlantProfile

# The hole's wall: a ring of prisms whose inner faces are tangent to the bore.  A round peg touches only the
# faces, so the polygon costs the fit r (1/cos(pi/n) - 1) of its clearance only: measured through the
# collider, the bore's diameter errs by < 2 um at 32 segments (sim/peg_fit.py bore_error).
HOLE_WALL_SEGMENTS = 32
# Peg-on-fixture contacts (the fixture's geoms carry priority: these win over the peg's own, the same today).
# Time constant at twice the 1 ms physics step (MuJoCo's stability floor); at the task's 15 N push a wedged
# peg penetrates 2.5-4 um, within a tenth of a 0.05 mm fit; at 80 N 7-12 um (docs/peg.md).  A
# stiffer impedance (0.99) halves that but raised the survey's touch forces past the task's moment limit.
FIT_SOLREF = "0.002 1"
FIT_SOLIMP = "0.95 0.99 0.0005"
PAD_MASS = 1.0  # kg: a spring-loaded wiping head; a lighter one chatters against the rigid table at 1 ms
# The convex collider's tolerance [m].  Contacts here penetrate 0.1-10 um, so MuJoCo's default (1e-6) is
# as large as the penetration itself: it reversed contact normals in ~5 % of the peg bench's physics steps
# (the peg pulled into the wall it touches: 87 N spikes, jams at the 0.05 mm fit), and its multi-point mode
# (multiccd, off) gave the mouth's corner contacts 20-55 um deep along the wrong face.  See config/plants/README.md.
CCD_TOLERANCE = 1e-9
HOLE_WALL_THICKNESS = 0.012  # m, radial; wide enough to land a peg that is off by a few mm


@dataclass(frozen=True)
class BuiltScene:
    xml: str
    tcp_offset: np.ndarray  # true TCP in the flange frame [m]
    tool_kind: str  # "wipe" or "peg"


def _fmt(v: np.ndarray | list[float]) -> str:
    return " ".join(f"{float(x):.9g}" for x in v)


def _quat(R: np.ndarray) -> str:
    q = pin.Quaternion(R)  # (x, y, z, w)
    return _fmt([q.w, q.x, q.y, q.z])


def _arm_bodies(urdf: Path, profile: PlantProfile) -> tuple[list[str], list[str]]:
    """Opening and closing tags of the arm's body chain, with the profile's true inertial parameters."""
    model = pin.buildModelFromUrdf(str(urdf))
    fr = profile.friction
    opening: list[str] = []
    closing: list[str] = []
    for j in range(1, model.njoints):
        link = LINKS[j - 1]
        placement = model.jointPlacements[j]
        inertia = model.inertias[j]
        mass = inertia.mass * profile.inertial.mass_scale[j - 1]
        com = profile.inertial.com.get(link, list(inertia.lever))
        diag = np.diag(inertia.inertia) * profile.inertial.inertia_scale[j - 1]
        lo, hi = model.lowerPositionLimit[j - 1], model.upperPositionLimit[j - 1]
        opening.append(
            f'<body name="{link}" pos="{_fmt(placement.translation)}" quat="{_quat(placement.rotation)}">'
            f'<inertial pos="{_fmt(com)}" mass="{mass:.6g}" diaginertia="{_fmt(diag)}"/>'
            f'<joint name="j{j}" type="hinge" axis="0 0 1" range="{lo:.6f} {hi:.6f}" limited="true"'
            f' armature="{profile.rotor_inertia[j - 1]:.6g}" damping="{fr.viscous[j - 1]:.6g}"'
            f' actuatorfrcrange="{-model.effortLimit[j - 1]:.6g} {model.effortLimit[j - 1]:.6g}"'
            f' frictionloss="{fr.coulomb[j - 1]:.6g}"/>'
            f'<geom type="capsule" fromto="0 0 0 {_fmt(np.asarray(com) * 1.5)}" size="0.04" rgba=".8 .8 .85 1"'
            f' contype="0" conaffinity="0"/>'
        )
        closing.append("</body>")
    return opening, closing


def _tool(profile: PlantProfile, kind: str) -> tuple[str, np.ndarray]:
    """Sensor + tool bodies on the flange; returns (xml, TCP offset in the flange frame)."""
    s, t = profile.sensor, profile.tool
    parts = [
        f'<body name="ft_sensor"><inertial pos="0 0 {s.length / 2:.6g}" mass="{s.mass:.6g}"'
        f' diaginertia="2e-4 2e-4 2e-4"/>'
        f'<geom type="cylinder" fromto="0 0 0 0 0 {s.length:.6g}" size="0.04" rgba=".3 .3 .3 1"'
        f' contype="0" conaffinity="0"/>'
        f'<body name="tool" pos="0 0 {s.length:.6g}"><site name="ft_site" pos="0 0 0"/>'
    ]
    if kind == "wipe":
        # The pad is its own body on a slide joint along the tool axis: a sprung wiping head whose
        # stiffness and damping are physical (N/m, N·s/m), so the compliance the force loop sees does
        # not depend on the arm's effective mass the way MuJoCo's soft contacts do.  Its contact with
        # the table is frictionless in MuJoCo (condim 1): sliding friction there lifts the head off
        # the table in bursts (the soft-contact solver trades normal against tangential force), so
        # the plant applies the head's Coulomb friction itself (Plant._wipe_friction).
        z = t.wipe_length
        parts.append(
            f'<inertial pos="0 0 {z / 2:.6g}" mass="{t.wipe_mass:.6g}" diaginertia="6e-4 6e-4 2e-4"/>'
            f'<geom type="cylinder" fromto="0 0 0 0 0 {z:.6g}" size="0.015" rgba=".2 .4 .8 1"'
            f' contype="0" conaffinity="0"/>'
            f'<body name="pad_body" pos="0 0 {z:.6g}">'
            f'<joint name="pad_slide" type="slide" axis="0 0 1" range="-0.015 0.005"'
            f' stiffness="{t.pad_stiffness:.6g}" damping="{t.pad_damping:.6g}"/>'
            f'<geom name="pad" type="sphere" size="{t.pad_radius:.6g}" mass="{PAD_MASS}" rgba=".9 .9 .2 1"'
            f' condim="1" solref="0.002 1" solimp="0.95 0.99 0.0005"/>'
            f'</body>'
        )
        tcp = np.array([0.0, 0.0, s.length + z + t.pad_radius])
    else:
        g, r = t.gripper_length, t.peg_diameter / 2
        parts.append(
            f'<inertial pos="0 0 {g / 2:.6g}" mass="{t.gripper_mass:.6g}" diaginertia="8e-4 8e-4 4e-4"/>'
            f'<geom type="box" pos="0 0 {g / 2:.6g}" size="0.03 0.03 {g / 2:.6g}" rgba=".2 .4 .8 1"'
            f' contype="0" conaffinity="0"/>'
            f'<geom name="peg" type="cylinder" pos="0 0 {g + t.peg_length / 2:.6g}"'
            f' size="{r:.6g} {t.peg_length / 2:.6g}" rgba=".8 .5 .2 1" mass="0"'
            f' friction="{t.peg_friction:.6g} 0.005 0.0001" solref="0.002 1" solimp="0.95 0.99 0.0005"/>'
        )
        tcp = np.array([0.0, 0.0, s.length + g + t.peg_length])
    parts.append('<site name="tcp" pos="' + _fmt(tcp - np.array([0, 0, s.length])) + '"/>')
    parts.append("</body></body>")
    return "".join(parts), tcp


def _table(scene: SceneConfig, profile: PlantProfile) -> str:
    cx, cy = scene.table_center
    sx, sy = scene.table_size
    thick = 0.04
    return (
        f'<geom name="table" type="box" pos="{cx:.6g} {cy:.6g} {scene.table_height - thick / 2:.6g}"'
        f' size="{sx / 2:.6g} {sy / 2:.6g} {thick / 2:.6g}" rgba=".6 .45 .3 1"'
        ' condim="1" solref="0.002 1" solimp="0.95 0.99 0.0005"/>'
    )


def hole_fixture(scene: SceneConfig, friction: float, tilt: tuple[float, float] = (0.0, 0.0),
                 segments: int = HOLE_WALL_SEGMENTS, solimp: str = FIT_SOLIMP, solref: str = FIT_SOLREF
                 ) -> tuple[str, str]:
    """A ring of prisms whose inner faces are tangent to the hole (no chamfer), and a bottom plate: the
    fixture's mesh asset and its body.

    Each prism is a segment of the ring, with radial sides that meet its neighbours' face to face: the fixture's
    top is flat.  (Overlapping boxes, as before, left each box's side face buried in its neighbour, and a peg
    rim crossing the line where it met the top touched that buried face: horizontal contacts of 100 N at a 1.5
    mm/s survey touch.)  `tilt` (rad, about world x then y, through the centre of the hole's mouth) tilts the
    whole fixture: the hole axis the peg-in-hole bench hides from the task."""
    cx, cy = scene.hole_center
    r_in = scene.hole_diameter / 2
    depth = scene.hole_depth
    top = scene.table_height
    n = segments
    t = HOLE_WALL_THICKNESS
    # The segment about +x: its inner face is the tangent plane x = r_in, its sides the rays at +-pi/n.
    half = math.tan(math.pi / n)
    corners = [(r, side * r * half) for r in (r_in, r_in + t) for side in (-1, 1)]
    vertex = " ".join(f"{x:.9g} {y:.9g} {z:.9g}" for z in (-depth, 0.0) for x, y in corners)
    mesh = f"hole_wall_{n}"
    asset = f'<mesh name="{mesh}" vertex="{vertex}"/>'
    geoms = [f'<body name="fixture" pos="{cx:.6g} {cy:.6g} {top:.6g}" euler="{tilt[0]:.9g} {tilt[1]:.9g} 0">']
    contact = (f'friction="{friction:.6g} 0.005 0.0001" priority="1" solref="{solref}"'
               f' solimp="{solimp}"')
    for i in range(n):
        geoms.append(f'<geom type="mesh" mesh="{mesh}" euler="0 0 {2 * math.pi * i / n:.9g}"'
                     f' rgba=".5 .5 .55 1" {contact}/>')
    geoms.append(
        f'<geom name="hole_bottom" type="box" pos="0 0 {-depth - 0.005:.6g}" size="{r_in + t:.6g}'
        f' {r_in + t:.6g} 0.005" rgba=".4 .4 .45 1" {contact}/>'
    )
    geoms.append('<site name="hole_top" pos="0 0 0"/>')
    geoms.append("</body>")
    return asset, "".join(geoms)


OBSTACLE_HALF = (0.1, 0.1, 0.01)  # m: the collision bench's plates (half sizes; the face is the xy plane)
OBSTACLE_PLATE_KG = 0.5  # the soft obstacle's plate: a light body on the spring


def _obstacles() -> str:
    """Two plates on mocap bodies, parked far away; the collision bench places one before each scripted
    impact.  `obstacle_rigid` is as stiff as the cell's fixtures; `obstacle_soft` is a light plate on a
    slide joint along its normal whose stiffness and damping (N/m, N·s/m: set per impact) make it a
    linear spring, as the body-region models of ISO/TS 15066 are (MuJoCo's soft contacts would scale
    with the arm's effective mass instead)."""
    hx, hy, hz = OBSTACLE_HALF
    plate = f'type="box" pos="0 0 {-hz:.6g}" size="{hx:.6g} {hy:.6g} {hz:.6g}" condim="3" friction="0.3 0.005 0.0001"'
    stiff = 'solref="0.002 1" solimp="0.95 0.99 0.0005"'
    return (
        '<body name="obstacle_rigid" mocap="true" pos="5 5 -5">'
        f'<geom name="obstacle_rigid" {plate} rgba=".8 .2 .2 .6" {stiff}/></body>'
        '<body name="obstacle_soft_base" mocap="true" pos="-5 5 -5">'
        '<body name="obstacle_soft">'
        '<joint name="obstacle_slide" type="slide" axis="0 0 1" range="-0.08 0.001" stiffness="20000" damping="100"/>'
        f'<geom name="obstacle_soft" {plate} mass="{OBSTACLE_PLATE_KG}" rgba=".2 .8 .2 .6" {stiff}/>'
        "</body></body>"
    )


def build_mjcf(
    urdf: Path, profile: PlantProfile, scene: SceneConfig, physics_dt: float,
    fixture_tilt: tuple[float, float] = (0.0, 0.0),
    tool_kind: str | None = None,
) -> BuiltScene:
    # The peg scene always carries the peg; other scenes the wiping tool unless `tool_kind` names
    # one ("wipe" or "peg"): the free scene collects data and calibrates with either tool mounted.
    kind = tool_kind or ("peg" if scene.kind == "peg" else "wipe")
    if kind not in TOOLS:
        raise ValueError(f"unknown tool {kind!r} ({' or '.join(TOOLS)})")
    opening, closing = _arm_bodies(urdf, profile)
    tool_xml, tcp = _tool(profile, kind)
    world = asset = ""
    if scene.kind == "table":
        world = _table(scene, profile)
    elif scene.kind == "peg":
        asset, world = hole_fixture(scene, profile.tool.peg_friction, fixture_tilt)
    # Bodies with joints of their own come after the arm: the plant takes the first six dofs as the arm's.
    after = _obstacles() if scene.kind == "obstacle" else ""
    # The servo's PD acts through position actuators so that MuJoCo integrates its stiffness and
    # damping implicitly (an explicit PD on the light wrist joints chatters against stiff contacts);
    # a motor per joint carries the servo's feedforward and integral terms.
    sv = profile.servo
    actuators = "".join(
        f'<position name="p{j}" joint="j{j}" kp="{sv.kp[j - 1]:.6g}" kv="{sv.kd[j - 1]:.6g}"/>'
        for j in range(1, 7)
    ) + "".join(f'<motor name="m{j}" joint="j{j}" gear="1"/>' for j in range(1, 7))
    xml = (
        '<mujoco model="tm5-700-plant">'
        '<compiler angle="radian" autolimits="true"/>'
        f'<option timestep="{physics_dt:.6g}" integrator="implicitfast" cone="elliptic" impratio="5"'
        f' ccd_tolerance="{CCD_TOLERANCE:.3g}">'
        '<flag multiccd="disable"/></option>'
        '<size memory="20M"/>'
        + (f"<asset>{asset}</asset>" if asset else "")
        + '<worldbody><geom name="floor" type="plane" size="2 2 0.1" rgba=".9 .9 .9 1" contype="0" conaffinity="0"/>'
        + world
        + '<body name="base">'
        + "".join(opening)
        + tool_xml
        + "".join(closing)
        + "</body>"
        + after
        + "</worldbody>"
        + f"<actuator>{actuators}</actuator>"
        '<sensor><force name="ft_force" site="ft_site"/><torque name="ft_torque" site="ft_site"/></sensor>'
        "</mujoco>"
    )
    return BuiltScene(xml=xml, tcp_offset=tcp, tool_kind=kind)
