"""Serial driver for the WACOH WEF-6A200-4-RCD (DynPick) 6-axis force/torque sensor: codec, framer, config, driver."""

from __future__ import annotations

import logging
import math
import re
import select
import termios
import threading
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal

import numpy as np
import serial

from drivers.errors import ConfigError, DriverError, LinkLostError, ProtocolError
from drivers.interfaces import ForceSensor, Wrench

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------ protocol facts
RECORD_LEN = 27  # digit + 6 x 4 hex digits + CR LF
RAW_ZERO = 8192  # 0x2000: nominal unloaded output (offset binary)
RAW_MAX = 0x3FFF  # effectively 14-bit
N_CHANNELS = 6
CRLF = b"\r\n"
_HEX_UPPER = b"0123456789ABCDEF"
_DIGITS = b"0123456789"
# A line longer than any reply we know (the `p` reply is ~49 bytes) is noise; cap what we buffer.
MAX_LINE = 256

CMD_RECORD = b"R"
CMD_SENSITIVITIES = b"p"
CMD_ZERO = b"O"
CMD_START = b"S"
CMD_STOP = b"E"
FILTER_SETTINGS = (1, 2, 4, 8)

# What a vanished port raises: pyserial's errors, raw OS errors, and termios.error (not an OSError)
# from tcflush; TypeError when pyserial's fd is already gone.
_LINK_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error, TypeError)

# Bit times per byte on an 8N1 line: start + 8 data + stop.
_BITS_PER_BYTE = 10
# pyserial reads block at most this long, so deadlines are kept to within a slice and a stream
# reader notices a stop request promptly without changing the port timeout per call (a tcsetattr).
_READ_SLICE_S = 0.005
# Writes are a few bytes, which leave at once unless the adapter is wedged, so their bound is not the
# reply timeout: pyserial checks its write deadline *after* the bytes went out, so with a 5 ms bound
# a thread descheduled for 5 ms between the call and that check raised a write timeout for a command
# that was sent (seen on the emulated cell under load, a lost link at connect).  A wedged adapter is
# still noticed, this late at most.
_WRITE_TIMEOUT_FLOOR_S = 0.2
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

# ------------------------------------------------------------------------------------ axis mapping
# The ONE place where the sensor's axes meet the cell's.  The sensor is mounted with its frame aligned
# to the tool frame, and its positive outputs are taken to be the wrench the tool exerts on the
# environment (pressing along the tool's +z reads +Fz), which is the cell convention, so the mapping is
# the identity.  A different mounting changes only these two constants: cell[i] = SIGN[i] * sensor[AXES[i]].
# (Not verified on hardware: confirm with a press test before the first real run.)
SENSOR_TO_CELL_AXES: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
SENSOR_TO_CELL_SIGNS: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)

_AXES = np.array(SENSOR_TO_CELL_AXES)
_SIGNS = np.array(SENSOR_TO_CELL_SIGNS, dtype=float)


def sensor_to_cell(values: np.ndarray) -> np.ndarray:
    """(6,) wrench in the sensor's axes -> the cell convention."""
    return _SIGNS * np.asarray(values, dtype=float)[_AXES]


def cell_to_sensor(values: np.ndarray) -> np.ndarray:
    """(6,) wrench in the cell convention -> the sensor's axes (the inverse of `sensor_to_cell`)."""
    out = np.empty(N_CHANNELS)
    out[_AXES] = _SIGNS * np.asarray(values, dtype=float)  # signs are +-1, their own inverse
    return out


# ------------------------------------------------------------------------------------ codec
@dataclass(frozen=True)
class Sensitivities:
    """Per-axis sensitivities: forces in LSB/N, moments in LSB/(N·m), in the order the sensor reports."""

    force: tuple[float, float, float] = (32.8, 32.8, 32.8)
    moment: tuple[float, float, float] = (1638.0, 1638.0, 1638.0)

    def __post_init__(self) -> None:
        values = (*self.force, *self.moment)
        if len(self.force) != 3 or len(self.moment) != 3:
            raise ValueError(f"sensitivities need 3 force and 3 moment values, got {values}")
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"sensitivities must be finite and positive, got {values}")

    @classmethod
    def from_values(cls, values: Sequence[float]) -> Sensitivities:
        """From six values Fx, Fy, Fz [LSB/N], Mx, My, Mz [LSB/(N·m)]."""
        if len(values) != N_CHANNELS:
            raise ValueError(f"sensitivities need 6 values, got {len(values)}")
        v = [float(x) for x in values]
        return cls(force=(v[0], v[1], v[2]), moment=(v[3], v[4], v[5]))

    @property
    def values(self) -> tuple[float, ...]:
        return (*self.force, *self.moment)

    def as_array(self) -> np.ndarray:
        return np.array(self.values, dtype=float)


