"""What planned motion must respect, checked ahead of time: no self- or fixture-collision (Pinocchio + Coal),
the TCP inside the safety workspace, joint ranges, joint and TCP speed limits."""

from __future__ import annotations

import numpy as np

from cell.collision.geometry import FIXTURE_THICKNESS, CollisionChecker, CollisionOptions, Fixture
from cell.config import CellConfig
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.motion import Motion
from cell.model.robot import RobotModel

LIMIT_MARGIN_RAD = np.radians(2.0)  # the servo overshoots a target at the limit by a hair; stay clear


def rad_ranges(ranges_deg: list[list[float]], robot: RobotModel) -> tuple[np.ndarray, np.ndarray]:
    """Joint ranges [deg] as (low, high) in radians, kept LIMIT_MARGIN_RAD inside the position limits."""
    r = np.radians(np.asarray(ranges_deg, float))
    lim = robot.limits
    return np.maximum(r[:, 0], lim.lower + LIMIT_MARGIN_RAD), np.minimum(r[:, 1], lim.upper - LIMIT_MARGIN_RAD)


def excitation_checker(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig,
                       reference: np.ndarray | None = None) -> CollisionChecker:
    """The collision checker excitation motion must satisfy: the URDF's boxes, the tool (a cylinder from the
    flange to the TCP), the table of the cell's scene and the floor, every pair on non-adjacent bodies but
    `ex.ignore_pairs` kept `ex.clearance_m` apart (contact only for pairs already that close at `reference`,
    default home)."""
    fixtures: list[Fixture] = []
    sc = cfg.scene
    if sc.kind in ("table", "peg"):
        z = sc.table_height - FIXTURE_THICKNESS / 2
        fixtures.append(Fixture("table", (sc.table_center[0], sc.table_center[1], z),
                                (sc.table_size[0], sc.table_size[1], FIXTURE_THICKNESS)))
    if ex.floor:
        fixtures.append(Fixture("floor", (0.0, 0.0, -0.05), (4.0, 4.0, 0.1)))
    options = CollisionOptions(tool_radius=ex.tool_radius_m, tool_capsule=False, tool_joint_gap=2, check_base=True,
                               ignore_pairs=tuple((a, b) for a, b in ex.ignore_pairs), clearance=ex.clearance_m)
    ref = np.asarray(reference if reference is not None else cfg.robot.home, float)
    return CollisionChecker(robot, fixtures, options, ref)


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


def check_motion(motion: Motion, robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig,
                 stride: int = 5) -> list[str]:
    """Problems a motion would run into (limits, workspace, collisions, speed); empty when fine."""
    cc = excitation_checker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    q = np.vstack([s.q for s in motion.segments])
    problems = []
    dq = np.diff(q, axis=0) / motion.dt
    if np.any(np.abs(dq) > robot.limits.velocity * cfg.safety.joint_speed_fraction):
        problems.append("joint speed above the safety limit")
    if np.any(q < robot.limits.lower) or np.any(q > robot.limits.upper):
        problems.append("joint position outside the limits")
    tcp = np.array([ws.tcp(x) for x in q])
    if np.any(tcp < np.asarray(cfg.safety.workspace_min)) or np.any(tcp > np.asarray(cfg.safety.workspace_max)):
        problems.append("TCP outside the safety workspace")
    v = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / motion.dt
    if v.max(initial=0.0) > cfg.safety.max_tcp_speed:
        problems.append(f"TCP speed {v.max():.2f} m/s above the safety limit")
    for x in q[::stride]:
        if not cc.free(x):
            problems.append(f"collision {cc.colliding_pairs(x)} at q={np.round(x, 3).tolist()}")
            break
    return problems
