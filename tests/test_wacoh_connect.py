"""Connecting the real `WacohSensor`: the `p` exchange's patience and retry, the drain after `E`, bounded writes."""

from __future__ import annotations

import logging
import os
import time
import tty
from collections.abc import Iterator

import pytest
import serial

from drivers.errors import LinkLostError
from drivers.serial_link import SerialLink
from drivers.wacoh.codec import RECORD_LEN
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import DRAIN_MIN_S, DRAIN_RECORDS, WacohSensor
from drivers.wacoh.sensitivity import P_TIMEOUT_S
from sim.wacoh_emulator import REAL_UNIT_SENSITIVITIES, FaultConfig
from tests.wacoh_fixtures import FALLBACK, EmulatorFactory, Source, connect

pytestmark = pytest.mark.timeout(25)


# ------------------------------------------------------------------------------------ `p`
def test_a_p_reply_slower_than_the_read_timeout_is_waited_for(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    """`p` got the per-read timeout (5.7 ms with the cell's 5 ms): a sensor a little slow to answer it was read
    with the configured sensitivities."""
    emulator = make_emulator(Source(), faults=FaultConfig(p_delay_s=0.05))
    sensor = connect(sensors, emulator, timeout_s=0.005)
    assert (sensor.sensitivities, sensor.sensitivities_source) == (REAL_UNIT_SENSITIVITIES, "sensor")
    assert emulator.commands["p"] == 2
    assert sensor.p_timeout_s == P_TIMEOUT_S


def test_a_first_p_without_reply_is_asked_once_more(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source(), faults=FaultConfig(ignore_first_p=1))
    sensor = connect(sensors, emulator, sensitivities=list(REAL_UNIT_SENSITIVITIES.values), timeout_s=0.005)
    assert sensor.sensitivities_source == "sensor"
    assert emulator.commands["p"] == 3  # the unanswered one, then two that agree


def test_a_sensor_that_never_answers_p_is_asked_twice_then_the_configured_values_are_used(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], caplog: pytest.LogCaptureFixture
) -> None:
    emulator = make_emulator(Source(), faults=FaultConfig(ignore_p=True))
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    sensor = connect(sensors, emulator, sensitivities=list(FALLBACK.values), timeout_s=0.005)
    assert emulator.commands["p"] == 2
    assert (sensor.sensitivities, sensor.sensitivities_source) == (FALLBACK, "config")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [f"WACOH sensor on {emulator.tty_path}: no reply to 'p' within 0.2 s, asked twice (some models "
                        f"never answer it); using the calibration sheet's sensitivities {FALLBACK.values}"]
    assert sensor.read().valid


def test_a_longer_configured_timeout_also_lengthens_the_p_wait() -> None:
    assert WacohSensor(WacohConfig(port="/dev/null", timeout_s=0.5)).p_timeout_s == 0.5


# ------------------------------------------------------------------------------------ the drain after `E`
@pytest.mark.parametrize(("baudrate", "expected_s"), [
    (921600, DRAIN_MIN_S), (115200, DRAIN_MIN_S), (9600, DRAIN_RECORDS * RECORD_LEN * 10 / 9600),
])
def test_the_drain_after_e_lasts_several_records_at_the_line_rate(baudrate: int, expected_s: float) -> None:
    sensor = WacohSensor(WacohConfig(port="/dev/null", baudrate=baudrate))
    assert sensor.stop_drain_s == pytest.approx(expected_s)
    assert sensor.stop_drain_s >= DRAIN_MIN_S and sensor.stop_drain_s >= 3 * RECORD_LEN * 10 / baudrate


def test_records_in_flight_after_e_at_9600_bit_s_do_not_reach_the_p_exchange(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    """Streaming left on by an earlier session, on a 9600 bit/s line: records keep landing for a record's time
    (28 ms) and more after `E`.  After a 20 ms drain they reached the first `p` reply's read and garbled it."""
    emulator = make_emulator(Source(), faults=FaultConfig(reply_delay_s=0.025))  # every byte lands 25 ms late
    with serial.Serial(emulator.tty_path, 9600) as port:
        port.write(b"S")  # ... and the session ends without `E`
    time.sleep(0.05)
    sensor = connect(sensors, emulator, baudrate=9600, timeout_s=0.05)
    assert sensor.sensitivities_source == "sensor"
    assert emulator.commands["p"] == 2  # the first reply read clean: nothing left of the stream
    assert not emulator.streaming and sensor.read().valid


# ------------------------------------------------------------------------------------ bounded writes
@pytest.fixture
def unread_pty() -> Iterator[tuple[int, str]]:
    """A pseudo-terminal whose other end never reads: what the port is given stays in its buffer."""
    master, slave = os.openpty()
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def fill(fd: int) -> None:
    """Write until the port takes nothing more, not even one byte once the kernel has moved what it holds on."""
    for _ in range(100):  # a hang guard: the buffers are a few tens of kB
        taken = 0
        for size in (1024, 1):
            try:
                while True:
                    taken += os.write(fd, b"x" * size)
            except BlockingIOError:
                pass
        if not taken:
            return
        time.sleep(0.02)  # the pty passes buffered bytes on to the other end's buffer in the background
    raise AssertionError("the pseudo-terminal kept taking data")


def test_a_write_the_port_does_not_take_is_a_lost_link_naming_the_command(unread_pty: tuple[int, str]) -> None:
    link = SerialLink(unread_pty[1], 921600, 0.005, "WACOH sensor")
    link.open()
    try:
        assert link.fd is not None
        fill(link.fd)
        with pytest.raises(LinkLostError) as err:
            link.write(b"R", "record request")
    finally:
        link.close()
    assert str(err.value) == (f"WACOH sensor on {unread_pty[1]}: record request failed: the port took no data for "
                              f"{link.write_bound(1) * 1e3:.1f} ms (0 of 1 bytes sent); the adapter or line is stuck")


def test_the_write_bound_follows_the_read_timeout() -> None:
    """It was at least 0.2 s, 40 times the cell's 5 ms reply timeout."""
    fast, slow = SerialLink("x", 921600, 0.005, "s"), SerialLink("x", 9600, 0.005, "s")
    assert fast.write_bound(1) == pytest.approx(0.005 + fast.wire_time(5))
    assert slow.write_bound(1) == pytest.approx(0.005 + 5 * 10 / 9600)  # the byte and four more byte times
    url = SerialLink("loop://", 921600, 0.005, "s")
    url.open()
    try:
        assert url.port.write_timeout == pytest.approx(url.write_bound(1))  # pyserial's bound on a URL port
    finally:
        url.close()


def test_a_wedged_adapter_during_reads_is_a_lost_link(unread_pty: tuple[int, str]) -> None:
    """No sensor behind the port (it falls back and reads nothing), then the port stops taking data."""
    sensor = WacohSensor(WacohConfig(port=unread_pty[1], timeout_s=0.005, sensitivities=FALLBACK))
    sensor.connect()
    try:
        assert sensor.sensitivities_source == "config" and sensor.connected  # nothing answers: no error yet
        assert sensor._link.fd is not None
        fill(sensor._link.fd)
        with pytest.raises(LinkLostError, match=r"record request failed: the port took no data for 5\.\d ms"):
            sensor.read()
    finally:
        sensor.disconnect()
    assert not sensor.connected
