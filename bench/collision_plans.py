"""Time-optimal free motion for `bench collision`'s false-alarm run: the moves `main.py plan` makes
(TOPP-RA on the hybrid model's torque limits, full acceleration from rest) between random
collision-free poses, as one stream of joint targets."""

from __future__ import annotations

import logging

import numpy as np

from cell.config import CONFIG_DIR, CellConfig
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.moves import random_moves
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from cell.planning.planner import PlanningError, ToppraPlanner, toppra_terms
from tasks.setup.plan import load_plan_file

REST_S = 0.25  # at rest between moves: each move starts from standstill, the hardest start
log = logging.getLogger(__name__)

TORQUE_SCALE = 0.8  # of the planning limit: the scale `plan` validates its first run at


def max_tcp_speed() -> float:
    """The TCP speed limit `plan` runs its moves under (config/plans.yaml)."""
    return load_plan_file(CONFIG_DIR / "plans.yaml").max_tcp_speed


def time_optimal_stream(robot: RobotModel, cfg: CellConfig, model: LearnedModel, seconds: float,
                        seed: int) -> np.ndarray:
    """(K, n) joint targets at the control period: time-optimal moves between random poses, each
    from rest, until `seconds` are filled (the last move may be cut)."""
    dt = cfg.loop.period_s
    plans = load_plan_file(CONFIG_DIR / "plans.yaml")
    planner = ToppraPlanner(robot, model.predict, plans.planner, None, toppra_terms(model))
    # The excitation's random test moves give collision-free poses whose straight joint lines are free.
    moves = random_moves(robot, cfg, ExcitationConfig(), dt, 1, max(2, int(seconds / 1.0)), [1.0], seed=seed)
    poses = [moves.start] + [s.q[-1] for s in moves.segments]
    rest = int(round(REST_S / dt))
    stream = [np.repeat(poses[0][None, :], rest, axis=0)]
    total = rest
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        if total * dt >= seconds:
            break
        try:
            traj = planner.plan(np.vstack([a, b]), np.full(robot.n, TORQUE_SCALE))
        except PlanningError as exc:
            # The stream must stay continuous: the moves after this one start from b, so stop here (the
            # caller counts the seconds actually played).
            log.warning("time-optimal free motion: stopped at an infeasible move (%s)", exc)
            break
        stream += [traj.q, np.repeat(b[None, :], rest, axis=0)]
        total += len(traj.q) + rest
    return np.vstack(stream)[: int(round(seconds / dt))]
