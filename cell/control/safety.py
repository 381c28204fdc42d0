"""Safety limits checked every control cycle: tool wrench, joint torque and speed, workspace, commands."""

from __future__ import annotations

import math

import numpy as np

from cell.config import SafetyConfig
from cell.model.robot import RobotModel
from drivers.errors import SafetyStopError
from drivers.interfaces import ArmState, Wrench


class SafetyMonitor:
    """Raises SafetyStopError naming the limit and the value; the loop then stops the arm."""

    def __init__(self, cfg: SafetyConfig, robot: RobotModel, dt: float) -> None:
        self.cfg = cfg
        self.robot = robot
        self.dt = dt
        lim = robot.limits
        self.max_torque = lim.effort * cfg.joint_torque_fraction
        self.max_speed = lim.velocity * cfg.joint_speed_fraction
        self.lower, self.upper = lim.lower, lim.upper
        self.ws_min = np.asarray(cfg.workspace_min, float)
        self.ws_max = np.asarray(cfg.workspace_max, float)
        self._invalid_wrench = 0
        self._last_tcp: np.ndarray | None = None

    def check_state(self, state: ArmState, wrench: Wrench | None) -> None:
        if not state.status.ok:
            raise SafetyStopError(f"controller reports {state.status}")
        # (Array methods and sqrt(f.f), numpy's own norm of a vector, without the dispatch of its functions:
        # this runs every control period.)
        over = np.abs(state.tau) > self.max_torque
        if over.any():
            j = int(np.argmax(np.abs(state.tau) / self.max_torque))
            raise SafetyStopError(
                f"joint {j + 1} torque {state.tau[j]:.1f} N·m exceeds limit {self.max_torque[j]:.1f} N·m"
            )
        fast = np.abs(state.dq) > self.max_speed
        if fast.any():
            j = int(np.argmax(np.abs(state.dq) / self.max_speed))
            raise SafetyStopError(
                f"joint {j + 1} speed {np.degrees(state.dq[j]):.1f} deg/s exceeds limit "
                f"{np.degrees(self.max_speed[j]):.1f} deg/s"
            )
        if wrench is None:
            return
        if not wrench.valid:
            self._invalid_wrench += 1
            if self._invalid_wrench > self.cfg.max_sensor_invalid_cycles:
                raise SafetyStopError(
                    f"force reading invalid for {self._invalid_wrench} consecutive cycles"
                )
            return
        self._invalid_wrench = 0
        f = math.sqrt(wrench.force.dot(wrench.force))
        if f > self.cfg.max_tool_force_n:
            raise SafetyStopError(f"tool force {f:.1f} N exceeds limit {self.cfg.max_tool_force_n:.1f} N")
        m = math.sqrt(wrench.torque.dot(wrench.torque))
        if m > self.cfg.max_tool_torque_nm:
            raise SafetyStopError(f"tool moment {m:.2f} N·m exceeds limit {self.cfg.max_tool_torque_nm:.2f} N·m")

    def check_command(self, q_cmd: np.ndarray) -> None:
        if q_cmd.shape != self.lower.shape or not np.isfinite(q_cmd).all():
            raise SafetyStopError(f"non-finite or malformed joint target rejected: {q_cmd!r}")
        if (q_cmd < self.lower).any() or (q_cmd > self.upper).any():
            j = int(np.argmax(np.maximum(self.lower - q_cmd, q_cmd - self.upper)))
            raise SafetyStopError(
                f"joint {j + 1} target {np.degrees(q_cmd[j]):.1f} deg is outside its limits"
            )
        tcp = self.robot.tcp_pose(q_cmd).translation
        if (tcp < self.ws_min).any() or (tcp > self.ws_max).any():
            raise SafetyStopError(f"TCP target {np.round(tcp, 3).tolist()} m is outside the workspace box")
        if self._last_tcp is not None:
            step = tcp - self._last_tcp
            speed = math.sqrt(step.dot(step)) / self.dt
            if speed > self.cfg.max_tcp_speed:
                raise SafetyStopError(
                    f"commanded TCP speed {speed:.2f} m/s exceeds limit {self.cfg.max_tcp_speed:.2f} m/s"
                )
        self._last_tcp = tcp
