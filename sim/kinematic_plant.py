"""A kinematic stand-in for the plant (joints lag their targets, toy kinematics): the emulator without MuJoCo."""

from __future__ import annotations

import math

import numpy as np

from drivers.interfaces import ArmState, ArmStatus
from drivers.tm5.registers import rpy_to_matrix


class KinematicPlant:
    """A documented stand-in satisfying `PlantLike`: every joint tracks its target as a first-order lag
    (time constant `tau_s`), the "measured torque" is a smooth gravity-like function of q (plus a damping
    term), and the flange/tool poses come from a toy planar-shoulder kinematic chain.  No contact, no
    sensor (the wrench is zero).  Good for wire tests and benchmarks, not for physics.  Starts at `HOME`
    (the cell's default home pose) unless given `q0`."""

    HOME = np.array([0.0, 0.0, math.pi / 2, 0.0, math.pi / 2, 0.0])

    def __init__(self, dt: float = 0.008, q0: np.ndarray | None = None, tau_s: float = 0.05,
                 tcp_offset_m: float = 0.155) -> None:
        self.dt = dt
        self.n_joints = 6
        self.q = self.HOME.copy() if q0 is None else np.array(q0, dtype=float)
        self.dq = np.zeros(6)
        self.target = self.q.copy()
        self.tau_s = tau_s
        self.tcp_offset_m = tcp_offset_m
        self.t = 0.0
        self.seq = 0
        self.holding = False
        self.status = ArmStatus()

    def step(self) -> None:
        alpha = 1.0 - math.exp(-self.dt / self.tau_s)
        q_new = self.q + alpha * (self.target - self.q)
        self.dq = (q_new - self.q) / self.dt
        self.q = q_new
        self.t += self.dt
        self.seq += 1

    def set_target(self, q: np.ndarray) -> None:
        if not self.holding:  # a protective stop ignores targets until released (like sim.plant.Plant)
            self.target = np.array(q, dtype=float)

    def hold(self) -> None:
        self.holding = True
        self.target = self.q.copy()
        self.status = ArmStatus(protective_stop=True)

    def release(self) -> None:
        self.holding = False
        self.target = self.q.copy()
        self.status = ArmStatus()

    def torque(self) -> np.ndarray:
        q = self.q
        gravity = np.array([0.0, 40.0 * math.cos(q[1]) + 12.0 * math.cos(q[1] + q[2]),
                            12.0 * math.cos(q[1] + q[2]), 1.5 * math.cos(q[1] + q[2] + q[3]),
                            0.4 * math.sin(q[4]), 0.0])
        return gravity + 2.0 * self.dq

    def measured_state(self) -> ArmState:
        return ArmState(t=self.t, q=self.q.copy(), dq=self.dq.copy(), tau=self.torque(), status=self.status,
                        seq=self.seq)

    def flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        q = self.q
        reach = 0.329 * math.cos(q[1]) + 0.312 * math.cos(q[1] + q[2])
        height = 0.146 + 0.329 * math.sin(q[1]) + 0.312 * math.sin(q[1] + q[2])
        pos = np.array([reach * math.cos(q[0]), reach * math.sin(q[0]), height])
        return pos, rpy_to_matrix(q[5], q[1] + q[2] + q[3] + q[4], q[0])

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        pos, rot = self.flange_pose()
        return pos + rot @ np.array([0.0, 0.0, self.tcp_offset_m]), rot

    def true_sensor_wrench(self) -> np.ndarray:
        return np.zeros(6)
