"""Fast moves: rest-to-rest moves between random poses, timed as `plan` times its moves (time-optimal under the
joint speed, TCP speed and torque limits), so the training data reaches the cell's working speeds."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from cell.config import CellConfig
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.motion import Motion, Segment
from cell.data.excitation.moves import random_moves, transfer
from cell.model.dynamics.physics import P1Model
from cell.model.robot import RobotModel
from cell.planning.config import PlannerConfig
from cell.planning.constraints import ToppraTerms
from cell.planning.planner import PlanningError, ToppraPlanner

log = logging.getLogger(__name__)


@dataclass
class FastConfig:
    """How the fast moves are timed and spaced (see `fast_moves`)."""

    # Of the planner's torque limit, on the nominal rigid body: the plant's rotor inertia, friction and
    # parameter error come on top and must stay under the safety monitor's stop (90 % of the motor limits).
    torque_scale: float = 0.45
    # rad/s^2: what `plan`'s moves reach braking joints 1-3 from full speed (40-48 rad/s^2).  The nominal rigid
    # body leaves out the rotors' inertia, which at these accelerations is as large as the links' torque.
    acceleration_limits: tuple[float, ...] = (50.0, 50.0, 50.0, 60.0, 60.0, 60.0)
    # kg·m², reflected to the joints: an upper bound on what a cobot's motors add through their gears (a
    # harmonic drive of ratio ~100 reflects a motor's ~1e-4 kg·m² as ~1 kg·m²), taken as known inertia.
    rotor_inertia_bound: tuple[float, ...] = (1.0, 1.0, 1.0, 0.1, 0.1, 0.1)
    rest_s: float = 0.25  # at rest between moves: each one starts from standstill, as a plan's first move does
    gridpoints: int = 200  # the timing's grid: coarser than `plan`'s (the data needs the speeds, not the optimum)
    seed_offset: int = 41


def fast_moves(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float, samples: int,
               planner_cfg: PlannerConfig, start: np.ndarray | None = None, traj_base: int = 0,
               segment_base: int = 0, fc: FastConfig | None = None) -> Motion:
    """About `samples` samples of time-optimal moves between random collision-free poses (`random_moves`'
    poses, whose straight joint lines are free and inside the workspace), each a trajectory of its own (the way
    in from `start` is a transfer, traj -1, outside the count).

    `prepare`'s other families stay under 0.5-0.8 rad/s and a few rad/s², where `plan` cruises at over
    2 rad/s and brakes at tens of rad/s²; beyond the training data's reach the learned residual is an
    extrapolation and the collision detector widens its thresholds.  The moves are timed by the planner
    `plan` uses (its joint speed fraction and TCP speed limit, `planner_cfg`) on the nominal rigid body
    (the identified model does not exist yet) plus a bound on the rotors' inertia, at `fc.torque_scale` of
    its torque limit and under `fc.acceleration_limits`.  The motion starts with a collision-free move from
    `start` (default: home) to the first pose.  The caller runs it under a TCP speed stop of at least
    `planner_cfg.tcp_speed_limit`."""
    fc = fc or FastConfig()
    p1 = P1Model(robot)
    rotor = np.asarray(fc.rotor_inertia_bound, float)
    pcfg = dataclasses.replace(planner_cfg, toppra_gridpoints=fc.gridpoints,
                               acceleration_limits=list(fc.acceleration_limits))

    def torque(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return p1.predict(q, dq, ddq) + rotor * ddq

    planner = ToppraPlanner(robot, torque, pcfg, None,
                            ToppraTerms(lambda q, dq, ddq: robot.rnea(q, dq, ddq) + rotor * ddq))
    scale = np.full(robot.n, fc.torque_scale)
    rest = int(round(fc.rest_s / dt))
    # About one second a move: draw enough poses, then keep moves until the samples are filled.
    poses_motion = random_moves(robot, cfg, ex, dt, 1, max(2, int(samples * dt / 1.0) + 2), [1.0],
                                seed=ex.seed + fc.seed_offset)
    poses = [poses_motion.start] + [s.q[-1] for s in poses_motion.segments]
    origin = np.asarray(cfg.robot.home if start is None else start, float)
    # The way in is a transfer (traj -1, as between motions): it neither counts as fast data nor fills the budget.
    segments = [dataclasses.replace(s, segment=segment_base + i)
                for i, s in enumerate(transfer(origin, poses[0], robot, cfg, ex, dt, speed=0.7))]
    seg_id = segment_base + len(segments)
    moves, filled, peak_speed, peak_accel = 0, 0, np.zeros(robot.n), np.zeros(robot.n)
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        if filled >= samples:
            break
        try:
            traj = planner.plan(np.vstack([a, b]), scale)
        except PlanningError as exc:
            # The motion must stay continuous: the later moves start from b, so the fast part ends here.
            log.warning("fast moves: stopped at an infeasible move (%s)", exc)
            break
        q = np.vstack([traj.q[1:], np.repeat(b[None, :], rest, axis=0)])
        segments.append(Segment(q, traj_base + moves, seg_id, 1.0, "fast"))
        filled += len(q)
        peak_speed = np.maximum(peak_speed, np.abs(traj.dq).max(axis=0))
        peak_accel = np.maximum(peak_accel, np.abs(traj.ddq).max(axis=0))
        seg_id += 1
        moves += 1
    if moves == 0:
        raise ValueError("no move between the drawn poses could be timed")
    return Motion(segments, dt, {"moves": moves, "torque_scale": fc.torque_scale,
                                 "tcp_speed_limit": pcfg.tcp_speed_limit,
                                 "peak_speed_rad_s": np.round(peak_speed, 2).tolist(),
                                 "peak_accel_rad_s2": np.round(peak_accel, 1).tolist()})
