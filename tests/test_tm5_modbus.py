"""The real TM5 Modbus driver against the TM5 emulator (127.0.0.1, port 0): state, poses, targets, stops."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from drivers.errors import LifecycleError, StaleDataError
from drivers.interfaces import ArmStatus, Lifecycle
from drivers.tm5.modbus import TM5ModbusArm
from sim.tm5_emulator import TM5Emulator
from tests.tm5_fixtures import DT, Q0, FakePlant, make_arm, wait_for

pytestmark = [pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning"),
              pytest.mark.usefixtures("no_leaked_threads")]


# ------------------------------------------------------------------------------------------------ state
@pytest.mark.timeout(20)
def test_state_at_rest_matches_plant_in_si(arm: TM5ModbusArm, plant: FakePlant) -> None:
    arm.arm()
    s = arm.read_state()
    np.testing.assert_allclose(s.q, plant.q, rtol=0, atol=1e-6)  # float32 degrees on the wire
    np.testing.assert_allclose(s.dq, 0.0, atol=1e-6)
    np.testing.assert_allclose(s.tau, FakePlant.torque_of(Q0), rtol=1e-6, atol=1e-6)  # mN·m -> N·m
    assert s.status == ArmStatus()
    assert s.status.ok
    assert arm.lifecycle is Lifecycle.ARMED


@pytest.mark.timeout(20)
def test_moving_state_matches_published_plant_state(arm: TM5ModbusArm, emulator: TM5Emulator) -> None:
    arm.arm()
    q = arm.read_state().q
    states = []
    for i in range(40):
        states.append(arm.read_state())
        arm.send_target(q + 0.02 * (i + 1) * np.array([1, -1, 0.5, 1, -0.5, 1]))
        time.sleep(DT)
    seqs = [s.seq for s in states]
    assert all(b >= a for a, b in zip(seqs, seqs[1:], strict=False)) and seqs[-1] > seqs[0]
    moving = 0
    for s in states:
        pub = emulator.published_state(s.seq)
        assert pub is not None
        # speed, torque and the counter come from one read of the user area: exactly the same cycle
        np.testing.assert_allclose(s.dq, pub.dq, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(s.tau, pub.tau, rtol=1e-6, atol=1e-6)
        # the angles are a separate read just before: the same cycle or the one before it
        candidates = [p for p in (pub, emulator.published_state(s.seq - 1)) if p is not None]
        assert any(np.allclose(s.q, p.q, rtol=0, atol=1e-6) for p in candidates)
        moving += bool(np.linalg.norm(s.dq) > 0.1)
    assert moving > 10  # the comparison was made while the plant moved, not only at rest


@pytest.mark.timeout(20)
def test_poses_in_metres_and_rotation(arm: TM5ModbusArm, plant: FakePlant) -> None:
    arm.read_state()
    pos, rot = arm.read_tool_pose()
    ppos, prot = plant.tool_pose()
    np.testing.assert_allclose(pos, ppos, atol=1e-6)
    np.testing.assert_allclose(rot, prot, atol=1e-6)
    fpos, frot = arm.read_flange_pose()
    np.testing.assert_allclose(fpos, plant.flange_pose()[0], atol=1e-6)
    np.testing.assert_allclose(frot, plant.flange_pose()[1], atol=1e-6)
    cached = arm.last_tool_pose
    assert cached is not None
    np.testing.assert_allclose(cached[0], ppos, atol=1e-6)


@pytest.mark.timeout(20)
def test_status_inputs_map_to_arm_status(arm: TM5ModbusArm, plant: FakePlant) -> None:
    plant.status = ArmStatus(estop=True, error=True, paused=True)
    wait_for(lambda: arm.read_state().status.estop, what="E-stop input 7208")
    s = arm.read_state()
    assert s.status.error and s.status.paused and s.status.project_running
    assert not s.status.ok
    with pytest.raises(LifecycleError, match="controller reports"):
        arm.arm()


@pytest.mark.timeout(20)
def test_target_arrives_at_plant_in_rad(arm: TM5ModbusArm, plant: FakePlant) -> None:
    arm.arm()
    q = arm.read_state().q
    target = q + np.array([0.01, -0.02, 0.005, 0.0, 0.02, -0.015])
    sent = arm.send_target(target)
    assert not sent.clipped
    wait_for(lambda: len(plant.accepted_targets) > 0, what="the target at the plant")
    np.testing.assert_allclose(plant.accepted_targets[-1], target, rtol=0, atol=1e-6)
    for _ in range(40):  # keep the heartbeat going (else the robot-side watchdog stops the arm)
        arm.send_target(target)
        time.sleep(DT)
    np.testing.assert_allclose(plant.q, target, atol=1e-4)
    assert arm.robot_side is not None


@pytest.mark.timeout(20)
def test_standard_client_reads_degrees_from_7013(emulator: TM5Emulator, plant: FakePlant) -> None:
    client = ModbusTcpClient("127.0.0.1", port=emulator.port, timeout=1.0)
    try:
        assert client.connect()
        rr = client.read_input_registers(7013, count=12, device_id=1)
        assert not rr.isError()
        angles = client.convert_from_registers(rr.registers, client.DATATYPE.FLOAT32)
        assert isinstance(angles, list)
        np.testing.assert_allclose(angles, np.degrees(plant.q), atol=1e-4)
        rr = client.read_input_registers(7001, count=12, device_id=1)
        flange = client.convert_from_registers(rr.registers, client.DATATYPE.FLOAT32)
        assert isinstance(flange, list)
        np.testing.assert_allclose(flange[:3], plant.flange_pose()[0] * 1000.0, atol=1e-3)  # mm
        di = client.read_discrete_inputs(7200, count=9, device_id=1)
        assert di.bits[2] and not di.bits[1] and not di.bits[8]  # running, no error, no E-stop
        counter = client.read_holding_registers(9000, count=2, device_id=1)
        robot_counter = client.convert_from_registers(counter.registers, client.DATATYPE.INT32)
        assert isinstance(robot_counter, int) and robot_counter > 0
    finally:
        client.close()


@pytest.mark.timeout(20)
def test_seq_is_monotonic_across_counter_wrap(plant: FakePlant) -> None:
    emu = TM5Emulator(plant)
    emu.program.counter = 2**31 - 4  # INT32 wraps to negative within a few cycles
    with emu:
        arm = make_arm(emu)
        with arm:
            seqs = []
            for _ in range(12):
                seqs.append(arm.read_state().seq)
                time.sleep(DT)
    assert emu.robot_counter < 0  # it did wrap
    assert all(b >= a for a, b in zip(seqs, seqs[1:], strict=False))
    assert seqs[-1] - seqs[0] >= 8


# ------------------------------------------------------------------------------------------------ stops
@pytest.mark.timeout(20)
def test_stop_holds_and_arm_releases(arm: TM5ModbusArm, plant: FakePlant) -> None:
    arm.arm()
    arm.stop()
    assert arm.lifecycle is Lifecycle.CONNECTED
    wait_for(lambda: plant.hold_calls == 1, what="the hold")
    wait_for(lambda: arm.read_state().status.protective_stop, what="HELD in the status word")
    arm.arm()
    assert plant.release_calls == 1 and arm.read_state().status.ok


@pytest.mark.timeout(20)
def test_stop_coil_ends_the_project(emulator: TM5Emulator, plant: FakePlant) -> None:
    arm = make_arm(emulator, stop_coil=True)
    with arm:
        arm.arm()
        arm.stop()
        assert not emulator.project_running
        wait_for(lambda: not arm.read_state().status.project_running, what="input 7202 to drop")
        with pytest.raises(StaleDataError):  # the robot-side program is the project: it stopped too
            arm.arm()
        emulator.restart_project()
        arm.arm()
        assert arm.read_state().status.ok


@pytest.mark.timeout(30)
def test_bench_reports_cycle_times() -> None:
    from bench.timing import bench_modbus

    # The report's shape, not the link's deadline (tested on its own): a busy machine may delay the emulator's
    # thread past the cell's 10 ms reply deadline.
    result = bench_modbus(200, timeout_s=1.0)
    assert result["n"] == 200
    assert 0 < result["modbus_cycle_median_ms"] <= result["modbus_cycle_p99_ms"]
