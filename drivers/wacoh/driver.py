"""Serial driver for the WACOH WEF-6A200-4-RCD (DynPick) 6-axis force/torque sensor: `WacohSensor`."""

from __future__ import annotations

import collections
import logging
import select
import threading
import time
from typing import Literal

import numpy as np

from drivers.errors import DriverError, LinkLostError
from drivers.interfaces import ForceSensor, Wrench
from drivers.serial_link import LINK_ERRORS, READ_SLICE_S, SerialLink, latency_timer_ms
from drivers.wacoh.codec import (
    CMD_SENSITIVITIES,
    CMD_START,
    CMD_STOP,
    CMD_ZERO,
    N_CHANNELS,
    RAW_MAX,
    RAW_ZERO,
    RECORD_LEN,
    RecordReader,
    Sensitivities,
    decode_counts,
    sensor_to_cell,
)
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.poll import Poller, Sample
from drivers.wacoh.sensitivity import (
    P_REPLY_BYTES,
    P_TIMEOUT_S,
    agreed_sensitivities,
    drain_until_quiet,
    read_line,
)
from drivers.wacoh.stats import FailureRun, ReadStats

log = logging.getLogger(__name__)

# After `E` the sensor may still have records in flight (and a USB adapter its buffer): let them land.  That is
# several records' time on the wire (one takes 28 ms at 9600 bit/s), and never less than DRAIN_MIN_S.
DRAIN_RECORDS = 4
DRAIN_MIN_S = 0.02
# `O` must be sent three times, about 1 ms apart.
_ZERO_REPEATS = 3
_ZERO_GAP_S = 0.001
_ZERO_SETTLE_S = 0.01
# `tare_from_recent` averages the records the reads returned over this last stretch of time (a task's tare state
# holds the arm still for longer: the wipe's 0.3 s, the peg's 1.2 s), when there are at least RECENT_TARE_MIN of
# them and the newest is at most RECENT_TARE_AGE_S old.
RECENT_TARE_WINDOW_S = 0.2
RECENT_TARE_MIN = 10
RECENT_TARE_AGE_S = 0.1


def _stat(name: str) -> property:
    return property(lambda self: getattr(self.stats, name), doc=f"ReadStats.{name}")