def decode_counts(frame: bytes) -> tuple[int, np.ndarray]:
    """Validate one 27-byte record; returns (record number, raw counts (6,) int).  ProtocolError if invalid."""
    if len(frame) != RECORD_LEN:
        raise ProtocolError(f"WACOH record {bytes(frame[:40])!r}: length {len(frame)}, expected {RECORD_LEN}")
    if frame[25:27] != CRLF:
        raise ProtocolError(f"WACOH record {bytes(frame)!r}: bytes 25-26 are not CR LF")
    if frame[0] not in _DIGITS:
        raise ProtocolError(f"WACOH record {bytes(frame)!r}: byte 0 is not a record-number digit")
    body = bytes(frame[1:25])
    if body.translate(None, _HEX_UPPER):  # whatever survives deleting the hex digits is invalid
        raise ProtocolError(f"WACOH record {bytes(frame)!r}: bytes 1-24 are not all upper-case hex digits")
    counts = np.array([int(body[i : i + 4], 16) for i in range(0, 24, 4)], dtype=np.int64)
    if np.any(counts > RAW_MAX):
        raise ProtocolError(f"WACOH record {bytes(frame)!r}: a value exceeds 0x{RAW_MAX:X}")
    return frame[0] - 0x30, counts


def counts_to_si(counts: np.ndarray, sens: Sensitivities, zero: np.ndarray) -> np.ndarray:
    """F [N] = (raw - zero) / S_F, M [N·m] = (raw - zero) / S_M: subtract first, then scale."""
    return (np.asarray(counts, dtype=float) - zero) / sens.as_array()


def decode_record(frame: bytes, sens: Sensitivities, zero: np.ndarray) -> tuple[int, np.ndarray]:
    """One 27-byte record -> (record number, (6,) Fx Fy Fz [N] Mx My Mz [N·m]) in the sensor's axes.

    `zero` is the per-channel no-load output in counts (8192 nominal, or a measured average).
    """
    record_no, counts = decode_counts(frame)
    return record_no, counts_to_si(counts, sens, np.asarray(zero, dtype=float))


def encode_record(record_no: int, raw_counts: Sequence[int] | np.ndarray) -> bytes:
    """(record number 0-9, six counts 0..0x3FFF) -> the 27 bytes the sensor sends."""
    if not 0 <= int(record_no) <= 9:
        raise ValueError(f"record number must be 0-9, got {record_no}")
    counts = [int(c) for c in raw_counts]
    if len(counts) != N_CHANNELS or not all(0 <= c <= RAW_MAX for c in counts):
        raise ValueError(f"need six counts in 0..0x{RAW_MAX:X}, got {counts}")
    return b"%d%04X%04X%04X%04X%04X%04X\r\n" % (int(record_no), *counts)


# ASCII only, on bytes: a str pattern's \s and \d also match Unicode whitespace and digits, and
# 0x1C-0x1F (one flipped bit turns CR into 0x1D) are whitespace to `re` but not to float().
_DECIMAL = re.compile(rb" *[0-9]+(?:\.[0-9]+)? *")
_AXIS_NAMES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
_AXIS_UNITS = ("LSB/N",) * 3 + ("LSB/(N·m)",) * 3
# Default relative band around the nominal sensitivities within which a `p` reply is believed.
SENSITIVITY_TOLERANCE = 0.10


