"""Position primitives: `move` (joint or Cartesian), `hold`, `wait`, `tare`, and `report` (a point from
named steps' results)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pinocchio as pin

from cell.control.loop import Observation
from cell.control.trajectory import QUINTIC_PEAK_SPEED, JointMove, quintic_blend
from drivers.configio import require
from tasks.primitives.base import Common, Context, Primitive, StepOut, base_wrench

MIN_MOVE_S = 0.2


@dataclass(kw_only=True)
class MoveParams(Common):
    """`to`: a named pose (or an inline {xyz, rpy_deg}); `by`: a displacement [m] of the reference (base
    frame).  `space`: cartesian (a straight line) or joint (quintic in joint space; `to` only)."""

    to: str | None = None
    by: list[float] | None = None
    space: Literal["cartesian", "joint"] = "cartesian"
    speed_mps: float = 0.05  # Cartesian: peak TCP speed
    angular_speed_dps: float = 30.0  # Cartesian: peak rotation speed [deg/s]
    speed_fraction: float = 0.15  # joint: of the joint speed limits

    def validate(self, where: str) -> None:
        super().validate(where)
        require((self.to is None) != (self.by is None), f"{where}", "needs exactly one of `to` (a pose) and `by`")
        require(self.by is None or len(self.by) == 3, f"{where}.by", "must be [dx, dy, dz] in m")
        require(self.by is None or self.space == "cartesian", f"{where}.space", "joint moves need `to`")
        require(0 < self.speed_mps <= 0.25, f"{where}.speed_mps", f"must lie in (0, 0.25] m/s, got {self.speed_mps}")
        require(0 < self.angular_speed_dps <= 90, f"{where}.angular_speed_dps", "must lie in (0, 90] deg/s")
        require(0 < self.speed_fraction <= 0.5, f"{where}.speed_fraction", "must lie in (0, 0.5]")


class Move(Primitive):
    kind = "move"

    def start(self, ctx: Context, obs: Observation) -> None:
        p: MoveParams = self.params
        ctx.regulation = None
        self.q0 = np.asarray(obs.q_cmd, float)
        self.joint: JointMove | None = None
        if p.space == "joint":
            assert p.to is not None
            target = ctx.poses[p.to]
            q1, ok = ctx.robot.ik(target, self.q0)
            if not ok:
                raise ValueError(f"pose '{p.to}' is not reachable")
            self.joint = JointMove(self.q0, q1, ctx.robot.limits.velocity * p.speed_fraction)
            self.target = target
            self.duration = self.joint.duration
            return
        self.p0 = ctx.ref.copy()
        if p.by is not None:
            self.target = pin.SE3(self.p0.rotation.copy(), self.p0.translation + np.asarray(p.by, float))
        else:
            assert p.to is not None
            self.target = ctx.poses[p.to]
        dist = float(np.linalg.norm(self.target.translation - self.p0.translation))
        self.rot = pin.log3(self.p0.rotation.T @ self.target.rotation)
        angle = float(np.linalg.norm(self.rot))
        self.duration = max(MIN_MOVE_S, QUINTIC_PEAK_SPEED * dist / p.speed_mps,
                            QUINTIC_PEAK_SPEED * angle / np.radians(p.angular_speed_dps))

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        done = t >= self.duration
        if self.joint is not None:
            q = self.joint.at(t)
            if done:
                ctx.ref = ctx.robot.tcp_pose(self.joint.q1)
            return StepOut(q=q, finished=done)
        s = float(quintic_blend(min(t / self.duration, 1.0)))
        ctx.ref = pin.SE3(self.p0.rotation @ pin.exp3(s * self.rot),
                          self.p0.translation + s * (self.target.translation - self.p0.translation))
        return StepOut(q=ctx.track(obs), finished=done)


@dataclass(kw_only=True)
class HoldParams(Common):
    """Stay for `time_s`: at the reference, or, right after a force_mode, regulating its wrench setpoint."""

    time_s: float

    def validate(self, where: str) -> None:
        super().validate(where)
        require(0 < self.time_s <= 600, f"{where}.time_s", f"must lie in (0, 600] s, got {self.time_s}")


class Hold(Primitive):
    kind = "hold"

    def start(self, ctx: Context, obs: Observation) -> None:
        self.regulation = ctx.regulation
        self.contact = self.regulates = self.regulation is not None

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        out: dict[str, float | str] = {}
        if self.regulation is not None:
            tcp = ctx.tcp(obs)
            e = self.regulation.step(ctx.ref, base_wrench(ctx, obs, tcp))
            out = self.regulation.log(e, tcp)
        return StepOut(q=ctx.track(obs), finished=t + ctx.dt >= self.params.time_s, log=out)


@dataclass(kw_only=True)
class WaitParams(Common):
    """Stay still until `time_s` has passed, or (with `until_force_n`) until the tool force exceeds it
    (e.g. an operator's tap): then `timeout_s` bounds the wait and `on_timeout` says what follows."""

    time_s: float | None = None
    until_force_n: float | None = None
    timeout_s: float = 30.0
    on_timeout: Literal["fail", "continue"] = "fail"

    def validate(self, where: str) -> None:
        super().validate(where)
        require((self.time_s is None) != (self.until_force_n is None), where,
                "needs exactly one of `time_s` and `until_force_n`")
        require(self.time_s is None or 0 < self.time_s <= 600, f"{where}.time_s", "must lie in (0, 600] s")
        require(self.until_force_n is None or self.until_force_n > 0, f"{where}.until_force_n", "must be > 0 N")
        require(0 < self.timeout_s <= 600, f"{where}.timeout_s", "must lie in (0, 600] s")


class Wait(Primitive):
    kind = "wait"

    def start(self, ctx: Context, obs: Observation) -> None:
        ctx.regulation = None

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        p: WaitParams = self.params
        q = ctx.track(obs)
        if p.time_s is not None:
            return StepOut(q=q, finished=t + ctx.dt >= p.time_s)
        assert p.until_force_n is not None
        f = float(np.linalg.norm(np.asarray(obs.wrench.force, float)))
        if np.isfinite(f) and f > p.until_force_n:
            self.result = {"force_n": f, "t_s": t}
            return StepOut(q=q, finished=True)
        if t + ctx.dt >= p.timeout_s:
            self.result = {"timed_out": True}
            failed = f"no force above {p.until_force_n:g} N within {p.timeout_s:g} s" if p.on_timeout == "fail" else ""
            return StepOut(q=q, finished=True, failed=failed)
        return StepOut(q=q)


@dataclass(kw_only=True)
class TareParams(Common):
    """Rest `time_s` (the arm settles), then re-zero the force source: in free space only."""

    time_s: float = 0.3

    def validate(self, where: str) -> None:
        super().validate(where)
        require(0 < self.time_s <= 10, f"{where}.time_s", "must lie in (0, 10] s")


class Tare(Primitive):
    kind = "tare"

    def start(self, ctx: Context, obs: Observation) -> None:
        ctx.regulation = None

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        done = t + ctx.dt >= self.params.time_s
        return StepOut(q=ctx.track(obs), finished=done, rebias=done)


@dataclass(kw_only=True)
class ReportParams(Common):
    """A named point from earlier steps' results: each coordinate a number or '<step name>.<x|y|z>' (a
    guarded move's contact point).  `expect` and `tolerance_m`: the task fails when it lies farther away."""

    point: list[Any]
    expect: list[float] | None = None
    tolerance_m: float = 0.001
    truth: str | None = None  # a simulated cell's landmark to score it against (sim/landmarks.py)

    def validate(self, where: str) -> None:
        super().validate(where)
        require(self.name is not None, f"{where}.name", "is required (the report's key in the summary)")
        require(2 <= len(self.point) <= 3, f"{where}.point", "must have 2 or 3 coordinates")
        for i, c in enumerate(self.point):
            ok = (isinstance(c, int | float) and not isinstance(c, bool)) or (
                isinstance(c, str) and c.count(".") == 1 and c.rsplit(".", 1)[1] in ("x", "y", "z"))
            require(ok, f"{where}.point[{i}]", f"must be a number or '<step name>.x|y|z', got {c!r}")
        require(self.expect is None or len(self.expect) == len(self.point), f"{where}.expect",
                "must have as many coordinates as `point`")
        require(self.tolerance_m > 0, f"{where}.tolerance_m", "must be > 0 m")

    def references(self) -> list[str]:
        return [c.rsplit(".", 1)[0] for c in self.point if isinstance(c, str)]


class Report(Primitive):
    kind = "report"

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        p: ReportParams = self.params
        values: list[float] = []
        for c in p.point:
            if isinstance(c, str):
                step, axis = c.rsplit(".", 1)
                contact = ctx.results.get(step, {}).get("contact_point_m")
                if contact is None:
                    return StepOut(q=ctx.track(obs), finished=True, failed=f"report {p.name}: step '{step}' "
                                   "found no contact")
                values.append(float(contact["xyz".index(axis)]))
            else:
                values.append(float(c))
        self.result = {"point_m": values}
        failed = ""
        if p.expect is not None:
            err = float(np.linalg.norm(np.asarray(values) - np.asarray(p.expect, float)))
            self.result.update(expect_m=p.expect, error_m=err)
            if err > p.tolerance_m:
                failed = f"report {p.name}: {err * 1e3:.2f} mm from the expected point (tolerance " \
                         f"{p.tolerance_m * 1e3:g} mm)"
        return StepOut(q=ctx.track(obs), finished=True, failed=failed)


def describe_point(values: list[float]) -> str:
    return "(" + ", ".join(f"{v * 1e3:.2f}" for v in values) + ") mm"
