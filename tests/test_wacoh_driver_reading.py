"""The real `WacohSensor` reading from the WACOH emulator: polling, tare, streaming, line faults, hygiene."""

from __future__ import annotations

import math
import os
import threading
import time

import numpy as np
import pytest

from bench.timing import bench_serial
from drivers.errors import LinkLostError
from drivers.wacoh.codec import RAW_ZERO
from drivers.wacoh.config import MAX_FAILURES, WacohConfig
from drivers.wacoh.driver import WacohSensor
from drivers.wacoh.record_sync import LATE_REPLY_S as _LATE_REPLY_S
from sim.wacoh_emulator import FaultConfig, WacohEmulator
from tests.wacoh_fixtures import (
    BIG_OFFSET,
    SLACK_TIMEOUT_S,
    EmulatorFactory,
    S,
    Source,
    close_to,
    connect,
    random_wrench,
)

pytestmark = pytest.mark.timeout(25)


# ------------------------------------------------------------------------------------ polling
def test_polling_matches_the_source_within_quantisation(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0)
    sensor = connect(sensors, emulator, timeout_s=SLACK_TIMEOUT_S)
    rng = np.random.default_rng(7)
    for _ in range(200):
        source.value = random_wrench(rng)
        w = sensor.read()
        assert w.valid
        assert close_to(w.vector, source.value, 0.5), (w.vector, source.value)
    assert sensor.records_ok == 200 and sensor.records_rejected == 0 and sensor.timeouts == 0


@pytest.mark.parametrize("mode", ["poll", "stream"])
def test_software_tare_removes_a_655_lsb_offset(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], mode: str
) -> None:
    source = Source()
    emulator = make_emulator(source, offset_lsb=BIG_OFFSET, noise=0.0)
    sensor = connect(sensors, emulator, tare="software", mode=mode, timeout_s=SLACK_TIMEOUT_S)
    before = sensor.read()
    assert close_to(before.vector, BIG_OFFSET / S, 0.5)  # untared: the offset shows (up to 20 N)
    sensor.tare(20)
    assert np.allclose(sensor.zero, np.rint(RAW_ZERO + BIG_OFFSET))
    rng = np.random.default_rng(3)
    for _ in range(20):
        source.value = random_wrench(rng)
        time.sleep(0.003 if mode == "stream" else 0.0)  # let a record with the new value arrive
        assert close_to(sensor.read().vector, source.value, 1.0)


@pytest.mark.parametrize("mode", ["poll", "stream"])
def test_a_control_loop_tares_on_the_records_it_already_read(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], mode: str
) -> None:
    """`tare_from_recent` zeroes at the mean of the reads of the last moments, with no request of its own (the
    loop is not held while a tare collects); too few of them, too old or a failed one in between: it declines."""
    from cell.sensing.ft_source import SensorForceSource
    from drivers.wacoh.driver import RECENT_TARE_AGE_S, RECENT_TARE_MIN, RECENT_TARE_WINDOW_S

    source = Source()
    emulator = make_emulator(source, offset_lsb=BIG_OFFSET, noise=0.0)
    sensor = connect(sensors, emulator, tare="software", mode=mode, tare_samples=20, timeout_s=SLACK_TIMEOUT_S)
    assert not sensor.tare_from_recent(20)  # nothing read yet
    for _ in range(RECENT_TARE_MIN - 1):
        sensor.read()
    assert not sensor.tare_from_recent(20)  # one short of the fewest it averages
    sensor.read()
    requests = emulator.commands.get("R", 0)
    assert sensor.tare_from_recent(20)
    assert emulator.commands.get("R", 0) == requests  # no record asked for: nothing to wait on
    assert np.allclose(sensor.zero, np.rint(RAW_ZERO + BIG_OFFSET))
    source.value = np.array([10.0, -20.0, 30.0, 0.5, -0.5, 0.25])
    time.sleep(0.003 if mode == "stream" else 0.0)
    assert close_to(sensor.read().vector, source.value, 1.0)
    # Only the reads of the last moments count: those before a pause are not the present state.
    for _ in range(20):
        sensor.read()
    time.sleep(RECENT_TARE_WINDOW_S + 0.05)
    for _ in range(RECENT_TARE_MIN - 1):
        sensor.read()
    assert not sensor.tare_from_recent(20)
    # Nor are reads the loop stopped taking a while ago.
    sensor.read()
    time.sleep(RECENT_TARE_AGE_S + 0.05)
    assert not sensor.tare_from_recent(20)
    # The control loop's source: declined, it tares with fresh records (here under the load: it reads zero).
    SensorForceSource(sensor, 20).rebias()
    time.sleep(0.003 if mode == "stream" else 0.0)
    assert close_to(sensor.read().vector, np.zeros(6), 1.0)


