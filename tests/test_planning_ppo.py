"""The PPO planner's environment (reward, termination), its policy artefact, and the planners it is compared with."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from cell.planning.baselines import KinematicPlanner
from cell.planning.config import PlannerConfig
from cell.planning.planner import GeometricPath, Planner, TimedTrajectory, ToppraPlanner
from cell.planning.ppo import PPOConfig, load_policy, load_snapshots, save_policy, save_snapshot
from cell.planning.ppo_planner import PpoPlanner, PpoSettings, train_policy
from cell.planning.speed_env import EnvConfig, PathSpeedEnv, SpeedEnvBatch, obs_dim, path_data, random_waypoints
from drivers.errors import ConfigError

PATH = np.radians([[0, -30, 90, 0, 90, 0], [60, 10, 60, -30, 90, 30], [120, 30, 30, 0, 90, 0]])
LIMIT = np.array([100.0, 100.0, 100.0, 30.0, 30.0, 30.0])
VLIM = np.full(6, 2.0)


def inertia_only(q, dq, ddq):
    """A toy torque model: 5 kg m^2 on every joint, nothing else (exact to reason about)."""
    return 5.0 * np.asarray(ddq)


def toy_inv_dyn(q, dq, ddq):
    return 5.0 * np.asarray(ddq)


def data(ec: EnvConfig):
    return path_data(GeometricPath(PATH).spline, VLIM, LIMIT, toy_inv_dyn, ec)


def test_an_episode_ends_at_the_last_knot_at_rest_and_its_time_is_the_profile_s():
    ec = EnvConfig(knots=8)
    env = SpeedEnvBatch(inertia_only, LIMIT, ec)
    env.reset([data(ec)])
    dones = []
    for _ in range(ec.knots):
        _, _, done, _ = env.step(np.array([0.0]))
        dones.append(done)
    assert dones == [False] * (ec.knots - 1) + [True]
    v = np.stack(env.speeds, axis=1)[0]
    assert v[0] == 0.0 and v[-1] == 0.0 and np.all(v[1:-1] > 0)
    # 0.0 -> half of each knot's cap; the duration is the sum of the constant-acceleration pieces
    assert np.allclose(v[1:-1], 0.5 * data(ec).cap[1:-1])
    assert env.durations()[0] == pytest.approx(np.sum(2.0 / ec.knots / (v[:-1] + v[1:])))


def test_the_reward_pays_for_time_saved_and_charges_the_torque_excess():
    ec = EnvConfig(knots=8, time_weight=10.0, torque_weight=7.0)
    d = data(ec)
    fast, slow = SpeedEnvBatch(inertia_only, LIMIT * 1e6, ec), SpeedEnvBatch(inertia_only, LIMIT * 1e6, ec)
    fast.reset([d])
    slow.reset([d])
    r_fast = sum(fast.step(np.array([1.0]))[1][0] for _ in range(ec.knots))
    r_slow = sum(slow.step(np.array([-0.8]))[1][0] for _ in range(ec.knots))
    assert r_fast > r_slow  # no limit in reach: only time counts
    # the time term sums to b x (T_ref - T) / T_ref
    t_ref = d.dt_ref.sum()
    assert r_fast == pytest.approx(10.0 * (t_ref - fast.durations()[0]) / t_ref)

    def twice_the_limit(q, dq, ddq):
        return np.tile(2.0 * LIMIT, (len(q), 1))

    over = SpeedEnvBatch(twice_the_limit, LIMIT, ec)
    over.reset([d])
    _, reward, _, peak = over.step(np.array([0.0]))
    assert np.allclose(peak, 2.0)
    time_part = 10.0 * (d.dt_ref[0] - 2.0 / ec.knots / (0.5 * d.cap[1])) / t_ref
    assert reward[0] == pytest.approx(time_part - 7.0 * 6 * 1.0)  # a x sum_j (ratio_j - 1)


def test_the_gymnasium_environment_passes_the_checker():
    ec = EnvConfig(knots=6)
    env = PathSpeedEnv(inertia_only, LIMIT, ec, lambda rng: data(ec))
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (obs_dim(ec),)


def test_random_waypoints_lie_in_the_workspace_and_apart():
    w = random_waypoints(np.random.default_rng(3), 5)
    assert w.shape == (5, 6)
    assert np.all(np.linalg.norm(np.diff(w, axis=0), axis=1) >= 0.6)


@pytest.fixture
def p1(robot):
    def fn(q, dq, ddq):
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    return fn


@pytest.fixture(scope="module")
def tiny_settings():
    return PpoSettings(env=EnvConfig(knots=12), ppo=PPOConfig(updates=3, n_envs=8, epochs=2, minibatches=2))


def test_the_ppo_planner_keeps_the_protocol_and_every_limit(robot, p1, tiny_settings, tmp_path):
    pcfg = PlannerConfig(acceleration_limits=[150.0] * 6, torque_margin=0.15)
    params, meta = train_policy(robot, p1, pcfg, None, tiny_settings, tmp_path / "ppo", "P1")
    assert meta["env_steps"] == 3 * 8 * 12 and meta["training_s"] > 0
    assert len(meta["returns"]) == 3  # one mean episode return per update: the training curve
    # no snapshot count below 3 updates is kept: the curve is the final policy alone
    assert load_snapshots(tmp_path / "ppo", obs_dim(tiny_settings.env, 6), tiny_settings.ppo.hidden) == {}
    planner: Planner = PpoPlanner(robot, p1, pcfg, params, tiny_settings)
    assert planner.name == "ppo"
    traj = planner.plan(PATH)
    assert isinstance(traj, TimedTrajectory) and traj.planner == "ppo"
    assert np.allclose(traj.q[0], PATH[0], atol=1e-6) and np.allclose(traj.q[-1], PATH[-1], atol=1e-6)
    lim = robot.limits
    assert np.all(np.abs(traj.dq) <= lim.velocity * pcfg.velocity_fraction * 1.01)
    tau = p1(traj.q, traj.dq, traj.ddq)
    assert np.all(np.max(np.abs(tau), axis=0) <= lim.effort * 0.85 * 1.002)
    # a tighter limit gives a plan no faster, that fits it
    tight = planner.plan(PATH, np.full(6, 0.3))
    assert tight.duration >= traj.duration
    assert np.all(np.max(np.abs(p1(tight.q, tight.dq, tight.ddq)), axis=0) <= lim.effort * 0.85 * 0.3 * 1.002)


def test_a_stored_policy_loads_and_a_mismatched_one_is_refused(tmp_path):
    from cell.planning.ppo import init_params

    params = init_params(np.random.default_rng(0), 10, 16, -0.5)
    save_policy(tmp_path, params, {"model": "x"})
    loaded, meta = load_policy(tmp_path, 10, 16)
    assert meta["model"] == "x" and all(np.array_equal(loaded[k], params[k]) for k in params)
    with pytest.raises(ConfigError, match="retrain it"):
        load_policy(tmp_path, 11, 16)
    (tmp_path / "policy.npz").write_bytes(b"not a policy")
    with pytest.raises(ConfigError, match="cannot read"):
        load_policy(tmp_path, 10, 16)


def test_the_kinematic_planner_keeps_its_speed_and_acceleration_limits(robot, p1):
    slow = [2.0, 2.0, 3.0, 5.0, 5.0, 5.0]
    k = KinematicPlanner(robot, p1, PlannerConfig(acceleration_limits=slow, velocity_fraction=0.75))
    traj = k.plan(PATH)
    assert traj.planner == "kinematic"
    assert np.all(np.max(np.abs(traj.ddq), axis=0) <= np.array(slow) * 1.01)
    assert np.all(np.abs(traj.dq) <= robot.limits.velocity * 0.75 * 1.01)
    fast = KinematicPlanner(robot, p1, PlannerConfig(acceleration_limits=[20.0] * 6, velocity_fraction=0.75))
    assert fast.plan(PATH).duration < traj.duration
    # torque_scale scales the accelerations, and the torque-aware planner is never slower on its own model
    assert k.plan(PATH, np.full(6, 0.5)).duration > traj.duration
    assert ToppraPlanner(robot, p1, PlannerConfig(acceleration_limits=slow, velocity_fraction=0.75)).plan(
        PATH).duration <= traj.duration * 1.02


def test_snapshots_are_stored_by_update_count_and_a_misshapen_one_is_skipped(tmp_path):
    from cell.planning.ppo import init_params

    params = init_params(np.random.default_rng(0), 10, 16, -0.5)
    save_policy(tmp_path, params, {"model": "x"})
    save_snapshot(tmp_path, 20, params)
    save_snapshot(tmp_path, 100, params)
    save_snapshot(tmp_path, 7, init_params(np.random.default_rng(0), 11, 16, -0.5))
    snaps = load_snapshots(tmp_path, 10, 16)
    assert sorted(snaps) == [20, 100]
    assert all(np.array_equal(snaps[20][k], params[k]) for k in params)
