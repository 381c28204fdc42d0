"""TM5-700 over Modbus/TCP: register codecs, the user-area contract, its configuration and the `TM5ModbusArm` driver."""

from __future__ import annotations

import enum
import logging
import math
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from drivers.errors import ConfigError, DriverError, LifecycleError, LinkLostError, ProtocolError, StaleDataError
from drivers.interfaces import Arm, ArmState, ArmStatus, JointLimits, Lifecycle

log = logging.getLogger(__name__)

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


_ROBOT_FLAGS_MASK = int(RobotFlags.WATCHDOG | RobotFlags.EXECUTING | RobotFlags.HELD)  # other bits: reserved


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


# ------------------------------------------------------------------------------------------------
# Configuration helpers (drivers stay independent of cell/: a small local validator)
# ------------------------------------------------------------------------------------------------
def _join(where: str, name: str) -> str:
    """'cell.yaml:' + 'x' -> 'cell.yaml: x'; 'cell.yaml: a' + 'x' -> 'cell.yaml: a.x' (as cell.configio)."""
    if not where:
        return name
    return f"{where} {name}" if where.endswith(":") else f"{where}.{name}"


def _require_mapping(d: Any, where: str) -> Mapping[str, Any]:
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where} must be a mapping, got {d!r}")
    return d


def _reject_unknown(d: Mapping[str, Any], known: Sequence[str], where: str) -> None:
    for key in d:
        if key not in known:
            raise ConfigError(f"{_join(where, str(key))} is not a known key (expected one of {list(known)})")


def _as_int(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where} must be an integer, got {value!r}")
    return value