def test_sensor_tare_sends_o_three_times_and_removes_the_offset(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    source = Source()
    emulator = make_emulator(source, offset_lsb=BIG_OFFSET, noise=0.0)
    sensor = connect(sensors, emulator, tare="sensor", timeout_s=SLACK_TIMEOUT_S)
    assert not close_to(sensor.read().vector, np.zeros(6), 100)
    sensor.tare()
    assert emulator.commands.get("O") == 3 and emulator.zero_events == 1
    rng = np.random.default_rng(4)
    for _ in range(20):
        source.value = random_wrench(rng)
        assert close_to(sensor.read().vector, source.value, 1.0)


def test_tare_with_noise_reads_zero_within_a_few_lsb(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source(), noise=0.5, seed=11)  # random offsets within +-655 LSB
    assert np.all(np.abs(emulator.offset_lsb) <= 655)
    sensor = connect(sensors, emulator, timeout_s=SLACK_TIMEOUT_S)
    sensor.tare(50)
    readings = np.array([sensor.read().vector for _ in range(50)])
    assert np.all(np.abs(readings) <= 3.0 / S)  # 0.5 LSB noise: 6 sigma of the reading + tare error


def test_saturated_channel_reads_nan(make_emulator: EmulatorFactory, sensors: list[WacohSensor]) -> None:
    emulator = make_emulator(Source(np.array([0, 0, 400.0, 0, 0, 0])), offset_lsb=np.zeros(6), noise=0.0)
    sensor = connect(sensors, emulator, timeout_s=SLACK_TIMEOUT_S)
    w = sensor.read()
    assert np.isnan(w.force[2])
    assert np.all(np.isfinite(np.delete(w.vector, 2)))
    assert sensor.records_saturated == 1


# ------------------------------------------------------------------------------------ streaming
def test_streaming_keeps_the_latest_record(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    """A read returns the newest record the line has delivered, not the oldest of a backlog.  Between reads the
    stream runs on (~20 records at 1 kHz) while the driver's reader is kept from the line (its lock held), so the
    records pile up and arrive together; then the emulator is held and the driver given time to take in every
    record written, so what the read must return does not depend on how soon the machine runs each thread."""
    source = Source(fresh_each_call=True)
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0)
    sensor = connect(sensors, emulator, mode="stream", timeout_s=SLACK_TIMEOUT_S)
    try:
        for _ in range(15):
            with sensor._cond:  # the reader thread waits for this lock before it takes anything in
                source.release()
                time.sleep(0.02)  # much slower than the 1 kHz stream: a backlog of ~20 records builds
                source.hold()
            # Every record written has arrived (the connect's first record was a polled one it does not count).
            delivered = emulator.records_sent - emulator.commands.get("R", 0)
            deadline = time.monotonic() + 10.0  # a hang guard, not a budget: a busy machine only takes longer
            while sensor.counters()["records_ok"] < delivered and time.monotonic() < deadline:
                time.sleep(0.001)
            assert sensor.counters()["records_ok"] == delivered, (sensor.counters(), delivered)
            w = sensor.read()
            assert w.valid, sensor.counters()
            distances = [np.max(np.abs(w.vector - p) * S) for p in source.produced]
            assert int(np.argmin(distances)) == len(source.produced) - 1  # the newest ...
            assert distances[-1] <= 0.5 + 1e-6  # ... and its value
    finally:
        source.release()
    assert emulator.streaming and emulator.commands.get("S") == 1
    sensor.disconnect()
    assert not emulator.streaming


# ------------------------------------------------------------------------------------ faults
FAULTS = FaultConfig(split_prob=0.3, split_max_delay_s=0.001, garbage_prob=0.2, drop_crlf_prob=0.1,
                     drop_reply_prob=0.1)


def test_polling_under_faults_never_accepts_a_wrong_value(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    source = Source()
    emulator = make_emulator(source, offset_lsb=BIG_OFFSET, noise=0.0, seed=5, faults=FAULTS)
    sensor = connect(sensors, emulator, timeout_s=0.03, max_consecutive_failures=50)
    sensor.tare(20)
    sens = sensor.sensitivities.as_array()
    rng = np.random.default_rng(9)
    valid = 0
    durations = []
    for _ in range(300):
        source.value = random_wrench(rng)  # a new value every read: a stale reply would be caught
        t0 = time.monotonic()
        w = sensor.read()
        durations.append(time.monotonic() - t0)
        if w.valid:
            valid += 1
            assert close_to(w.vector, source.value, 1.0, sens), (w.vector, source.value)
        else:
            assert np.all(np.isnan(w.vector))  # invalid is all NaN, never a partial or 0
    # The deadline holds (timeout + one 5 ms read slice), and no read hangs even on a busy machine.
    assert np.percentile(durations, 95) < 0.03 + 0.01
    assert max(durations) < 0.03 + 0.25
    c = sensor.counters()
    assert valid >= 180  # ~0.9 * 0.9 * (1 - garbage without LF) of 300
    assert c["timeouts"] > 0 and c["records_rejected"] > 0


def test_streaming_under_faults_never_accepts_a_wrong_value(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    source = Source(fresh_each_call=True)
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, seed=6, faults=FAULTS)
    sensor = connect(sensors, emulator, mode="stream", timeout_s=0.03, max_consecutive_failures=50)
    sens = sensor.sensitivities.as_array()
    valid = 0
    for _ in range(200):
        time.sleep(0.002)
        w = sensor.read()
        if not w.valid:
            assert np.all(np.isnan(w.vector))
            continue
        valid += 1
        expected = np.array(source.produced) * S / sens  # every value the emulator put in a record
        assert np.min(np.max(np.abs(expected - w.vector) * sens, axis=1)) <= 0.5 + 1e-6
    assert valid >= 150
    assert sensor.records_rejected > 0


def test_dropped_replies_give_nan_then_link_lost(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source())
    sensor = connect(sensors, emulator, timeout_s=0.02, max_consecutive_failures=4)
    assert sensor.read().valid
    emulator.faults.drop_reply_prob = 1.0
    for _ in range(3):
        assert np.all(np.isnan(sensor.read().vector))
    with pytest.raises(LinkLostError, match="no valid record in 4 consecutive reads"):
        sensor.read()
    assert sensor.timeouts == 4
    emulator.faults.drop_reply_prob = 0.0
    assert sensor.read().valid  # the link recovers without reconnecting


@pytest.mark.parametrize("fault", ["drop_reply_prob", "garbage_prob"])
@pytest.mark.parametrize("burst", [10, 17, 30])
def test_after_a_burst_of_bad_records_current_readings_resume_after_a_resync(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], fault: str, burst: int
) -> None:
    """A line that drops or garbles every record for `burst` reads, then recovers.  Ten unanswered requests
    use up the record numbers (0-9): a reply could then be any of theirs.  The driver stops requesting,
    discards what arrives until no reply can still come (_LATE_REPLY_S after its last request), then asks
    afresh: current readings again within that window plus a couple of reads, never a stale one.  (A
    garbled reply is a reply: it leaves no request unanswered, and reading normally resumes at once.)"""
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, seed=burst)
    timeout = 0.005
    sensor = connect(sensors, emulator, timeout_s=timeout, max_consecutive_failures=MAX_FAILURES)
    assert sensor.read().valid
    rng = np.random.default_rng(burst)

    def read_current() -> bool:
        source.value = random_wrench(rng)  # a new value every read: a stale reply would be caught
        w = sensor.read()
        if w.valid:
            assert close_to(w.vector, source.value, 0.5), f"a stale record was returned as current: {sensor.counters()}"
        else:
            assert np.all(np.isnan(w.vector))
        return w.valid

    setattr(emulator.faults, fault, 1.0)
    assert not any(read_current() for _ in range(burst))
    setattr(emulator.faults, fault, 0.0)
    # The resync's window is wall time (_LATE_REPLY_S after the last request): how many reads fall in it
    # depends on the machine's load, so the bound is on resyncs, with a generous cap on reads.
    window_reads = math.ceil(_LATE_REPLY_S / timeout) + 1
    resyncs_before = sensor.resyncs
    failed = 0
    while not read_current():
        failed += 1
        assert failed <= 20 * (window_reads + 2), sensor.counters()
    assert sensor.resyncs - resyncs_before <= 2, sensor.counters()
    assert all(read_current() for _ in range(10))  # and it stays in step
    if fault == "drop_reply_prob":
        assert sensor.resyncs >= 1


