"""Force primitives: `guarded_move` (along a direction until a force or a distance) and `force_mode`
(force on selected axes, position on the others)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from cell.control.impedance import ImpedanceParams
from cell.control.loop import Observation
from cell.control.trajectory import PathProfile
from drivers.configio import require
from tasks.primitives.base import (
    Common,
    Context,
    ForceRegulation,
    Frame,
    Primitive,
    StepOut,
    base_wrench,
    frame_rotation,
    unit,
)


@dataclass(kw_only=True)
class GuardedMoveParams(Common):
    """Move the reference along `direction` (base frame, or the tool's) at `speed_mps` until the force the
    tool exerts along it exceeds `force_n` (`confirm_cycles` readings in a row), or `max_distance_m`,
    whichever first.  The contact point is the measured TCP's farthest point along the direction, plus
    `probe_offset_m` (from the TCP to the touching surface of the tool, e.g. a peg's radius for a side touch).
    The reference never leads the measured TCP by more than `max_lead_m`: a stiff contact then presses with
    the servo's stiffness over that lead only, not over the detection delay's travel.  After a contact the
    tool backs off by `retreat_m`."""

    direction: list[float]
    speed_mps: float
    force_n: float
    max_distance_m: float
    frame: Frame = "base"
    probe_offset_m: float = 0.0
    confirm_cycles: int = 2
    max_lead_m: float = 0.0005
    retreat_m: float = 0.0
    retreat_speed_mps: float = 0.005
    on_no_contact: Literal["fail", "continue"] = "fail"

    def validate(self, where: str) -> None:
        super().validate(where)
        unit(self.direction, f"{where}.direction")
        require(0 < self.speed_mps <= 0.05, f"{where}.speed_mps", f"must lie in (0, 0.05] m/s, got {self.speed_mps}")
        require(self.force_n > 0, f"{where}.force_n", f"must be > 0 N, got {self.force_n}")
        require(0 < self.max_distance_m <= 0.5, f"{where}.max_distance_m", "must lie in (0, 0.5] m")
        require(0 <= self.probe_offset_m <= 0.1, f"{where}.probe_offset_m", "must lie in [0, 0.1] m")
        require(1 <= self.confirm_cycles <= 50, f"{where}.confirm_cycles", "must lie in [1, 50]")
        require(0 < self.max_lead_m <= 0.01, f"{where}.max_lead_m", "must lie in (0, 0.01] m")
        require(0 <= self.retreat_m <= 0.05, f"{where}.retreat_m", "must lie in [0, 0.05] m")
        require(0 < self.retreat_speed_mps <= 0.05, f"{where}.retreat_speed_mps", "must lie in (0, 0.05] m/s")


class GuardedMove(Primitive):
    kind = "guarded_move"
    contact = True

    def start(self, ctx: Context, obs: Observation) -> None:
        p: GuardedMoveParams = self.params
        ctx.regulation = None
        tcp = ctx.tcp(obs)
        d = unit(p.direction, "direction")
        self.u = d if p.frame == "base" else tcp.rotation @ d
        self.origin = ctx.ref.translation.copy()
        self.start_tcp = tcp.translation.copy()
        self.farthest = float(self.u @ tcp.translation)
        self.count = 0
        self.phase = "move"
        self.contact_at: np.ndarray | None = None
        self.retreat_from = 0.0

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        p: GuardedMoveParams = self.params
        tcp = ctx.tcp(obs)
        along = float(self.u @ tcp.translation)
        f = float(self.u @ base_wrench(ctx, obs, tcp)[:3])
        log: dict[str, float | str] = {"f_along": f}
        if self.phase == "move":
            self.farthest = max(self.farthest, along)
            self.count = self.count + 1 if np.isfinite(f) and f > p.force_n else 0
            if self.count >= p.confirm_cycles:
                # Stop pressing: the reference goes back to where the tool is.
                ctx.ref.translation = tcp.translation.copy()
                point = tcp.translation + (self.farthest - along) * self.u + p.probe_offset_m * self.u
                self.contact_at = point
                self.result = {"contact": True, "contact_point_m": point.tolist(), "force_n": f,
                               "distance_m": float(self.farthest - self.u @ self.start_tcp), "t_s": t}
                if p.retreat_m <= 0:
                    return StepOut(q=ctx.track(obs), finished=True, log=log)
                self.phase, self.retreat_from = "retreat", float(self.u @ ctx.ref.translation)
                return StepOut(q=ctx.track(obs), log=log)
            travelled = float(self.u @ (ctx.ref.translation - self.origin))
            if travelled >= p.max_distance_m:
                self.result = {"contact": False, "distance_m": travelled}
                failed = (f"no contact within {p.max_distance_m * 1e3:.1f} mm" if p.on_no_contact == "fail" else "")
                return StepOut(q=ctx.track(obs), finished=True, failed=failed, log=log)
            lead = float(self.u @ ctx.ref.translation) - along
            step = min(p.speed_mps * ctx.dt, max(0.0, p.max_lead_m - lead))
            ctx.ref.translation = ctx.ref.translation + step * self.u
            return StepOut(q=ctx.track(obs), log=log)
        # Retreat: back along the direction, then done.
        ctx.ref.translation = ctx.ref.translation - p.retreat_speed_mps * ctx.dt * self.u
        done = self.retreat_from - float(self.u @ ctx.ref.translation) >= p.retreat_m
        return StepOut(q=ctx.track(obs), finished=done, log=log)


@dataclass(kw_only=True)
class EndCondition:
    """A force_mode ends on the first of: `time_s`; `distance_m` (the position axes' motion done);
    `force_above_n` (the force along the first regulated axis's magnitude) ; `settled_n` (the regulated
    error within this for `settled_s`).  `max_time_s` bounds any of them (then `on_timeout`)."""

    time_s: float | None = None
    distance_m: float | None = None
    force_above_n: float | None = None
    settled_n: float | None = None
    settled_s: float = 0.5
    max_time_s: float = 60.0
    on_timeout: Literal["fail", "continue"] = "fail"

    def validate(self, where: str) -> None:
        given = [k for k in ("time_s", "distance_m", "force_above_n", "settled_n") if getattr(self, k) is not None]
        require(len(given) >= 1, where, "needs one of time_s, distance_m, force_above_n, settled_n")
        for k in given:
            require(getattr(self, k) > 0, f"{where}.{k}", "must be > 0")
        require(0 < self.max_time_s <= 600, f"{where}.max_time_s", "must lie in (0, 600] s")
        require(self.settled_s > 0, f"{where}.settled_s", "must be > 0 s")


@dataclass(kw_only=True)
class ForceModeParams(Common):
    """`selection` (6 of 0/1: Fx Fy Fz Mx My Mz in `frame`): the axes that regulate `wrench` (the wrench the
    tool exerts: pressing down on a table is Fz = -F in the base frame); the others follow `move_by`
    (a displacement [m], base frame, at `speed_mps`) or hold.  `max_speed_mps` / `max_speed_dps` cap the
    compliant axes' motion.  `ramp_s`: the setpoint ramps from the measured wrench to `wrench` over it."""

    selection: list[int]
    wrench: list[float]
    end: EndCondition
    frame: Frame = "base"
    move_by: list[float] | None = None
    speed_mps: float = 0.02
    accel_mps2: float = 0.1
    max_speed_mps: float = 0.02
    max_speed_dps: float = 10.0
    ramp_s: float = 0.0
    impedance: ImpedanceParams = field(default_factory=lambda: ImpedanceParams(m=1.0, b=50.0, k_tau=0.05))
    keep: bool = True  # a following `hold` keeps regulating this wrench

    def validate(self, where: str) -> None:
        super().validate(where)
        require(len(self.selection) == 6 and all(s in (0, 1) for s in self.selection), f"{where}.selection",
                f"must be 6 values of 0 or 1 (Fx Fy Fz Mx My Mz), got {self.selection}")
        require(any(self.selection), f"{where}.selection", "selects no axis: use move instead")
        require(len(self.wrench) == 6, f"{where}.wrench", "must be [Fx, Fy, Fz, Mx, My, Mz] (N, N m)")
        require(self.move_by is None or len(self.move_by) == 3, f"{where}.move_by", "must be [dx, dy, dz] in m")
        if self.move_by is not None:
            free = np.asarray(self.move_by, float) @ np.asarray(self.selection[:3], float)
            require(abs(free) < 1e-12 or self.frame == "tool", f"{where}.move_by",
                    "moves along a force-regulated axis: that axis follows the force, not a position")
        require(0 < self.speed_mps <= 0.25, f"{where}.speed_mps", "must lie in (0, 0.25] m/s")
        require(0 < self.accel_mps2 <= 2, f"{where}.accel_mps2", "must lie in (0, 2] m/s^2")
        require(0 < self.max_speed_mps <= 0.1, f"{where}.max_speed_mps", "must lie in (0, 0.1] m/s")
        require(0 < self.max_speed_dps <= 30, f"{where}.max_speed_dps", "must lie in (0, 30] deg/s")
        require(0 <= self.ramp_s <= 30, f"{where}.ramp_s", "must lie in [0, 30] s")

    def peak_force(self) -> float:
        return float(np.linalg.norm(np.asarray(self.wrench[:3]) * np.asarray(self.selection[:3])))


class ForceMode(Primitive):
    kind = "force_mode"
    contact = True
    regulates = True

    def start(self, ctx: Context, obs: Observation) -> None:

        p: ForceModeParams = self.params
        tcp = ctx.tcp(obs)
        R = frame_rotation(p.frame, tcp)
        sel = np.asarray(p.selection, bool)
        w0 = base_wrench(ctx, obs, tcp)
        start = np.where(np.isfinite(w0), np.concatenate([R.T @ w0[:3], R.T @ w0[3:]]), 0.0)
        speed = np.array([p.max_speed_mps] * 3 + [np.radians(p.max_speed_dps)] * 3)
        self.reg = ForceRegulation(R, sel, np.asarray(p.wrench, float), p.impedance, ctx.dt, speed, p.ramp_s,
                                   start if p.ramp_s > 0 else None)
        ctx.regulation = self.reg if p.keep else None
        self.origin = ctx.ref.translation.copy()
        self.path: PathProfile | None = None
        if p.move_by is not None and np.linalg.norm(p.move_by) > 0:
            self.path = PathProfile(np.array([[0.0], [float(np.linalg.norm(p.move_by))]]), p.speed_mps, p.accel_mps2)
            self.dir = np.asarray(p.move_by, float) / np.linalg.norm(p.move_by)
        self.moved = 0.0
        self.t_settled = 0.0

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        p: ForceModeParams = self.params
        end = p.end
        tcp = ctx.tcp(obs)
        w = base_wrench(ctx, obs, tcp)
        path_done = self.path is None
        if self.path is not None:
            s, path_done = self.path.at(t)
            ds = float(s[0]) - self.moved
            self.moved = float(s[0])
            ctx.ref.translation = ctx.ref.translation + ds * self.dir
        e = self.reg.step(ctx.ref, w)
        log = self.reg.log(e, tcp)
        i = self.reg.primary_axis()
        finished, failed = False, ""
        if end.time_s is not None and t + ctx.dt >= end.time_s:
            finished = True
        if end.distance_m is not None and (self.moved >= end.distance_m or (self.path is not None and path_done)):
            finished = True
        measured = float(self.reg.setpoint()[i] - e[i])
        if end.force_above_n is not None and np.isfinite(measured) and abs(measured) > end.force_above_n:
            finished = True
        if end.settled_n is not None and np.isfinite(e[i]):
            full = self.reg.ramp_s <= 0 or self.reg.t >= self.reg.ramp_s
            self.t_settled = self.t_settled + ctx.dt if full and abs(e[i]) < end.settled_n else 0.0
            finished = finished or self.t_settled >= end.settled_s
        if not finished and t + ctx.dt >= end.max_time_s:
            finished = True
            if end.on_timeout == "fail":
                failed = f"force mode did not reach its end condition within {end.max_time_s:g} s"
        if finished:
            self.result = {"moved_m": self.moved, "t_s": t + ctx.dt,
                           "end_force_n": float(self.reg.setpoint()[i] - e[i])}
        return StepOut(q=ctx.track(obs), finished=finished, failed=failed, log=log)
