"""Collision checks with Pinocchio's geometry model (Coal): the arm and its tool against themselves and fixtures."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from cell.config import SceneConfig
from cell.model.robot import RobotModel

log = logging.getLogger(__name__)

# The tool (sensor + tool body) as a capsule along the flange z axis, from the flange to the TCP.
TOOL_RADIUS = 0.04
FIXTURE_THICKNESS = 0.04  # the table top (or the peg's block) as a box this thick below its top face
PEG_BLOCK_SIZE = (0.12, 0.12)  # the block the peg's hole is cut in, centred on the hole


@dataclass(frozen=True)
class Collision:
    first: str
    second: str

    def __str__(self) -> str:
        return f"{self.first} touches {self.second}"


@dataclass(frozen=True)
class Fixture:
    """A box fixed in the world (a table, a block, the floor): its centre and edge lengths [m]."""

    name: str
    centre: tuple[float, float, float]
    size: tuple[float, float, float]


@dataclass(frozen=True)
class CollisionOptions:
    """What is added to the URDF's link boxes besides the fixtures, and which pairs are checked.

    Pairs on the same or adjacent bodies are never checked (their boxes overlap at the joint by
    construction); nor are fixtures against each other.
    """

    tool_radius: float = TOOL_RADIUS
    tool_capsule: bool = True  # a capsule whose cap ends at the TCP; else a cylinder from the flange to the TCP
    tool_joint_gap: int = 3  # the tool against links this many joints below its own or more: the upper arm, forearm
    check_base: bool = False  # the robot's base against the links, the tool and fixtures
    ignore_pairs: tuple[tuple[str, str], ...] = ()  # by geometry name: pairs that can never meet
    clearance: float = 0.0  # `free` wants every checked pair at least this far apart [m]


def scene_fixtures(scene: SceneConfig, margin: float = 0.0) -> list[Fixture]:
    """The scene's fixture: the table top (scene "table") or the peg's block around the hole (scene "peg"),
    its top face `margin` lower than the working surface; none for a free scene."""
    if scene.kind not in ("table", "peg"):
        return []
    cx, cy = scene.table_center if scene.kind == "table" else scene.hole_center
    sx, sy = scene.table_size if scene.kind == "table" else PEG_BLOCK_SIZE
    z = scene.table_height - FIXTURE_THICKNESS / 2 - margin
    return [Fixture("table", (cx, cy, z), (sx, sy, FIXTURE_THICKNESS))]


class CollisionChecker:
    """Self-collision between non-adjacent bodies, and the links and tool against fixtures (boxes).

    The URDF's collision boxes are coarse link envelopes.  A fixture's top face may be a working
    surface the tool touches: `collisions` skips the tool against fixtures unless asked.  `free` asks
    for `clearance` between every checked pair, except pairs already closer than twice that at the
    `reference` configuration (checked for contact only).
    """

    def __init__(self, robot: RobotModel, fixtures: Sequence[Fixture] = (),
                 options: CollisionOptions | None = None, reference: np.ndarray | None = None) -> None:
        opts = options or CollisionOptions()
        self.robot = robot
        self.options = opts
        model = robot.model
        geom = pin.buildGeomFromUrdf(model, str(robot.urdf), pin.GeometryType.COLLISION)
        links = [i for i, o in enumerate(geom.geometryObjects) if opts.check_base or o.parentJoint > 0]
        self.tool_id = self._add_tool(geom, robot, opts)
        self.fixture_ids = [
            geom.addGeometryObject(pin.GeometryObject(f.name, 0, 0, pin.SE3(np.eye(3), np.array(f.centre, float)),
                                                      coal.Box(*f.size)))
            for f in fixtures
        ]
        self.fixtures = [f.name for f in fixtures]
        objs = geom.geometryObjects
        ignored = {frozenset(p) for p in opts.ignore_pairs}
        bodies = sorted(links + ([self.tool_id] if self.tool_id is not None else []) + self.fixture_ids)
        for i, j in itertools.combinations(bodies, 2):
            gap = abs(objs[i].parentJoint - objs[j].parentJoint)
            if gap <= 1 or frozenset((objs[i].name, objs[j].name)) in ignored:
                continue  # same or adjacent bodies (and fixture vs fixture or base)
            if self.tool_id in (i, j) and gap < opts.tool_joint_gap:
                continue
            geom.addCollisionPair(pin.CollisionPair(i, j))
        self.geom = geom
        self.data = pin.GeometryData(geom)
        self._model_data = model.createData()
        self.pairs = [(objs[p.first].name, objs[p.second].name) for p in geom.collisionPairs]
        tool_fixture = {frozenset((self.tool_id, f)) for f in self.fixture_ids}
        self._tool_fixture_pairs = {k for k, p in enumerate(geom.collisionPairs)
                                    if frozenset((p.first, p.second)) in tool_fixture}
        self.threshold = np.zeros(len(self.pairs))
        if opts.clearance > 0.0:
            if reference is None:
                raise ValueError("a collision clearance needs a reference configuration")
            d0 = self.distances(np.asarray(reference, float))
            self.threshold = np.where(d0 < 2 * opts.clearance, 0.0, opts.clearance)
            near = [f"{a}/{b}" for (a, b), t in zip(self.pairs, self.threshold, strict=True) if t == 0.0]
            if near:
                log.debug("pairs checked for contact only (close at the reference pose): %s", ", ".join(near))

    @staticmethod
    def _add_tool(geom: pin.GeometryModel, robot: RobotModel, opts: CollisionOptions) -> int | None:
        model = robot.model
        flange = model.frames[robot.flange_id]
        tcp = model.frames[robot.tcp_id].placement
        length = float(np.linalg.norm(tcp.translation - flange.placement.translation))
        r = opts.tool_radius
        if opts.tool_capsule:
            # Segment from the flange to one radius short of the TCP, so the cap ends at the TCP.
            seg = max(length - r, 1e-3)
            pose = flange.placement * pin.SE3(np.eye(3), np.array([0.0, 0.0, seg / 2]))
            shape = coal.Capsule(r, seg)
        elif length > 1e-3:
            pose = flange.placement * pin.SE3(np.eye(3), np.array([0.0, 0.0, length / 2]))
            shape = coal.Cylinder(r, length)
        else:
            return None  # no tool to speak of: the TCP is at the flange
        return geom.addGeometryObject(pin.GeometryObject("tool", flange.parentJoint, robot.flange_id, pose, shape))

    @classmethod
    def for_scene(cls, robot: RobotModel, scene: SceneConfig, margin: float = 0.0) -> CollisionChecker:
        """The planner's checker: the arm, the tool (a capsule) and the scene's fixture."""
        return cls(robot, scene_fixtures(scene, margin))

    def collisions(self, q: np.ndarray, tool_may_touch: bool = True) -> list[Collision]:
        """Pairs in contact at q; the tool against a fixture only when `tool_may_touch` is False."""
        pin.computeCollisions(self.robot.model, self._model_data, self.geom, self.data, np.asarray(q, float), False)
        return [Collision(*self.pairs[k]) for k in range(len(self.pairs))
                if not (tool_may_touch and k in self._tool_fixture_pairs)
                and self.data.collisionResults[k].isCollision()]

    def path_collisions(self, qs: np.ndarray, tool_may_touch: bool = True) -> tuple[int, list[Collision]] | None:
        """First sample index along a sampled path that collides, with what touches; None if clear."""
        for i, q in enumerate(qs):
            hits = self.collisions(q, tool_may_touch)
            if hits:
                return i, hits
        return None

    def distances(self, q: np.ndarray) -> np.ndarray:
        """Distance of every checked pair at q [m] (negative: penetration)."""
        pin.computeDistances(self.robot.model, self._model_data, self.geom, self.data, np.asarray(q, float))
        return np.array([r.min_distance for r in self.data.distanceResults])

    def free(self, q: np.ndarray) -> bool:
        """Every checked pair further apart than its clearance (tool against fixtures included)."""
        return bool(np.all(self.distances(q) > self.threshold))

    def colliding_pairs(self, q: np.ndarray) -> list[tuple[str, str]]:
        d = self.distances(q)
        return [nm for nm, di, t in zip(self.pairs, d, self.threshold, strict=True) if di <= t]
