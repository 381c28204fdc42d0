"""Settings of a WACOH sensor (`devices.sensor.settings`): each one bounded, loaded with drivers/configio."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from drivers.configio import describe, integer_in, join, load_dataclass, number_in, number_near, one_of
from drivers.errors import ConfigError
from drivers.wacoh.codec import (
    AXIS_NAMES,
    FILTER_SETTINGS,
    MODEL_SENSITIVITIES,
    MODEL_SPREAD,
    N_CHANNELS,
    SENSITIVITY_TOLERANCE,
    Sensitivities,
)

TareMode = Literal["sensor", "software"]
ReadMode = Literal["poll", "stream"]

# The family's variants run at 9600, 115200 and 921600 bit/s; USB-serial adapters stop near 3 Mbit/s.
BAUDRATE_RANGE = (9600, 3_000_000)
# A record is 0.29 ms on the wire at 921600 bit/s, plus the adapter's latency: 1 ms is the least a reply
# can be given.  Beyond 1 s a silent sensor would hold the control loop for over a hundred periods.
TIMEOUT_RANGE_S = (0.001, 1.0)
MAX_TARE_SAMPLES = 10_000  # 10 s of records at 1 kHz; the tare blocks the cell while it averages
MAX_FAILURES = 100  # reads in a row without a record: beyond this a dead sensor goes unnoticed too long
# The `p` band: at least the reply's resolution (3 decimals of ~32.8), at most what `doctor` accepts.
TOLERANCE_RANGE = (0.001, 0.05)
_SENSITIVITY_FIELDS = ("sensitivities", "nominal_sensitivities")
_MODEL = "the model's nominal"
_NOMINAL = "nominal_sensitivities"


def _port(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{key} must be a non-empty string (e.g. /dev/ttyUSB0), got {describe(value)}")
    return value


def _near(values: Any, key: str, reference: Sequence[float], rel_tol: float, against: str) -> tuple[float, ...]:
    """Six numbers, each within `rel_tol` of its `reference` value (`against` names it); ConfigError naming
    the axis otherwise."""
    if isinstance(values, Sensitivities):
        values = values.values
    if not isinstance(values, list | tuple) or len(values) != N_CHANNELS:
        raise ConfigError(f"{key} must be a list of 6 numbers [Fx, Fy, Fz in LSB/N, Mx, My, Mz in LSB/(N·m)], "
                          f"got {describe(values)}")
    return tuple(number_near(v, f"{key}[{i}] ({axis}, against {against})", ref, rel_tol)
                 for i, (v, ref, axis) in enumerate(zip(values, reference, AXIS_NAMES, strict=True)))


@dataclass
class WacohConfig:
    """Settings of one WACOH sensor (YAML keys are the field names)."""

    port: str  # pyserial port or URL, e.g. /dev/ttyUSB0
    baudrate: int = 921600
    timeout_s: float = 0.05  # per request (plus the reply's time on the wire)
    # The unit's calibration sheet: Fx, Fy, Fz then Mx, My, Mz, within `sensitivity_tolerance` of
    # `nominal_sensitivities`.  When set, a `p` reply is believed only within SHEET_TOLERANCE of it (the
    # only check that catches a corrupted digit inside the band) and it is used when `p` is not believed;
    # None: no sheet, `p` is checked against the band only and `nominal_sensitivities` is the fallback.
    sensitivities: Sensitivities | None = None
    tare: TareMode = "software"  # "sensor": `O` x3 in the sensor; "software": mean of tare_samples
    tare_samples: int = 50
    filter: int | None = None  # sensor moving average over 1/2/4/8 samples; None leaves it as it is
    mode: ReadMode = "poll"  # "poll": one `R` per read; "stream": `S`, keep the latest record
    max_consecutive_failures: int = 10  # reads in a row with no valid record before LinkLostError

    # Without a sheet, a `p` reply is believed only if every value lies within `sensitivity_tolerance`
    # (relative) of these (by default the model's 32.8 LSB/N and 1638 LSB/(N·m); a unit further off: its
    # calibration sheet, within 10 % of the model's) and two replies agree; else these are used.
    nominal_sensitivities: Sensitivities = field(default_factory=Sensitivities)
    sensitivity_tolerance: float = SENSITIVITY_TOLERANCE

    def validate(self, where: str = "WacohConfig") -> None:
        """ConfigError naming the first field out of its type or range."""
        _port(self.port, join(where, "port"))
        integer_in(self.baudrate, join(where, "baudrate"), *BAUDRATE_RANGE)
        number_in(self.timeout_s, join(where, "timeout_s"), *TIMEOUT_RANGE_S, unit=" s")
        one_of(self.tare, join(where, "tare"), ("sensor", "software"))
        integer_in(self.tare_samples, join(where, "tare_samples"), 1, MAX_TARE_SAMPLES)
        if self.filter is not None:
            one_of(self.filter, join(where, "filter"), FILTER_SETTINGS)
        one_of(self.mode, join(where, "mode"), ("poll", "stream"))
        integer_in(self.max_consecutive_failures, join(where, "max_consecutive_failures"), 1, MAX_FAILURES)
        number_in(self.sensitivity_tolerance, join(where, "sensitivity_tolerance"), *TOLERANCE_RANGE)
        nominal = _near(self.nominal_sensitivities, join(where, "nominal_sensitivities"),
                        MODEL_SENSITIVITIES.values, MODEL_SPREAD, _MODEL)
        if self.sensitivities is not None:
            _near(self.sensitivities, join(where, "sensitivities"), nominal, self.sensitivity_tolerance, _NOMINAL)

    @property
    def fallback_sensitivities(self) -> Sensitivities:
        """What is used when `p` is missing or not believed: the sheet, else the nominal values."""
        return self.sensitivities if self.sensitivities is not None else self.nominal_sensitivities

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, where: str) -> WacohConfig:
        """Build from a config mapping; ConfigError('<where>.<field> must be ..., got ...') on any bad value."""
        if d is not None and not isinstance(d, Mapping):
            raise ConfigError(f"{where} must be a mapping, got {describe(d)}")
        d = dict(d or {})
        # The shared loader reads every other field (types, unknown and missing keys, `validate`); the
        # sensitivities are written as plain lists of six, which it has no type for.
        lists = {name: d.pop(name) for name in _SENSITIVITY_FIELDS if name in d}
        cfg = load_dataclass(cls, d, where)
        nominal = _near(lists.get("nominal_sensitivities", cfg.nominal_sensitivities),
                        join(where, "nominal_sensitivities"), MODEL_SENSITIVITIES.values, MODEL_SPREAD, _MODEL)
        sheet = lists.get("sensitivities", cfg.sensitivities)
        if sheet is not None:
            sheet = Sensitivities.from_values(_near(sheet, join(where, "sensitivities"), nominal,
                                                    cfg.sensitivity_tolerance, _NOMINAL))
        return dataclasses.replace(cfg, nominal_sensitivities=Sensitivities.from_values(nominal), sensitivities=sheet)
