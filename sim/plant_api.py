"""The contract between a simulated plant and whatever drives it (simulated drivers, wire emulators)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from drivers.interfaces import ArmState


class PlantLike(Protocol):
    """A simulated arm with its joint servo, F/T sensor and tool, advanced one control period at a time.

    All values SI.  `measured_state()` is what the arm controller would report (noisy, quantised,
    possibly delayed torque); `true_sensor_wrench()` is the noiseless wrench at the F/T sensor in the
    cell's convention (the tool on the environment, sensor frame).
    """

    dt: float  # control period [s]
    n_joints: int

    def step(self) -> None:
        """Advance the physics by one control period, servoing toward the current target."""

    def set_target(self, q: np.ndarray) -> None:
        """New joint-position target for the arm's own servo (held until the next one)."""

    def hold(self) -> None:
        """Protective stop: the servo holds the current measured position."""

    def measured_state(self) -> ArmState:
        """The controller's view: t, q, dq, measured joint torque, status flags, sequence counter."""

    def flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Flange position [m] and rotation matrix in the robot base frame."""

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Tool centre point position [m] and rotation matrix in the robot base frame."""

    def true_sensor_wrench(self) -> np.ndarray:
        """(6,) noiseless wrench at the F/T sensor: Fx, Fy, Fz [N], Mx, My, Mz [N·m]."""
