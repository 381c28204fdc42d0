"""The controller's Modbus table as a cross-check of TM's Ethernet Slave: reader, doctor, status and arming."""

from __future__ import annotations

import contextlib
import json
import math
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.errors import ConfigError, DriverError, LifecycleError, LinkLostError
from drivers.interfaces import JointLimits, Lifecycle
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.table_check import JOINT_TOLERANCE_DEG, check_arm, read_modbus_table
from sim.kinematic_plant import KinematicPlant
from sim.serve_cell import _apply, arm_endpoint
from sim.tm_ethernet_emulator import TMEthernetEmulator
from tasks.setup.doctor import Doctor, DoctorSettings

ROOT = Path(__file__).resolve().parents[1]
DT = 0.0156
Q0 = np.array([0.3, -0.4, 1.2, 0.25, 1.5, -0.7])  # rad: every joint distinct
LIMITS = JointLimits(lower=np.full(6, -2 * math.pi), upper=np.full(6, 2 * math.pi), velocity=np.full(6, math.pi),
                     effort=np.full(6, 150.0))


@pytest.fixture
def emulator() -> Iterator[TMEthernetEmulator]:
    with TMEthernetEmulator(KinematicPlant(dt=DT, q0=Q0), period_s=DT) as emu:
        yield emu


def make_arm(emu: TMEthernetEmulator, modbus_port: int | None) -> TMEthernetArm:
    cfg = TMEthernetConfig(host="127.0.0.1", slave_port=emu.slave_port, listen_port=emu.listen_port,
                           modbus_port=modbus_port, connect_timeout_s=2.0)
    return TMEthernetArm(cfg, LIMITS, DT)


@pytest.fixture
def arm(emulator: TMEthernetEmulator) -> Iterator[TMEthernetArm]:
    a = make_arm(emulator, emulator.modbus_port)
    a.connect()
    yield a
    a.disconnect()


