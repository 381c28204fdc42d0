"""The planners: refused inputs, respected limits, and a torque-bound path slowed rather than violated."""

from __future__ import annotations

import numpy as np
import pytest

from cell.collision import CollisionChecker
from cell.planner import PlannerConfig, PlanningError, ToppraPlanner, UniformScalingPlanner

PATH = np.radians([[0, -30, 90, 0, 90, 0], [60, 10, 60, -30, 90, 30], [120, 30, 30, 0, 90, 0]])


@pytest.fixture
def p1(robot):
    def fn(q, dq, ddq):
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    return fn


@pytest.fixture
def pcfg():
    return PlannerConfig(acceleration_limits=[150.0] * 6, torque_margin=0.15)


def test_waypoint_outside_joint_limits_is_refused(robot, p1, pcfg):
    bad = PATH.copy()
    bad[1, 2] = np.radians(170)  # J3 is +-155 deg
    with pytest.raises(PlanningError, match=r"waypoint 1: joint 3 at 170.0 deg is outside its limits"):
        ToppraPlanner(robot, p1, pcfg).plan(bad)


def test_path_through_the_table_is_refused(robot, p1, pcfg, cfg):
    checker = CollisionChecker(robot, cfg.scene)
    down = np.radians([[0, 0, 90, 0, 90, 0], [0, 110, 20, 0, 90, 0]])  # reaches down through the table
    with pytest.raises(PlanningError, match="collides"):
        ToppraPlanner(robot, p1, pcfg, checker).plan(down)
    with pytest.raises(PlanningError, match="collides"):
        UniformScalingPlanner(robot, p1, pcfg, checker).plan(down)


def test_nan_or_single_waypoint_is_refused(robot, p1, pcfg):
    with pytest.raises(PlanningError, match="NaN"):
        ToppraPlanner(robot, p1, pcfg).plan(np.full((2, 6), np.nan))
    with pytest.raises(PlanningError, match="at least 2 rows"):
        ToppraPlanner(robot, p1, pcfg).plan(PATH[:1])


@pytest.mark.parametrize("planner_cls", [ToppraPlanner, UniformScalingPlanner])
def test_plans_pass_the_waypoints_and_respect_every_limit(robot, p1, pcfg, planner_cls):
    planner = planner_cls(robot, p1, pcfg)
    traj = planner.plan(PATH)
    np.testing.assert_allclose(traj.q[0], PATH[0], atol=1e-6)
    np.testing.assert_allclose(traj.q[-1], PATH[-1], atol=1e-6)
    assert np.min(np.linalg.norm(traj.q - PATH[1], axis=1)) < 0.02  # passes near the via point
    vlim = robot.limits.velocity * pcfg.velocity_fraction
    assert np.all(np.abs(traj.dq) <= vlim * 1.01)
    assert np.all(np.abs(traj.ddq) <= np.asarray(pcfg.acceleration_limits) * 1.02)
    assert np.all(planner.excess(traj) <= 1.0 + 2e-3)


def test_time_optimal_is_faster_than_the_uniform_baseline(robot, p1, pcfg):
    opt = ToppraPlanner(robot, p1, pcfg).plan(PATH)
    base = UniformScalingPlanner(robot, p1, pcfg).plan(PATH)
    assert opt.duration < 0.75 * base.duration
    assert opt.plan_time_s < 1.0


def test_a_path_at_the_torque_limit_is_slowed_not_violated(robot, p1, pcfg):
    """A model with twice the nominal inertial torque plus friction (a heavy payload, sticky joints):
    the rigid-body bound toppra sees is not enough, so it must iterate until the full model fits."""

    def heavy(q, dq, ddq):
        rigid = p1(q, dq, ddq)
        gravity = p1(q, np.zeros_like(dq), np.zeros_like(ddq))
        return gravity + 2.0 * (rigid - gravity) + 8.0 * np.tanh(dq / 0.05)

    light = ToppraPlanner(robot, p1, pcfg).plan(PATH)
    planner = ToppraPlanner(robot, heavy, pcfg)
    traj = planner.plan(PATH)
    assert traj.iterations > 1
    assert np.all(planner.excess(traj) <= 1.0 + 2e-3)
    assert traj.duration > light.duration * 1.05
    # and the nominal plan would have violated the heavy model's limits
    assert np.max(planner.excess(light)) > 1.0
