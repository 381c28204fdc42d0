"""Driver lifecycle (no commands before arming or after a fault) and the loop's safety limits."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cell.control.loop import Command, ControlLoop, Observation
from cell.control.safety import SafetyMonitor
from cell.data.recorder import Recorder, read_log
from drivers.errors import CommandRejectedError, LifecycleError, SafetyStopError
from drivers.interfaces import ArmState, Lifecycle, Wrench
from sim.cell import make_sim_cell


@pytest.fixture
def simcell(cfg, robot):
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")
    yield holder
    holder.close()


def test_no_command_before_arming_and_none_after_a_fault(simcell, home):
    cell = simcell.open()
    arm = cell.arm
    with pytest.raises(LifecycleError, match="connected"):
        arm.send_target(home)
    arm.arm()
    arm.send_target(home)
    arm.fault("test fault")
    assert arm.lifecycle is Lifecycle.FAULT
    with pytest.raises(LifecycleError, match="test fault"):
        arm.send_target(home)
    assert simcell.plant.holding  # a fault stops the arm
    arm.arm()  # re-arming clears it
    assert arm.lifecycle is Lifecycle.ARMED
    arm.send_target(home)


def test_nan_and_malformed_targets_are_rejected_before_the_arm(simcell, home):
    cell = simcell.open()
    cell.arm.arm()
    before = simcell.plant.target.copy()
    bad = home.copy()
    bad[2] = np.nan
    with pytest.raises(CommandRejectedError, match="non-finite"):
        cell.arm.send_target(bad)
    with pytest.raises(CommandRejectedError, match="shape"):
        cell.arm.send_target(home[:5])
    np.testing.assert_array_equal(simcell.plant.target, before)


def test_send_target_clips_to_limits_and_speed_and_reports_it(simcell, home, robot):
    cell = simcell.open()
    cell.arm.arm()
    far = home + 1.0
    sent = cell.arm.send_target(far)
    assert sent.clipped
    step = robot.limits.velocity * cell.arm.dt
    np.testing.assert_allclose(np.abs(sent.q - home), np.minimum(step, 1.0), atol=1e-9)
    np.testing.assert_array_equal(sent.requested, far)


def state(tau=None, dq=None) -> ArmState:
    return ArmState(t=0.0, q=np.zeros(6), dq=np.zeros(6) if dq is None else dq,
                    tau=np.zeros(6) if tau is None else tau)


def wrench(f) -> Wrench:
    return Wrench(t=0.0, force=np.asarray(f, float), torque=np.zeros(3))


def test_safety_monitor_names_each_limit(cfg, robot, home):
    mon = SafetyMonitor(cfg.safety, robot, cfg.loop.period_s)
    with pytest.raises(SafetyStopError, match="tool force 200.0 N exceeds"):
        mon.check_state(state(), wrench([0, 0, 200.0]))
    with pytest.raises(SafetyStopError, match="joint 2 torque"):
        mon.check_state(state(tau=np.array([0, 150.0, 0, 0, 0, 0])), None)
    with pytest.raises(SafetyStopError, match="joint 5 speed"):
        mon.check_state(state(dq=np.array([0, 0, 0, 0, 4.0, 0])), None)
    with pytest.raises(SafetyStopError, match="non-finite"):
        mon.check_command(np.full(6, np.nan))
    mon.check_state(state(), wrench([0, 0, 100.0]))
    mon.check_command(np.zeros(6))  # arm straight up: TCP at z ~0.89 m, inside the default box
    low_ceiling = SafetyMonitor(replace(cfg.safety, workspace_max=[0.8, 0.8, 0.5]), robot, cfg.loop.period_s)
    with pytest.raises(SafetyStopError, match="outside the workspace"):
        low_ceiling.check_command(np.zeros(6))
    jump = SafetyMonitor(cfg.safety, robot, cfg.loop.period_s)
    jump.check_command(home)
    with pytest.raises(SafetyStopError, match="TCP speed"):
        jump.check_command(home + 0.05)


def test_invalid_force_readings_stop_after_a_few_cycles(cfg, robot):
    mon = SafetyMonitor(cfg.safety, robot, cfg.loop.period_s)
    nan = wrench([np.nan, 0, 0])
    for _ in range(cfg.safety.max_sensor_invalid_cycles):
        mon.check_state(state(), nan)
    with pytest.raises(SafetyStopError, match="invalid"):
        mon.check_state(state(), nan)


class Scripted:
    """A task that holds the pose, then commands what `script(cycle, q)` returns."""

    name = "scripted"

    def __init__(self, script, cycles=40):
        self.script, self.cycles, self._done, self.aborted = script, cycles, False, ""

    @property
    def done(self):
        return self._done

    @property
    def state_name(self):
        return "run"

    def step(self, obs: Observation) -> Command:
        if obs.cycle >= self.cycles:
            self._done = True
        return Command(q=self.script(obs.cycle, obs.q_cmd), log={"x": 0.0})

    def abort(self, reason):
        self.aborted = reason
        self._done = True

    def summary(self):
        return {"outcome": "done"}


def run_loop(holder, cfg, robot, task, tmp_path, safety_cfg=None):
    cell = holder.open()
    rec = Recorder(tmp_path / "run", chunk_rows=7)
    loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(safety_cfg or cfg.safety, robot, cfg.loop.period_s),
                       cell.ticker, rec, cfg.loop.period_s, 10.0)
    return loop.run(), rec


def test_force_spike_stops_the_arm_and_closes_the_recording(cfg, robot, tmp_path):
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")
    plant = holder.plant

    def script(cycle, q):
        if cycle == 20:
            plant.external_wrench = np.array([0.0, 0.0, 400.0, 0, 0, 0])  # someone slams the tool
        return q

    task = Scripted(script)
    result, rec = run_loop(holder, cfg, robot, task, tmp_path)
    assert result.outcome == "safety_stop"
    assert "tool force" in result.reason
    assert plant.holding and holder.arm.lifecycle is not Lifecycle.ARMED
    log = read_log(tmp_path / "run").to_pydict()
    assert rec.closed and len(log["t"]) == result.cycles + 1
    # The last row is the sample that tripped the stop: its force is over the limit.
    assert np.hypot(np.hypot(log["fx"][-1], log["fy"][-1]), log["fz"][-1]) > cfg.safety.max_tool_force_n
    assert 20 <= result.cycles <= 23  # stopped within a couple of periods of the spike
    assert "safety stop" in task.aborted


def test_nan_target_from_a_task_is_a_safety_stop_not_a_crash(cfg, robot, tmp_path):
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")
    task = Scripted(lambda cycle, q: q * np.nan if cycle == 5 else q)
    result, rec = run_loop(holder, cfg, robot, task, tmp_path)
    assert result.outcome == "safety_stop" and "non-finite" in result.reason
    assert holder.plant.holding and rec.closed


def test_ctrl_c_stops_the_arm_and_keeps_the_log(cfg, robot, tmp_path):
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")

    def script(cycle, q):
        if cycle == 30:
            raise KeyboardInterrupt
        return q

    result, rec = run_loop(holder, cfg, robot, Scripted(script), tmp_path)
    assert result.outcome == "interrupted"
    assert holder.plant.holding and rec.closed
    assert read_log(tmp_path / "run").num_rows == 30


def test_unexpected_exception_still_stops_the_arm(cfg, robot, tmp_path):
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")

    def script(cycle, q):
        if cycle == 3:
            raise ZeroDivisionError("bug in a task")
        return q

    with pytest.raises(ZeroDivisionError):
        run_loop(holder, cfg, robot, Scripted(script), tmp_path)
    assert holder.plant.holding


def test_joint_torque_limit_trips_on_a_hard_push(cfg, robot, tmp_path):
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")
    plant = holder.plant

    def script(cycle, q):
        if cycle == 10:
            plant.external_wrench = np.array([0.0, 0.0, -140.0, 0, 0, 0])
        return q

    safety = replace(cfg.safety, max_tool_force_n=1000.0, joint_torque_fraction=0.5)
    result, _ = run_loop(holder, cfg, robot, Scripted(script, cycles=200), tmp_path, safety)
    assert result.outcome == "safety_stop" and "torque" in result.reason


def test_wall_clock_pacing_runs_the_sim_at_real_speed(cfg, robot, tmp_path, monkeypatch):
    """Each cycle starts no earlier than its period boundary: the sim runs at real speed, never faster.
    (A busy machine can only make cycles later, so this holds whatever the load.)"""
    import time
    from dataclasses import replace as dc_replace

    from cell.control.loop import WallTicker

    early: list[float] = []
    waits = 0
    wait = WallTicker.wait

    def checked_wait(self: WallTicker) -> None:
        nonlocal waits
        deadline = self._next
        wait(self)
        waits += 1
        early.append(max(0.0, deadline - time.perf_counter()))

    monkeypatch.setattr(WallTicker, "wait", checked_wait)
    cfg.loop = dc_replace(cfg.loop, clock="wall")
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free")
    result, _ = run_loop(holder, cfg, robot, Scripted(lambda c, q: q, cycles=50), tmp_path)
    assert result.outcome == "done"
    assert waits >= 50 and max(early) == 0.0, f"a cycle started {max(early) * 1e3:.2f} ms early"
