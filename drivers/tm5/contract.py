"""The user-area contract with the robot-side program: field layout, control lease, decoded robot-side status."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

from drivers.configio import join, load_dataclass, require
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
# The user holding area contract (9000-9999), shared with docs/robot-side-program.md
# ------------------------------------------------------------------------------------------------
FIELD_WIDTH: dict[str, int] = {
    "robot_counter": 2,  # INT32, +1 every robot cycle (wraps)
    "torque": 2 * N_JOINTS,  # FLOAT32 J1..J6, mN·m (Joint_Torque)
    "speed": 2 * N_JOINTS,  # FLOAT32 J1..J6, deg/s (Joint_Speed)
    "robot_status": 1,  # UINT16 bit word, see RobotFlags
    "host_seq_echo": 2,  # INT32, last host sequence the robot-side program acted upon
    "lease_holder": 2,  # INT32, token of the host that holds control (0: nobody)
    "lease_age_ms": 1,  # UINT16, ms since the holder last renewed its lease (saturates at 65535)
    "host_seq": 2,  # INT32, +1 with every host write (the host heartbeat)
    "targets": 2 * N_JOINTS,  # FLOAT32 J1..J6, deg
    "command": 1,  # UINT16, see Command
    "host_token": 2,  # INT32, the writing host's random token: its claim on control, renewed by every write
}
ROBOT_FIELDS = ("robot_counter", "torque", "speed", "robot_status", "host_seq_echo", "lease_holder", "lease_age_ms")
HOST_FIELDS = ("host_seq", "targets", "command", "host_token")


@dataclass(frozen=True)
class UserAreaLayout:
    """Start address of every field of the user area.  Robot->host fields form one block read per cycle,
    host->robot fields one block written per cycle (registers in gaps of the host block are written 0)."""

    robot_counter: int = 9000
    torque: int = 9002
    speed: int = 9014
    robot_status: int = 9026
    host_seq_echo: int = 9027
    lease_holder: int = 9029
    lease_age_ms: int = 9031
    host_seq: int = 9100
    targets: int = 9102
    command: int = 9114
    host_token: int = 9115

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
            value = getattr(self, name)
            require(not isinstance(value, bool) and isinstance(value, int), join(where, name),
                    f"must be an integer, got {value!r}")
            first, last = value, value + FIELD_WIDTH[name] - 1
            if first < USER_AREA_FIRST or last > USER_AREA_LAST:
                # Name the width only when the start is fine but the field spills over the end.
                spills = USER_AREA_FIRST <= first <= USER_AREA_LAST
                span = f" (it needs {FIELD_WIDTH[name]} registers: {first}-{last})" if spills else ""
                raise ConfigError(
                    f"{join(where, name)} must lie in {USER_AREA_FIRST}-{USER_AREA_LAST}, got {value}{span}"
                )
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                (a0, a1), (b0, b1) = self.extent(a), self.extent(b)
                if a0 <= b1 and b0 <= a1:
                    raise ConfigError(
                        f"{join(where, b)} ({b0}-{b1}) overlaps {join(where, a)} ({a0}-{a1})"
                    )
        r0, rn = self.robot_block
        h0, hn = self.host_block
        for name in HOST_FIELDS:
            f0, f1 = self.extent(name)
            if f0 <= r0 + rn - 1 and r0 <= f1:
                raise ConfigError(
                    f"{join(where, name)} ({f0}-{f1}) lies inside the robot->host block {r0}-{r0 + rn - 1}; "
                    "host fields must be outside it (the host writes its block in one go)"
                )
        for name in ROBOT_FIELDS:
            f0, f1 = self.extent(name)
            if f0 <= h0 + hn - 1 and h0 <= f1:
                raise ConfigError(
                    f"{join(where, name)} ({f0}-{f1}) lies inside the host->robot block {h0}-{h0 + hn - 1}; "
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
        return load_dataclass(cls, d, where)

    def as_table(self) -> list[tuple[str, int, int, str]]:
        """(field, first, last, direction) rows, sorted by address (used by docs and tests)."""
        rows = [(n, *self.extent(n), "robot->host" if n in ROBOT_FIELDS else "host->robot") for n in FIELD_WIDTH]
        return sorted(rows, key=lambda r: r[1])


@dataclass(frozen=True)
class RobotSideStatus:
    """The robot-side program's view, decoded from the user area (for diagnostics)."""

    counter: int
    flags: RobotFlags
    host_seq_echo: int
    lease_holder: int = 0  # unsigned 32-bit token of the host holding control; 0: nobody
    lease_age_s: float = 0.0  # since the holder last renewed its lease


def token_text(token: int) -> str:
    """A host token as the operator reads it in messages and logs."""
    return f"0x{token & 0xFFFFFFFF:08x}"