def parse_sensitivities(
    line: bytes, nominal: Sensitivities | None = None, tolerance: float = SENSITIVITY_TOLERANCE
) -> Sensitivities:
    """Parse the reply to `p`: six comma-separated decimals (Fx,Fy,Fz in LSB/N then Mx,My,Mz in LSB/N·m) + CR LF.

    Every malformed reply raises ProtocolError (one line).  With `nominal`, each value must also lie
    within `tolerance` (relative) of its nominal value (`check_sensitivities`).
    """
    raw = bytes(line)
    shown = raw[:80]
    if not raw.endswith(CRLF) or b"\r" in raw[:-2] or b"\n" in raw[:-2]:
        raise ProtocolError(f"WACOH sensitivities reply {shown!r}: not one line ending in CR LF")
    parts = raw[:-2].split(b",")
    # A strict decimal pattern (not float()) so 'nan', 'inf', '1e3', '-5' and control bytes are all refused.
    if len(parts) != N_CHANNELS or not all(_DECIMAL.fullmatch(p) for p in parts):
        raise ProtocolError(f"WACOH sensitivities reply {shown!r}: expected six comma-separated decimals")
    try:
        values = [float(p) for p in parts]
        sens = Sensitivities.from_values(values)
    except ValueError:  # zero, or anything float() still refuses: the reply is wrong, not the program
        raise ProtocolError(f"WACOH sensitivities reply {shown!r}: values must be positive decimals") from None
    if nominal is not None:
        check_sensitivities(sens, nominal, tolerance)
    return sens


def check_sensitivities(sens: Sensitivities, nominal: Sensitivities, tolerance: float) -> Sensitivities:
    """ProtocolError naming the first axis whose value is not within `tolerance` (relative) of `nominal`."""
    for name, unit, value, ref in zip(_AXIS_NAMES, _AXIS_UNITS, sens.values, nominal.values, strict=True):
        if not abs(value - ref) <= tolerance * ref:
            raise ProtocolError(
                f"WACOH sensitivities reply: {name} = {value:g} {unit} is not within {tolerance:.0%} of "
                f"the nominal {ref:g}"
            )
    return sens


class RecordReader:
    """Framer: arbitrary chunks of bytes in, complete valid 27-byte records out.

    Frames are delimited by LF: a record is accepted only if exactly the 27 bytes since the previous LF
    (or since the start/reset) form a valid record.  Any byte lost or inserted inside a frame changes its
    length, so garbage, a missing CR LF or a leftover fragment costs the affected frame(s) and the reader
    is back in step at the next LF; it never splices a record out of pieces of two.
    """

    def __init__(self) -> None:
        self._pending = bytearray()
        self._pending_len = 0  # bytes since the last LF, including ones dropped once the line overran
        self.accepted = 0
        self.rejected = 0  # LF-terminated lines that were not a valid record
        self.long_rejected = 0  # ... of which at least a record long: a reply arrived, but corrupt

    @property
    def pending(self) -> int:
        """Bytes received since the last LF."""
        return self._pending_len

    def reset(self) -> None:
        """Forget a partial line (call together with discarding the port's input)."""
        self._pending.clear()
        self._pending_len = 0

    def feed(self, chunk: bytes) -> list[bytes]:
        """Consume `chunk`; returns the valid records it completed, oldest first."""
        out: list[bytes] = []
        start = 0
        while True:
            lf = chunk.find(b"\n", start)
            if lf < 0:
                self._append(chunk[start:])
                return out
            self._append(chunk[start : lf + 1])
            line_len = self._pending_len
            line = bytes(self._pending)
            self.reset()
            start = lf + 1
            if line_len == RECORD_LEN and _is_valid(line):
                self.accepted += 1
                out.append(line)
            else:
                self.rejected += 1
                if line_len >= RECORD_LEN:
                    self.long_rejected += 1

    def _append(self, data: bytes) -> None:
        self._pending_len += len(data)
        # Past one record length the line is already doomed: stop buffering it, just count its length.
        if self._pending_len <= RECORD_LEN:
            self._pending += data
        else:
            self._pending.clear()


def _is_valid(frame: bytes) -> bool:
    try:
        decode_counts(frame)
    except ProtocolError:
        return False
    return True


# ------------------------------------------------------------------------------------ config
TareMode = Literal["sensor", "software"]
ReadMode = Literal["poll", "stream"]


