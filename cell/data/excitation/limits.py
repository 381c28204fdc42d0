"""What planned motion must respect, checked ahead of time: no self- or fixture-collision (Pinocchio + Coal),
the TCP inside the safety workspace, joint ranges, joint and TCP speed limits."""

from __future__ import annotations

import itertools
import logging

import coal
import numpy as np
import pinocchio as pin

from cell.config import CellConfig
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.plan import Plan
from cell.model.robot import RobotModel

log = logging.getLogger(__name__)


LIMIT_MARGIN_RAD = np.radians(2.0)  # the servo overshoots a target at the limit by a hair; stay clear


def rad_ranges(ranges_deg: list[list[float]], robot: RobotModel) -> tuple[np.ndarray, np.ndarray]:
    """Joint ranges [deg] as (low, high) in radians, kept LIMIT_MARGIN_RAD inside the position limits."""
    r = np.radians(np.asarray(ranges_deg, float))
    lim = robot.limits
    return np.maximum(r[:, 0], lim.lower + LIMIT_MARGIN_RAD), np.minimum(r[:, 1], lim.upper - LIMIT_MARGIN_RAD)


class CollisionChecker:
    """Self- and fixture-collision checks on the URDF's collision geometry (Pinocchio + Coal).

    Added to the URDF's boxes: the tool (a cylinder from the flange to the TCP), the table of the
    cell's scene, and the floor.  Pairs on adjacent links are never checked (their boxes overlap at
    the joint by construction); pairs that already sit closer than the clearance at the reference
    configuration are checked for contact only.
    """

    def __init__(self, robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig,
                 reference: np.ndarray | None = None) -> None:
        self.robot = robot
        self.model = robot.model
        self.data = self.model.createData()
        gm = pin.buildGeomFromUrdf(self.model, str(robot.urdf), pin.GeometryType.COLLISION)
        n = self.model.nv
        flange = self.model.frames[robot.flange_id]
        tcp = self.model.frames[robot.tcp_id].placement
        length = float(np.linalg.norm(flange.placement.actInv(tcp).translation))
        if length > 1e-3:
            centre = flange.placement * pin.SE3(np.eye(3), np.array([0.0, 0.0, length / 2]))
            gm.addGeometryObject(pin.GeometryObject(
                "tool", flange.parentJoint, robot.flange_id, centre, coal.Cylinder(ex.tool_radius_m, length)))
        fixtures: list[str] = []
        sc = cfg.scene
        if sc.kind in ("table", "peg"):
            thick = 0.04
            pose = pin.SE3(np.eye(3), np.array([sc.table_center[0], sc.table_center[1], sc.table_height - thick / 2]))
            gm.addGeometryObject(pin.GeometryObject(
                "table", 0, 0, pose, coal.Box(sc.table_size[0], sc.table_size[1], thick)))
            fixtures.append("table")
        if ex.floor:
            gm.addGeometryObject(pin.GeometryObject(
                "floor", 0, 0, pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.05])), coal.Box(4.0, 4.0, 0.1)))
            fixtures.append("floor")
        self.fixtures = fixtures
        objs = gm.geometryObjects
        ignored = {frozenset(p) for p in ex.ignore_pairs}
        for i, j in itertools.combinations(range(len(objs)), 2):
            ji, jj = objs[i].parentJoint, objs[j].parentJoint
            if abs(ji - jj) <= 1:
                continue  # same or adjacent bodies (and fixture vs fixture / base / link 1)
            if frozenset((objs[i].name, objs[j].name)) in ignored:
                continue
            gm.addCollisionPair(pin.CollisionPair(i, j))
        self.geom = gm
        self.gdata = pin.GeometryData(gm)
        ref = np.asarray(reference if reference is not None else cfg.robot.home, float)
        d0 = self.distances(ref)
        self.threshold = np.where(d0 < 2 * ex.clearance_m, 0.0, ex.clearance_m)
        self.names = [(objs[p.first].name, objs[p.second].name) for p in gm.collisionPairs]
        near = [f"{a}/{b}" for (a, b), t in zip(self.names, self.threshold, strict=True) if t == 0.0]
        if near:
            log.debug("pairs checked for contact only (close at the reference pose): %s", ", ".join(near))
        self.n = n

    def distances(self, q: np.ndarray) -> np.ndarray:
        pin.computeDistances(self.model, self.data, self.geom, self.gdata, np.asarray(q, float))
        return np.array([r.min_distance for r in self.gdata.distanceResults])

    def free(self, q: np.ndarray) -> bool:
        return bool(np.all(self.distances(q) > self.threshold))

    def colliding_pairs(self, q: np.ndarray) -> list[tuple[str, str]]:
        d = self.distances(q)
        return [nm for nm, di, t in zip(self.names, d, self.threshold, strict=True) if di <= t]


class Workspace:
    """The safety monitor's TCP box (shrunk by a margin) and its speed limits, checked ahead of time."""

    def __init__(self, robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig) -> None:
        self.robot = robot
        self.lo = np.asarray(cfg.safety.workspace_min, float) + ex.workspace_margin_m
        self.hi = np.asarray(cfg.safety.workspace_max, float) - ex.workspace_margin_m
        lim = robot.limits
        self.vmax = lim.velocity * cfg.safety.joint_speed_fraction * ex.joint_speed_fraction
        self.tcp_vmax = cfg.safety.max_tcp_speed * ex.tcp_speed_fraction
        self.amax = np.asarray(ex.max_accel, float)
        self.lower, self.upper = lim.lower, lim.upper

    def tcp(self, q: np.ndarray) -> np.ndarray:
        return self.robot.tcp_pose(q).translation.copy()

    def inside(self, q: np.ndarray) -> bool:
        p = self.tcp(q)
        return bool(np.all(p >= self.lo) and np.all(p <= self.hi))



def trajectory_ok(q: np.ndarray, cc: CollisionChecker, ws: Workspace, dt: float, stride: int) -> bool:
    """Samples `q` within the joint limits; every `stride`-th one free, inside the workspace, under the TCP speed."""
    if np.any(q < ws.lower) or np.any(q > ws.upper):
        return False
    pts = q[::stride]
    for x in pts:
        if not (ws.inside(x) and cc.free(x)):
            return False
    tcp = np.array([ws.tcp(x) for x in pts])
    speed = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / (dt * stride)
    return bool(speed.max(initial=0.0) <= ws.tcp_vmax)



def check_plan(plan: Plan, robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, stride: int = 5) -> list[str]:
    """Problems a plan would run into (limits, workspace, collisions, speed); empty when fine."""
    cc = CollisionChecker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    q = np.vstack([s.q for s in plan.segments])
    problems = []
    dq = np.diff(q, axis=0) / plan.dt
    if np.any(np.abs(dq) > robot.limits.velocity * cfg.safety.joint_speed_fraction):
        problems.append("joint speed above the safety limit")
    if np.any(q < robot.limits.lower) or np.any(q > robot.limits.upper):
        problems.append("joint position outside the limits")
    tcp = np.array([ws.tcp(x) for x in q])
    if np.any(tcp < np.asarray(cfg.safety.workspace_min)) or np.any(tcp > np.asarray(cfg.safety.workspace_max)):
        problems.append("TCP outside the safety workspace")
    v = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / plan.dt
    if v.max(initial=0.0) > cfg.safety.max_tcp_speed:
        problems.append(f"TCP speed {v.max():.2f} m/s above the safety limit")
    for x in q[::stride]:
        if not cc.free(x):
            problems.append(f"collision {cc.colliding_pairs(x)} at q={np.round(x, 3).tolist()}")
            break
    return problems
