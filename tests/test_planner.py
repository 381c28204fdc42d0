"""The planners: refused inputs, respected limits, a torque-bound path slowed rather than violated, a clean start."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cell.collision.geometry import CollisionChecker
from cell.planning.baselines import KinematicPlanner, UniformScalingPlanner
from cell.planning.config import PlannerConfig
from cell.planning.constraints import ToppraTerms
from cell.planning.planner import GeometricPath, PlanningError, ToppraPlanner
from cell.planning.speed_env import random_waypoints
from drivers.errors import ConfigError

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
    checker = CollisionChecker.for_scene(robot, cfg.scene)
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
    # Quick because the model is toppra's own constraint: re-plans only tighten the bound locally where the
    # torque between grid points exceeded it.  The wall time is reported, not judged here (`bench planning`).
    assert opt.iterations <= 3 and opt.plan_time_s > 0


@pytest.mark.parametrize("start_margin", [0.0, None])
def test_a_path_at_the_torque_limit_is_slowed_not_violated(robot, p1, pcfg, start_margin):
    """A model with twice the nominal inertial torque plus friction (a heavy payload, sticky joints):
    the rigid-body bound toppra sees is not enough, so it must iterate until the full model fits (the heavy
    plan is 4.2 % longer, with or without the start margin)."""

    def heavy(q, dq, ddq):
        rigid = p1(q, dq, ddq)
        gravity = p1(q, np.zeros_like(dq), np.zeros_like(ddq))
        return gravity + 2.0 * (rigid - gravity) + 8.0 * np.tanh(dq / 0.05)

    cfg = pcfg if start_margin is None else replace(pcfg, start_margin=start_margin)
    light = ToppraPlanner(robot, p1, cfg).plan(PATH)
    planner = ToppraPlanner(robot, heavy, cfg)
    traj = planner.plan(PATH)
    assert traj.iterations > 1
    assert np.all(planner.excess(traj) <= 1.0 + 2e-3)
    assert traj.duration > light.duration * 1.03
    # and the nominal plan would have violated the heavy model's limits
    assert np.max(planner.excess(light)) > 1.0


# A random path (seed 0 of cell.speed_env.random_waypoints) on which toppra's default discretisation stalls.
FROM_REST = np.radians([[-48.1, -11.2, 33.1, -67.6, 90.4, 26.5], [27.7, -14.3, 139.7, 86.6, 91.7, 27.1],
                        [45.2, -13.9, 44.9, 39.9, 77.3, -34.2]])


def torque_ratios(planner: ToppraPlanner, path: GeometricPath, grid: np.ndarray, sd: np.ndarray,
                  limit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per grid point: the profile's time there, and the largest |rigid-body torque| / limit of the
    constant-acceleration segments on either side of it."""
    x = sd**2
    u = np.diff(x) / (2.0 * np.diff(grid))
    t = np.concatenate([[0.0], np.cumsum(2.0 * np.diff(grid) / np.maximum(sd[:-1] + sd[1:], 1e-9))])
    p, dp, ddp = path.eval(grid)
    coulomb = np.zeros(len(limit)) if planner.terms.coulomb is None else planner.terms.coulomb
    ratio = np.zeros(len(grid))
    for i, a in enumerate(u):
        for k in (i, i + 1):
            tau = planner.terms.inv_dyn(p[k], dp[k] * sd[k], ddp[k] * x[k] + dp[k] * a) + coulomb * np.sign(dp[k])
            ratio[k] = max(ratio[k], float(np.max(np.abs(tau) / limit)))
    return t, ratio


def from_rest(robot, p1, pcfg, **settings):
    """FROM_REST's planner (rigid body + Coulomb friction as toppra's constraint), path, grid and bound."""
    terms = ToppraTerms(robot.rnea, np.array([5.5, 5.5, 4.0, 1.5, 1.5, 1.2]))
    planner = ToppraPlanner(robot, p1, replace(pcfg, velocity_fraction=0.75, **settings), None, terms)
    return planner, planner.check_waypoints(FROM_REST), np.linspace(0.0, 1.0, pcfg.gridpoints + 1), \
        planner.torque_limit(np.full(6, 0.7))


