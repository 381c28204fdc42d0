"""The paper's generator: digitised joint configurations, the collision filter, and one Eulerian chain through
every ordered pair of the free ones, run at each speed."""

from __future__ import annotations

import itertools
import logging

import numpy as np

from cell.collision.geometry import CollisionChecker
from cell.config import CellConfig
from cell.control.trajectory import quintic_samples
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.limits import Workspace, excitation_checker, rad_ranges
from cell.data.excitation.motion import Motion, Segment
from cell.data.excitation.moves import path_clear, quintic_duration
from cell.model.robot import RobotModel

log = logging.getLogger(__name__)


def digitised_configurations(robot: RobotModel, ex: ExcitationConfig) -> np.ndarray:
    """Every combination of N+1 evenly spaced values per joint (both ends of the range included)."""
    lo, hi = rad_ranges(ex.ranges_deg, robot)
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
                max_samples: int | None = None, traj_base: int = 0, segment_base: int = 0) -> Motion:
    """The paper's generator: digitise, drop colliding configurations, chain every ordered pair of the
    rest into one continuous trajectory, and run it at V speeds (one trajectory id per speed).

    M configurations are drawn (seeded) from the free ones: `max_configs`, or, with `max_samples`,
    as many as give about that many samples (P(M,2) moves x V speeds); the last pass is cut there.
    """
    cc = excitation_checker(robot, cfg, ex)
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
    return Motion(segments, dt, info)


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