def test_no_request_is_sent_while_resynchronising(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source(), offset_lsb=np.zeros(6), noise=0.0)
    sensor = connect(sensors, emulator, timeout_s=0.005, max_consecutive_failures=MAX_FAILURES)
    emulator.faults.drop_reply_prob = 1.0
    for _ in range(10):  # ten unanswered requests: every record number is one of theirs
        assert not sensor.read().valid
    emulator.faults.drop_reply_prob = 0.0
    requests = emulator.commands["R"]
    assert not sensor.read().valid  # the resync starts: no request, no reading
    assert sensor.resyncs == 1
    reads = 1
    while not sensor.read().valid:
        reads += 1
    assert emulator.commands["R"] == requests + 1  # the one fresh request after the quiet window
    assert reads >= 2


def test_systematically_late_replies_are_never_read_as_current_and_end_as_a_lost_link(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    """Every reply 55-60 ms late against a 5 ms timeout: about eleven requests are unanswered at any time,
    so record numbers repeat among them.  Taking replies about ten requests late as current returned 51
    of 90 readings stale.  Resynchronising, the driver returns none, and a sensor that never answers in
    time is a lost link (safe), not a source of old forces."""
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, seed=5,
                             faults=FaultConfig(reply_delay_s=0.055, reply_delay_jitter_s=0.005))
    sensor = connect(sensors, emulator, timeout_s=0.005, max_consecutive_failures=MAX_FAILURES)
    rng = np.random.default_rng(55)
    reads = 0
    with pytest.raises(LinkLostError, match=f"no valid record in {MAX_FAILURES} consecutive reads"):
        while True:
            source.value = random_wrench(rng)
            w = sensor.read()
            reads += 1
            assert not w.valid, f"read {reads}: a reply 55-60 ms late returned as current ({sensor.counters()})"
    assert reads == MAX_FAILURES - 1  # the last failure raised
    assert sensor.resyncs >= 2 and sensor.records_stale > 0  # late replies arrived, and were discarded

