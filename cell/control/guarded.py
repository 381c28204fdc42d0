"""Guarded motion: the highest speed at which an unplanned head-on contact stays under a force limit,
and the check of a task's contact-approach speeds against it.

A position-controlled arm meeting a stiff surface feels an impact force that grows with its speed
(the transient is over before any detector acts, so detecting faster does not lower it):
F_peak ~ impact_n_per_mps x v.  `main.py bench collision` measures the coefficient on rigid plates
(its `rigid_impact_n_per_mps_p95`); the cell's configured value is that measurement.  A task's speeds
toward a surface whose position is not known better than the speed's own stopping distance must stay
under limit / coefficient.  Moves that keep a margin above every surface larger than its uncertainty
(e.g. the peg's survey moves between touch points) and sliding contacts are not head-on and are not
bounded here.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.configio import require
from drivers.errors import ConfigError


@dataclass
class GuardedSettings:
    """`collision.guarded`: the measured impact coefficient and whether the tasks' speeds are held to it."""

    enabled: bool = True
    # Peak contact force per unit TCP speed on a rigid obstacle (N per m/s): bench collision's p95
    # over rigid-plate impacts at 0.05-0.5 m/s (why: docs/collision.md, "Guarded motion").
    impact_n_per_mps: float = 9300.0

    def validate(self, where: str) -> None:
        require(100 <= self.impact_n_per_mps <= 1e6, f"{where}.impact_n_per_mps", "must lie in [100, 1e6] N/(m/s)")

    def speed_bound(self, limit_n: float) -> float:
        """m/s: the head-on speed whose impact stays under `limit_n`."""
        return limit_n / self.impact_n_per_mps


def check_speeds(settings: GuardedSettings, speeds: dict[str, float], limit_n: float, where: str) -> float:
    """Each named head-on speed (m/s) within the bound for `limit_n` N, else a ConfigError naming the
    first one over it; returns the bound."""
    bound = settings.speed_bound(limit_n)
    if not settings.enabled:
        return bound
    for name, v in speeds.items():
        if v > bound * (1 + 1e-9):
            raise ConfigError(
                f"{where}.{name}: {v * 1e3:.1f} mm/s is faster than guarded motion allows ({bound * 1e3:.1f} mm/s): "
                f"an unplanned rigid contact at it would exceed the task's {limit_n:.0f} N limit "
                f"(collision.guarded.impact_n_per_mps {settings.impact_n_per_mps:.0f} N per m/s)")
    return bound
