"""The paper's discretised impedance law (eq. 22-24), in joint space or along a Cartesian direction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.model.robot import RobotModel
from drivers.configio import require


@dataclass
class ImpedanceParams:
    """m, b: virtual mass and damping; k_tau, k_v: the torque-error stiffness terms of eq. 23."""

    m: float = 1.0
    b: float = 50.0
    k_tau: float = 0.08
    k_v: float = 0.0

    def validate(self, where: str) -> None:
        require(self.m >= 0 and self.b >= 0, f"{where}.m", "and b must be >= 0")
        require(self.m > 0 or self.b > 0, f"{where}.m", "or b must be > 0 (the law divides by them)")
        require(self.k_tau >= 0 and self.k_v >= 0, f"{where}.k_tau", "and k_v must be >= 0")


class DiscreteImpedance:
    """theta_dc = (k_tau * e + k_v * de/dt) / (m / dt^2 + b / dt)        (paper eq. 24)

    `e` is the force/torque error (setpoint - measured) on each axis.  The paper writes the stiffness
    k(t) of eq. 23 in terms of that error, so after discretisation the spring term cancels and the
    displacement to add this cycle depends only on the error and its rate; we take the rate as the
    backward difference of the error (the paper's tau/dt), so a constant error gives a constant
    displacement per cycle: an integrating force controller with zero steady-state error, whose gain
    per cycle is k_tau / (m/dt^2 + b/dt) times the contact stiffness.
    """

    def __init__(self, params: ImpedanceParams, dt: float, n: int = 1) -> None:
        self.p = params
        self.dt = dt
        self.denominator = params.m / dt**2 + params.b / dt
        self._prev = np.zeros(n)
        self._first = True

    def reset(self) -> None:
        self._prev[:] = 0.0
        self._first = True

    def update(self, error: np.ndarray | float) -> np.ndarray:
        e = np.atleast_1d(np.asarray(error, float))
        de = np.zeros_like(e) if self._first else (e - self._prev) / self.dt
        self._first = False
        self._prev = e.copy()
        return (self.p.k_tau * e + self.p.k_v * de) / self.denominator


def cartesian_increment(robot: RobotModel, q: np.ndarray, twist: np.ndarray, damping: float = 1e-4) -> np.ndarray:
    """Joint increment realising a small TCP displacement `twist` (6,: dx, dy, dz, drx, dry, drz in the
    world-aligned TCP frame) through the damped pseudo-inverse of Pinocchio's TCP Jacobian."""
    J = robot.tcp_jacobian(q, world_aligned=True)
    return J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), twist)


class CartesianImpedance:
    """The discretised law along one Cartesian direction (unit vector in the world frame)."""

    def __init__(self, robot: RobotModel, params: ImpedanceParams, dt: float, direction: np.ndarray) -> None:
        self.robot = robot
        self.law = DiscreteImpedance(params, dt, 1)
        u = np.asarray(direction, float)
        self.direction = u / np.linalg.norm(u)

    def step(self, q: np.ndarray, force_error: float) -> tuple[np.ndarray, float]:
        """Joint increment and the displacement [m] along the direction for this cycle."""
        dx = float(self.law.update(force_error)[0])
        twist = np.concatenate([self.direction * dx, np.zeros(3)])
        return cartesian_increment(self.robot, q, twist), dx