def closed_port() -> int:
    """A loopback port nobody listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_doctor(arm: TMEthernetArm) -> dict[str, Any]:
    checks = Doctor(arm, None, LIMITS, DoctorSettings(period_s=DT, timing_steps=10, tail_periods=3.0)).run()
    with contextlib.suppress(DriverError):
        arm.disconnect()
    return {c.name: c for c in checks}


def test_the_emulated_table_reads_as_the_plant_in_si(emulator: TMEthernetEmulator) -> None:
    port = emulator.modbus_port
    assert port is not None and port not in (emulator.slave_port, emulator.listen_port)
    assert arm_endpoint(emulator)["modbus_port"] == port
    table = read_modbus_table("127.0.0.1", port, 1.0)
    np.testing.assert_allclose(table.q, Q0, atol=1e-6)  # rad, from float32 degrees
    assert (table.error, table.project_running, table.estop) == (False, True, False)


def test_the_reader_agrees_with_the_ethernet_slave(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    check = check_arm(arm)
    assert check.agrees and check.max_joint_diff_deg < 1e-3, check.summary()
    assert check.differing_flags == () and check.unchecked_flags == ()
    assert check.as_dict()["agrees"] is True
    # Both tables come from one controller: a pressed E-stop reads on both, and they still agree.
    emulator.press_estop()
    check = check_arm(arm)
    assert check.agrees, check.summary()


def test_a_disagreeing_table_fails_doctor_with_its_line(emulator: TMEthernetEmulator) -> None:
    _apply(["table_offset", "5"], emulator, None)  # the emulated cell's fault command
    checks = run_doctor(make_arm(emulator, emulator.modbus_port))
    assert checks["joint_data"].status == "pass"
    cross = checks["modbus_cross_check"]
    assert cross.status == "fail", cross
    assert "5.000 deg off the Ethernet Slave's" in cross.detail and f"allowed {JOINT_TOLERANCE_DEG:.2f}" in cross.detail
    assert "\n" not in cross.detail and "modbus_port" in cross.fix
    # Cleared, the same check passes and says how close the tables are.
    _apply(["clear"], emulator, None)
    checks = run_doctor(make_arm(emulator, emulator.modbus_port))
    assert checks["modbus_cross_check"].status == "pass", checks["modbus_cross_check"]
    assert "joints within 0.000 deg" in checks["modbus_cross_check"].detail


def test_doctor_skips_the_check_when_modbus_port_is_null(emulator: TMEthernetEmulator) -> None:
    cross = run_doctor(make_arm(emulator, None))["modbus_cross_check"]
    assert cross.status == "skipped" and "modbus_port is null" in cross.detail


def test_a_closed_port_is_one_line_in_the_reader_and_doctor(emulator: TMEthernetEmulator) -> None:
    port = closed_port()
    with pytest.raises(LinkLostError) as err:
        read_modbus_table("127.0.0.1", port, 1.0)
    assert str(err.value) == f"TM Modbus table 127.0.0.1:{port}: no Modbus/TCP server answers (Connection refused)"
    cross = run_doctor(make_arm(emulator, port))["modbus_cross_check"]
    assert cross.status == "fail" and "no Modbus/TCP server answers" in cross.detail and "\n" not in cross.detail
    assert "Setting > Connection > Modbus" in cross.fix


def test_a_port_that_never_answers_is_one_line() -> None:
    with socket.socket() as silent:  # accepts the connection (the kernel's backlog) and never replies
        silent.bind(("127.0.0.1", 0))
        silent.listen(1)
        port = int(silent.getsockname()[1])
        with pytest.raises(LinkLostError) as err:
            read_modbus_table("127.0.0.1", port, 0.2)
    assert str(err.value) == f"TM Modbus table 127.0.0.1:{port}: read input registers 7013: no reply within 200 ms"


def test_arming_checks_the_table_once_per_connection(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED
    reads = emulator.modbus_reads
    assert reads > 0
    # The control loop's re-arm after a stop sends no Modbus request: it would block the loop.
    arm.stop()
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED and emulator.modbus_reads == reads
    arm.stop()
    arm.confirm_stop()
    # New links are checked again on their first arm.
    arm.disconnect()
    emulator.offset_modbus_joints(2.0)
    arm.connect()
    with pytest.raises(LifecycleError, match=r"^cannot arm: Modbus table .* 2\.000 deg off .*modbus_port: null"):
        arm.arm()
    assert arm.lifecycle is not Lifecycle.ARMED and emulator.modbus_reads > reads


def test_arming_refuses_an_unreadable_table_in_one_line(emulator: TMEthernetEmulator) -> None:
    a = make_arm(emulator, closed_port())
    a.connect()
    try:
        with pytest.raises(LinkLostError) as err:
            a.arm()
        assert str(err.value).startswith("cannot arm: TM Modbus table") and "\n" not in str(err.value)
        assert "modbus_port: null" in str(err.value) and a.lifecycle is not Lifecycle.ARMED
    finally:
        a.disconnect()


def test_an_emulator_without_the_table_serves_none() -> None:
    with TMEthernetEmulator(KinematicPlant(dt=DT), period_s=DT, modbus_port=None) as emu:
        assert emu.modbus_port is None and "modbus_port" not in arm_endpoint(emu)


def test_modbus_port_is_bounded_null_by_default() -> None:
    where = "cell.yaml: devices.arm.settings"
    assert TMEthernetConfig.from_dict({"host": "h"}, where).modbus_port is None
    assert TMEthernetConfig.from_dict({"host": "h", "modbus_port": 502}, where).modbus_port == 502
    for value, words in [(0, "modbus_port must lie in 1-65535"), (5891, "modbus_port must differ from slave_port"),
                         ("502", "modbus_port must be")]:
        with pytest.raises(ConfigError, match=words):
            TMEthernetConfig.from_dict({"host": "h", "modbus_port": value}, where)


def test_status_json_carries_the_cross_check(emulator: TMEthernetEmulator, tmp_path: Path, capsys: Any) -> None:
    from main import main
    from sim.wacoh_emulator import WacohEmulator

    with WacohEmulator(lambda: np.zeros(6), noise=0.0) as sensor:
        path = tmp_path / "cell.yaml"
        path.write_text(
            f"base: {ROOT / 'config' / 'tm-ethernet.yaml'}\n"
            f"loop: {{period_s: {DT}}}\n"
            "devices:\n"
            f"  arm: {{kind: real, settings: {{protocol: tm-ethernet, host: 127.0.0.1, slave_port: "
            f"{emulator.slave_port}, listen_port: {emulator.listen_port}, modbus_port: {emulator.modbus_port}, "
            "stale_after_s: 0.06}}\n"
            f"  sensor: {{kind: real, settings: {{port: {sensor.tty_path}}}}}\n", encoding="utf-8")
        assert main(["-q", "status", "--cell", "real", "--config", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    cross = out["modbus_cross_check"]
    assert cross["agrees"] is True and cross["max_joint_diff_deg"] < 1e-3
    assert cross["endpoint"] == f"127.0.0.1:{emulator.modbus_port}"


def test_the_reader_reads_the_documented_inputs_only() -> None:
    # A controller that serves 7200-7202, 7204 and 7208 alone (exception 2 for a read over 7203, 7205-7207).
    from sim.tm5_emulator import TM5Emulator
    from tests.tm5_fixtures import Q0 as TM5_Q0
    from tests.tm5_fixtures import FakePlant, wait_for

    with TM5Emulator(FakePlant(TM5_Q0)) as emulator:
        emulator.serve_documented_inputs_only()
        table = read_modbus_table("127.0.0.1", emulator.port, 1.0)
        assert table.project_running and not table.estop and not table.error
        emulator.press_estop()
        wait_for(lambda: read_modbus_table("127.0.0.1", emulator.port, 1.0).estop, what="input 7208 read alone")


def test_the_emulated_cells_safeguard_and_listen_lag_commands_fail_their_checks(emulator: TMEthernetEmulator) -> None:
    _apply(["safeguard"], emulator, None)
    checks = run_doctor(make_arm(emulator, None))
    assert checks["estop_and_errors"].status == "fail" and "Safeguard_A" in checks["estop_and_errors"].detail
    _apply(["clear"], emulator, None)
    _apply(["listen_lag", "100"], emulator, None)  # 100 ms a packet: the node falls behind a 64 Hz stream
    checks = run_doctor(make_arm(emulator, None))
    assert checks["estop_and_errors"].status == "pass"
    assert checks["command_round_trip"].status == "fail", checks["command_round_trip"]
    _apply(["clear"], emulator, None)  # the lag too
    assert emulator.script_interval_s == 0.0
    with pytest.raises(ValueError, match="listen_lag takes 1 argument"):
        _apply(["listen_lag"], emulator, None)
