"""The real `WacohSensor` in poll mode against emulators whose record number advances per reply, per internal sample,
or not at all: the fact sheet says only "a wrapping counter", so no reading may depend on its step."""

from __future__ import annotations

import re
from collections.abc import Callable

import numpy as np
import pytest
import serial

from drivers.errors import LinkLostError
from drivers.wacoh.config import MAX_FAILURES
from drivers.wacoh.driver import WacohSensor
from sim.wacoh_emulator import COUNTER_MODES, CounterMode, FaultConfig
from tests.wacoh_fixtures import SLACK_TIMEOUT_S, EmulatorFactory, Source, close_to, connect, random_wrench

pytestmark = pytest.mark.timeout(25)

TIMEOUT_S = 0.005  # the cell's reply timeout
LATE_S = 0.015  # a late reply: three timeouts after its request, so it lands while a later read waits


def test_the_emulators_record_number_follows_its_counter_mode(make_emulator: EmulatorFactory) -> None:
    now = [0.0]
    sampled = make_emulator(Source(), counter="sample", sample_period_s=0.001, clock=lambda: now[0])
    numbers = []
    for t in (0.0, 0.0004, 0.0035, 0.0125, 0.0251):
        now[0] = t
        numbers.append(sampled.record_number())
    assert numbers == [0, 0, 3, 2, 5]  # the sampling clock's count, whatever was asked in between
    constant = make_emulator(Source(), counter="constant")
    with serial.Serial(constant.tty_path, 921600, timeout=0.5) as port:
        for _ in range(3):
            port.write(b"R")
            assert port.read(27)[:1] == b"0"
    with pytest.raises(ValueError, match=r"^counter must be one of \['reply', 'sample', 'constant'\], got 'tick'$"):
        make_emulator(Source(), counter="tick")


def reader(sensor: WacohSensor, source: Source, seed: int) -> Callable[[], bool]:
    """A read with a new true load each time: a record that answered an earlier request carries an older load,
    and returned as current it fails the check."""
    rng = np.random.default_rng(seed)
    sens = sensor.sensitivities.as_array()

    def read() -> bool:
        source.value = random_wrench(rng)
        w = sensor.read()
        if w.valid:
            assert close_to(w.vector, source.value, 0.5, sens), f"a stale record was returned: {sensor.counters()}"
        else:
            assert np.all(np.isnan(w.vector))
        return w.valid

    return read


@pytest.mark.parametrize("counter", COUNTER_MODES)
def test_polling_reads_every_reply_whatever_advances_the_record_number(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], counter: CounterMode
) -> None:
    """Taking only replies numbered one past the last one read 90 % of a sampling-clock sensor's replies as
    missing and lost a constant-number sensor after ten reads."""
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, counter=counter)
    sensor = connect(sensors, emulator, timeout_s=SLACK_TIMEOUT_S)
    assert sensor.counter_steps_by_one is (counter == "reply")  # learned at connect
    read = reader(sensor, source, 1)
    assert all(read() for _ in range(200))
    c = sensor.counters()
    assert (c["records_ok"], c["timeouts"], c["records_stale"], c["resyncs"]) == (200, 0, 0, 0)


@pytest.mark.parametrize("counter", COUNTER_MODES)
def test_a_late_reply_after_a_timeout_is_never_returned_as_current(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], counter: CounterMode
) -> None:
    """One reply LATE_S late against a 5 ms timeout, five times: it arrives while a later read waits.  A number
    that steps by one per reply tells it apart; otherwise the driver sends nothing until it has arrived."""
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, counter=counter)
    sensor = connect(sensors, emulator, timeout_s=TIMEOUT_S, max_consecutive_failures=MAX_FAILURES)
    emulator.faults.reply_delay_s, emulator.faults.reply_delay_prob = LATE_S, 0.0  # only the forced ones
    read = reader(sensor, source, 2)
    for _ in range(5):
        assert read()
        emulator.faults.late_replies = 1
        assert not read()  # its reply is late
        failed = 1
        while not read():
            failed += 1
            assert failed <= 60, sensor.counters()  # a hang guard: the late reply settles it long before
        assert all(read() for _ in range(5))  # and in step again
    c = sensor.counters()
    assert c["timeouts"] >= 5 and c["records_stale"] >= 1, c
    if counter == "reply":
        assert c["resyncs"] == 0, c  # told by its number: no read waits for it
    else:
        assert c["resyncs"] == 5 and c["resync_reads"] >= 5, c  # one wait for each, ended by its arrival
        assert c["timeouts"] == 5 and c["records_stale"] == 5, c  # no request was sent while it was awaited