def _as_float(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return float(value)


# ------------------------------------------------------------------------------------------------
# The user holding area contract (9000-9999), shared with docs/robot-side-program.md
# ------------------------------------------------------------------------------------------------
FIELD_WIDTH: dict[str, int] = {
    "robot_counter": 2,  # INT32, +1 every robot cycle (wraps)
    "torque": 2 * N_JOINTS,  # FLOAT32 J1..J6, mN·m (Joint_Torque)
    "speed": 2 * N_JOINTS,  # FLOAT32 J1..J6, deg/s (Joint_Speed)
    "robot_status": 1,  # UINT16 bit word, see RobotFlags
    "host_seq_echo": 2,  # INT32, last host sequence the robot-side program acted upon
    "host_seq": 2,  # INT32, +1 with every host write (the host heartbeat)
    "targets": 2 * N_JOINTS,  # FLOAT32 J1..J6, deg
    "command": 1,  # UINT16, see Command
}
ROBOT_FIELDS = ("robot_counter", "torque", "speed", "robot_status", "host_seq_echo")
HOST_FIELDS = ("host_seq", "targets", "command")


@dataclass(frozen=True)
class UserAreaLayout:
    """Start address of every field of the user area.  Robot->host fields form one block read per cycle,
    host->robot fields one block written per cycle (registers in gaps of the host block are written 0)."""

    robot_counter: int = 9000
    torque: int = 9002
    speed: int = 9014
    robot_status: int = 9026
    host_seq_echo: int = 9027
    host_seq: int = 9100
    targets: int = 9102
    command: int = 9114

    def extent(self, name: str) -> tuple[int, int]:
        """First and last register of field `name`."""
        start = int(getattr(self, name))
        return start, start + FIELD_WIDTH[name] - 1

    def _block(self, names: Sequence[str]) -> tuple[int, int]:
        first = min(self.extent(n)[0] for n in names)
        last = max(self.extent(n)[1] for n in names)
        return first, last - first + 1

    @property
    def robot_block(self) -> tuple[int, int]:
        """(start, count) of the robot->host block."""
        return self._block(ROBOT_FIELDS)

    @property
    def host_block(self) -> tuple[int, int]:
        """(start, count) of the host->robot block."""
        return self._block(HOST_FIELDS)

    def slice_in(self, name: str, block_start: int) -> slice:
        """Where field `name` sits inside a register list that starts at `block_start`."""
        start = int(getattr(self, name)) - block_start
        return slice(start, start + FIELD_WIDTH[name])

    def validate(self, where: str = "user_area") -> None:
        """Every field inside 9000-9999, no two fields overlapping, host and robot blocks disjoint and each
        within one Modbus transaction.  Raises ConfigError naming the offending field."""
        names = [f.name for f in fields(self)]
        for name in names:
            value = _as_int(getattr(self, name), _join(where, name))
            first, last = value, value + FIELD_WIDTH[name] - 1
            if first < USER_AREA_FIRST or last > USER_AREA_LAST:
                # Name the width only when the start is fine but the field spills over the end.
                spills = USER_AREA_FIRST <= first <= USER_AREA_LAST
                span = f" (it needs {FIELD_WIDTH[name]} registers: {first}-{last})" if spills else ""
                raise ConfigError(
                    f"{_join(where, name)} must lie in {USER_AREA_FIRST}-{USER_AREA_LAST}, got {value}{span}"
                )
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                (a0, a1), (b0, b1) = self.extent(a), self.extent(b)
                if a0 <= b1 and b0 <= a1:
                    raise ConfigError(
                        f"{_join(where, b)} ({b0}-{b1}) overlaps {_join(where, a)} ({a0}-{a1})"
                    )
        r0, rn = self.robot_block
        h0, hn = self.host_block
        for name in HOST_FIELDS:
            f0, f1 = self.extent(name)
            if f0 <= r0 + rn - 1 and r0 <= f1:
                raise ConfigError(
                    f"{_join(where, name)} ({f0}-{f1}) lies inside the robot->host block {r0}-{r0 + rn - 1}; "
                    "host fields must be outside it (the host writes its block in one go)"
                )
        for name in ROBOT_FIELDS:
            f0, f1 = self.extent(name)
            if f0 <= h0 + hn - 1 and h0 <= f1:
                raise ConfigError(
                    f"{_join(where, name)} ({f0}-{f1}) lies inside the host->robot block {h0}-{h0 + hn - 1}; "
                    "robot fields must be outside it (the host overwrites that block every cycle)"
                )
        if rn > MAX_READ_REGISTERS:
            raise ConfigError(f"{where}: robot->host fields span {rn} registers; one read carries at most "
                              f"{MAX_READ_REGISTERS}")
        if hn > MAX_WRITE_REGISTERS:
            raise ConfigError(f"{where}: host->robot fields span {hn} registers; one write carries at most "
                              f"{MAX_WRITE_REGISTERS}")

    @classmethod
    def from_dict(cls, d: Any, where: str) -> UserAreaLayout:
        """Build from a (partial) mapping of field -> start address, defaults for the rest, validated."""
        d = _require_mapping(d, where)
        names = [f.name for f in fields(cls)]
        _reject_unknown(d, names, where)
        layout = cls(**{k: _as_int(v, _join(where, k)) for k, v in d.items()})
        layout.validate(where)
        return layout

    def as_table(self) -> list[tuple[str, int, int, str]]:
        """(field, first, last, direction) rows, sorted by address (used by docs and tests)."""
        rows = [(n, *self.extent(n), "robot->host" if n in ROBOT_FIELDS else "host->robot") for n in FIELD_WIDTH]
        return sorted(rows, key=lambda r: r[1])


# ------------------------------------------------------------------------------------------------
# Driver configuration
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TM5ModbusConfig:
    """How to reach the controller and how strict to be about it (the `devices.arm` settings)."""

    host: str
    port: int = 502
    unit_id: int = 1
    timeout_s: float = 0.01  # per Modbus transaction and per connect attempt
    stale_after_s: float = 0.05  # robot counter not advancing this long -> StaleDataError
    reconnect_initial_s: float = 0.05  # backoff between reconnect attempts: doubles up to reconnect_max_s
    reconnect_max_s: float = 2.0
    arm_timeout_s: float = 1.0  # arm(): time to get the link back and the robot-side acknowledgement
    stop_coil: bool = False  # also pulse coil 7105 on stop (ends the robot project: operator must restart)
    user_area: UserAreaLayout = field(default_factory=UserAreaLayout)

    def validate(self, where: str = "tm5_modbus") -> None:
        def need(cond: bool, name: str, message: str) -> None:
            if not cond:
                raise ConfigError(f"{_join(where, name)} {message}, got {getattr(self, name)!r}")

        need(isinstance(self.host, str) and bool(self.host.strip()), "host", "must be the controller's address")
        need(1 <= _as_int(self.port, _join(where, "port")) <= 65535, "port", "must lie in 1-65535")
        need(0 <= _as_int(self.unit_id, _join(where, "unit_id")) <= 255, "unit_id", "must lie in 0-255")
        for name in ("timeout_s", "stale_after_s", "reconnect_initial_s", "reconnect_max_s", "arm_timeout_s"):
            need(_as_float(getattr(self, name), _join(where, name)) > 0, name, "must be > 0")
        need(self.timeout_s <= 1.0, "timeout_s", "must be <= 1 s (the control loop waits this long on a dead link)")
        need(self.reconnect_max_s >= self.reconnect_initial_s, "reconnect_max_s", "must be >= reconnect_initial_s")
        need(isinstance(self.stop_coil, bool), "stop_coil", "must be true or false")
        self.user_area.validate(_join(where, "user_area"))

    @classmethod
    def from_dict(cls, d: Any, where: str) -> TM5ModbusConfig:
        d = dict(_require_mapping(d, where))
        names = [f.name for f in fields(cls)]
        _reject_unknown(d, names, where)
        if "host" not in d:
            raise ConfigError(f"{_join(where, 'host')} is required (the controller's IP address)")
        if "user_area" in d:
            d["user_area"] = UserAreaLayout.from_dict(d["user_area"], _join(where, "user_area"))
        for name in ("timeout_s", "stale_after_s", "reconnect_initial_s", "reconnect_max_s", "arm_timeout_s"):
            if name in d:
                d[name] = _as_float(d[name], _join(where, name))
        cfg = cls(**d)
        cfg.validate(where)
        return cfg


# ------------------------------------------------------------------------------------------------
# The driver
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RobotSideStatus:
    """The robot-side program's view, decoded from the user area (for diagnostics)."""

    counter: int
    flags: RobotFlags
    host_seq_echo: int


class TM5ModbusArm(Arm):
    """The TM5-700 through its Modbus/TCP slave plus the robot-side program of docs/robot-side-program.md.

    Per cycle: `read_state` = 3 reads (input registers 7001-7036, discrete inputs 7200-7208, the robot->host
    user block); `send_target` = 1 write (the host->robot user block).  Units are converted here only.
    The link is a sync pymodbus client with `retries=0`, so a dead link costs at most `timeout_s`.
    """

    def __init__(self, config: TM5ModbusConfig, limits: JointLimits, dt: float, speed_scale: float = 1.0) -> None:
        super().__init__(limits, dt, speed_scale)
        config.validate()
        if limits.n != N_JOINTS:
            raise ConfigError(f"the TM5-700 has {N_JOINTS} joints, the joint limits describe {limits.n}")
        self.config = config
        self._layout = config.user_area
        self._client: ModbusTcpClient | None = None
        self._down_reason = "not connected"
        self._backoff_s = config.reconnect_initial_s
        self._stop_failed = False  # the last stop attempt raised: the next one may reconnect
        self._next_attempt = 0.0
        self._host_seq = 0
        self._counter_raw: int | None = None
        self._counter_seen_at = 0.0
        self._new_stale_window = False
        self._seq = 0
        self._last_q: np.ndarray | None = None
        self._flange_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._tool_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._robot_side: RobotSideStatus | None = None
        self._warned_untested = False

    # ----------------------------------------------------------------------------- public extras
    @property
    def endpoint(self) -> str:
        return f"{self.config.host}:{self.config.port}"

    @property
    def link_up(self) -> bool:
        return self._client is not None and self._client.connected

    @property
    def robot_side(self) -> RobotSideStatus | None:
        """Robot-side program status from the last successful read."""
        return self._robot_side

    @property
    def last_flange_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(position [m], rotation) of the flange from the last `read_state` (no extra transaction)."""
        return self._flange_pose

    @property
    def last_tool_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(position [m], rotation) of the TCP from the last `read_state` (no extra transaction)."""
        return self._tool_pose

    def read_tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Fresh TCP pose in the current base (input registers 7025-7036): (position [m], rotation matrix)."""
        return self._read_pose(IR_TOOL_POSE, "tool pose")

    def read_flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Fresh flange pose in the current base (input registers 7001-7012)."""
        return self._read_pose(IR_FLANGE_POSE, "flange pose")

    def reconnect(self, timeout_s: float | None = None) -> None:
        """Re-open the link now, retrying with exponential backoff for up to `timeout_s` (default
        `arm_timeout_s`).  Does not leave FAULT: commanding still needs `arm()`.  Raises LinkLostError."""
        with self._lock:
            if self.lifecycle is Lifecycle.DISCONNECTED:
                raise LifecycleError("cannot reconnect: the arm is not connected (call connect())")
            self._reconnect_blocking(self.config.arm_timeout_s if timeout_s is None else timeout_s)

    # ----------------------------------------------------------------------------- wire: lifecycle
    def _connect(self) -> None:
        if not self._warned_untested:
            log.warning("TM5ModbusArm %s: the real-hardware path is UNTESTED on a physical arm (it has only run "
                        "against sim.tm5_emulator); keep a hand on the E-stop", self.endpoint)
            self._warned_untested = True
        # A first contact may be slow (a controller just booted, a busy machine): keep trying for
        # arm_timeout_s before giving up, as arming does.
        # A refused connection (nobody listening) fails at once.
        deadline = time.monotonic() + self.config.arm_timeout_s
        while True:
            self._next_attempt = 0.0
            self._open_link()
            try:
                # Start our heartbeat right after whatever the robot last acted upon, so a restarted
                # host never repeats a sequence number the robot-side program would ignore.
                self._host_seq = self._read_robot_block().host_seq_echo
                return
            except DriverError:
                self._close_link("connect failed")
                if time.monotonic() >= deadline:
                    raise
                time.sleep(self.config.reconnect_initial_s)

    def _disconnect(self) -> None:
        self._close_link("disconnected")
        self._client = None

    def _arm(self) -> None:
        """Get the link back if needed, then the IDLE handshake: the robot-side program must echo our new
        host sequence (which also clears its latched stop / watchdog trip) within `arm_timeout_s`."""
        deadline = time.monotonic() + self.config.arm_timeout_s
        if not self.link_up:
            self._reconnect_blocking(self.config.arm_timeout_s)
        q = self._read_joints()
        seq = self._write_host_block(Command.IDLE, q)
        first_counter: int | None = None
        while True:
            rs = self._read_robot_block()
            first_counter = rs.counter if first_counter is None else first_counter
            if rs.host_seq_echo == seq:
                # Armed on a working link: a stop that failed before this is moot, so a fault's first stop
                # again never waits on the link (it would double the time a lost link takes to report).
                self._stop_failed = False
                return
            if time.monotonic() >= deadline:
                break
            time.sleep(0.002)  # a robot cycle is several ms: poll gently
        if rs.counter == first_counter:
            raise StaleDataError(
                f"TM5 {self.endpoint}: robot counter at {self._layout.robot_counter} stuck at {rs.counter}: "
                "the robot-side program is not running (see docs/robot-side-program.md)"
            )
        raise ProtocolError(
            f"TM5 {self.endpoint}: robot-side program did not acknowledge host sequence {seq} within "
            f"{self.config.arm_timeout_s:g} s (echo at {self._layout.host_seq_echo} reads {rs.host_seq_echo}); "
            "does its register layout match devices.arm.user_area?"
        )

    def _stop(self) -> None:
        # A first stop never waits on the link: a dead one fails at once (the robot's watchdog stops the arm
        # then; a fault's stop must not add a connect to the time a lost link takes to detect).  A stop
        # retried after a failed one may open the link again -- one connect attempt, bounded by timeout_s --
        # so a stop whose reply was lost gets through on a fresh link.
        retry, self._stop_failed = self._stop_failed, True
        q = self._last_sent if self._last_sent is not None else self._last_q
        self._write_host_block(Command.STOP, q, may_reconnect=retry)
        if self.config.stop_coil:
            self._call("write coil", COIL_STOP, lambda c, dev: c.write_coil(COIL_STOP, True, device_id=dev),
                       may_reconnect=retry)
        self._stop_failed = False

    # ----------------------------------------------------------------------------- wire: data
    def _read_state(self) -> ArmState:
        layout = self._layout
        ir = self._read_registers("input", IR_FIRST, IR_COUNT)
        di = self._read_bits(DI_FIRST, DI_COUNT)
        rb_start, rb_count = layout.robot_block
        hr = self._read_registers("holding", rb_start, rb_count)
        t = time.monotonic()

        q_deg = self._finite(regs_to_floats(ir[IR_JOINTS - IR_FIRST:IR_JOINTS - IR_FIRST + 12]), "joint angles",
                             IR_JOINTS)
        tau_mnm = self._finite(regs_to_floats(hr[layout.slice_in("torque", rb_start)]), "joint torque",
                               layout.torque)
        dq_deg = self._finite(regs_to_floats(hr[layout.slice_in("speed", rb_start)]), "joint speed", layout.speed)
        robot = self._decode_robot_block(hr, rb_start)
        self._flange_pose = regs_to_pose(ir[0:12])
        self._tool_pose = regs_to_pose(ir[IR_TOOL_POSE - IR_FIRST:IR_TOOL_POSE - IR_FIRST + 12])
        self._check_counter(robot.counter, t)

        q = np.radians(q_deg)
        self._last_q = q
        status = ArmStatus(
            error=di[DI_ERROR - DI_FIRST],
            estop=di[DI_ESTOP - DI_FIRST],
            project_running=di[DI_RUNNING - DI_FIRST],
            paused=di[DI_PAUSED - DI_FIRST],
            protective_stop=bool(robot.flags & (RobotFlags.WATCHDOG | RobotFlags.HELD)),
        )
        return ArmState(t=t, q=q, dq=np.radians(dq_deg), tau=tau_mnm / 1000.0, status=status, seq=self._seq)

    def _write_target(self, q: np.ndarray) -> None:
        self._write_host_block(Command.TRACK, q, may_reconnect=False)

    # ----------------------------------------------------------------------------- helpers
    def _read_pose(self, address: int, what: str) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            if self.lifecycle is Lifecycle.DISCONNECTED:
                raise LifecycleError(f"cannot read the {what}: the arm is not connected")
            try:
                regs = self._read_registers("input", address, 12)
            except (LinkLostError, StaleDataError) as exc:
                self.fault(str(exc))
                raise
            pos, rot = regs_to_pose(regs)
            self._finite(np.concatenate([pos, rot.ravel()]), what, address)
            return pos, rot

    def _finite(self, values: np.ndarray, what: str, address: int) -> np.ndarray:
        if not np.all(np.isfinite(values)):
            raise ProtocolError(f"TM5 {self.endpoint}: {what} at {address} holds non-finite values {values!r}")
        return values

    def _decode_robot_block(self, hr: list[int], start: int) -> RobotSideStatus:
        lay = self._layout
        rs = RobotSideStatus(
            counter=regs_to_int32(hr[lay.slice_in("robot_counter", start)]),
            flags=RobotFlags(hr[lay.slice_in("robot_status", start)][0] & _ROBOT_FLAGS_MASK),
            host_seq_echo=regs_to_int32(hr[lay.slice_in("host_seq_echo", start)]),
        )
        self._robot_side = rs
        return rs

    def _read_robot_block(self) -> RobotSideStatus:
        start, count = self._layout.robot_block
        return self._decode_robot_block(self._read_registers("holding", start, count), start)

    def _read_joints(self) -> np.ndarray:
        regs = self._read_registers("input", IR_JOINTS, 12)
        q = np.radians(self._finite(regs_to_floats(regs), "joint angles", IR_JOINTS))
        self._last_q = q
        return q

    def _check_counter(self, counter: int, t: float) -> None:
        """Unwrap the robot counter into ArmState.seq and raise StaleDataError when it stops advancing."""
        if self._counter_raw is None:
            self._counter_raw, self._counter_seen_at = counter, t
            self._seq = counter & 0xFFFFFFFF
            return
        step = counter_delta(counter, self._counter_raw)
        if step or self._new_stale_window:
            self._seq += step
            self._counter_raw, self._counter_seen_at = counter, t
            self._new_stale_window = False
            return
        stuck = t - self._counter_seen_at
        if stuck > self.config.stale_after_s:
            raise StaleDataError(
                f"TM5 {self.endpoint}: robot counter at {self._layout.robot_counter} stuck at {counter} for "
                f"{stuck * 1000:.0f} ms (limit {self.config.stale_after_s * 1000:.0f} ms): robot-side program "
                "stalled or stopped"
            )

    def _write_host_block(self, command: Command, q_rad: np.ndarray | None, *, may_reconnect: bool = False) -> int:
        """One FC16 write of host seq + targets + command; returns the host sequence used."""
        lay = self._layout
        start, count = lay.host_block
        regs = [0] * count
        seq = wrap_int32(self._host_seq + 1)
        targets = np.zeros(N_JOINTS) if q_rad is None else np.degrees(np.asarray(q_rad, dtype=float))
        try:
            regs[lay.slice_in("targets", start)] = floats_to_regs(targets)
        except ValueError as exc:
            raise ProtocolError(f"TM5 {self.endpoint}: cannot encode joint targets: {exc}") from None
        regs[lay.slice_in("host_seq", start)] = int32_to_regs(seq)
        regs[lay.slice_in("command", start)] = [int(command)]
        # The number is used up once sent, reply or not: a write whose reply was lost may have reached the
        # robot-side program, which ignores a number it already acted upon (a re-arm reusing it would
        # never clear the latched stop).
        self._host_seq = seq
        self._call("write holding", start, lambda c, dev: c.write_registers(start, regs, device_id=dev),
                   may_reconnect=may_reconnect)
        return seq

    def _read_registers(self, kind: str, address: int, count: int) -> list[int]:
        def read(c: ModbusTcpClient, dev: int) -> ModbusPDU:
            if kind == "input":
                return c.read_input_registers(address, count=count, device_id=dev)
            return c.read_holding_registers(address, count=count, device_id=dev)

        rr = self._call(f"read {kind}", address, read, may_reconnect=True)
        regs = list(rr.registers)
        if len(regs) != count:
            raise ProtocolError(f"TM5 {self.endpoint}: read {kind} {address}: asked {count} registers, "
                                f"got {len(regs)}")
        return regs

    def _read_bits(self, address: int, count: int) -> list[bool]:
        rr = self._call("read discrete inputs", address,
                        lambda c, dev: c.read_discrete_inputs(address, count=count, device_id=dev),
                        may_reconnect=True)
        bits = list(rr.bits)
        if len(bits) < count:
            raise ProtocolError(f"TM5 {self.endpoint}: read discrete inputs {address}: asked {count} bits, "
                                f"got {len(bits)}")
        return [bool(b) for b in bits[:count]]

    def _call(self, op: str, address: int, fn: Callable[[ModbusTcpClient, int], ModbusPDU], *,
              may_reconnect: bool) -> ModbusPDU:
        """One Modbus transaction; every failure becomes LinkLostError (link closed) or ProtocolError."""
        client = self._require_link(may_reconnect)
        try:
            rr = fn(client, self.config.unit_id)
        except ConnectionException as exc:
            raise self._link_lost(f"{op} {address}: connection lost ({_first_line(exc)})") from None
        except ModbusIOException as exc:
            # No (matching) reply in time.  Close the socket: a late reply must not be taken for the next one.
            raise self._link_lost(f"{op} {address}: no valid reply within {self.config.timeout_s * 1000:.0f} ms "
                                  f"({_first_line(exc)})") from None
        except (ModbusException, OSError) as exc:
            raise self._link_lost(f"{op} {address}: {type(exc).__name__}: {_first_line(exc)}") from None
        if rr is None:
            raise self._link_lost(f"{op} {address}: no reply")
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            raise ProtocolError(f"TM5 {self.endpoint}: {op} {address}: Modbus exception reply code {code} "
                                f"({_exception_name(code)})")
        return rr

    def _require_link(self, may_reconnect: bool) -> ModbusTcpClient:
        if self._client is not None and self._client.connected:
            return self._client
        now = time.monotonic()
        if may_reconnect and now >= self._next_attempt:
            return self._open_link()
        wait = max(0.0, self._next_attempt - now)
        hint = f"; next reconnect attempt in {wait * 1000:.0f} ms" if may_reconnect else ""
        raise LinkLostError(f"TM5 {self.endpoint}: link is down ({self._down_reason}){hint}")

    def _open_link(self) -> ModbusTcpClient:
        """One connect attempt (bounded by timeout_s); on failure schedule the next one with backoff."""
        if self._client is None:
            # retries=0: one try per transaction so a dead link costs at most timeout_s per call.
            self._client = ModbusTcpClient(self.config.host, port=self.config.port, timeout=self.config.timeout_s,
                                           retries=0, name="tm5")
        client = self._client
        if not client.connect():
            now = time.monotonic()
            self._down_reason = f"connect to {self.endpoint} failed"
            self._next_attempt = now + self._backoff_s
            self._backoff_s = min(2 * self._backoff_s, self.config.reconnect_max_s)
            raise LinkLostError(f"TM5 {self.endpoint}: cannot connect (next attempt in "
                                f"{(self._next_attempt - now) * 1000:.0f} ms)")
        if client.socket is not None:
            # Request/reply of a few dozen bytes: never let Nagle hold a request back.
            client.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._backoff_s = self.config.reconnect_initial_s
        self._new_stale_window = True  # a new link starts a new staleness window; seq keeps unwrapping
        log.info("TM5 %s: link up", self.endpoint)
        return client

    def _reconnect_blocking(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._require_link(may_reconnect=True)
                return
            except LinkLostError:
                now = time.monotonic()
                if now >= deadline:
                    raise
                time.sleep(min(max(self._next_attempt - now, 0.001), deadline - now))

    def _link_lost(self, reason: str) -> LinkLostError:
        self._close_link(reason)
        self._next_attempt = time.monotonic()  # the first retry may be immediate; failures then back off
        log.warning("TM5 %s: link lost: %s", self.endpoint, reason)
        return LinkLostError(f"TM5 {self.endpoint}: {reason}")

    def _close_link(self, reason: str) -> None:
        self._down_reason = reason
        if self._client is not None:
            self._client.close()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


_EXCEPTION_NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                    4: "server device failure", 5: "acknowledge", 6: "server device busy",
                    8: "memory parity error", 10: "gateway path unavailable", 11: "gateway target no response"}


def _exception_name(code: Any) -> str:
    return _EXCEPTION_NAMES.get(code, "unknown") if isinstance(code, int) else "unknown"


# ------------------------------------------------------------------------------------------------
# Benchmark
# ------------------------------------------------------------------------------------------------
