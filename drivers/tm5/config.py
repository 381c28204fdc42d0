"""The arm's settings (`devices.arm.settings`): how to reach the TM5 controller and how strict to be, bounded."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from drivers.configio import join, load_dataclass, require
from drivers.tm5.contract import UserAreaLayout

# A stale limit shorter than this many control periods trips on the normal jitter of a host-paced read
# against the controller's own cycle.
MIN_STALE_PERIODS = 3

# (least, most, why): the range every time setting must lie in [s].  The upper bounds keep a dead link
# or a stalled robot-side program from going unnoticed for longer than a person can react to it.
TIME_BOUNDS: dict[str, tuple[float, float, str]] = {
    "timeout_s": (0.001, 1.0, "the control loop waits this long on a dead link"),
    "stale_after_s": (0.001, 1.0, "the arm runs on frozen data this long"),
    "reconnect_initial_s": (0.001, 1.0, "the first retry after a lost link"),
    "reconnect_max_s": (0.001, 10.0, "the longest wait between reconnect attempts"),
    "arm_timeout_s": (0.01, 10.0, "arming waits this long for the link and the acknowledgement"),
}


def _number(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def check_stale_periods(stale_after_s: float, dt: float, where: str) -> None:
    """An arm's stale-data limit is at least MIN_STALE_PERIODS control periods `dt` [s], on either route."""
    least = MIN_STALE_PERIODS * dt
    require(stale_after_s >= least - 1e-12, join(where, "stale_after_s"),
            f"must be >= {MIN_STALE_PERIODS} control periods ({least:g} s at {dt:g} s), got {stale_after_s!r}")


@dataclass(frozen=True)
class TM5ModbusConfig:
    """How to reach the controller and how strict to be about it (the `devices.arm.settings`)."""

    host: str
    port: int = 502
    unit_id: int = 1
    timeout_s: float = 0.01  # per Modbus transaction and per connect attempt
    stale_after_s: float = 0.05  # robot counter not advancing this long -> StaleDataError
    reconnect_initial_s: float = 0.05  # backoff between reconnect attempts: doubles up to reconnect_max_s
    reconnect_max_s: float = 2.0
    arm_timeout_s: float = 1.0  # arm(): time to get the link back, the control lease and the acknowledgement
    stop_coil: bool = False  # also pulse coil 7105 on stop (ends the robot project: operator must restart)
    user_area: UserAreaLayout = field(default_factory=UserAreaLayout)

    def validate(self, where: str = "devices.arm.settings") -> None:
        """Every setting typed and in range; raises ConfigError naming the first offending key."""
        def need(cond: bool, name: str, message: str) -> None:
            require(cond, join(where, name), f"{message}, got {getattr(self, name)!r}")

        need(isinstance(self.host, str) and bool(self.host.strip()), "host", "must be the controller's address")
        for name, (lo, hi) in (("port", (1, 65535)), ("unit_id", (0, 255))):
            value = getattr(self, name)
            need(not isinstance(value, bool) and isinstance(value, int), name, "must be an integer")
            need(lo <= value <= hi, name, f"must lie in {lo}-{hi}")
        for name, (least, most, why) in TIME_BOUNDS.items():
            value = getattr(self, name)
            need(_number(value), name, "must be a finite number of seconds")
            need(least <= value <= most, name, f"must lie in {least:g}-{most:g} s ({why})")
        need(self.reconnect_max_s >= self.reconnect_initial_s, "reconnect_max_s", "must be >= reconnect_initial_s")
        need(isinstance(self.stop_coil, bool), "stop_coil", "must be true or false")
        need(isinstance(self.user_area, UserAreaLayout), "user_area", "must be a mapping of field -> address")
        self.user_area.validate(join(where, "user_area"))

    def check_period(self, dt: float, where: str = "devices.arm.settings") -> None:
        """The settings that depend on the control period `dt` [s]: stale data is a few periods at least."""
        check_stale_periods(self.stale_after_s, dt, where)

    @classmethod
    def from_dict(cls, d: Any, where: str) -> TM5ModbusConfig:
        """Typed and validated from a `devices.arm.settings` mapping (ConfigError naming the key otherwise)."""
        return load_dataclass(cls, d, where)
