"""Collision checks with Pinocchio's geometry model (Coal): the arm against itself and the cell's fixtures."""

from __future__ import annotations

from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from cell.config import SceneConfig
from cell.model.robot import RobotModel

# The tool (sensor + tool body) as a capsule along the flange z axis, from the flange to the TCP.
TOOL_RADIUS = 0.04


@dataclass(frozen=True)
class Collision:
    first: str
    second: str

    def __str__(self) -> str:
        return f"{self.first} touches {self.second}"


class CollisionChecker:
    """Self-collision between non-adjacent links, and links/tool against the scene's fixtures.

    The URDF's collision boxes are coarse link envelopes; the fixtures come from the scene config
    (table top as a box; its top face is the working surface, so the tool may touch it: the tool is
    only checked against fixtures when `tool_may_touch` is False).
    """

    def __init__(self, robot: RobotModel, scene: SceneConfig, margin: float = 0.0) -> None:
        self.robot = robot
        model = robot.model
        self.geom = pin.buildGeomFromUrdf(model, str(robot.urdf), pin.GeometryType.COLLISION)
        tool_len = float(np.linalg.norm(robot.model.frames[robot.tcp_id].placement.translation
                                        - robot.model.frames[robot.flange_id].placement.translation))
        flange = model.frames[robot.flange_id]
        # Capsule segment from the flange to one radius short of the TCP, so its cap ends at the TCP.
        seg = max(tool_len - TOOL_RADIUS, 1e-3)
        tool_pose = flange.placement * pin.SE3(np.eye(3), np.array([0.0, 0.0, seg / 2]))
        self.tool_id = self.geom.addGeometryObject(
            pin.GeometryObject("tool", flange.parentJoint, tool_pose, coal.Capsule(TOOL_RADIUS, seg))
        )
        self.fixture_ids: list[int] = []
        if scene.kind in ("table", "peg"):
            cx, cy = scene.table_center if scene.kind == "table" else scene.hole_center
            sx, sy = scene.table_size if scene.kind == "table" else (0.12, 0.12)
            thick = 0.04
            pose = pin.SE3(np.eye(3), np.array([cx, cy, scene.table_height - thick / 2 - margin]))
            self.fixture_ids.append(
                self.geom.addGeometryObject(pin.GeometryObject("table", 0, pose, coal.Box(sx, sy, thick)))
            )
        names = [o.name for o in self.geom.geometryObjects]
        self.names = names
        link_ids = [i for i, o in enumerate(self.geom.geometryObjects) if o.parentJoint > 0 and i != self.tool_id]
        for a in range(len(link_ids)):
            for b in range(a + 1, len(link_ids)):
                ja = self.geom.geometryObjects[link_ids[a]].parentJoint
                jb = self.geom.geometryObjects[link_ids[b]].parentJoint
                if abs(ja - jb) > 1:  # adjacent links overlap at their joint by construction
                    self.geom.addCollisionPair(pin.CollisionPair(link_ids[a], link_ids[b]))
        # The tool against the upper arm and forearm (it can fold back onto them).
        for i in link_ids:
            if self.geom.geometryObjects[i].parentJoint <= 3:
                self.geom.addCollisionPair(pin.CollisionPair(i, self.tool_id))
        # Links 1-5 against fixtures; the tool against fixtures is checked on request.
        self._tool_fixture_pairs = []
        for f in self.fixture_ids:
            for i in link_ids:
                if self.geom.geometryObjects[i].parentJoint >= 2:
                    self.geom.addCollisionPair(pin.CollisionPair(i, f))
            self._tool_fixture_pairs.append(len(self.geom.collisionPairs))
            self.geom.addCollisionPair(pin.CollisionPair(self.tool_id, f))
        self.data = pin.GeometryData(self.geom)
        self._model_data = model.createData()

    def collisions(self, q: np.ndarray, tool_may_touch: bool = True) -> list[Collision]:
        pin.computeCollisions(self.robot.model, self._model_data, self.geom, self.data, np.asarray(q, float), False)
        found = []
        for k, pair in enumerate(self.geom.collisionPairs):
            if tool_may_touch and k in self._tool_fixture_pairs:
                continue
            if self.data.collisionResults[k].isCollision():
                found.append(Collision(self.names[pair.first], self.names[pair.second]))
        return found

    def path_collisions(self, qs: np.ndarray, tool_may_touch: bool = True) -> tuple[int, list[Collision]] | None:
        """First sample index along a sampled path that collides, with what touches; None if clear."""
        for i, q in enumerate(qs):
            hits = self.collisions(q, tool_may_touch)
            if hits:
                return i, hits
        return None
