"""`spiral_search`: press along a direction with a force while the reference spirals out in the plane
across it, until the tool sinks by a depth (a hole found) or the pressing force drops, or the radius is spent."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from cell.control.impedance import ImpedanceParams
from cell.control.loop import Observation
from drivers.configio import require
from tasks.primitives.base import Common, Context, ForceRegulation, Primitive, StepOut, base_wrench, unit


@dataclass(kw_only=True)
class SpiralSearchParams(Common):
    """Archimedean spiral r = pitch_m * turns in the plane normal to `direction` (base frame: where the tool
    presses), at `speed_mps` along the spiral, pressing with `force_n` along `direction`.  Ends found when
    the measured TCP has sunk `depth_m` along `direction` from where it started, or (with `force_below_n`)
    when the pressing force falls under it; not found at `max_radius_m` (then `on_not_found`)."""

    direction: list[float] = field(default_factory=lambda: [0.0, 0.0, -1.0])
    force_n: float = 10.0
    pitch_m: float = 0.001
    max_radius_m: float = 0.005
    speed_mps: float = 0.005
    depth_m: float = 0.002
    force_below_n: float | None = None
    max_speed_mps: float = 0.01
    impedance: ImpedanceParams = field(default_factory=lambda: ImpedanceParams(m=1.0, b=50.0, k_tau=0.05))
    on_not_found: Literal["fail", "continue"] = "fail"

    def validate(self, where: str) -> None:
        super().validate(where)
        unit(self.direction, f"{where}.direction")
        require(self.force_n > 0, f"{where}.force_n", "must be > 0 N")
        require(0 < self.pitch_m <= 0.01, f"{where}.pitch_m", "must lie in (0, 0.01] m")
        require(self.pitch_m < self.max_radius_m <= 0.05, f"{where}.max_radius_m", "must lie in (pitch_m, 0.05] m")
        require(0 < self.speed_mps <= 0.05, f"{where}.speed_mps", "must lie in (0, 0.05] m/s")
        require(0 < self.depth_m <= 0.05, f"{where}.depth_m", "must lie in (0, 0.05] m")
        require(self.force_below_n is None or 0 < self.force_below_n < self.force_n, f"{where}.force_below_n",
                "must lie between 0 and force_n")
        require(0 < self.max_speed_mps <= 0.1, f"{where}.max_speed_mps", "must lie in (0, 0.1] m/s")

    def peak_force(self) -> float:
        return self.force_n


class SpiralSearch(Primitive):
    kind = "spiral_search"
    contact = True
    regulates = True

    def start(self, ctx: Context, obs: Observation) -> None:
        p: SpiralSearchParams = self.params
        n = unit(p.direction, "direction")
        a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(n, a)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        self.R = np.column_stack([e1, e2, n])  # frame z: the pressing direction
        speed = np.array([p.max_speed_mps] * 3 + [0.1] * 3)
        self.reg = ForceRegulation(self.R, np.array([0, 0, 1, 0, 0, 0], bool),
                                   np.array([0.0, 0.0, p.force_n, 0, 0, 0]), p.impedance, ctx.dt, speed)
        ctx.regulation = None
        self.centre = ctx.ref.translation.copy()
        self.start_depth = float(n @ ctx.tcp(obs).translation)
        self.theta = 0.0
        self.offset = np.zeros(3)

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        p: SpiralSearchParams = self.params
        tcp = ctx.tcp(obs)
        n = self.R[:, 2]
        # Advance the angle so that the speed along the spiral is speed_mps: ds = sqrt(r^2 + (dr/dtheta)^2) dtheta.
        b = p.pitch_m / (2 * np.pi)
        r = b * self.theta
        self.theta += p.speed_mps * ctx.dt / max(np.hypot(r, b), 1e-6)
        r = b * self.theta
        offset = r * (np.cos(self.theta) * self.R[:, 0] + np.sin(self.theta) * self.R[:, 1])
        ctx.ref.translation = ctx.ref.translation + (offset - self.offset)
        self.offset = offset
        e = self.reg.step(ctx.ref, base_wrench(ctx, obs, tcp))
        log = self.reg.log(e, tcp)
        sunk = float(n @ tcp.translation) - self.start_depth
        f = float(self.reg.setpoint()[2] - e[2])
        found = sunk >= p.depth_m or (p.force_below_n is not None and self.reg.t > 0.5 and np.isfinite(f)
                                      and f < p.force_below_n)
        if found:
            # contact_point_m: where it was found, for a `report` (as a guarded move's contact point).
            self.result = {"found": True, "offset_m": offset.tolist(), "radius_m": float(r), "sunk_m": sunk,
                           "point_m": tcp.translation.tolist(), "contact_point_m": tcp.translation.tolist()}
            ctx.ref.translation = tcp.translation.copy()
            return StepOut(q=ctx.track(obs), finished=True, log=log)
        if r >= p.max_radius_m:
            self.result = {"found": False, "radius_m": float(r)}
            failed = f"spiral search found nothing within {p.max_radius_m * 1e3:.1f} mm" \
                if p.on_not_found == "fail" else ""
            return StepOut(q=ctx.track(obs), finished=True, failed=failed, log=log)
        return StepOut(q=ctx.track(obs), log=log)
