"""The controller's nominal robot model: Pinocchio kinematics, Jacobians, dynamics and inverse kinematics."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from drivers.errors import ConfigError
from drivers.interfaces import JointLimits


@dataclass(frozen=True)
class ToolSpec:
    """The tool mounted on the flange as the controller believes it to be (nominal payload)."""

    tcp_offset: np.ndarray  # (3,) TCP position in the flange frame [m]
    mass: float = 0.0  # kg, sensor + tool
    com: np.ndarray | None = None  # (3,) in the flange frame [m]


class RobotModel:
    """Nominal rigid-body model of a serial arm loaded from URDF (Pinocchio), with a TCP frame."""

    def __init__(self, urdf: Path, tool: ToolSpec, flange_frame: str = "flange") -> None:
        try:
            self.model: pin.Model = pin.buildModelFromUrdf(str(urdf))
        except (RuntimeError, ValueError) as exc:
            raise ConfigError(f"{urdf}: cannot load URDF: {str(exc).splitlines()[0]}") from None
        self.urdf = Path(urdf)
        if not self.model.existFrame(flange_frame):
            raise ConfigError(f"{urdf}: no frame named '{flange_frame}'")
        flange_id = self.model.getFrameId(flange_frame)
        flange = self.model.frames[flange_id]
        joint = flange.parentJoint
        placement = flange.placement
        if tool.mass > 0:
            com = tool.com if tool.com is not None else tool.tcp_offset / 2
            inertia = pin.Inertia(tool.mass, placement.act(np.asarray(com, float)), np.eye(3) * 1e-4)
            self.model.appendBodyToJoint(joint, inertia, pin.SE3.Identity())
        tcp = pin.Frame(
            "tcp", joint, flange_id, placement * pin.SE3(np.eye(3), np.asarray(tool.tcp_offset, float)),
            pin.FrameType.OP_FRAME,
        )
        self.tcp_id = self.model.addFrame(tcp)
        self.flange_id = self.model.getFrameId(flange_frame)
        self.data = self.model.createData()
        self.tool = tool
        self.n = self.model.nv

    @property
    def limits(self) -> JointLimits:
        m = self.model
        return JointLimits(
            lower=np.array(m.lowerPositionLimit, float),
            upper=np.array(m.upperPositionLimit, float),
            velocity=np.array(m.velocityLimit, float),
            effort=np.array(m.effortLimit, float),
        )

    # --------------------------------------------------------------------------- kinematics
    def tcp_pose(self, q: np.ndarray) -> pin.SE3:
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, self.tcp_id).copy()

    def frame_pose(self, q: np.ndarray, frame: str) -> pin.SE3:
        fid = self.model.getFrameId(frame)
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, fid).copy()

    def tcp_jacobian(self, q: np.ndarray, world_aligned: bool = True) -> np.ndarray:
        """6xn Jacobian of the TCP: LOCAL_WORLD_ALIGNED (origin at the TCP, world axes) or LOCAL."""
        ref = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED if world_aligned else pin.ReferenceFrame.LOCAL
        return pin.computeFrameJacobian(self.model, self.data, q, self.tcp_id, ref)

    def ik(
        self,
        target: pin.SE3,
        q_seed: np.ndarray,
        iters: int = 100,
        tol: float = 1e-6,
        damping: float = 1e-6,
        max_step: float = 0.2,
    ) -> tuple[np.ndarray, bool]:
        """Damped least-squares IK on the TCP.  Returns (q, converged); q stays within limits."""
        # The control loop solves one pose per period: the per-iteration work is kept to Pinocchio's and two
        # small products (norms as sqrt(x.x), numpy's own arithmetic for a vector, without its checks).
        m, d, tcp = self.model, self.data, self.tcp_id
        lower, upper = m.lowerPositionLimit, m.upperPositionLimit
        regularise = _regulariser(damping)
        local = pin.ReferenceFrame.LOCAL
        q = np.array(q_seed, float)
        for _ in range(iters):
            err = self.pose_error(q, target)
            if math.sqrt(err.dot(err)) < tol:
                return q, True
            J = pin.Jlog6(self._last_err_se3) @ pin.computeFrameJacobian(m, d, q, tcp, local)
            dq = -J.T @ np.linalg.solve(J @ J.T + regularise, err)
            norm = math.sqrt(dq.dot(dq))
            if norm > max_step:
                dq *= max_step / norm
            q = np.minimum(np.maximum(q + dq, lower), upper)  # np.clip's result, without its dispatch
        err = self.pose_error(q, target)
        return q, bool(math.sqrt(err.dot(err)) < tol)

    def pose_error(self, q: np.ndarray, target: pin.SE3) -> np.ndarray:
        """log6(target^-1 * current) in the TCP frame (6,)."""
        pin.forwardKinematics(self.model, self.data, q)
        current = pin.updateFramePlacement(self.model, self.data, self.tcp_id)
        self._last_err_se3 = target.actInv(current)
        return np.asarray(pin.log6(self._last_err_se3).vector)

    # --------------------------------------------------------------------------- dynamics
    def gravity(self, q: np.ndarray) -> np.ndarray:
        return np.array(pin.computeGeneralizedGravity(self.model, self.data, q))

    def rnea(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return np.array(pin.rnea(self.model, self.data, q, dq, ddq))


@functools.lru_cache(maxsize=8)
def _regulariser(damping: float) -> np.ndarray:
    """damping * I (6x6) for the IK, made once per damping value (read-only: it is shared)."""
    out = damping * np.eye(6)
    out.flags.writeable = False
    return out


def load_robot(urdf: Path, tcp_offset: list[float], tool_mass: float, tool_com: list[float] | None) -> RobotModel:
    tool = ToolSpec(
        tcp_offset=np.asarray(tcp_offset, float),
        mass=tool_mass,
        com=None if tool_com is None else np.asarray(tool_com, float),
    )
    return RobotModel(urdf, tool)
