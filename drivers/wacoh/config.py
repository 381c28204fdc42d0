"""Settings of a WACOH sensor (`devices.sensor.settings`) and their validation."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Literal

from drivers.errors import ConfigError
from drivers.wacoh.codec import FILTER_SETTINGS, N_CHANNELS, SENSITIVITY_TOLERANCE, Sensitivities

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