class WacohSensor(ForceSensor):
    """The WACOH WEF-6A200-4-RCD on a serial port (pyserial, 8N1, no flow control).

    Reads return N and N·m in the cell convention (see wacoh_codec.SENSOR_TO_CELL_*), `t` = host receive time
    (time.monotonic()).  Failure policy: a read that times out or receives only corrupted data returns
    an all-NaN Wrench and is counted; the `max_consecutive_failures`-th such read in a row raises
    LinkLostError instead.  An OS-level port error (device unplugged, emulator gone) raises LinkLostError
    at once.  A channel at the ends of the 14-bit range (saturated) reads NaN.  In poll mode a reading is
    always the answer to its own request: when a late reply could not be told from a current one the driver
    resynchronises (see record_sync.py), and its reads meanwhile are failures too.
    Software tare and the nominal zero reset on every connect; `tare()` after connecting.
    """

    def __init__(self, config: WacohConfig) -> None:
        super().__init__()
        config.validate()
        self.config = config
        self._link = SerialLink(config.port, config.baudrate, config.timeout_s, "WACOH sensor")
        self._sens = config.fallback_sensitivities
        self._scale = self._sens.as_array()
        self.sensitivities_source: Literal["sensor", "config"] = "config"
        self._zero = np.full(N_CHANNELS, float(RAW_ZERO))
        self._framer = RecordReader()
        # Counters for diagnostics (the stream thread updates them under _cond), and what the current run of
        # failed reads met (for the lost-link error).
        self.stats = ReadStats()
        self._run = FailureRun()
        self.consecutive_failures = 0
        self._warned_saturation = False
        self.p_timeout_s = max(P_TIMEOUT_S, config.timeout_s)  # each `p` ask's patience (see sensitivity.py)
        self._poller = Poller(self._link, self._framer, config.port, config.timeout_s, self.stats, self._run)
        # Stream mode.
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._latest: Sample | None = None
        self._last_seq = 0
        self._link_error: str | None = None
        # The raw records the reads returned, newest last (`tare_from_recent`); emptied by a failed read.
        self._recent: collections.deque[Sample] = collections.deque(maxlen=max(config.tare_samples, 1))

    # ------------------------------------------------------------------ diagnostics
    records_ok = _stat("records_ok")
    records_rejected = _stat("records_rejected")
    records_saturated = _stat("records_saturated")
    timeouts = _stat("timeouts")
    records_stale = _stat("records_stale")
    resyncs = _stat("resyncs")
    resync_reads = _stat("resync_reads")

    @property
    def counter_steps_by_one(self) -> bool:
        """Poll mode: whether the record number has been seen to step by one per reply (see record_sync.py)."""
        return self._poller.sync.counter_steps_by_one

    @property
    def stop_drain_s(self) -> float:
        """How long records may still arrive after `E`: DRAIN_RECORDS records' time on the wire, at least
        DRAIN_MIN_S."""
        return max(DRAIN_MIN_S, DRAIN_RECORDS * self._link.wire_time(RECORD_LEN))

    @property
    def sensitivities(self) -> Sensitivities:
        """The sensitivities in use: from `p` if the sensor answered, else the configured ones."""
        return self._sens

    @property
    def zero(self) -> np.ndarray:
        """Per-channel no-load output in counts (8192 until a software tare)."""
        return self._zero.copy()

    def adapter_latency_ms(self) -> int | None:
        """The USB-serial adapter's latency timer (ms), where the system shows it: after `connect`, the one the
        low-latency request left (1 ms on an FTDI adapter that took it)."""
        return latency_timer_ms(self.config.port)

    def counters(self) -> dict[str, int]:
        with self._cond:
            return {**self.stats.as_dict(), "consecutive_failures": self.consecutive_failures}

    # ------------------------------------------------------------------ lifecycle
    def _connect(self) -> None:
        cfg = self.config
        self._link.open()
        self._poller.reset()
        self._run.clear()
        try:
            self._stop_stream_and_drain()  # a previous session may have left streaming on
            self._sens, self.sensitivities_source = self._request_sensitivities()
            self._scale = self._sens.as_array()
            if cfg.filter is not None:
                self._link.write(b"%dF" % cfg.filter, "filter command")
            self._zero = np.full(N_CHANNELS, float(RAW_ZERO))
            self.consecutive_failures = 0
            if cfg.mode == "stream":
                self._start_stream()
            elif self._poller.probe() == 0:
                log.warning("WACOH sensor on %s: no valid record at connect", cfg.port)
        except BaseException:
            self._stop_stream_thread()
            self._link.close()
            raise
        checked = ("against the calibration sheet" if cfg.sensitivities is not None else
                   "against the nominal band only: no calibration sheet in `sensitivities`")
        log.info("WACOH sensor on %s: connected (%s mode, sensitivities from %s: %s; `p` checked %s)", cfg.port,
                 cfg.mode, self.sensitivities_source, self._sens.values, checked)

    def _disconnect(self) -> None:
        try:
            if self._link.ser is not None:
                try:
                    self._link.write(CMD_STOP, "stop-streaming command")
                except LinkLostError as exc:
                    log.debug("WACOH sensor on %s: could not send E on close: %s", self.config.port, exc)
                self._stop_stream_thread()
                try:
                    time.sleep(self.stop_drain_s)
                    self._link.ser.reset_input_buffer()
                except LINK_ERRORS as exc:
                    log.debug("WACOH sensor on %s: could not drain on close: %s", self.config.port, exc)
        finally:
            self._stop_stream_thread()
            self._link.close()

    # ------------------------------------------------------------------ wire helpers
    def _discard_input(self) -> None:
        self._framer.reset()
        self._link.discard_input()

    def _stop_stream_and_drain(self) -> None:
        self._link.write(CMD_STOP, "stop-streaming command")
        time.sleep(self.stop_drain_s)
        self._discard_input()

    def _request_sensitivities(self) -> tuple[Sensitivities, Literal["sensor", "config"]]:
        """The sensitivities from `p` if two believable replies agree (see sensitivity.py), else the sheet's,
        else the nominal values."""
        cfg = self.config
        sens, problem = agreed_sensitivities(self._ask_sensitivities, cfg, self.p_timeout_s)
        if sens is not None:
            return sens, "sensor"
        used = ("the calibration sheet's" if cfg.sensitivities is not None
                else "the nominal (no calibration sheet configured)")
        log.warning("WACOH sensor on %s: %s; using %s sensitivities %s", cfg.port, problem, used,
                    cfg.fallback_sensitivities.values)
        return cfg.fallback_sensitivities, "config"

    def _ask_sensitivities(self, after_silence: bool = False) -> bytes | None:
        """Send one `p`: its reply line, or None if none came in time.  After an ask without a reply, first let
        the line fall quiet: a reply that was only slow must not be cut in two by the discard."""
        if after_silence:
            drain_until_quiet(self._link, self.stop_drain_s, self.p_timeout_s)
        self._discard_input()
        self._link.write(CMD_SENSITIVITIES, "sensitivities request")
        return read_line(self._link, time.monotonic() + self.p_timeout_s + self._link.wire_time(P_REPLY_BYTES))

    # ------------------------------------------------------------------ reading
    def _read(self) -> Wrench:
        sample = self._next_sample()
        if sample is None:
            self._recent.clear()
            self._note_failure()
            nan = np.full(3, np.nan)
            return Wrench(t=time.monotonic(), force=nan, torque=nan.copy())
        self._note_success()
        self._recent.append(sample)
        return self._to_wrench(sample)

    def _next_sample(self) -> Sample | None:
        return self._wait_stream_sample() if self.config.mode == "stream" else self._poller.poll()

    def _note_success(self) -> None:
        self.consecutive_failures = 0
        self._run.clear()

    def _note_failure(self) -> None:
        with self._cond:
            self.consecutive_failures += 1
            n = self.consecutive_failures
        if n >= self.config.max_consecutive_failures:
            steps = self.counter_steps_by_one if self.config.mode == "poll" else None
            raise LinkLostError(f"WACOH sensor on {self.config.port}: no valid record in {n} consecutive reads "
                                f"({self._run.describe(steps)})")

    def _to_wrench(self, sample: Sample) -> Wrench:
        values = (sample.counts - self._zero) / self._scale
        saturated = (sample.counts <= 0) | (sample.counts >= RAW_MAX)
        if saturated.any():
            # A clipped channel is not the true load: NaN, not a plausible-looking wrong number.
            values[saturated] = np.nan
            self.stats.records_saturated += 1
            if not self._warned_saturation:
                self._warned_saturation = True
                log.warning("WACOH sensor on %s: channel(s) %s saturated; reading them as NaN",
                            self.config.port, np.flatnonzero(saturated).tolist())
        v = sensor_to_cell(values)
        return Wrench(t=sample.t, force=v[:3].copy(), torque=v[3:].copy())

    # ------------------------------------------------------------------ streaming
    def _start_stream(self) -> None:
        self._discard_input()
        with self._cond:
            self._latest, self._last_seq, self._link_error = None, 0, None
            self._framer.reset()
        self._stop.clear()
        self._link.write(CMD_START, "start-streaming command")
        self._thread = threading.Thread(target=self._stream_loop, name=f"wacoh-stream-{self.config.port}",
                                        daemon=True)
        self._thread.start()

    def _stop_stream_thread(self) -> None:
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()  # the reader waits at most one read slice at a time
        thread.join(timeout=1.0)
        if thread.is_alive():
            log.error("WACOH sensor on %s: stream reader did not stop", self.config.port)

    def _stream_loop(self) -> None:
        """Background reader: keeps consuming the stream so the port never holds an old backlog."""
        fd = self._link.fd  # None: a URL port without a file descriptor, polled instead
        while not self._stop.is_set():
            try:
                if fd is not None:
                    readable, _, _ = select.select([fd], [], [], READ_SLICE_S)
                    if not readable:
                        continue
                else:
                    time.sleep(READ_SLICE_S / 10)
                with self._cond:
                    # At least 1 byte after select said readable: a vanished device reads as an error
                    # then, not as an endless stream of empty reads.
                    self._pump_locked(at_least_one=fd is not None)
            except LINK_ERRORS as exc:
                if not self._stop.is_set():
                    with self._cond:
                        self._link_error = f"WACOH sensor on {self.config.port}: stream read failed: {exc}"
                        self._cond.notify_all()
                return

    def _pump_locked(self, at_least_one: bool = False) -> None:
        """Read what the port holds now, frame it, keep the newest record.  Caller holds `_cond`."""
        ser = self._link.port
        n = ser.in_waiting
        if n == 0 and not at_least_one:
            return
        chunk = ser.read(max(1, n))
        if not chunk:
            return
        t = time.monotonic()
        framer = self._framer
        rejected0 = framer.rejected
        frames = framer.feed(chunk)
        self.stats.records_rejected += framer.rejected - rejected0
        if frames:
            self.stats.records_ok += len(frames)
            _, counts = decode_counts(frames[-1])
            seq = self._latest.seq + 1 if self._latest else 1
            self._latest = Sample(seq=seq, t=t, counts=counts)
            self._cond.notify_all()

    def _wait_stream_sample(self) -> Sample | None:
        """The newest record not returned yet, waiting up to the timeout for one."""
        deadline = self._link.reply_deadline(RECORD_LEN)
        with self._cond:
            if self._link_error is None:
                try:
                    # Take what has already arrived ourselves: the newest record must not wait for the
                    # reader thread's next turn at the GIL (up to the 5 ms switch interval).
                    self._pump_locked()
                except LINK_ERRORS as exc:
                    raise self._link.link_lost("stream read", exc) from None
            while True:
                if self._link_error is not None:
                    raise LinkLostError(self._link_error)
                latest = self._latest
                if latest is not None and latest.seq > self._last_seq:
                    self._last_seq = latest.seq
                    return latest
                left = deadline - time.monotonic()
                if left <= 0:
                    self.stats.timeouts += 1
                    self._run.timeouts += 1
                    return None
                self._cond.wait(left)

    def _skip_stream_backlog(self) -> None:
        with self._cond:
            if self._latest is not None:
                self._last_seq = self._latest.seq

    # ------------------------------------------------------------------ tare
    def tare_from_recent(self, samples: int = 50) -> bool:
        """The software tare over the records the reads returned in the last RECENT_TARE_WINDOW_S (at most `samples`
        of them, at least RECENT_TARE_MIN, the newest at most RECENT_TARE_AGE_S old, none failed or saturated in
        between): no request and no wait, so the control loop is not held while a tare collects (50 polls on a USB
        adapter take longer than the robot side waits for the host).  False otherwise, and with `tare: sensor`
        (the sensor zeroes itself)."""
        super().tare_from_recent(samples)
        if self.config.tare == "sensor" or not self._recent:
            return False
        newest = self._recent[-1].t
        recent = [r for r in self._recent if r.t >= newest - RECENT_TARE_WINDOW_S][-max(samples, 1):]
        if len(recent) < min(samples, RECENT_TARE_MIN) or time.monotonic() - newest > RECENT_TARE_AGE_S:
            return False
        counts = np.array([r.counts for r in recent])
        if np.any((counts <= 0) | (counts >= RAW_MAX)):
            return False  # `tare` reads afresh and says which channel is saturated
        self._zero = counts.mean(axis=0)
        log.info("WACOH sensor on %s: software tare over the last %d records read, zero %s", self.config.port,
                 len(recent), np.round(self._zero, 1).tolist())
        return True

    def _tare(self, samples: int) -> None:
        """`tare: sensor` sends `O` three times; `tare: software` averages `samples` records."""
        if self.config.tare == "sensor":
            self._tare_in_sensor()
        else:
            self._tare_in_software(max(1, samples))

    def _tare_in_sensor(self) -> None:
        for i in range(_ZERO_REPEATS):
            if i:
                time.sleep(_ZERO_GAP_S)
            self._link.write(CMD_ZERO, "zero command")
        time.sleep(_ZERO_SETTLE_S)
        self._zero = np.full(N_CHANNELS, float(RAW_ZERO))
        self._skip_stream_backlog()  # records streamed before the zero are not tared
        log.info("WACOH sensor on %s: zeroed in the sensor", self.config.port)

    def _tare_in_software(self, samples: int) -> None:
        self._skip_stream_backlog()
        collected: list[np.ndarray] = []
        while len(collected) < samples:
            sample = self._next_sample()
            if sample is None:
                self._note_failure()
                continue
            self._note_success()
            if np.any((sample.counts <= 0) | (sample.counts >= RAW_MAX)):
                raise DriverError(f"WACOH sensor on {self.config.port}: cannot tare, a channel is saturated "
                                  f"(counts {sample.counts.tolist()})")
            collected.append(sample.counts)
        self._zero = np.mean(collected, axis=0)
        log.info("WACOH sensor on %s: software tare over %d samples, zero %s", self.config.port, samples,
                 np.round(self._zero, 1).tolist())
