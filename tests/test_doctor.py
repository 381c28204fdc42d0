"""`doctor`: the bring-up checks pass on a healthy emulated cell and name each fault injected into its emulators."""

from __future__ import annotations

import contextlib
import json

import pytest

from drivers.errors import DriverError
from main import main
from tasks.setup.doctor import Doctor, DoctorSettings, report

CHECKS = ["arm_reachable", "modbus_connect", "register_map", "robot_program_heartbeat", "state_rate",
          "estop_and_errors", "sensor_port", "sensor_sensitivities", "sensor_tare_stability", "sensor_line",
          "control_step_timing"]


def test_doctor_passes_on_the_healthy_emulated_cell(capsys):
    code = main(["-q", "doctor", "--cell", "emulated", "--tare-s", "0.5", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0, out
    assert out["passed"] is True and out["failed"] == []
    assert [c["name"] for c in out["checks"]] == CHECKS
    assert all(c["status"] == "pass" and c["detail"] for c in out["checks"])


@pytest.fixture(scope="module")
def emulated():
    from app.tasks_registry import robot_for
    from cell.config import load_config
    from sim.emulated import EmulatedCell

    cfg = load_config()
    robot = robot_for(cfg, "wipe")
    holder = EmulatedCell(cfg, robot.limits, scene_kind="free")
    try:
        yield holder, robot, cfg
    finally:
        holder.close()


# fault command -> the check that must fail for it (and name it in its detail)
FAULTS = [
    ("estop", "estop_and_errors", "E-stop pressed"),
    ("delay 20", "control_step_timing", "p50"),
    ("exceptions", "modbus_connect", "exception"),
    ("sensor drop 0.5", "sensor_line", "timed out"),
    ("sensor garbage 0.5", "sensor_line", "corrupted"),
    # A stalled robot-side program latches its hold (released when a host arms): late in the list.
    ("freeze", "robot_program_heartbeat", "stuck"),
    ("drop_link 1", "arm_reachable", "refused"),  # last: the link comes back on its own schedule, not on clear
]


@pytest.mark.parametrize(("fault", "check", "words"), FAULTS, ids=[f for f, _, _ in FAULTS])
def test_doctor_names_each_injected_fault(emulated, fault, check, words):
    holder, robot, cfg = emulated
    holder.inject(fault)
    try:
        checks = Doctor(holder.arm, holder.sensor, robot.limits,
                        DoctorSettings(period_s=cfg.loop.period_s, tare_s=0.3, timing_steps=40,
                                       tail_periods=3.0)).run()
    finally:
        for device in (holder.arm, holder.sensor):
            with contextlib.suppress(DriverError):
                device.disconnect()
        holder.inject("clear")
        holder.inject("sensor clear")
    out = report(checks, "emulated")
    # A lossy line may also spoil the tare window before it (the sensor checks run in order): both say so.
    first_allowed = {check, "sensor_tare_stability"} if check == "sensor_line" else {check}
    assert out["passed"] is False and out["failed"][0] in first_allowed and check in out["failed"], out
    failed = next(c for c in out["checks"] if c["name"] == check)
    assert words in failed["detail"] and failed["fix"], failed
    # The checks before the failing one still pass: the report points at the cause, not at everything.
    first = CHECKS.index(out["failed"][0])
    assert all(c["status"] == "pass" for c in out["checks"][:first])
    assert [c["name"] for c in out["checks"]] == CHECKS


def test_the_stream_stop_check_asked_for_on_the_modbus_route_says_why_it_does_not_run(emulated):
    holder, robot, cfg = emulated
    try:
        checks = Doctor(holder.arm, holder.sensor, robot.limits,
                        DoctorSettings(period_s=cfg.loop.period_s, tare_s=0.3, timing_steps=40, tail_periods=3.0,
                                       stream_stop=True)).run()
    finally:
        for device in (holder.arm, holder.sensor):
            with contextlib.suppress(DriverError):
                device.disconnect()
    out = report(checks, "emulated")
    skipped = next(c for c in out["checks"] if c["name"] == "stream_stop")
    assert skipped["status"] == "skipped" and "Modbus route streams no speeds" in skipped["detail"]
    # (The other checks' results depend on the faults other tests left on this module's shared cell.)
    assert "stream_stop" not in out["failed"]
    assert [c["name"] for c in out["checks"] if c["name"] != "stream_stop"] == CHECKS


@pytest.mark.parametrize("over", [False, True])
def test_the_sensor_port_check_reads_the_usb_adapters_latency_timer(emulated, monkeypatch, over):
    from drivers.wacoh.driver import WacohSensor

    holder, robot, cfg = emulated
    timeout_ms = holder.sensor.config.timeout_s * 1e3
    timer_ms = int(timeout_ms) + 11 if over else 1  # (FTDI's default is 16 ms; the low-latency mode's 1 ms)
    monkeypatch.setattr(WacohSensor, "adapter_latency_ms", lambda self: timer_ms)
    try:
        checks = Doctor(holder.arm, holder.sensor, robot.limits,
                        DoctorSettings(period_s=cfg.loop.period_s, tare_s=0.3, timing_steps=40,
                                       tail_periods=3.0)).run()
    finally:
        for device in (holder.arm, holder.sensor):
            with contextlib.suppress(DriverError):
                device.disconnect()
    by_name = {c.name: c for c in checks}
    port = by_name["sensor_port"]
    assert f"USB adapter latency timer {timer_ms} ms" in port.detail
    # The emulated sensor numbers its records one per reply, and the driver learnt that at connect.
    assert "record number steps by one per reply" in port.detail
    if over:  # longer than the reply timeout: nearly every read would come late
        assert port.status == "fail" and "reply timeout" in port.detail and "latency timer" in port.fix
        assert by_name["sensor_line"].status == "skipped"
    else:
        assert port.status == "pass" and by_name["sensor_line"].status == "pass"


def test_doctor_refuses_faults_on_the_real_cell(capsys):
    assert main(["doctor", "--cell", "real", "--inject", "freeze"]) == 2
    assert "emulated cell only" in capsys.readouterr().err


def test_state_rate_fails_when_the_arm_streams_slower_than_the_loop():
    """The emulator's robot side cycles every 8 ms; a config asking for a 4 ms loop must not pass."""
    from app.tasks_registry import robot_for
    from cell.config import load_config
    from sim.emulated import EmulatedCell

    cfg = load_config()
    robot = robot_for(cfg, "wipe")
    holder = EmulatedCell(cfg, robot.limits, scene_kind="free")  # its own: the fault cases leave theirs lagging
    try:
        checks = Doctor(holder.arm, None, robot.limits,
                        DoctorSettings(period_s=cfg.loop.period_s / 2, timing_steps=10, tail_periods=3.0)).run()
    finally:
        with contextlib.suppress(DriverError):
            holder.arm.disconnect()
        holder.close()
    out = report(checks, "emulated")
    rate = next(c for c in out["checks"] if c["name"] == "state_rate")
    assert out["passed"] is False and rate["status"] == "fail", out
    measured = float(rate["detail"].split(" Hz")[0].split()[-1])
    assert 0.9 / cfg.loop.period_s <= measured <= 1.1 / cfg.loop.period_s, rate["detail"]
    assert "loop.period_s" in rate["fix"]
    # No sensor on this cell: its checks are skipped, shown as skipped, and not counted as passed.
    assert "sensor_port" in out["skipped"]
    assert all(not c["passed"] for c in out["checks"] if c["status"] == "skipped")
