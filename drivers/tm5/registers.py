"""The TM5-700's Modbus registers: controller addresses, command/status words, FLOAT32/INT32/string/pose codecs."""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence

import numpy as np

# ------------------------------------------------------------------------------------------------
# The controller's own addresses (docs tm5-700.md section 3): protocol addresses, no 30001/40001 offset.
# ------------------------------------------------------------------------------------------------
N_JOINTS = 6
IR_FLANGE_POSE = 7001  # X, Y, Z [mm], Rx, Ry, Rz [deg], FLOAT32 ABCD
IR_JOINTS = 7013  # J1..J6 [deg]
IR_TOOL_POSE = 7025  # X, Y, Z [mm], Rx, Ry, Rz [deg]
IR_FIRST, IR_COUNT = 7001, 36  # the three blocks are contiguous: one read per cycle
DI_FIRST, DI_COUNT = 7200, 9  # 7200 link, 7201 error, 7202 running, 7204 paused, 7208 E-stop
DI_ERROR, DI_RUNNING, DI_PAUSED, DI_ESTOP = 7201, 7202, 7204, 7208
# The documented inputs as runs of consecutive addresses (first, count).  7203 and 7205-7207 lie between them
# undocumented: a controller may refuse a read that covers them (exception 2, illegal data address).
DI_RUNS: tuple[tuple[int, int], ...] = ((7200, 3), (7204, 1), (7208, 1))
COIL_PLAY_PAUSE, COIL_STOP = 7104, 7105
USER_AREA_FIRST, USER_AREA_LAST = 9000, 9999
MAX_READ_REGISTERS, MAX_WRITE_REGISTERS = 125, 123  # Modbus PDU limits for FC03/04 and FC16

_F32_MAX = float(np.finfo(np.float32).max)


class Command(enum.IntEnum):
    """The host's command word in the user area."""

    IDLE = 0  # hold still; with a new host sequence it also acknowledges (clears) a stop or watchdog trip
    TRACK = 1  # follow the joint targets, one per host sequence
    STOP = 2  # protective stop; latched until an IDLE with a new host sequence


class RobotFlags(enum.IntFlag):
    """Bits of the robot-side status word in the user area."""

    WATCHDOG = 1  # the host heartbeat stalled while tracking: the robot stopped itself (latched)
    EXECUTING = 2  # the robot is tracking host targets
    HELD = 4  # protective hold (host STOP or the controller's own protective stop), latched


# ------------------------------------------------------------------------------------------------
# Register codecs (pure functions).  A register is an int in 0..65535; multi-register values are
# big-endian bytes with the high word first ("ABCD").
# ------------------------------------------------------------------------------------------------
def _check_registers(regs: Sequence[int], n: int | None = None) -> np.ndarray:
    arr = np.asarray(regs, dtype=np.int64).reshape(-1)
    if n is not None and arr.size != n:
        raise ValueError(f"expected {n} registers, got {arr.size}")
    if arr.size and (arr.min() < 0 or arr.max() > 0xFFFF):
        raise ValueError(f"registers must lie in 0..65535, got {list(regs)!r}")
    return arr


def floats_to_regs(values: Sequence[float] | np.ndarray, *, allow_nonfinite: bool = False) -> list[int]:
    """FLOAT32 ABCD, two registers per value.  NaN/inf and values beyond float32 range raise ValueError
    unless `allow_nonfinite` (then out-of-range finite values still raise: they would silently become inf)."""
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    finite = np.isfinite(arr)
    if not allow_nonfinite and not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"value {bad} is not finite ({arr[bad]!r}); FLOAT32 registers carry finite values")
    too_big = finite & (np.abs(arr) > _F32_MAX)
    if too_big.any():
        bad = int(np.flatnonzero(too_big)[0])
        raise ValueError(f"value {bad} ({arr[bad]!r}) exceeds the float32 range")
    return np.frombuffer(arr.astype(">f4").tobytes(), dtype=">u2").astype(int).tolist()


def regs_to_floats(regs: Sequence[int]) -> np.ndarray:
    """Inverse of `floats_to_regs`; NaN/inf patterns decode as such (the caller decides what they mean)."""
    arr = _check_registers(regs)
    if arr.size % 2:
        raise ValueError(f"FLOAT32 needs an even number of registers, got {arr.size}")
    return np.frombuffer(arr.astype(">u2").tobytes(), dtype=">f4").astype(np.float64)


