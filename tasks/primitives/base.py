"""What every primitive shares: the task file's running context, the step's output, common parameters,
and the force regulation that force_mode starts and hold carries on."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pinocchio as pin

from cell.control.impedance import DiscreteImpedance, ImpedanceParams
from cell.control.loop import Observation
from cell.model.robot import RobotModel
from drivers.configio import require

log = logging.getLogger(__name__)

Reaction = Literal["stop", "retract", "comply", "monitor"]
Frame = Literal["base", "tool"]


@dataclass(kw_only=True)
class Common:
    """Parameters every primitive takes.  `collision`: the reaction to a detected collision in this step
    (default: the task file's); `max_force_n`: the step aborts the task above this tool force (default:
    the task file's, never above the cell's safety limit)."""

    name: str | None = None
    collision: Reaction | None = None
    max_force_n: float | None = None

    def validate(self, where: str) -> None:
        require(self.max_force_n is None or self.max_force_n > 0, f"{where}.max_force_n", "must be > 0 N")


@dataclass
class StepOut:
    """One control period of a primitive: the joint target and whether the primitive has ended."""

    q: np.ndarray
    finished: bool = False
    failed: str = ""  # non-empty: the task fails with this reason
    rebias: bool = False
    log: dict[str, float | str] = field(default_factory=dict)


@dataclass
class Context:
    """What the primitives of one task file share while it runs."""

    robot: RobotModel
    dt: float
    poses: dict[str, pin.SE3]
    ref: pin.SE3 = field(default_factory=pin.SE3.Identity)  # the TCP reference, base frame
    results: dict[str, dict[str, Any]] = field(default_factory=dict)  # named steps' results
    regulation: ForceRegulation | None = None  # left active by force_mode for a following hold

    def track(self, obs: Observation) -> np.ndarray:
        """Joint target for the reference: a few damped Newton steps from the last command (as the wipe)."""
        q, _ = self.robot.ik(self.ref, obs.q_cmd, iters=3, tol=1e-7)
        return q

    def tcp(self, obs: Observation) -> pin.SE3:
        """The measured TCP pose (forward kinematics of the measured joints)."""
        return self.robot.tcp_pose(np.asarray(obs.state.q, float))


def base_wrench(ctx: Context, obs: Observation, tcp: pin.SE3) -> np.ndarray:
    """The wrench the tool exerts (cell convention), rotated from the tool frame into the base frame (6,);
    NaN when the force source had no reading."""
    w = np.asarray(obs.wrench.vector, float)
    R = tcp.rotation
    return np.concatenate([R @ w[:3], R @ w[3:]])


def unit(v: list[float] | np.ndarray, where: str) -> np.ndarray:
    a = np.asarray(v, float)
    n = float(np.linalg.norm(a))
    require(a.shape == (3,) and n > 1e-9, where, f"must be a non-zero 3-vector, got {list(v)}")
    return a / n


def frame_rotation(frame: Frame, tcp: pin.SE3) -> np.ndarray:
    """The regulation frame's axes in the base frame: the base's, or the tool's at the step's start."""
    return np.eye(3) if frame == "base" else tcp.rotation.copy()


class ForceRegulation:
    """Force control on the selected axes of a frame by the discretised impedance law (paper eq. 24), one
    law per axis: each period the reference moves along a regulated axis by the law's increment for that
    axis's error (setpoint - measured, the force the tool exerts), capped at the axis's speed limit.  The
    other axes are left to the caller (they follow a position)."""

    def __init__(self, R: np.ndarray, selection: np.ndarray, setpoint: np.ndarray, params: ImpedanceParams,
                 dt: float, max_speed: np.ndarray, ramp_s: float = 0.0, start: np.ndarray | None = None) -> None:
        self.R = R  # frame axes in the base frame (columns)
        self.sel = np.asarray(selection, bool)
        self.target = np.asarray(setpoint, float)
        self.start = self.target.copy() if start is None else np.asarray(start, float)
        self.ramp_s = ramp_s
        self.t = 0.0
        self.dt = dt
        self.law = DiscreteImpedance(params, dt, 6)
        self.max_step = np.asarray(max_speed, float) * dt

    def setpoint(self) -> np.ndarray:
        a = 1.0 if self.ramp_s <= 0 else min(1.0, self.t / self.ramp_s)
        return self.start + a * (self.target - self.start)

    def in_frame(self, w_base: np.ndarray) -> np.ndarray:
        return np.concatenate([self.R.T @ w_base[:3], self.R.T @ w_base[3:]])

    def error(self, w_base: np.ndarray) -> np.ndarray:
        """Setpoint - measured on every axis of the frame (unselected axes too, for the log)."""
        return self.setpoint() - self.in_frame(w_base)

    def step(self, ref: pin.SE3, w_base: np.ndarray) -> np.ndarray:
        """Move `ref` in place along the regulated axes; returns the error (frame axes)."""
        self.t += self.dt
        e = self.error(w_base)
        if not np.all(np.isfinite(e[self.sel])):
            return e  # a missing reading: hold the reference (the safety monitor counts them)
        d = np.where(self.sel, self.law.update(np.where(self.sel, e, 0.0)), 0.0)
        d = np.clip(d, -self.max_step, self.max_step)
        ref.translation = ref.translation + self.R @ d[:3]
        if np.any(d[3:]):
            ref.rotation = pin.exp3(self.R @ d[3:]) @ ref.rotation
        return e

    def primary_axis(self) -> int:
        """The regulated force axis the log and the scores follow (the first selected force axis)."""
        idx = [i for i in range(3) if self.sel[i]]
        return idx[0] if idx else int(np.flatnonzero(self.sel)[0])

    def log(self, e: np.ndarray, tcp: pin.SE3) -> dict[str, float | str]:
        """The primary axis's setpoint and estimate, and that axis in the measured tool frame (so that the
        F/T sensor's ground truth, logged in the tool frame, can be scored along it afterwards)."""
        i = self.primary_axis()
        sp = float(self.setpoint()[i])
        axis_tool = tcp.rotation.T @ self.R[:, i % 3]
        out: dict[str, float | str] = {"f_setpoint": sp, "f_estimate": sp - float(e[i]),
                                       "f_axis_tx": float(axis_tool[0]), "f_axis_ty": float(axis_tool[1]),
                                       "f_axis_tz": float(axis_tool[2]), "f_axis_moment": float(i >= 3)}
        # The default plot's setpoint is the tool-frame Fz: the regulated force seen along the tool's z.
        out["fz_setpoint"] = sp * float(axis_tool[2]) if i < 3 else 0.0
        return out


class Primitive:
    """One step of a task file.  `start` is called on its first period, then `step` every period until it
    returns finished (or failed).  `contact`: the step expects contact (the collision guard reads the
    residual as a tool force against the contact limit there, instead of as a collision)."""

    kind = "primitive"
    contact = False
    regulates = False  # scored as force regulation (its force error per sample)

    def __init__(self, params: Any, line: int) -> None:
        self.params = params
        self.line = line
        self.result: dict[str, Any] = {}

    def start(self, ctx: Context, obs: Observation) -> None:
        """Called once, on the step's first control period."""

    def step(self, ctx: Context, obs: Observation, t: float) -> StepOut:
        raise NotImplementedError
