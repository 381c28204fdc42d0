"""The user-area contract with the robot-side program (field layout, decoded status) and the `devices.arm` settings."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

from drivers.errors import ConfigError
from drivers.tm5.registers import (
    MAX_READ_REGISTERS,
    MAX_WRITE_REGISTERS,
    N_JOINTS,
    USER_AREA_FIRST,
    USER_AREA_LAST,
    RobotFlags,
)


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


@dataclass(frozen=True)
class RobotSideStatus:
    """The robot-side program's view, decoded from the user area (for diagnostics)."""

    counter: int
    flags: RobotFlags
    host_seq_echo: int