def test_a_write_delayed_past_the_reply_timeout_is_not_a_lost_link(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], monkeypatch: pytest.MonkeyPatch
) -> None:
    """pyserial checks its write deadline after the bytes went out: a thread descheduled longer than
    the 5 ms reply timeout around a write must not turn a sent command into a lost link."""
    import types

    import drivers.serial_link as serial_link

    stalls = []

    def descheduled_write(fd: int, data: bytes) -> int:
        n = os.write(fd, data)
        stalls.append(n)
        time.sleep(0.02)  # the OS runs something else for 20 ms right after the bytes left
        return n

    emulator = make_emulator(Source(), offset_lsb=np.zeros(6), noise=0.0)
    # Only the driver's port sees the stall (the emulator writes with the real os.write).
    driver_os = types.SimpleNamespace(**{k: getattr(os, k) for k in dir(os) if not k.startswith("__")})
    driver_os.write = descheduled_write
    monkeypatch.setattr(serial_link, "os", driver_os)
    sensor = connect(sensors, emulator, timeout_s=0.005)
    assert sensor.sensitivities_source == "sensor"
    for _ in range(5):
        assert sensor.read().valid  # the reply came while the thread was away
    assert len(stalls) >= 6, "the stall was not exercised"
    assert sensor.connected


@pytest.mark.parametrize("mode", ["poll", "stream"])
def test_closed_emulator_raises_link_lost_instead_of_hanging(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], mode: str
) -> None:
    emulator = make_emulator(Source())
    sensor = connect(sensors, emulator, mode=mode, timeout_s=0.05)
    assert sensor.read().valid
    emulator.stop()
    with pytest.raises(LinkLostError):  # within the failure limit's count of reads, each bounded by timeout_s
        for _ in range(sensor.config.max_consecutive_failures):
            assert not sensor.read().valid  # NaN at most, until the failure limit
    sensor.disconnect()  # closing a dead link does not raise
    assert not sensor.connected