@pytest.mark.parametrize("counter", COUNTER_MODES)
def test_randomly_late_replies_never_give_a_stale_reading(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], counter: CounterMode
) -> None:
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, seed=4, counter=counter)
    sensor = connect(sensors, emulator, timeout_s=TIMEOUT_S, max_consecutive_failures=MAX_FAILURES)
    emulator.faults.reply_delay_s, emulator.faults.reply_delay_prob = 0.012, 0.3
    emulator.faults.reply_delay_jitter_s = 0.004
    read = reader(sensor, source, 3)
    valid = sum(read() for _ in range(150))
    assert emulator.replies_delayed > 10
    assert valid >= 30, sensor.counters()


@pytest.mark.parametrize("counter", COUNTER_MODES)
def test_after_a_lost_reply_readings_resume_and_none_is_stale(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], counter: CounterMode
) -> None:
    """A reply that never comes: a number that steps by one shows the next reply is current at once; otherwise
    reads wait out the late-reply window (LATE_REPLY_S after the request) before asking again."""
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, counter=counter)
    sensor = connect(sensors, emulator, timeout_s=TIMEOUT_S, max_consecutive_failures=MAX_FAILURES)
    read = reader(sensor, source, 5)
    assert read()
    emulator.faults.drop_reply_prob = 1.0
    assert not read()
    emulator.faults.drop_reply_prob = 0.0
    failed = 0
    while not read():
        failed += 1
        assert failed < MAX_FAILURES - 1, sensor.counters()
    if counter == "reply":
        assert failed == 0
    else:
        assert failed >= 1 and sensor.resync_reads == failed and sensor.timeouts == 1
    assert all(read() for _ in range(10))


def test_the_lost_link_error_says_the_reads_waited_for_a_quiet_line(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source(), counter="constant")
    sensor = connect(sensors, emulator, timeout_s=TIMEOUT_S, max_consecutive_failures=10)
    assert sensor.read().valid
    emulator.faults.drop_reply_prob = 1.0
    with pytest.raises(LinkLostError) as err:
        for _ in range(10):
            assert not sensor.read().valid
    message = str(err.value)
    match = re.search(r"no valid record in 10 consecutive reads \((\d+) request\(s\) unanswered in time, (\d+) "
                      r"read\(s\) resynchronising without a request; the record number was not seen to step by one "
                      r"per reply", message)
    assert match and int(match[1]) + int(match[2]) == 10 and int(match[1]) >= 1, message
    assert message.startswith(f"WACOH sensor on {emulator.tty_path}: ") and "\n" not in message


def test_the_lost_link_error_counts_late_records_apart_from_timeouts(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    """Every reply 12 ms late: records do arrive, each answering an earlier request.  The error said "10
    timeouts" as if the sensor were silent."""
    emulator = make_emulator(Source(), offset_lsb=np.zeros(6), noise=0.0)
    sensor = connect(sensors, emulator, timeout_s=TIMEOUT_S, max_consecutive_failures=20)
    emulator.faults.reply_delay_s = 0.012
    with pytest.raises(LinkLostError) as err:
        for _ in range(20):
            assert not sensor.read().valid
    match = re.search(r"no valid record in 20 consecutive reads \((\d+) request\(s\) unanswered in time, (\d+) late "
                      r"record\(s\) that answered earlier requests, discarded as stale\)$", str(err.value))
    assert match and int(match[1]) == 20 and int(match[2]) >= 10, str(err.value)


@pytest.mark.parametrize(("name", "value"), [("late_replies", -1), ("late_replies", 1.5), ("ignore_first_p", True)])
def test_the_emulator_refuses_a_fault_count_that_is_not_a_whole_number(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf"^FaultConfig.{name} must be an integer >= 0, got {value!r}$"):
        FaultConfig(**{name: value})  # type: ignore[arg-type]
