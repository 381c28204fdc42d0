"""Serial driver for the WACOH WEF-6A200-4-RCD (DynPick) 6-axis force/torque sensor: `WacohSensor`."""

from __future__ import annotations

import logging
import select
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from drivers.errors import DriverError, LinkLostError, ProtocolError
from drivers.interfaces import ForceSensor, Wrench
from drivers.serial_link import LINK_ERRORS, READ_SLICE_S, SerialLink
from drivers.wacoh.codec import (
    CMD_RECORD,
    CMD_SENSITIVITIES,
    CMD_START,
    CMD_STOP,
    CMD_ZERO,
    MAX_LINE,
    N_CHANNELS,
    RAW_MAX,
    RAW_ZERO,
    RECORD_LEN,
    RecordReader,
    Sensitivities,
    decode_counts,
    parse_sensitivities,
    sensor_to_cell,
)
from drivers.wacoh.config import WacohConfig

log = logging.getLogger(__name__)

# After `E` the sensor may still have records in flight (and a USB adapter its buffer): let them land.
_DRAIN_S = 0.02
# `O` must be sent three times, about 1 ms apart.
_ZERO_REPEATS = 3
# The sensitivities set every reading's scale, and the reply has no checksum: a flipped bit in a digit
# (32.800 -> 32.801) is still a plausible reply.  So `p` is asked until two replies are byte-identical,
# well-formed and plausible (a garbled reply is asked again), at most this many times.
_P_ATTEMPTS = 6
# Poll mode matches each reply's record number (a digit 0-9 the sensor increments per record) to its
# request.  A request whose reply did not come in time stays "unsettled" (its reply may still arrive,
# and must not pass for a later request's) until a later record settles it or this long has passed.
_LATE_REPLY_S = 0.1
# At connect, one `R` with this much patience learns the sensor's record number.
_SYNC_WAIT_S = 0.1
_ZERO_GAP_S = 0.001
_ZERO_SETTLE_S = 0.01


@dataclass(frozen=True)
class _Sample:
    seq: int  # increments with every valid record received (stream mode freshness)
    t: float  # host receive time, time.monotonic()
    counts: np.ndarray  # (6,) raw counts, sensor axes


