"""Point-to-point moves: quintic rest-to-rest timing within the limits, collision-free transfers between
motions, joined motions, and random moves (the test family)."""

from __future__ import annotations

import numpy as np

from cell.collision.geometry import CollisionChecker
from cell.config import CellConfig
from cell.control.trajectory import QUINTIC_PEAK_ACCEL, QUINTIC_PEAK_SPEED, quintic_samples
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.limits import Workspace, excitation_checker, rad_ranges
from cell.data.excitation.motion import Motion, Segment
from cell.model.robot import RobotModel


def _line(q0: np.ndarray, q1: np.ndarray, step: float) -> np.ndarray:
    k = max(2, int(np.ceil(np.max(np.abs(q1 - q0)) / step)) + 1)
    s = np.linspace(0.0, 1.0, k)[:, None]
    return q0 + (q1 - q0) * s


def path_clear(q0: np.ndarray, q1: np.ndarray, cc: CollisionChecker, ws: Workspace, step: float) -> bool:
    return all(cc.free(q) and ws.inside(q) for q in _line(q0, q1, step)[1:-1])


def quintic_duration(q0: np.ndarray, q1: np.ndarray, ws: Workspace, speed: float, step: float) -> float:
    """Shortest quintic rest-to-rest time within joint speed, joint acceleration and TCP speed limits."""
    span = np.abs(q1 - q0)
    t_v = float(np.max(QUINTIC_PEAK_SPEED * span / (ws.vmax * speed)))
    t_a = float(np.max(np.sqrt(QUINTIC_PEAK_ACCEL * span / (ws.amax * speed))))
    pts = np.array([ws.tcp(q) for q in _line(q0, q1, step)])
    # |dp/ds| along the straight joint path; the quintic's ds/dt peaks at 1.875 / T.
    dpds = np.linalg.norm(np.diff(pts, axis=0), axis=1).max() * (len(pts) - 1) if len(pts) > 1 else 0.0
    t_c = QUINTIC_PEAK_SPEED * dpds / (ws.tcp_vmax * speed) * 1.05  # 5 %: the sampled chord under-reads the arc
    return max(t_v, t_a, t_c, 0.3)


def join_motions(motions: list[Motion], robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig) -> Motion:
    """Concatenate motions, inserting a quintic move wherever one ends away from where the next starts."""
    if not motions:
        raise ValueError("nothing to join")
    ws = Workspace(robot, cfg, ex)
    dt = motions[0].dt
    segments: list[Segment] = []
    for p in motions:
        if segments and np.max(np.abs(segments[-1].q[-1] - p.start)) > 1e-9:
            a, b = segments[-1].q[-1], p.start
            T = quintic_duration(a, b, ws, 0.7, ex.path_step_rad)
            segments.append(Segment(quintic_samples(a, b, T, dt, 0.2), -1, -1, 0.7, "transfer"))
        segments.extend(p.segments)
    return Motion(segments, dt, {"parts": [p.info for p in motions]})


def transfer(q_from: np.ndarray, q_to: np.ndarray, robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig,
             dt: float, speed: float = 0.5, tries: int = 400, seed: int = 0) -> list[Segment]:
    """Collision-free moves (traj -1) from one motion's end to the next one's start: straight when the
    straight joint path is clear, else through the home posture (retract, turn joint 1, extend),
    else through one or two random free via configurations (a small randomised search)."""
    cc = excitation_checker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    a, b = np.asarray(q_from, float), np.asarray(q_to, float)
    if np.max(np.abs(a - b)) < 1e-9:
        return []
    home = np.asarray(cfg.robot.home, float)
    via1, via2 = home.copy(), home.copy()
    via1[0], via2[0] = a[0], b[0]

    def clear(x: np.ndarray, y: np.ndarray) -> bool:
        return path_clear(x, y, cc, ws, ex.path_step_rad)

    def ok(route: list[np.ndarray]) -> bool:
        return all(cc.free(p) and ws.inside(p) for p in route[1:-1]) and all(
            clear(x, y) for x, y in zip(route[:-1], route[1:], strict=True))

    route: list[np.ndarray] | None = None
    for cand in ([a, b], [a, via1, via2, b], [a, via1, b], [a, via2, b]):
        if ok(cand):
            route = cand
            break
    if route is None:
        rng = np.random.default_rng(seed)
        lo, hi = rad_ranges(ex.test_ranges_deg, robot)
        vias = [v for v in (rng.uniform(lo, hi) for _ in range(tries)) if cc.free(v) and ws.inside(v)]
        from_a = [v for v in vias if clear(a, v)]
        to_b = [v for v in vias if clear(v, b)]
        both = [v for v in from_a if any(v is w for w in to_b)]
        two = ([a, v, w, b] for v in from_a for w in to_b if clear(v, w))
        route = [a, both[0], b] if both else next(two, None)
    if route is None:
        raise ValueError(f"no collision-free transfer from {np.round(a, 3).tolist()} to {np.round(b, 3).tolist()}")
    out = []
    for x, y in zip(route[:-1], route[1:], strict=True):
        if np.max(np.abs(x - y)) < 1e-9:
            continue
        T = quintic_duration(x, y, ws, speed, ex.path_step_rad)
        out.append(Segment(quintic_samples(x, y, T, dt, 0.1), -1, -1, speed, "transfer"))
    return out



def random_moves(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float, trajectories: int,
                 moves: int, speeds: list[float], repeats: int = 1, seed: int = 1,
                 traj_base: int = 0, segment_base: int = 0) -> Motion:
    """Random point-to-point moves (the test family): random collision-free configurations in
    `test_ranges_deg`, chained; trajectory i runs at speeds[i % len(speeds)]; each one is played
    `repeats` times (there and back again, so repeats stay continuous)."""
    cc = excitation_checker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    lo, hi = rad_ranges(ex.test_ranges_deg, robot)
    rng = np.random.default_rng(seed)
    q = np.asarray(cfg.robot.home, float)
    segments: list[Segment] = []
    seg_id = segment_base
    for i in range(trajectories):
        v = speeds[i % len(speeds)]
        waypoints = [q]
        while len(waypoints) < moves + 1:
            cand = rng.uniform(lo, hi)
            if cc.free(cand) and ws.inside(cand) and path_clear(waypoints[-1], cand, cc, ws, ex.path_step_rad):
                waypoints.append(cand)
        for r in range(repeats):
            pts = waypoints if r % 2 == 0 else waypoints[::-1]
            tid = traj_base + i * repeats + r
            for a, b in zip(pts[:-1], pts[1:], strict=True):
                T = quintic_duration(a, b, ws, v, ex.path_step_rad)
                segments.append(Segment(quintic_samples(a, b, T, dt, 0.25), tid, seg_id, v, "random"))
                seg_id += 1
        q = waypoints[-1] if repeats % 2 == 1 else waypoints[0]
    return Motion(segments, dt, {"trajectories": trajectories * repeats, "moves_per_trajectory": moves,
                               "speeds": list(speeds), "repeats": repeats})
