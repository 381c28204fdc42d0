"""Motion generators for data collection: the paper's digitised-configuration chain, Fourier excitation, random moves.

All of them return a `Plan`: joint-position samples at the control period, cut into segments (moves)
and trajectories, that avoid self-collision and the cell's fixtures (Pinocchio geometry / Coal on the
URDF's collision boxes plus the tool, the table and the floor), keep the TCP inside the safety
workspace, and respect joint speed, joint acceleration and commanded TCP speed limits.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import coal
import numpy as np
import pinocchio as pin

from cell.config import CellConfig
from cell.configio import join, load_dataclass, read_yaml, require
from cell.robot import RobotModel

log = logging.getLogger(__name__)

QUINTIC_PEAK_SPEED = 1.875  # max of d/ds of 10s^3 - 15s^4 + 6s^5
QUINTIC_PEAK_ACCEL = 5.7735  # max of d2/ds2 of the same


# ----------------------------------------------------------------------------------------- config
@dataclass
class FourierConfig:
    """Identification-grade excitation: finite Fourier series per joint (Swevers' parameterisation)."""

    harmonics: int = 5
    base_hz: float = 0.1  # fundamental: one period is 1 / base_hz seconds
    periods: int = 2
    ramp_s: float = 2.0  # smooth fade in/out so the trajectory starts and ends at rest
    candidates: int = 20  # random coefficient sets tried; the lowest condition number wins
    trajectories: int = 4  # independent excitation trajectories (each around its own centre)
    amplitude_fraction: float = 0.8  # of the room to the position limits around the centre
    centre_margin: float = 0.1  # centres are drawn in the joint ranges less this fraction at each end

    def validate(self, where: str) -> None:
        require(1 <= self.harmonics <= 20, join(where, "harmonics"), "must lie in 1..20")
        require(0 < self.base_hz <= 2, join(where, "base_hz"), "must lie in (0, 2] Hz")
        require(self.periods >= 1, join(where, "periods"), "must be >= 1")
        require(self.ramp_s > 0, join(where, "ramp_s"), "must be > 0")
        require(self.candidates >= 1, join(where, "candidates"), "must be >= 1")
        require(0 < self.amplitude_fraction <= 1, join(where, "amplitude_fraction"), "must lie in (0, 1]")
        require(0 <= self.centre_margin < 0.5, join(where, "centre_margin"), "must lie in [0, 0.5)")


@dataclass
class ExcitationConfig:
    """Joint ranges (a workspace restriction inside the hardware limits) and generator settings.

    The defaults keep the paper's workspace restrictions J2 +-80 deg and J3 +-150 deg (not the hardware
    limits, +-180 and +-155) and narrow J1 and J6 from the paper's +-270 to +-150 / +-180 deg: under the
    cell's commanded TCP speed limit, a 540 deg swing of J1 is a slow sweep during which every other
    joint crawls, which starves identification of acceleration.  J1-J3 get 4 steps (5 values each).
    """

    ranges_deg: list[list[float]] = field(default_factory=lambda: [
        [-150, 150], [-80, 80], [-150, 150], [-180, 180], [-180, 180], [-180, 180]])
    steps: list[int] = field(default_factory=lambda: [4, 4, 4, 2, 2, 2])  # N: N + 1 values per joint
    speeds: list[float] = field(default_factory=lambda: [0.4, 0.7, 1.0])  # V: fractions of the allowed speed
    max_configs: int = 0  # 0: every collision-free configuration; else this many drawn at random
    max_accel: list[float] = field(default_factory=lambda: [5.0, 5.0, 6.0, 8.0, 8.0, 8.0])  # rad/s^2
    joint_speed_fraction: float = 0.9  # of the safety monitor's joint speed limit
    tcp_speed_fraction: float = 0.85  # of the safety monitor's commanded TCP speed limit
    workspace_margin_m: float = 0.03  # TCP stays this far inside the safety workspace box
    clearance_m: float = 0.02  # minimum distance between bodies for a configuration to count as free
    path_step_rad: float = 0.04  # collision-check resolution along moves (largest joint step)
    tool_radius_m: float = 0.035  # tool envelope: a cylinder from the flange to the TCP
    # Pairs never checked: in the compact wrist the URDF's coarse boxes overlap where the real links
    # clear each other (geometry names from the URDF: <link>_0).
    ignore_pairs: list[list[str]] = field(default_factory=lambda: [["link_3_0", "link_5_0"], ["link_4_0", "link_6_0"]])
    floor: bool = True  # the mounting surface (z = 0) is a fixture
    rest_s: float = 0.25  # pause at each configuration (the arm settles; stiction is part of the data)
    test_ranges_deg: list[list[float]] = field(default_factory=lambda: [
        [-150, 150], [-80, 80], [-150, 150], [-150, 150], [-150, 150], [-180, 180]])
    seed: int = 0
    fourier: FourierConfig = field(default_factory=FourierConfig)

    def validate(self, where: str) -> None:
        for name in ("ranges_deg", "test_ranges_deg"):
            ranges = getattr(self, name)
            for i, r in enumerate(ranges):
                require(len(r) == 2 and r[0] < r[1], join(where, f"{name}[{i}]"),
                        f"must be [low, high] with low < high, got {r}")
        require(len(self.steps) == len(self.ranges_deg), join(where, "steps"), "needs one value per joint range")
        require(all(s >= 1 for s in self.steps), join(where, "steps"), "must all be >= 1")
        require(len(self.speeds) >= 1 and all(0 < v <= 1 for v in self.speeds), join(where, "speeds"),
                "must be fractions in (0, 1]")
        require(len(self.max_accel) == len(self.ranges_deg) and all(a > 0 for a in self.max_accel),
                join(where, "max_accel"), "needs one positive value per joint")
        require(0 < self.joint_speed_fraction <= 1, join(where, "joint_speed_fraction"), "must lie in (0, 1]")
        require(0 < self.tcp_speed_fraction <= 1, join(where, "tcp_speed_fraction"), "must lie in (0, 1]")
        require(self.clearance_m >= 0, join(where, "clearance_m"), "must be >= 0")
        require(self.path_step_rad > 0, join(where, "path_step_rad"), "must be > 0")
        require(self.max_configs >= 0, join(where, "max_configs"), "must be >= 0")
        for i, p in enumerate(self.ignore_pairs):
            require(len(p) == 2, join(where, f"ignore_pairs[{i}]"), f"must name two geometries, got {p}")


def load_excitation_config(raw: dict | None, where: str) -> ExcitationConfig:
    return load_dataclass(ExcitationConfig, raw or {}, where)


def read_excitation_config(path: str | None) -> ExcitationConfig:
    if path is None:
        return ExcitationConfig()
    return load_dataclass(ExcitationConfig, read_yaml(path), f"{path}:")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------- plan
@dataclass
class Segment:
    """One move: joint targets at the control period (the first sample is one period after the start)."""

    q: np.ndarray  # (K, n)
    traj: int  # trajectory id (per-trajectory statistics group by it)
    segment: int  # move id, unique within the plan
    speed: float  # the speed fraction it was timed for
    kind: str  # "chain", "fourier", "random"


@dataclass
class Plan:
    segments: list[Segment]
    dt: float
    info: dict = field(default_factory=dict)

    @property
    def start(self) -> np.ndarray:
        return self.segments[0].q[0]

    @property
    def samples(self) -> int:
        return sum(len(s.q) for s in self.segments)

    @property
    def labelled_samples(self) -> int:
        """Samples that belong to a trajectory (transfers between plans, traj -1, do not)."""
        return sum(len(s.q) for s in self.segments if s.traj >= 0)

    @property
    def duration_s(self) -> float:
        return self.samples * self.dt

    def stream(self) -> Iterator[tuple[np.ndarray, Segment]]:
        for s in self.segments:
            for row in s.q:
                yield row, s

    def trajectories(self) -> list[int]:
        return sorted({s.traj for s in self.segments})


# ----------------------------------------------------------------------------------------- collisions
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


# ----------------------------------------------------------------------------------------- moves
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


def quintic_samples(q0: np.ndarray, q1: np.ndarray, duration: float, dt: float, rest_s: float = 0.0) -> np.ndarray:
    k = int(np.ceil(duration / dt))
    s = np.minimum(np.arange(1, k + 1) * dt / duration, 1.0)[:, None]
    blend = s**3 * (10 - 15 * s + 6 * s**2)
    q = q0 + (q1 - q0) * blend
    hold = int(round(rest_s / dt))
    if hold:
        q = np.vstack([q, np.repeat(q1[None, :], hold, axis=0)])
    return q


LIMIT_MARGIN_RAD = np.radians(2.0)  # the servo overshoots a target at the limit by a hair; stay clear


def _rad_ranges(ranges_deg: list[list[float]], robot: RobotModel) -> tuple[np.ndarray, np.ndarray]:
    r = np.radians(np.asarray(ranges_deg, float))
    lim = robot.limits
    return np.maximum(r[:, 0], lim.lower + LIMIT_MARGIN_RAD), np.minimum(r[:, 1], lim.upper - LIMIT_MARGIN_RAD)


# ----------------------------------------------------------------------------------------- generators
def digitised_configurations(robot: RobotModel, ex: ExcitationConfig) -> np.ndarray:
    """Every combination of N+1 evenly spaced values per joint (both ends of the range included)."""
    lo, hi = _rad_ranges(ex.ranges_deg, robot)
    axes = [np.linspace(a, b, s + 1) for a, b, s in zip(lo, hi, ex.steps, strict=True)]
    return np.array(list(itertools.product(*axes)))


def free_configurations(configs: np.ndarray, cc: CollisionChecker, ws: Workspace) -> tuple[np.ndarray, dict]:
    keep = []
    dropped_collision = dropped_workspace = 0
    for q in configs:
        if not cc.free(q):
            dropped_collision += 1
        elif not ws.inside(q):
            dropped_workspace += 1
        else:
            keep.append(q)
    info = {"configurations": int(len(configs)), "dropped_collision": dropped_collision,
            "dropped_workspace": dropped_workspace, "free": len(keep)}
    return np.array(keep).reshape(-1, configs.shape[1]), info


def eulerian_chain(adj: dict[int, list[int]], start: int) -> list[int]:
    """Hierholzer: a closed walk using every directed edge once (each edge is an ordered pair)."""
    remaining = {k: list(v) for k, v in adj.items()}
    stack, walk = [start], []
    while stack:
        v = stack[-1]
        if remaining.get(v):
            stack.append(remaining[v].pop())
        else:
            walk.append(stack.pop())
    return walk[::-1]


def paper_chain(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float,
                max_samples: int | None = None, traj_base: int = 0, segment_base: int = 0) -> Plan:
    """The paper's generator: digitise, drop colliding configurations, chain every ordered pair of the
    rest into one continuous trajectory, and run it at V speeds (one trajectory id per speed).

    M configurations are drawn (seeded) from the free ones: `max_configs`, or, with `max_samples`,
    as many as give about that many samples (P(M,2) moves x V speeds); the last pass is cut there.
    """
    cc = CollisionChecker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    free, info = free_configurations(digitised_configurations(robot, ex), cc, ws)
    if len(free) < 2:
        raise ValueError(f"only {len(free)} collision-free configuration(s) in the ranges; widen them or add steps")
    m = len(free) if not ex.max_configs else min(ex.max_configs, len(free))
    if max_samples is not None:
        m = min(m, _configs_for(max_samples, free, ws, ex, dt, np.random.default_rng(ex.seed)))
    while True:
        rng = np.random.default_rng(ex.seed)
        order = rng.permutation(len(free))[:m]
        configs = free[np.sort(order)]
        segments, chained, pairs, blocked = _chain(configs, cc, ws, ex, dt, rng, cfg, max_samples,
                                                   traj_base, segment_base)
        total = sum(len(s.q) for s in segments)
        # Blocked paths shrink the chain: add configurations until the sample budget is met.
        if max_samples is None or total >= max_samples or m >= len(free) or ex.max_configs:
            break
        m = min(len(free), int(np.ceil(m * np.sqrt(max_samples / max(total, 1)))) + 1)
    info.update(pairs_blocked=blocked, chain_configurations=chained, ordered_pairs=pairs,
                speeds=list(ex.speeds), moves=len(segments))
    log.info("paper chain: %d configurations chained (of %d free, %d digitised), %d ordered pairs, %d moves, %.0f s",
             chained, info["free"], info["configurations"], pairs, len(segments), total * dt)
    return Plan(segments, dt, info)


def _chain(configs: np.ndarray, cc: CollisionChecker, ws: Workspace, ex: ExcitationConfig, dt: float,
           rng: np.random.Generator, cfg: CellConfig, max_samples: int | None, traj_base: int,
           segment_base: int) -> tuple[list[Segment], int, int, int]:
    m = len(configs)
    # Ordered pairs whose straight joint-space path is also free (symmetric, so every vertex keeps
    # in-degree = out-degree and each connected component has an Eulerian circuit).
    adj: dict[int, list[int]] = {i: [] for i in range(m)}
    blocked = 0
    for i, j in itertools.combinations(range(m), 2):
        if path_clear(configs[i], configs[j], cc, ws, ex.path_step_rad):
            adj[i].append(j)
            adj[j].append(i)
        else:
            blocked += 1
    for v in adj.values():
        rng.shuffle(v)
    comp = _largest_component(adj)
    adj = {k: [x for x in v if x in comp] for k, v in adj.items() if k in comp}
    home = np.asarray(cfg.robot.home, float)
    start = min(comp, key=lambda k: float(np.max(np.abs(configs[k] - home))))
    walk = eulerian_chain(adj, start)  # closed: every pass starts and ends at `start`
    pairs = list(zip(walk[:-1], walk[1:], strict=True))
    segments: list[Segment] = []
    total = 0
    seg_id = segment_base
    for vi, speed in enumerate(ex.speeds):
        for a, b in pairs:
            T = quintic_duration(configs[a], configs[b], ws, speed, ex.path_step_rad)
            seg = Segment(quintic_samples(configs[a], configs[b], T, dt, ex.rest_s), traj_base + vi, seg_id, speed,
                          "chain")
            segments.append(seg)
            seg_id += 1
            total += len(seg.q)
            if max_samples is not None and total >= max_samples:
                return segments, len(comp), len(pairs), blocked
    return segments, len(comp), len(pairs), blocked


def _configs_for(samples: int, configs: np.ndarray, ws: Workspace, ex: ExcitationConfig, dt: float,
                 rng: np.random.Generator) -> int:
    """Configurations M whose P(M,2) x V moves last about `samples` periods (from the mean move time)."""
    k = min(200, len(configs) * (len(configs) - 1))
    durations = []
    for _ in range(k):
        i, j = rng.choice(len(configs), 2, replace=False)
        v = ex.speeds[int(rng.integers(len(ex.speeds)))]
        durations.append(quintic_duration(configs[i], configs[j], ws, v, ex.path_step_rad * 4) + ex.rest_s)
    moves = samples * dt / max(float(np.mean(durations)), 1e-3)
    per_speed = moves / len(ex.speeds)
    m = int(np.ceil((1 + np.sqrt(1 + 4 * per_speed)) / 2)) + 1  # M(M-1) >= moves per speed, one spare
    return max(2, m)


def _largest_component(adj: dict[int, list[int]]) -> set[int]:
    seen: set[int] = set()
    best: set[int] = set()
    for v in adj:
        if v in seen:
            continue
        comp, todo = {v}, [v]
        while todo:
            x = todo.pop()
            for y in adj[x]:
                if y not in comp:
                    comp.add(y)
                    todo.append(y)
        seen |= comp
        if len(comp) > len(best):
            best = comp
    return best


def random_moves(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float, trajectories: int,
                 moves: int, speeds: list[float], repeats: int = 1, seed: int = 1,
                 traj_base: int = 0, segment_base: int = 0) -> Plan:
    """Random point-to-point moves (the test family): random collision-free configurations in
    `test_ranges_deg`, chained; trajectory i runs at speeds[i % len(speeds)]; each one is played
    `repeats` times (there and back again, so repeats stay continuous)."""
    cc = CollisionChecker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    lo, hi = _rad_ranges(ex.test_ranges_deg, robot)
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
    return Plan(segments, dt, {"trajectories": trajectories * repeats, "moves_per_trajectory": moves,
                               "speeds": list(speeds), "repeats": repeats})


# ----------------------------------------------------------------------------------------- Fourier
def fourier_trajectory(coef_a: np.ndarray, coef_b: np.ndarray, q0: np.ndarray, wf: float, t: np.ndarray,
                       ramp_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q(t) = q0 + env(t) * sum_l a_l/(l wf) sin(l wf t) - b_l/(l wf) cos(l wf t), with a quintic fade
    env at both ends (start and end at rest).  Returns q, dq, ddq (numerical derivatives of the fade)."""
    L = coef_a.shape[1]
    lw = wf * np.arange(1, L + 1)
    s, c = np.sin(np.outer(t, lw)), np.cos(np.outer(t, lw))
    f = s @ (coef_a / lw).T - c @ (coef_b / lw).T
    f = f - f[0]  # start exactly at q0
    T = t[-1]
    u = np.clip(np.minimum(t, T - t) / ramp_s, 0.0, 1.0)
    env = u**3 * (10 - 15 * u + 6 * u**2)
    q = q0 + env[:, None] * f
    dt = t[1] - t[0]
    dq = np.gradient(q, dt, axis=0)
    ddq = np.gradient(dq, dt, axis=0)
    return q, dq, ddq


def fourier_excitation(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float,
                       traj_base: int = 0, segment_base: int = 0, centres: np.ndarray | None = None,
                       speed_fraction: float = 1.0) -> Plan:
    """Identification-grade excitation: per trajectory, random Fourier coefficients scaled into the
    position / speed / acceleration limits; among the collision-free candidates the one whose base
    regressor (column-scaled) has the lowest condition number is kept.  Trajectories are joined by
    quintic moves (which are segments too).  `speed_fraction` < 1 caps the joint speeds at that
    fraction of the limits (slow, small-amplitude excitation: the friction's low-speed regime)."""
    from cell.dynamics.physics import base_parameters, full_regressor

    fc = ex.fourier
    cc = CollisionChecker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    lo, hi = _rad_ranges(ex.ranges_deg, robot)
    n = robot.n
    rng = np.random.default_rng(ex.seed + 17)
    wf = 2 * np.pi * fc.base_hz
    duration = fc.periods / fc.base_hz + 2 * fc.ramp_s
    t = np.arange(0.0, duration + dt / 2, dt)
    bp = base_parameters(robot.model)
    data = robot.model.createData()
    def random_centre() -> np.ndarray:
        while True:
            c = rng.uniform(lo + fc.centre_margin * (hi - lo), hi - fc.centre_margin * (hi - lo))
            if cc.free(c) and ws.inside(c):
                return c

    def best_around(q0: np.ndarray) -> tuple[float, np.ndarray] | None:
        best: tuple[float, np.ndarray] | None = None
        room = np.minimum(q0 - lo, hi - q0) * fc.amplitude_fraction
        for _ in range(fc.candidates):
            a = rng.normal(size=(n, fc.harmonics))
            b = rng.normal(size=(n, fc.harmonics))
            q, dq, ddq = fourier_trajectory(a, b, q0, wf, t, fc.ramp_s)
            dev = np.abs(q - q0).max(axis=0)
            scale = np.min([
                np.min(room / np.maximum(dev, 1e-9)),
                np.min(ws.vmax * speed_fraction / np.maximum(np.abs(dq).max(axis=0), 1e-9)),
                np.min(ws.amax / np.maximum(np.abs(ddq).max(axis=0), 1e-9)),
            ])
            q = q0 + (q - q0) * scale
            dq, ddq = dq * scale, ddq * scale
            stride = max(1, int(0.05 / dt))
            tcp = np.array([ws.tcp(x) for x in q[::stride]])
            tcp_speed = float(np.max(np.linalg.norm(np.diff(tcp, axis=0), axis=1)) / (dt * stride))
            if tcp_speed > ws.tcp_vmax:  # the TCP speed is about linear in the amplitude: shrink once more
                shrink = 0.95 * ws.tcp_vmax / tcp_speed
                q, dq, ddq = q0 + (q - q0) * shrink, dq * shrink, ddq * shrink
            if not _trajectory_ok(q, cc, ws, dt, stride=stride):
                continue
            rows = np.linspace(0, len(t) - 1, 150).astype(np.int64)
            Y = full_regressor(robot.model, data, q[rows], dq[rows], ddq[rows], 0.005)[:, bp.base]
            Y = Y / np.maximum(np.linalg.norm(Y, axis=0), 1e-12)
            cond = float(np.linalg.cond(Y))
            if best is None or cond < best[0]:
                best = (cond, q)
        return best

    segments: list[Segment] = []
    seg_id = segment_base
    prev = np.asarray(cfg.robot.home, float)
    conds = []
    count = len(centres) if centres is not None else fc.trajectories
    for k in range(count):
        # A centre whose every candidate leaves the limits or collides, or that cannot be reached,
        # is replaced by another (given centres are tried first).
        found = None
        for attempt in range(8):
            q0 = centres[k] if centres is not None and attempt == 0 else random_centre()
            best = best_around(q0)
            if best is None:
                continue
            try:
                lead = transfer(prev, best[1][0], robot, cfg, ex, dt, speed=0.7)
            except ValueError:
                continue
            found = (best, lead)
            break
        if found is None:
            log.warning("Fourier trajectory %d: no centre gave a free trajectory within the limits", k)
            continue
        (cond, q), lead = found
        conds.append(cond)
        for seg in lead:  # the way to the start is motion data too: it belongs to this trajectory
            seg.traj, seg.segment, seg.kind = traj_base + k, seg_id, "fourier"
            seg_id += 1
            segments.append(seg)
        # Cut the excitation into one-period segments (whole-segment subsampling stays meaningful).
        per = max(1, int(round(1.0 / fc.base_hz / dt)))
        body = q[1:]
        for c0 in range(0, len(body), per):
            segments.append(Segment(body[c0:c0 + per], traj_base + k, seg_id, 1.0, "fourier"))
            seg_id += 1
        prev = q[-1]
    return Plan(segments, dt, {"trajectories": len(conds), "condition_numbers": [round(c, 1) for c in conds],
                               "duration_s": round(duration, 2)})


def _trajectory_ok(q: np.ndarray, cc: CollisionChecker, ws: Workspace, dt: float, stride: int) -> bool:
    if np.any(q < ws.lower) or np.any(q > ws.upper):
        return False
    pts = q[::stride]
    for x in pts:
        if not (ws.inside(x) and cc.free(x)):
            return False
    tcp = np.array([ws.tcp(x) for x in pts])
    speed = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / (dt * stride)
    return bool(speed.max(initial=0.0) <= ws.tcp_vmax)


def join_plans(plans: list[Plan], robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig) -> Plan:
    """Concatenate plans, inserting a quintic move wherever one ends away from where the next starts."""
    if not plans:
        raise ValueError("nothing to join")
    ws = Workspace(robot, cfg, ex)
    dt = plans[0].dt
    segments: list[Segment] = []
    for p in plans:
        if segments and np.max(np.abs(segments[-1].q[-1] - p.start)) > 1e-9:
            a, b = segments[-1].q[-1], p.start
            T = quintic_duration(a, b, ws, 0.7, ex.path_step_rad)
            segments.append(Segment(quintic_samples(a, b, T, dt, 0.2), -1, -1, 0.7, "transfer"))
        segments.extend(p.segments)
    return Plan(segments, dt, {"parts": [p.info for p in plans]})


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


def transfer(q_from: np.ndarray, q_to: np.ndarray, robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig,
             dt: float, speed: float = 0.5, tries: int = 400, seed: int = 0) -> list[Segment]:
    """Collision-free moves (traj -1) from one plan's end to the next one's start: straight when the
    straight joint path is clear, else through the home posture (retract, turn joint 1, extend),
    else through one or two random free via configurations (a small randomised search)."""
    cc = CollisionChecker(robot, cfg, ex)
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
        lo, hi = _rad_ranges(ex.test_ranges_deg, robot)
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


@dataclass
class SweepConfig:
    """Slow constant-velocity sweeps around a tool's working posture (see `sweep_excitation`)."""

    speed_range: tuple[float, float] = (0.002, 0.06)  # rad/s, log-uniform per joint: careful task motion
    box_rad: float = 0.2  # a joint further than half of this from the centre turns back towards it
    sweep_s: tuple[float, float] = (0.8, 2.0)  # each sweep's length, uniform
    blend_s: float = 0.2  # cosine blend from one sweep's velocity to the next's
    sweeps_per_block: int = 12  # a block is checked (limits, collisions, workspace) as a whole
    seed_offset: int = 29


def sweep_excitation(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float, samples: int,
                     centre: np.ndarray, start: np.ndarray | None = None, traj_base: int = 0,
                     segment_base: int = 0, sc: SweepConfig | None = None) -> Plan:
    """Slow sweeps around `centre` (a tool's working posture): every joint moves at its own constant
    speed (log-uniform in `speed_range`, random sign) for about a second, then blends into the next.

    A task's careful motion (a peg's search slides at 1-5 mm/s, its feed, a wipe's approach) holds
    joints at a few mrad/s for seconds, where the friction is in its Stribeck regime; a sinusoid only
    crosses those speeds at its turning points, under acceleration, and the friction's position ripple
    and load differ from posture to posture.  With these sweeps around the peg's task start (lifted
    clear of the table, as `prepare` places them) the virtual sensor's My error over 50 bench
    insertions fell from 0.28 to 0.21 N·m, its Fz error from 2.06 to 1.49 N.  The plan starts with a
    collision-free move from `start` (default: home) to `centre`; a block that would leave the limits
    or the workspace, or collide, is drawn again."""
    sc = sc or SweepConfig()
    cc = CollisionChecker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    n = robot.n
    c = np.asarray(centre, float)
    if not (cc.free(c) and ws.inside(c)):
        raise ValueError(f"sweep centre {np.round(c, 3).tolist()} collides or is outside the workspace")
    rng = np.random.default_rng(ex.seed + sc.seed_offset)
    vlo, vhi = np.log(sc.speed_range[0]), np.log(sc.speed_range[1])
    nb = max(2, int(round(sc.blend_s / dt)))
    blend = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, nb + 1) / nb)  # 0 -> 1
    stride = max(1, int(0.05 / dt))

    def block(q: np.ndarray) -> list[np.ndarray]:
        """Sweeps from rest at q, ending at rest."""
        v = np.zeros(n)
        out = []
        for _ in range(sc.sweeps_per_block):
            speed = np.minimum(np.exp(rng.uniform(vlo, vhi, n)), ws.vmax)
            sign = rng.choice([-1.0, 1.0], n)
            sign = np.where(np.abs(q - c) > 0.5 * sc.box_rad, -np.sign(q - c), sign)
            v_new = sign * speed
            k = max(nb + 1, int(round(rng.uniform(*sc.sweep_s) / dt)))
            vel = np.vstack([v + (v_new - v) * blend[:, None], np.repeat(v_new[None], k - nb, axis=0)])
            seg = q + np.cumsum(vel, axis=0) * dt
            q, v = seg[-1].copy(), v_new
            out.append(seg)
        out.append(q + np.cumsum(v * (1.0 - blend)[:, None], axis=0) * dt)  # to rest
        return out

    way_in = transfer(np.asarray(cfg.robot.home if start is None else start, float), c, robot, cfg, ex, dt, speed=0.7)
    segments = [replace(s, traj=traj_base, segment=segment_base + i, kind="sweep") for i, s in enumerate(way_in)]
    seg_id = segment_base + len(segments)
    q = c.copy()
    blocks = 0
    while sum(len(s.q) for s in segments) < samples:
        for _ in range(20):
            parts = block(q)
            if _trajectory_ok(np.vstack(parts), cc, ws, dt, stride):
                break
        else:
            raise ValueError(f"sweeps around {np.round(c, 3).tolist()}: no block within the limits after 20 draws")
        for p in parts:
            segments.append(Segment(p, traj_base + blocks, seg_id, 0.0, "sweep"))
            seg_id += 1
        q = parts[-1][-1].copy()
        blocks += 1
    return Plan(segments, dt, {"blocks": blocks, "centre": np.round(c, 4).tolist(),
                               "speed_range": list(sc.speed_range), "box_rad": sc.box_rad})