class WacohSensor(ForceSensor):
    """The WACOH WEF-6A200-4-RCD on a serial port (pyserial, 8N1, no flow control).

    Reads return N and N·m in the cell convention (see wacoh_codec.SENSOR_TO_CELL_*), `t` = host receive time
    (time.monotonic()).  Failure policy: a read that times out or receives only corrupted data returns
    an all-NaN Wrench and is counted; the `max_consecutive_failures`-th such read in a row raises
    LinkLostError instead.  An OS-level port error (device unplugged, emulator gone) raises LinkLostError
    at once.  A channel at the ends of the 14-bit range (saturated) reads NaN.
    Software tare and the nominal zero reset on every connect; `tare()` after connecting.
    """

    def __init__(self, config: WacohConfig) -> None:
        super().__init__()
        config.validate()
        self.config = config
        self._link = SerialLink(config.port, config.baudrate, config.timeout_s, "WACOH sensor")
        self._sens = config.sensitivities
        self._scale = self._sens.as_array()
        self.sensitivities_source: Literal["sensor", "config"] = "config"
        self._zero = np.full(N_CHANNELS, float(RAW_ZERO))
        self._framer = RecordReader()
        # Counters for diagnostics; the stream thread updates them under _cond.
        self.records_ok = 0
        self.records_rejected = 0
        self.records_saturated = 0
        self.timeouts = 0
        self.records_stale = 0  # poll mode: records that answered an earlier request (discarded)
        self.consecutive_failures = 0
        self._warned_saturation = False
        # Poll mode: the record number the sensor gives its next record (None: not known), and the
        # (record number, send time) of earlier requests whose replies may still arrive.
        self._next_no: int | None = None
        self._unsettled: deque[tuple[int | None, float]] = deque()
        # Stream mode.
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._latest: _Sample | None = None
        self._last_seq = 0
        self._link_error: str | None = None

    # ------------------------------------------------------------------ diagnostics
    @property
    def sensitivities(self) -> Sensitivities:
        """The sensitivities in use: from `p` if the sensor answered, else the configured ones."""
        return self._sens

    @property
    def zero(self) -> np.ndarray:
        """Per-channel no-load output in counts (8192 until a software tare)."""
        return self._zero.copy()

    def counters(self) -> dict[str, int]:
        with self._cond:
            return {
                "records_ok": self.records_ok,
                "records_rejected": self.records_rejected,
                "records_saturated": self.records_saturated,
                "timeouts": self.timeouts,
                "records_stale": self.records_stale,
                "consecutive_failures": self.consecutive_failures,
            }

    # ------------------------------------------------------------------ lifecycle
    def _connect(self) -> None:
        cfg = self.config
        self._link.open()
        self._next_no, self._unsettled = None, deque()
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
            elif self._poll_once(wait_s=max(cfg.timeout_s, _SYNC_WAIT_S), count=False) is None:
                log.warning("WACOH sensor on %s: no record at connect; reads wait until no earlier "
                            "request can still be answered", cfg.port)
        except BaseException:
            self._stop_stream_thread()
            self._link.close()
            raise
        log.info("WACOH sensor on %s: connected (%s mode, sensitivities from %s: %s)", cfg.port, cfg.mode,
                 self.sensitivities_source, self._sens.values)

    def _disconnect(self) -> None:
        try:
            if self._link.ser is not None:
                try:
                    self._link.ser.write(CMD_STOP)
                except LINK_ERRORS as exc:
                    log.debug("WACOH sensor on %s: could not send E on close: %s", self.config.port, exc)
                self._stop_stream_thread()
                try:
                    time.sleep(_DRAIN_S)
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
        time.sleep(_DRAIN_S)
        self._discard_input()

    def _read_line(self, deadline: float) -> bytes | None:
        """Bytes up to and including the first LF, or None at the deadline."""
        buf = bytearray()
        while True:
            chunk = self._link.read_chunk(MAX_LINE, deadline)
            if not chunk:
                if time.monotonic() >= deadline:
                    return None
                continue
            lf = chunk.find(b"\n")
            if lf >= 0:
                return bytes(buf + chunk[: lf + 1])  # the rest is discarded with the next request
            buf += chunk
            if len(buf) > MAX_LINE:
                return bytes(buf)  # not a reply we know; let the parser reject it

    def _request_sensitivities(self) -> tuple[Sensitivities, Literal["sensor", "config"]]:
        """Ask `p` until two replies agree byte for byte and are well-formed and plausible (within the
        configured band of the nominal values); a garbled or implausible reply is asked again, no
        reply at all to the first request (some models never answer) falls back at once."""
        cfg = self.config
        port, fallback = cfg.port, cfg.sensitivities
        problem = ""
        believed: set[bytes] = set()
        for attempt in range(_P_ATTEMPTS):
            self._discard_input()
            self._link.write(CMD_SENSITIVITIES, "sensitivities request")
            line = self._read_line(self._link.reply_deadline(64))
            if line is None:
                problem = f"no reply to 'p' within {cfg.timeout_s:.3g} s"
                if attempt == 0:
                    break
                continue
            try:
                sens = parse_sensitivities(line, cfg.nominal_sensitivities, cfg.sensitivity_tolerance)
            except ProtocolError as exc:
                problem = str(exc)
                log.debug("WACOH sensor on %s: %s; asking again", port, exc)
                continue
            if line in believed:
                return sens, "sensor"
            believed.add(line)
            problem = "no two replies to 'p' agreed"
        log.warning("WACOH sensor on %s: %s; using configured sensitivities %s", port, problem, fallback.values)
        return fallback, "config"

    # ------------------------------------------------------------------ reading
    def _read(self) -> Wrench:
        sample = self._next_sample()
        if sample is None:
            self._note_failure()
            nan = np.full(3, np.nan)
            return Wrench(t=time.monotonic(), force=nan, torque=nan.copy())
        self.consecutive_failures = 0
        return self._to_wrench(sample)

    def _next_sample(self) -> _Sample | None:
        return self._wait_stream_sample() if self.config.mode == "stream" else self._poll_once()

    def _note_failure(self) -> None:
        with self._cond:
            self.consecutive_failures += 1
            n = self.consecutive_failures
        if n >= self.config.max_consecutive_failures:
            raise LinkLostError(
                f"WACOH sensor on {self.config.port}: no valid record in {n} consecutive reads "
                f"({self.timeouts} timeouts, {self.records_rejected} rejected records so far)"
            )

    def _poll_once(self, wait_s: float | None = None, count: bool = True) -> _Sample | None:
        """Send one `R` and read until *its* record arrives; None on timeout or a corrupt reply.

        A record is this request's only if its record number is the one the sensor gives its next
        record: a reply to an earlier request that arrived late (after its own read gave up) carries an
        earlier number and is discarded, never returned as new.  `wait_s` overrides the timeout
        (connect's first read, which learns the numbering); `count=False` leaves the counters alone.
        """
        # Clear leftovers first: a late or partial earlier reply must not pass for this one (pitfall 4).
        self._discard_input()
        self._expire_unsettled()
        if self._next_no is None and self._unsettled:
            # The numbering is not known yet and an earlier request may still be answered: no reply
            # could be told from that one.  Send nothing until it cannot come any more.
            self._wait_until(self._link.reply_deadline(RECORD_LEN))
            self.timeouts += count
            return None
        expected = self._next_no
        self._link.write(CMD_RECORD, "record request")
        sent = time.monotonic()
        if expected is not None:
            self._next_no = (expected + 1) % 10
        deadline = sent + (self.config.timeout_s if wait_s is None else wait_s)
        deadline += self._link.wire_time(RECORD_LEN)
        framer = self._framer
        rejected0, long0 = framer.rejected, framer.long_rejected
        try:
            while True:
                # Ask for exactly what completes the record: the read returns as soon as it is there.
                chunk = self._link.read_chunk(max(1, RECORD_LEN - framer.pending), deadline)
                if not chunk:
                    if time.monotonic() >= deadline:
                        break
                    continue
                for frame in framer.feed(chunk):
                    record_no, counts = decode_counts(frame)
                    if self._is_this_reply(record_no, expected):
                        self._unsettled.clear()  # replies come in order: every earlier one is done
                        if expected is None:
                            self._next_no = (record_no + 1) % 10
                        self.records_ok += count
                        return _Sample(seq=self.records_ok, t=time.monotonic(), counts=counts)
                    self.records_stale += count
                if framer.long_rejected > long0 and wait_s is None:
                    # The reply came but was corrupt (or it was a late reply of another command and
                    # this one's is still to come: this request stays unsettled).
                    break
            if framer.long_rejected == long0:
                self.timeouts += count
            self._unsettled.append((expected, sent))
            return None
        finally:
            self.records_rejected += (framer.rejected - rejected0) * count

    def _is_this_reply(self, record_no: int, expected: int | None) -> bool:
        """Whether a record numbered `record_no` answers the request just sent (expecting `expected`).

        A record that answers an unsettled earlier request settles it and every request before it.
        """
        if expected is None:
            return True  # nothing unsettled (see _poll_once): whatever comes answers this request
        earlier = [no for no, _ in self._unsettled]
        if record_no in earlier:
            # An earlier request's reply (or, if `expected` too, ambiguous after a wrap: refused).
            for _ in range(earlier.index(record_no) + 1):  # the oldest it may answer: settle the fewest
                self._unsettled.popleft()
            return False
        return record_no == expected

    def _expire_unsettled(self) -> None:
        limit = time.monotonic() - _LATE_REPLY_S
        while self._unsettled and self._unsettled[0][1] < limit:
            self._unsettled.popleft()

    def _wait_until(self, deadline: float) -> None:
        while time.monotonic() < deadline:
            self._link.read_chunk(MAX_LINE, deadline)  # whatever arrives now is an earlier request's: discarded

    def _to_wrench(self, sample: _Sample) -> Wrench:
        values = (sample.counts - self._zero) / self._scale
        saturated = (sample.counts <= 0) | (sample.counts >= RAW_MAX)
        if saturated.any():
            # A clipped channel is not the true load: NaN, not a plausible-looking wrong number.
            values[saturated] = np.nan
            self.records_saturated += 1
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
        self.records_rejected += framer.rejected - rejected0
        if frames:
            self.records_ok += len(frames)
            _, counts = decode_counts(frames[-1])
            seq = self._latest.seq + 1 if self._latest else 1
            self._latest = _Sample(seq=seq, t=t, counts=counts)
            self._cond.notify_all()

    def _wait_stream_sample(self) -> _Sample | None:
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
                    self.timeouts += 1
                    return None
                self._cond.wait(left)

    def _skip_stream_backlog(self) -> None:
        with self._cond:
            if self._latest is not None:
                self._last_seq = self._latest.seq

    # ------------------------------------------------------------------ tare
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
            self.consecutive_failures = 0
            if np.any((sample.counts <= 0) | (sample.counts >= RAW_MAX)):
                raise DriverError(f"WACOH sensor on {self.config.port}: cannot tare, a channel is saturated "
                                  f"(counts {sample.counts.tolist()})")
            collected.append(sample.counts)
        self._zero = np.mean(collected, axis=0)
        log.info("WACOH sensor on %s: software tare over %d samples, zero %s", self.config.port, samples,
                 np.round(self._zero, 1).tolist())
