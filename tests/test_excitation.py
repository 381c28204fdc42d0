"""Motion generators: collision filtering with Coal, the paper's chain, Fourier excitation within limits, playback."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest
import yaml

from cell.control.loop import Observation
from cell.data.excitation.chain import digitised_configurations, eulerian_chain, free_configurations, paper_chain
from cell.data.excitation.config import ExcitationConfig, FourierConfig
from cell.data.excitation.fourier import fourier_excitation
from cell.data.excitation.limits import Workspace, check_motion, excitation_checker
from cell.data.excitation.moves import path_clear, random_moves, transfer
from cell.data.excitation.sweep import sweep_excitation
from drivers.configio import load_dataclass
from drivers.errors import ConfigError
from drivers.interfaces import ArmState, Wrench
from tasks.lab.playback import PlaybackTask

DT = 0.008
SMALL = ExcitationConfig(steps=[2, 2, 2, 2, 2, 2], speeds=[0.5, 1.0], max_configs=5,
                         fourier=FourierConfig(harmonics=3, periods=1, base_hz=0.25, candidates=4, trajectories=1))


def test_config_loads_from_yaml_and_names_bad_fields(tmp_path):
    raw = yaml.safe_load("steps: [3, 3, 3, 2, 2, 2]\nspeeds: [0.5]\nfourier: {harmonics: 4}\n")
    ex = load_dataclass(ExcitationConfig, raw, "ex.yaml:")
    assert ex.steps[0] == 3 and ex.fourier.harmonics == 4
    with pytest.raises(ConfigError, match=r"ex.yaml: speeds must be fractions"):
        load_dataclass(ExcitationConfig, {"speeds": [1.5]}, "ex.yaml:")
    with pytest.raises(ConfigError, match=r"ranges_deg\[1\] must be \[low, high\]"):
        load_dataclass(ExcitationConfig, {"ranges_deg": [[-1, 1], [5, -5], [-1, 1], [-1, 1], [-1, 1], [-1, 1]]},
                       "ex.yaml:")


def test_paper_ranges_are_restrictions_inside_the_hardware_limits(robot):
    ex = ExcitationConfig()
    configs = digitised_configurations(robot, ex)
    assert len(configs) == np.prod(np.asarray(ex.steps) + 1)
    assert np.degrees(configs[:, 1]).max() <= 80 + 1e-9  # J2 +-80: a workspace restriction
    assert np.all(configs >= robot.limits.lower) and np.all(configs <= robot.limits.upper)


def test_colliding_configurations_are_dropped(robot, cfg):
    ex = ExcitationConfig()
    cc = excitation_checker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    home = np.asarray(cfg.robot.home)
    assert cc.free(home)
    # Shoulder forward and elbow folded down: the upper arm goes into the table (in front of the robot).
    into_table = np.array([0.0, np.radians(80), np.radians(90), 0.0, np.radians(90), 0.0])
    assert not cc.free(into_table)
    assert any("table" in pair for pair in cc.colliding_pairs(into_table))
    # Elbow folded fully and the wrist bent back, facing away from the table: the tool hits the upper arm.
    folded = np.radians([180.0, -60.0, 150.0, 0.0, 90.0, 0.0])
    assert cc.colliding_pairs(folded) == [("link_2_0", "tool")]
    kept, info = free_configurations(np.array([home, into_table, folded]), cc, ws)
    assert len(kept) == 1 and np.allclose(kept[0], home)
    assert info["dropped_collision"] == 2


def test_the_table_only_counts_where_the_scene_has_one(robot, cfg):
    into_table = np.array([0.0, np.radians(80), np.radians(90), 0.0, np.radians(90), 0.0])
    free_cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, kind="free"))
    ex = ExcitationConfig()
    assert "table" not in excitation_checker(robot, free_cfg, ex).fixtures
    assert "table" in excitation_checker(robot, cfg, ex).fixtures
    assert not any("table" in p for p in excitation_checker(robot, free_cfg, ex).colliding_pairs(into_table))


def test_eulerian_chain_uses_every_ordered_pair_once():
    m = 5
    adj = {i: [j for j in range(m) if j != i] for i in range(m)}
    walk = eulerian_chain(adj, 0)
    pairs = list(zip(walk[:-1], walk[1:], strict=True))
    assert len(pairs) == m * (m - 1) and len(set(pairs)) == m * (m - 1)
    assert walk[0] == walk[-1] == 0


def test_paper_chain_is_continuous_free_and_within_limits(robot, cfg):
    plan = paper_chain(robot, cfg, SMALL, DT)
    assert plan.info["chain_configurations"] >= 3
    moves = Counter(s.traj for s in plan.segments)
    assert set(moves) == {0, 1} and moves[0] == moves[1] == plan.info["ordered_pairs"]  # every pair at V speeds
    for a, b in zip(plan.segments[:-1], plan.segments[1:], strict=True):
        step = np.abs(b.q[0] - a.q[-1])
        assert np.all(step <= robot.limits.velocity * DT)  # no jumps between moves
    assert check_motion(plan, robot, cfg, SMALL) == []


def test_paper_chain_meets_a_sample_budget(robot, cfg):
    ex = dataclasses.replace(SMALL, max_configs=0)
    plan = paper_chain(robot, cfg, ex, DT, max_samples=20000)
    assert 20000 <= plan.samples <= 20000 + max(len(s.q) for s in plan.segments)


def test_fourier_excitation_respects_limits_and_starts_at_rest(robot, cfg):
    plan = fourier_excitation(robot, cfg, SMALL, DT)
    assert plan.info["trajectories"] == 1 and plan.info["condition_numbers"][0] < 1e4
    ws = Workspace(robot, cfg, SMALL)
    body = [s for s in plan.segments if s.speed == 1.0]
    q = np.vstack([s.q for s in body])
    dq = np.diff(q, axis=0) / DT
    ddq = np.diff(dq, axis=0) / DT
    lo = np.radians(np.asarray(SMALL.ranges_deg)[:, 0])
    hi = np.radians(np.asarray(SMALL.ranges_deg)[:, 1])
    assert np.all(q >= lo - 1e-9) and np.all(q <= hi + 1e-9)
    assert np.all(np.abs(dq).max(axis=0) <= ws.vmax * 1.01)
    assert np.all(np.abs(ddq).max(axis=0) <= ws.amax * 1.05)
    assert np.abs(dq[:3]).max() < 0.01 and np.abs(dq[-3:]).max() < 0.01  # fades in and out at rest
    assert np.ptp(q, axis=0)[:3].min() > 0.05  # and it does excite the main joints
    assert check_motion(plan, robot, cfg, SMALL) == []


def test_sweeps_hold_slow_constant_speeds_around_the_working_posture(robot, cfg):
    centre = np.array(cfg.robot.home, float) + np.array([0.3, 0.2, -0.3, 0.1, 0.0, 0.2])
    plan = sweep_excitation(robot, cfg, SMALL, DT, 6000, centre)
    sweeps = [s for s in plan.segments if s.kind == "sweep" and s.traj >= 0]
    assert plan.samples >= 6000 and plan.info["blocks"] >= 2
    q = np.vstack([s.q for s in plan.segments])
    np.testing.assert_allclose(q[0], cfg.robot.home, atol=0.05)  # it starts with the way from home
    body = np.vstack([s.q for s in sweeps[1:]])  # after the first block's transfer
    dq = np.diff(body, axis=0) / DT
    # Every joint stays near the centre (turns back past half the box) and never outruns the range.
    assert np.all(np.abs(body - centre).max(axis=0) < 0.2)
    speed = np.abs(dq)
    assert speed.max() <= 0.06 * 1.001
    # Long stretches at constant speed, most of them slow: the friction's steady low-speed branch.
    steady = np.all(np.abs(np.diff(dq, axis=0)) < 1e-9, axis=1)
    assert steady.mean() > 0.6
    assert np.median(speed[1:][steady]) < 0.03 and np.mean(speed[1:][steady] < 0.01) > 0.2
    assert check_motion(plan, robot, cfg, SMALL) == []


def test_sweeps_refuse_a_centre_in_collision(robot, cfg):
    low = np.array(cfg.robot.home, float)
    low[1] = np.radians(100.0)  # far down: the arm in the table
    with pytest.raises(ValueError, match="sweep centre"):
        sweep_excitation(robot, cfg, SMALL, DT, 1000, low)


def test_random_test_moves_are_another_family(robot, cfg):
    plan = random_moves(robot, cfg, SMALL, DT, trajectories=2, moves=2, speeds=[0.5], repeats=2, seed=4)
    assert sorted({s.traj for s in plan.segments}) == [0, 1, 2, 3]
    first, again = [np.vstack([s.q for s in plan.segments if s.traj == t]) for t in (0, 1)]
    np.testing.assert_allclose(first[-1], again[0], atol=1e-9)  # a repeat runs back from where it ended
    assert check_motion(plan, robot, cfg, SMALL) == []


def test_transfer_goes_around_when_the_straight_path_is_blocked(robot, cfg):
    ex = ExcitationConfig()
    a = np.radians([-120.0, 40.0, 60.0, 0.0, 90.0, 0.0])
    b = np.radians([150.0, 40.0, 60.0, 0.0, 90.0, 0.0])
    cc = excitation_checker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    assert cc.free(a) and cc.free(b) and not path_clear(a, b, cc, ws, ex.path_step_rad)
    legs = transfer(a, b, robot, cfg, ex, DT)
    assert len(legs) == 3
    q = np.vstack([s.q for s in legs])
    np.testing.assert_allclose(q[-1], b, atol=1e-9)
    assert all(cc.free(x) for x in q[::10])


def _obs(q: np.ndarray, k: int) -> Observation:
    st = ArmState(t=k * DT, q=q, dq=np.zeros(6), tau=np.zeros(6))
    return Observation(t=k * DT, cycle=k, state=st, wrench=Wrench(k * DT, np.zeros(3), np.zeros(3)), q_cmd=q)


def test_playback_task_moves_to_start_plays_every_sample_and_labels_rows(robot, cfg):
    plan = random_moves(robot, cfg, SMALL, DT, trajectories=1, moves=1, speeds=[1.0], seed=2)
    seen = []
    task = PlaybackTask(plan, robot, DT, progress=lambda k: seen.append(k))
    q = np.asarray(cfg.robot.home, float) + 0.1
    played, k = [], 0
    while not task.done:
        cmd = task.step(_obs(q, k))
        if float(cmd.log["traj"]) >= 0:
            played.append(cmd.q)
        q = cmd.q
        k += 1
        assert k < 100000
    np.testing.assert_allclose(np.array(played), np.vstack([s.q for s in plan.segments]))
    assert sum(seen) == plan.samples and task.summary()["outcome"] == "done"
    task2 = PlaybackTask(plan, robot, DT)
    task2.abort("test")
    assert task2.summary()["outcome"] == "failed" and task2.summary()["reason"] == "test"


def test_training_plan_adds_sweeps_around_the_given_posture(robot, cfg):
    from tasks.lab.collect import training_plan

    centre = np.array(cfg.robot.home, float) + np.array([0.3, 0.2, -0.3, 0.1, 0.0, 0.2])
    plan = training_plan(robot, cfg, SMALL, DT, 3000, "fourier", sweep_share=0.5, sweep_centre=centre)
    sweeps = [s for s in plan.segments if s.kind == "sweep"]
    assert sum(len(s.q) for s in sweeps) >= 1500 and plan.info["sweep"]["centre"] == np.round(centre, 4).tolist()
    q = np.vstack([s.q for s in plan.segments])
    assert np.max(np.abs(np.diff(q, axis=0))) < 0.05  # one continuous motion: the sweeps follow on
    assert check_motion(plan, robot, cfg, SMALL) == []
    with pytest.raises(ConfigError, match="working posture"):
        training_plan(robot, cfg, SMALL, DT, 3000, "fourier", sweep_share=0.5)


@pytest.mark.parametrize("tool", ["wipe", "peg"])
def test_each_tools_working_posture_is_free_and_above_its_task_start(cfg, tool):
    from app.tasks_registry import SWEEP_LIFT_M, TASK_TOOLS, build_task, robot_for, working_posture
    from cell.model.specs import robot_by_name

    robot = robot_for(cfg, tool)
    q = working_posture(cfg, tool, robot)
    task, _ = build_task(next(t for t, k in TASK_TOOLS.items() if k == tool), cfg, robot)
    lift = robot.tcp_pose(q).translation - robot.tcp_pose(task.q_start).translation
    np.testing.assert_allclose(lift, [0.0, 0.0, SWEEP_LIFT_M], atol=1e-3)
    ex = ExcitationConfig()
    assert excitation_checker(robot_by_name(cfg), cfg, ex).free(q) and Workspace(robot_by_name(cfg), cfg, ex).inside(q)