@pytest.mark.parametrize("discretization", ["interpolation", "collocation"])
def test_the_torque_bound_holds_across_each_segment_so_the_plan_leaves_rest_without_a_stall(robot, p1, pcfg,
                                                                                             discretization):
    """The clamped spline has dp/ds = 0 at s = 0: checked at each segment's start only (toppra's default), the
    first segment's acceleration is free, the rigid-body torque at its end is several times the bound and the
    path speed stalls to recover from it (the plant's servo overshot there: docs/planning.md).  Checked at
    both ends (the default), the bound holds everywhere and the speed rises from rest."""
    planner, path, grid, limit = from_rest(robot, p1, pcfg, torque_discretization=discretization, start_margin=0.0)
    sd = planner.speed_profile(path, grid, limit)
    ratio = float(np.max(torque_ratios(planner, path, grid, sd, limit)[1]))
    if discretization == "interpolation":
        assert ratio <= 1.0 + 1e-3
        assert np.all(np.diff(sd[:10]) > 0)  # speeding up from rest, no stall
    else:  # the artefact the default avoids, so that this test would notice a return to it
        assert ratio > 2.0
        assert sd[2] < 0.5 * sd[1]


def test_a_bad_torque_discretization_is_refused():
    with pytest.raises(ConfigError, match=r"plans.yaml planner.torque_discretization must be one of interpolation"):
        PlannerConfig(torque_discretization="midpoint").validate("plans.yaml planner")


@pytest.mark.parametrize("margin", [0.15, 0.0])
def test_leaving_rest_the_plan_keeps_the_start_margin_then_uses_the_whole_bound(robot, p1, pcfg, margin):
    """The plant's torque overshoots the model's as the arm leaves rest: over the first start_margin_s the
    profile plans to (1 - start_margin) of the bound, after that to all of it (this path is torque-bound at
    its start: without the margin the start reaches the bound)."""
    planner, path, grid, limit = from_rest(robot, p1, pcfg, start_margin=margin, start_margin_s=0.1)
    t, ratio = torque_ratios(planner, path, grid, planner.speed_profile(path, grid, limit), limit)
    assert np.max(ratio[t <= 0.1]) == pytest.approx(1.0 - margin, abs=2e-3)
    assert np.max(ratio[t > 0.15]) == pytest.approx(1.0, abs=2e-3)
    assert np.max(ratio) <= 1.0 + 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("acc", [[150.0] * 6, [2.0, 2.0, 3.0, 5.0, 5.0, 5.0], [31.6, 18.5, 56.0, 122.9, 150, 150]])
def test_the_timing_never_exceeds_the_speed_and_acceleration_limits_it_is_given(robot, p1, pcfg, seed, acc):
    """Speed-bound (loose accelerations), acceleration-bound (tight ones) and in between: every sample of the
    re-timed result is within the joint limits, however the smoothing mixed the profile."""
    planner = KinematicPlanner(robot, p1, replace(pcfg, acceleration_limits=acc, velocity_fraction=0.75))
    traj = planner.plan(random_waypoints(np.random.default_rng(seed), 4))
    assert np.all(np.abs(traj.dq) <= planner.vlim * (1 + 1e-9))
    assert np.all(np.abs(traj.ddq) <= np.asarray(acc) * (1 + 1e-9))


def tcp_speeds(robot, traj) -> np.ndarray:
    """The commanded TCP speed as the safety monitor checks it: the chord between successive set-points."""
    tcp = np.array([robot.tcp_pose(q).translation for q in traj.q])
    return np.linalg.norm(np.diff(tcp, axis=0), axis=1) / np.diff(traj.t)