def _key(where: str, name: str) -> str:
    if not where:
        return name
    return f"{where} {name}" if where.endswith(":") else f"{where}.{name}"


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _positive_int(value: Any, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"{key} must be a positive integer, got {_show(value)}")
    return value


def _positive_float(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{key} must be a positive number, got {_show(value)}")
    return float(value)


def _choice(value: Any, key: str, options: tuple[Any, ...]) -> Any:
    # bool is an int: keep `True` from passing as filter 1.
    if isinstance(value, bool) or value not in options:
        raise ConfigError(f"{key} must be one of {list(options)}, got {_show(value)}")
    return value


def _port(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{key} must be a non-empty string (e.g. /dev/ttyUSB0), got {_show(value)}")
    return value


def _sensitivities(value: Any, key: str) -> Sensitivities:
    if isinstance(value, Sensitivities):
        return value
    message = f"{key} must be a list of 6 positive numbers [Fx, Fy, Fz in LSB/N, Mx, My, Mz in LSB/(N·m)]"
    if not isinstance(value, list | tuple) or len(value) != N_CHANNELS:
        raise ConfigError(f"{message}, got {_show(value)}")
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{message}, got {_show(value)}")
    return Sensitivities.from_values(value)


def _fraction(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 1:
        raise ConfigError(f"{key} must be a number between 0 and 1 (exclusive), got {_show(value)}")
    return float(value)


def _filter(value: Any, key: str) -> int | None:
    return None if value is None else int(_choice(value, key, FILTER_SETTINGS))


@dataclass
class WacohConfig:
    """Settings of one WACOH sensor (YAML keys are the field names)."""

    port: str  # pyserial port or URL, e.g. /dev/ttyUSB0
    baudrate: int = 921600
    timeout_s: float = 0.05  # per request (plus the reply's time on the wire)
    # Used when the sensor does not answer `p` (some models never do): Fx, Fy, Fz then Mx, My, Mz.
    sensitivities: Sensitivities = field(default_factory=Sensitivities)
    tare: TareMode = "software"  # "sensor": `O` x3 in the sensor; "software": mean of tare_samples
    tare_samples: int = 50
    filter: int | None = None  # sensor moving average over 1/2/4/8 samples; None leaves it as it is
    mode: ReadMode = "poll"  # "poll": one `R` per read; "stream": `S`, keep the latest record
    max_consecutive_failures: int = 10  # reads in a row with no valid record before LinkLostError

    # A `p` reply is believed only if every value lies within `sensitivity_tolerance` (relative) of these
    # nominal values of the sensor class (200 N / 4 N·m: ~32.8 LSB/N, ~1638 LSB/(N·m)); else it is
    # asked again, and the configured `sensitivities` are used if no plausible reply comes.
    nominal_sensitivities: Sensitivities = field(default_factory=Sensitivities)
    sensitivity_tolerance: float = SENSITIVITY_TOLERANCE

    def validate(self, where: str = "WacohConfig") -> None:
        """ConfigError naming the first bad field."""
        for name, check in _CHECKS.items():
            check(getattr(self, name), _key(where, name))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, where: str) -> WacohConfig:
        """Build from a config mapping; ConfigError('<where>.<field> must be ..., got ...') on any bad value."""
        if d is None:
            d = {}
        if not isinstance(d, Mapping):
            raise ConfigError(f"{where} must be a mapping, got {_show(d)}")
        known = [f.name for f in fields(cls)]
        unknown = sorted(str(k) for k in d if k not in known)
        if unknown:
            head = where if where.endswith(":") else f"{where}:"
            raise ConfigError(f"{head} unknown key '{unknown[0]}' (known: {', '.join(sorted(known))})")
        if "port" not in d:
            raise ConfigError(f"{_key(where, 'port')} is required")
        kwargs = {name: _CHECKS[name](d[name], _key(where, name)) for name in known if name in d}
        return cls(**kwargs)


_CHECKS: dict[str, Any] = {
    "port": _port,
    "baudrate": _positive_int,
    "timeout_s": _positive_float,
    "sensitivities": _sensitivities,
    "tare": lambda v, k: _choice(v, k, ("sensor", "software")),
    "tare_samples": _positive_int,
    "filter": _filter,
    "mode": lambda v, k: _choice(v, k, ("poll", "stream")),
    "max_consecutive_failures": _positive_int,
    "nominal_sensitivities": _sensitivities,
    "sensitivity_tolerance": _fraction,
}


# ------------------------------------------------------------------------------------ driver
@dataclass(frozen=True)
class _Sample:
    seq: int  # increments with every valid record received (stream mode freshness)
    t: float  # host receive time, time.monotonic()
    counts: np.ndarray  # (6,) raw counts, sensor axes


class WacohSensor(ForceSensor):
    """The WACOH WEF-6A200-4-RCD on a serial port (pyserial, 8N1, no flow control).

    Reads return N and N·m in the cell convention (see SENSOR_TO_CELL_*), `t` = host receive time
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
        self._ser: serial.Serial | None = None
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
        self._fd: int | None = None
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
        try:
            self._ser = serial.serial_for_url(
                cfg.port,
                baudrate=cfg.baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                xonxoff=False,
                rtscts=False,
                dsrdtr=False,
                timeout=min(cfg.timeout_s, _READ_SLICE_S),
                write_timeout=max(cfg.timeout_s, _WRITE_TIMEOUT_FLOOR_S),
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkLostError(f"WACOH sensor: cannot open {cfg.port}: {exc}") from None
        try:
            self._fd = self._ser.fileno()
        except (AttributeError, NotImplementedError, serial.SerialException):
            self._fd = None  # a URL port without a file descriptor
        self._next_no, self._unsettled = None, deque()
        try:
            self._stop_stream_and_drain()  # a previous session may have left streaming on
            self._sens, self.sensitivities_source = self._request_sensitivities()
            self._scale = self._sens.as_array()
            if cfg.filter is not None:
                self._write(b"%dF" % cfg.filter, "filter command")
            self._zero = np.full(N_CHANNELS, float(RAW_ZERO))
            self.consecutive_failures = 0
            if cfg.mode == "stream":
                self._start_stream()
            elif self._poll_once(wait_s=max(cfg.timeout_s, _SYNC_WAIT_S), count=False) is None:
                log.warning("WACOH sensor on %s: no record at connect; reads wait until no earlier "
                            "request can still be answered", cfg.port)
        except BaseException:
            self._stop_stream_thread()
            self._close_port()
            raise
        log.info("WACOH sensor on %s: connected (%s mode, sensitivities from %s: %s)", cfg.port, cfg.mode,
                 self.sensitivities_source, self._sens.values)

    def _disconnect(self) -> None:
        try:
            if self._ser is not None:
                try:
                    self._ser.write(CMD_STOP)
                except _LINK_ERRORS as exc:
                    log.debug("WACOH sensor on %s: could not send E on close: %s", self.config.port, exc)
                self._stop_stream_thread()
                try:
                    time.sleep(_DRAIN_S)
                    self._ser.reset_input_buffer()
                except _LINK_ERRORS as exc:
                    log.debug("WACOH sensor on %s: could not drain on close: %s", self.config.port, exc)
        finally:
            self._stop_stream_thread()
            self._close_port()

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except _LINK_ERRORS as exc:
                log.debug("WACOH sensor on %s: close failed: %s", self.config.port, exc)

    # ------------------------------------------------------------------ wire helpers
    def _port(self) -> serial.Serial:
        if self._ser is None:
            raise LinkLostError(f"WACOH sensor on {self.config.port}: port is not open")
        return self._ser

    def _link_lost(self, what: str, exc: BaseException) -> LinkLostError:
        return LinkLostError(f"WACOH sensor on {self.config.port}: {what} failed: {exc}")

    def _write(self, data: bytes, what: str) -> None:
        try:
            self._port().write(data)
        except _LINK_ERRORS as exc:
            raise self._link_lost(what, exc) from None

    def _discard_input(self) -> None:
        self._framer.reset()
        try:
            self._port().reset_input_buffer()
        except _LINK_ERRORS as exc:
            raise self._link_lost("clearing input", exc) from None

    def _read_chunk(self, size: int, deadline: float) -> bytes:
        """Up to `size` bytes of what has arrived, waiting for the first one until `deadline` at most
        (b'' then).  The wait is the time left, not pyserial's per-read timeout: a read loop that
        restarted that timeout overshot the deadline by up to a whole timeout (5 ms -> 10.3 ms)."""
        port = self._port()
        left = max(0.0, deadline - time.monotonic())
        try:
            if self._fd is None:
                port.timeout = left  # URL ports: no descriptor to wait on
                return bytes(port.read(size))
            readable, _, _ = select.select([self._fd], [], [], left)
            if not readable:
                return b""
            # At least 1 byte after select said readable: a vanished device reads as an error then.
            return bytes(port.read(max(1, min(size, port.in_waiting))))
        except _LINK_ERRORS as exc:
            raise self._link_lost("read", exc) from None

    def _reply_deadline(self, reply_bytes: int) -> float:
        # The timeout plus the reply's own time on the wire, so slow baud rates do not time out early.
        return time.monotonic() + self.config.timeout_s + reply_bytes * _BITS_PER_BYTE / self.config.baudrate

    def _stop_stream_and_drain(self) -> None:
        self._write(CMD_STOP, "stop-streaming command")
        time.sleep(_DRAIN_S)
        self._discard_input()

    def _read_line(self, deadline: float) -> bytes | None:
        """Bytes up to and including the first LF, or None at the deadline."""
        buf = bytearray()
        while True:
            chunk = self._read_chunk(MAX_LINE, deadline)
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
            self._write(CMD_SENSITIVITIES, "sensitivities request")
            line = self._read_line(self._reply_deadline(64))
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
            self._wait_until(self._reply_deadline(RECORD_LEN))
            self.timeouts += count
            return None
        expected = self._next_no
        self._write(CMD_RECORD, "record request")
        sent = time.monotonic()
        if expected is not None:
            self._next_no = (expected + 1) % 10
        deadline = sent + (self.config.timeout_s if wait_s is None else wait_s)
        deadline += RECORD_LEN * _BITS_PER_BYTE / self.config.baudrate
        framer = self._framer
        rejected0, long0 = framer.rejected, framer.long_rejected
        try:
            while True:
                # Ask for exactly what completes the record: the read returns as soon as it is there.
                chunk = self._read_chunk(max(1, RECORD_LEN - framer.pending), deadline)
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
            self._read_chunk(MAX_LINE, deadline)  # whatever arrives now is an earlier request's: discarded

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
        self._write(CMD_START, "start-streaming command")
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
        ser = self._port()
        try:
            fd: int | None = ser.fileno()
        except (AttributeError, NotImplementedError, serial.SerialException):
            fd = None  # a URL port without a file descriptor: poll it instead
        while not self._stop.is_set():
            try:
                if fd is not None:
                    readable, _, _ = select.select([fd], [], [], _READ_SLICE_S)
                    if not readable:
                        continue
                else:
                    time.sleep(_READ_SLICE_S / 10)
                with self._cond:
                    # At least 1 byte after select said readable: a vanished device reads as an error
                    # then, not as an endless stream of empty reads.
                    self._pump_locked(at_least_one=fd is not None)
            except _LINK_ERRORS as exc:
                if not self._stop.is_set():
                    with self._cond:
                        self._link_error = f"WACOH sensor on {self.config.port}: stream read failed: {exc}"
                        self._cond.notify_all()
                return

    def _pump_locked(self, at_least_one: bool = False) -> None:
        """Read what the port holds now, frame it, keep the newest record.  Caller holds `_cond`."""
        ser = self._port()
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
        deadline = self._reply_deadline(RECORD_LEN)
        with self._cond:
            if self._link_error is None:
                try:
                    # Take what has already arrived ourselves: the newest record must not wait for the
                    # reader thread's next turn at the GIL (up to the 5 ms switch interval).
                    self._pump_locked()
                except _LINK_ERRORS as exc:
                    raise self._link_lost("stream read", exc) from None
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
            self._write(CMD_ZERO, "zero command")
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


# ------------------------------------------------------------------------------------ benchmark
