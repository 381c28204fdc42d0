"""The WACOH WEF-6A200-4-RCD's wire format: protocol facts, records, sensitivities, sensor<->cell axes, framer."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError

# ------------------------------------------------------------------------------------ protocol facts
RECORD_LEN = 27  # digit + 6 x 4 hex digits + CR LF
RAW_ZERO = 8192  # 0x2000: nominal unloaded output (offset binary)
RAW_MAX = 0x3FFF  # effectively 14-bit
N_CHANNELS = 6
CRLF = b"\r\n"
# The sensor sends upper-case hex; a lower-case digit is still a hex digit (the fact sheet's validity rule), so
# it is read as one.
_HEX = b"0123456789ABCDEFabcdef"
_DIGITS = b"0123456789"
# A line longer than any reply we know (the `p` reply is ~49 bytes) is noise; cap what we buffer.
MAX_LINE = 256

CMD_RECORD = b"R"
CMD_SENSITIVITIES = b"p"
CMD_ZERO = b"O"
CMD_START = b"S"
CMD_STOP = b"E"
FILTER_SETTINGS = (1, 2, 4, 8)

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
    if body.translate(None, _HEX):  # whatever survives deleting the hex digits is invalid
        raise ProtocolError(f"WACOH record {bytes(frame)!r}: bytes 1-24 are not all hex digits")
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
AXIS_NAMES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
_AXIS_UNITS = ("LSB/N",) * 3 + ("LSB/(N·m)",) * 3
# The WEF-6A200-4-RCD's nominal sensitivities: +-6553 LSB at the rated 200 N and 4 N·m.
MODEL_SENSITIVITIES = Sensitivities()
# How far one unit's factory values may lie from the model's (a configured reference beyond is a typo
# or another model).
MODEL_SPREAD = 0.10
# Default relative band around the nominal sensitivities within which a `p` reply is believed.  The
# real unit's worst axis sits 0.97 % from nominal (Mx 1653.801 against 1638); a corrupted digit that
# stays within the band cannot be told from a real value, so the band is as tight as real units allow.
SENSITIVITY_TOLERANCE = 0.015
# With the unit's calibration sheet configured, a `p` reply must match it this closely.  The band cannot
# catch a digit changed within it, the sheet can: any reply within this of the sheet gives a scale error
# of at most 0.1 %, about 3 LSB at full scale.  The reply's own resolution (0.001 of ~32.8, 0.003 %) and a
# sheet printed with fewer decimals stay well inside it.
SHEET_TOLERANCE = 0.001


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


def check_sensitivities(
    sens: Sensitivities, nominal: Sensitivities, tolerance: float, against: str = "the nominal"
) -> Sensitivities:
    """ProtocolError naming the first axis whose value is not within `tolerance` (relative) of `nominal`
    (`against` names those values in the message)."""
    for name, unit, value, ref in zip(AXIS_NAMES, _AXIS_UNITS, sens.values, nominal.values, strict=True):
        if not abs(value - ref) <= tolerance * ref:
            raise ProtocolError(
                f"WACOH sensitivities reply: {name} = {value:g} {unit} is not within {tolerance * 100:g}% of "
                f"{against} {ref:g}"
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