def test_the_plan_keeps_the_cells_tcp_speed_limit_and_pays_for_it_only_where_it_binds(robot, p1, pcfg):
    cfg = replace(pcfg, velocity_fraction=0.75)
    free = ToppraPlanner(robot, p1, cfg).plan(PATH)
    assert np.max(tcp_speeds(robot, free)) > 1.5  # the path is fast enough for a 1.5 m/s limit to bind
    capped = ToppraPlanner(robot, p1, replace(cfg, tcp_speed_limit=1.5)).plan(PATH)
    assert np.max(tcp_speeds(robot, capped)) <= 1.5
    assert capped.duration > free.duration
    assert ToppraPlanner(robot, p1, replace(cfg, tcp_speed_limit=5.0)).plan(PATH).duration == free.duration


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_exact_step_delivers_toppras_profile_plus_the_smoothing_window_only(robot, p1, pcfg, seed):
    """Speed-bound paths (the joint speed caps bind most of the way): the set-points take toppra's time plus
    the averaging window and a few periods of local slow-down, not the smoothed step's stretch."""
    cfg = replace(pcfg, velocity_fraction=0.75, start_margin=0.0)
    planner = ToppraPlanner(robot, p1, cfg)
    path = planner.check_waypoints(random_waypoints(np.random.default_rng(seed), 4))
    grid = np.linspace(0.0, 1.0, cfg.gridpoints + 1)
    sd = planner.speed_profile(path, grid, planner.torque_limit(), None, planner.speed_cap(path, grid))
    raw = float(np.sum(2.0 * np.diff(grid) / np.maximum(sd[:-1] + sd[1:], 1e-9)))
    exact = planner.timed(path, grid, sd)
    assert exact.duration <= raw + cfg.exact_smoothing_s + 4 * cfg.sample_period_s
    assert np.all(np.abs(exact.dq) <= planner.vlim * 1.002)
    smoothed = planner.timed_smoothed(path, grid, sd)
    assert exact.duration < smoothed.duration


def test_a_shorter_window_where_the_arm_leaves_or_reaches_rest_saves_half_the_difference_and_keeps_every_bound():
    """The exact step's average: equal windows are the plain moving average (from its last sample at rest); a
    shorter start or stop window ends the motion (w_motion - w) / 2 samples sooner, leaves and reaches rest, and
    no speed or acceleration grows."""
    from cell.planning.averaging import BLEND_S, rest_to_rest_average

    dt, n = 0.008, 120
    t = np.arange(n) * dt
    T = t[-1]
    s = 0.5 - 0.5 * np.cos(np.pi * t / T)
    q = np.column_stack([s * k for k in (1.0, -2.0, 0.5)])
    dq = np.column_stack([0.5 * np.pi / T * np.sin(np.pi * t / T) * k for k in (1.0, -2.0, 0.5)])
    ddq = np.column_stack([0.5 * (np.pi / T) ** 2 * np.cos(np.pi * t / T) * k for k in (1.0, -2.0, 0.5)])
    end = q[-1].copy()
    w = 5
    plain = np.convolve(np.concatenate([np.zeros(w), s, np.ones(w)]), np.ones(w) / w, mode="valid")
    same = rest_to_rest_average(q, dq, ddq, s, end, dt, w * dt, w * dt)
    # the plain average without its first sample (the padding alone): one sample at rest, then moving
    assert np.allclose(same[3][:-1], plain[1: len(same[3])])
    assert same[3][0] == 0.0 and same[3][1] > 0.0
    short = rest_to_rest_average(q, dq, ddq, s, end, dt, 1 * dt, w * dt)
    assert len(short[0]) == len(same[0]) - 2
    # the same at the stop: a shorter stop window ends the motion sooner by half the difference, and the middle
    # of the motion keeps the motion's window (the stop's takes over only within BLEND_S of the end)
    stop = rest_to_rest_average(q, dq, ddq, s, end, dt, 1 * dt, w * dt, 1 * dt)
    assert len(stop[0]) == len(short[0]) - 2
    middle = slice(int(BLEND_S / dt) + 2, n - int(BLEND_S / dt) - 2)
    assert np.array_equal(stop[2][middle], short[2][middle])
    end_part = slice(n - 20, len(stop[2]))
    assert not np.allclose(stop[2][end_part], short[2][end_part])  # a steeper end: the stop's shorter ramp
    for q_avg, dq_avg, ddq_avg, s_avg in (same, short, stop):
        assert np.allclose(q_avg[0], q[0]) and np.allclose(q_avg[-1], end) and s_avg[-1] == 1.0
        assert np.allclose(dq_avg[[0, -1]], 0.0, atol=1e-3)
        assert np.all(np.abs(dq_avg) <= np.max(np.abs(dq), axis=0) + 1e-12)
        assert np.all(np.abs(ddq_avg) <= np.max(np.abs(ddq), axis=0) + 1e-12)
        assert np.all(np.diff(s_avg) >= -1e-12)