@pytest.mark.parametrize("delay_prob", [1.0, 0.4])
def test_a_late_reply_is_never_returned_as_the_next_reading(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], delay_prob: float
) -> None:
    """Replies 12 ms late against a 5 ms timeout: each arrives while a later request waits.  Taken as
    that request's answer, 13 of 60 reads returned the previous record; the record number says whose
    reply it is."""
    source = Source()
    emulator = make_emulator(source, offset_lsb=np.zeros(6), noise=0.0, seed=3,
                             faults=FaultConfig(reply_delay_s=0.012, reply_delay_prob=delay_prob))
    sensor = connect(sensors, emulator, timeout_s=0.005, max_consecutive_failures=MAX_FAILURES)
    sens = sensor.sensitivities.as_array()
    rng = np.random.default_rng(12)
    valid = 0
    for _ in range(MAX_FAILURES - 10):  # with every reply late, each read fails: stay below the lost link
        source.value = random_wrench(rng)  # a new value every read: a stale reply would be caught
        w = sensor.read()
        if w.valid:
            valid += 1
            assert close_to(w.vector, source.value, 0.5, sens), "a stale record was returned as new"
        else:
            assert np.all(np.isnan(w.vector))  # the missing reading
        if delay_prob == 1.0 and _ % 3 == 0:
            time.sleep(0.004)  # vary the phase, so late replies land inside later reads' windows
    assert emulator.replies_delayed > 0
    assert sensor.records_stale > 0  # late replies did arrive during later reads, and were discarded
    if delay_prob == 1.0:
        assert valid == 0  # every reply is later than its read's deadline
    else:
        assert valid >= 20, sensor.counters()


def test_a_missing_reply_costs_the_configured_timeout(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    """The read loop restarted pyserial's per-read timeout: 5 ms cost 10.3 ms."""
    emulator = make_emulator(Source())
    timeout = 0.005
    sensor = connect(sensors, emulator, timeout_s=timeout, max_consecutive_failures=MAX_FAILURES)
    emulator.faults.drop_reply_prob = 1.0
    durations = []
    for _ in range(15):
        t0 = time.monotonic()
        w = sensor.read()
        durations.append(time.monotonic() - t0)
        assert not w.valid
    median = float(np.median(durations))
    assert timeout <= median <= timeout + 0.003, durations


# ------------------------------------------------------------------------------------ hygiene, speed
def test_no_threads_or_file_descriptors_leak(make_emulator: EmulatorFactory) -> None:
    threads0, fds0 = threading.active_count(), len(os.listdir("/proc/self/fd"))
    for mode in ("poll", "stream"):
        with WacohEmulator(Source()) as emulator:
            sensor = WacohSensor(WacohConfig(port=emulator.tty_path, mode=mode, timeout_s=SLACK_TIMEOUT_S))
            with sensor:
                sensor.tare(5)
                assert sensor.read().valid
    assert threading.active_count() == threads0
    assert len(os.listdir("/proc/self/fd")) == fds0


def test_bench_serial_reports_latency() -> None:
    result = bench_serial(100)
    assert result["n"] == 100