def float32_to_regs(value: float, *, allow_nonfinite: bool = False) -> list[int]:
    return floats_to_regs([value], allow_nonfinite=allow_nonfinite)


def regs_to_float32(regs: Sequence[int]) -> float:
    _check_registers(regs, 2)
    return float(regs_to_floats(regs)[0])


def int32_to_regs(value: int) -> list[int]:
    """INT32 two's complement, high word first."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"INT32 needs an integer, got {value!r}")
    if not -(2**31) <= int(value) < 2**31:
        raise ValueError(f"{value} does not fit INT32")
    u = int(value) & 0xFFFFFFFF
    return [u >> 16, u & 0xFFFF]


def regs_to_int32(regs: Sequence[int]) -> int:
    hi, lo = (int(r) for r in _check_registers(regs, 2))
    u = (hi << 16) | lo
    return u - (1 << 32) if u & 0x80000000 else u


def wrap_int32(n: int) -> int:
    """Map any integer onto INT32 the way a 32-bit counter wraps."""
    u = int(n) & 0xFFFFFFFF
    return u - (1 << 32) if u & 0x80000000 else u


def counter_delta(new: int, old: int) -> int:
    """How far a wrapping 32-bit counter advanced from `old` to `new` (0..2**32-1)."""
    return (int(new) - int(old)) & 0xFFFFFFFF


def string_to_regs(text: str, n_regs: int) -> list[int]:
    """ASCII, two characters per register, high byte first, NUL-padded (NUL-terminated when shorter)."""
    try:
        raw = text.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"{text!r} is not ASCII") from None
    if b"\x00" in raw:
        raise ValueError(f"{text!r} contains NUL, which terminates a register string")
    if len(raw) > 2 * n_regs:
        raise ValueError(f"{text!r} needs {len(raw)} bytes, only {2 * n_regs} available")
    raw = raw.ljust(2 * n_regs, b"\x00")
    return [(raw[i] << 8) | raw[i + 1] for i in range(0, len(raw), 2)]


def regs_to_string(regs: Sequence[int]) -> str:
    arr = _check_registers(regs)
    raw = arr.astype(">u2").tobytes().split(b"\x00", 1)[0]
    try:
        return raw.decode("ascii")
    except UnicodeDecodeError:
        raise ValueError(f"register string is not ASCII: {raw!r}") from None


# ------------------------------------------------------------------------------------------------
# Poses: X, Y, Z [mm], Rx, Ry, Rz [deg] with R = Rz(Rz) @ Ry(Ry) @ Rx(Rx) (fixed-axis XYZ).
# ------------------------------------------------------------------------------------------------
def rpy_to_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation matrix of fixed-axis XYZ angles [rad]: R = Rz @ Ry @ Rx."""
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    return np.array([
        [cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
        [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
        [-sy, cy * sx, cy * cx],
    ])


def matrix_to_rpy(rot: np.ndarray) -> tuple[float, float, float]:
    """Inverse of `rpy_to_matrix` (rad); at the Ry = +-90 deg singularity Rz is set to 0."""
    r = np.asarray(rot, dtype=float)
    cy = math.hypot(r[0, 0], r[1, 0])
    ry = math.atan2(-r[2, 0], cy)
    if cy > 1e-9:
        return math.atan2(r[2, 1], r[2, 2]), ry, math.atan2(r[1, 0], r[0, 0])
    return math.atan2(-r[1, 2], r[1, 1]), ry, 0.0


def pose_to_regs(position_m: np.ndarray, rot: np.ndarray, *, allow_nonfinite: bool = False) -> list[int]:
    rx, ry, rz = matrix_to_rpy(rot)
    values = np.concatenate([np.asarray(position_m, dtype=float) * 1000.0, np.degrees([rx, ry, rz])])
    return floats_to_regs(values, allow_nonfinite=allow_nonfinite)


def regs_to_pose(regs: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """12 registers -> (position [m], rotation matrix)."""
    _check_registers(regs, 12)
    v = regs_to_floats(regs)
    rx, ry, rz = np.radians(v[3:6])
    return v[:3] / 1000.0, rpy_to_matrix(float(rx), float(ry), float(rz))
