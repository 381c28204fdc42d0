"""The Ethernet Slave table's safety items: arming needs them all, losing one while armed stops the arm,
Safeguard_A is a protective stop, a stale table is not armed on, a project speed below 100 % is reported."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.errors import LifecycleError, StaleDataError
from drivers.interfaces import Lifecycle
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_slave import (
    SAFETY_ITEMS,
    SlaveTableError,
    SvrFrame,
    decode_table,
    encode_items,
    encode_state_items,
)
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator
from tasks.setup.doctor import Doctor, DoctorSettings
from tests.tm_ethernet_fixtures import LIMITS, connected, make_arm, start, wait_for

ALL_ITEMS = [name for name, _ in encode_state_items(np.zeros(6), np.zeros(6), np.zeros(6))]


@pytest.fixture
def emulator() -> Iterator[TMEthernetEmulator]:
    emu = start(KinematicPlant(dt=0.008))
    yield emu
    emu.stop()


@pytest.fixture
def arm(emulator: TMEthernetEmulator) -> Iterator[TMEthernetArm]:
    yield from connected(emulator)


def read_until(arm: TMEthernetArm, cond: object, what: str) -> None:
    wait_for(lambda: bool(cond(arm.read_state())), what=what)  # type: ignore[operator]


# ------------------------------------------------------------------------------------------------ decoding
def test_safeguard_a_decodes_and_reads_as_a_protective_stop() -> None:
    content = encode_items(encode_state_items(np.zeros(6), np.zeros(6), np.zeros(6), safeguard=True))
    table = decode_table(SvrFrame("0", 1, content))
    assert table.safeguard is True and table.estop is False and table.missing_safety_items == ()
    status = TMEthernetArm._status(table)
    assert status.protective_stop and not status.ok and not status.estop


@pytest.mark.parametrize("missing", ["Robot_Error", "ESTOP", "Project_Run", "Safeguard_A", "Robot_Link"])
def test_a_missing_safety_item_never_reads_as_healthy(missing: str) -> None:
    items = [(n, v) for n, v in encode_state_items(np.zeros(6), np.zeros(6), np.zeros(6)) if n != missing]
    table = decode_table(SvrFrame("0", 1, encode_items(items)))  # reading needs only the joint items
    assert table.missing_safety_items == (missing,)
    assert not TMEthernetArm._status(table).ok


# ------------------------------------------------------------------------------------------------ arming
@pytest.mark.parametrize("missing", [("ESTOP",), ("Robot_Error", "Project_Pause", "Safeguard_A")])
def test_arming_refuses_a_table_without_the_safety_items(missing: tuple[str, ...]) -> None:
    emu = start(KinematicPlant(dt=0.008), items=[n for n in ALL_ITEMS if n not in missing])
    try:
        arm = make_arm(emu)
        arm.connect()  # a reading session is allowed
        assert not arm.read_state().status.ok
        scripts = emu.node.scripts
        with pytest.raises(SlaveTableError) as info:
            arm.arm()
        message = str(info.value)
        assert message.startswith(f"cannot arm: Ethernet Slave data table lacks {', '.join(missing)}: ")
        assert "Data Table Setting" in message and "\n" not in message
        assert arm.lifecycle is not Lifecycle.ARMED and emu.node.scripts == scripts  # nothing was sent
        arm.disconnect()
    finally:
        emu.stop()


def test_a_table_losing_estop_while_armed_stops_the_arm(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    arm.arm()
    wait_for(lambda: emulator.node.vmode.active, what="streaming")
    emulator.set_items([n for n in ALL_ITEMS if n != "ESTOP"])
    with pytest.raises(SlaveTableError, match="lacks ESTOP: the table changed while armed"):
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            arm.read_state()
            time.sleep(0.008)
    assert arm.lifecycle is Lifecycle.FAULT
    wait_for(lambda: not emulator.node.vmode.active, what="the fault's stop")


def test_safeguard_while_armed_faults_and_refuses_to_arm(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    arm.arm()
    emulator.trigger_safeguard()
    read_until(arm, lambda st: st.status.protective_stop, "Safeguard_A in the table")
    assert arm.lifecycle is Lifecycle.FAULT and "protective_stop" in (arm.fault_reason or "")
    assert arm.latest_table is not None and arm.latest_table.safeguard is True
    wait_for(lambda: not emulator.node.vmode.active, what="the fault's stop")
    with pytest.raises(LifecycleError, match="cannot arm: controller reports .*protective_stop=True"):
        arm.arm()
    emulator.clear_faults()
    read_until(arm, lambda st: st.status.ok, "the safeguard released")
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED


def test_arming_needs_a_table_no_older_than_stale_after_s(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    emulator.go_silent()
    time.sleep(3 * arm.config.stale_after_s)  # well short of link_lost_after_s: the link still counts as up
    with pytest.raises(StaleDataError, match=r"cannot arm: the latest data table is \d+ ms old \(limit stale_after_s "
                                             r"60 ms\)"):
        arm.arm()
    assert arm.link_up and arm.lifecycle is not Lifecycle.ARMED


# ------------------------------------------------------------------------------------------------ project speed
def test_a_project_speed_below_100_is_warned_once_and_fails_doctor(
        arm: TMEthernetArm, emulator: TMEthernetEmulator, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.tm5.ethernet")
    emulator.set_project_speed(50)
    read_until(arm, lambda st: arm.latest_table is not None and arm.latest_table.project_speed == 50, "speed 50")
    seq = arm.read_state().seq
    read_until(arm, lambda st: st.seq >= seq + 3, "three more tables")
    warnings = [r.getMessage() for r in caplog.records if "Project_Speed" in r.getMessage()]
    assert len(warnings) == 1 and "Project_Speed is 50 %, not 100 %" in warnings[0]
    checks = {c.name: c for c in Doctor(arm, None, LIMITS, DoctorSettings(period_s=0.0156, timing_steps=5,
                                                                            tail_periods=3.0)).run()}
    assert checks["project_speed"].status == "fail"
    assert checks["project_speed"].detail == "Project_Speed is 50 %, not 100 %"
    assert "100 %" in checks["project_speed"].fix
    assert checks["slave_table"].status == "pass" and "Safeguard_A" in checks["slave_table"].detail


def test_doctor_fails_a_table_without_safeguard(emulator: TMEthernetEmulator) -> None:
    emulator.set_items([n for n in ALL_ITEMS if n != "Safeguard_A"])
    arm = make_arm(emulator)
    try:
        checks = {c.name: c for c in Doctor(arm, None, LIMITS, DoctorSettings(period_s=0.0156, timing_steps=5,
                                                                                tail_periods=3.0)).run()}
    finally:
        arm.disconnect()
    table = checks["slave_table"]
    assert table.status == "fail" and "missing Safeguard_A" in table.detail and "refuses to arm" in table.detail
    assert all(name in table.fix for name in SAFETY_ITEMS)



def test_doctor_names_a_triggered_safeguard(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    emulator.trigger_safeguard()
    read_until(arm, lambda st: st.status.protective_stop, "Safeguard_A in the table")
    checks = {c.name: c for c in Doctor(arm, None, LIMITS, DoctorSettings(period_s=0.0156, timing_steps=5,
                                                                            tail_periods=3.0)).run()}
    assert checks["estop_and_errors"].status == "fail"
    assert checks["estop_and_errors"].detail == "protective stop (Safeguard_A triggered)"
