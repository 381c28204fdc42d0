"""Fixtures of the TM5 driver tests: a scripted plant behind the TM5 emulator, the emulator, a connected arm."""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from drivers.errors import DriverError, LinkLostError
from drivers.interfaces import ArmState, ArmStatus, JointLimits, Lifecycle
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.modbus import TM5ModbusArm
from sim.tm5_emulator import TM5Emulator

DT = 0.008
Q0 = np.array([0.1, -0.4, 1.2, 0.3, 1.5, -0.2])
LIMITS = JointLimits(lower=np.full(6, -math.pi), upper=np.full(6, math.pi), velocity=np.full(6, math.pi),
                     effort=np.full(6, 150.0))


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rz @ Ry @ Rx built from elementary rotations (independent of the driver's closed form)."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


class FakePlant:
    """PlantLike stand-in: first-order joint tracking, torque a smooth function of q, recorded calls.

    Mutated on the emulator thread; arrays are replaced, never modified in place, so the test thread always
    sees consistent values."""

    n_joints = 6

    def __init__(self, q0: np.ndarray, dt: float = DT, tau_s: float = 0.04) -> None:
        self.dt = dt
        self.tau_s = tau_s
        self.q = np.array(q0, dtype=float)
        self.dq = np.zeros(6)
        self.target = self.q.copy()
        self.t = 0.0
        self.steps = 0
        self.holding = False
        self.status = ArmStatus()
        self.accepted_targets: list[np.ndarray] = []
        self.hold_calls = 0
        self.release_calls = 0

    @staticmethod
    def torque_of(q: np.ndarray) -> np.ndarray:
        return np.array([3.0 * np.sin(q[0]), 55.0 * np.cos(q[1]), 21.0 * np.cos(q[1] + q[2]),
                         2.5 * np.sin(q[3]), -1.25 * np.cos(q[4]), 0.3 * q[5]])

    def step(self) -> None:
        q_new = self.q + (1.0 - math.exp(-self.dt / self.tau_s)) * (self.target - self.q)
        self.dq = (q_new - self.q) / self.dt
        self.q = q_new
        self.t += self.dt
        self.steps += 1

    def set_target(self, q: np.ndarray) -> None:
        if not self.holding:
            self.target = np.array(q, dtype=float)
            self.accepted_targets.append(self.target)

    def hold(self) -> None:
        self.hold_calls += 1
        self.holding = True
        self.target = self.q.copy()
        self.status = ArmStatus(protective_stop=True)

    def release(self) -> None:
        self.release_calls += 1
        self.holding = False
        self.target = self.q.copy()
        self.status = ArmStatus()

    def measured_state(self) -> ArmState:
        return ArmState(t=self.t, q=self.q, dq=self.dq, tau=self.torque_of(self.q) + 0.5 * self.dq,
                        status=self.status, seq=self.steps)

    def flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        q = self.q
        return np.array([0.4 + 0.1 * q[0], 0.1 * q[1], 0.5 + 0.1 * q[2]]), _rot(q[3], 0.5 * q[4], q[5])

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        pos, rot = self.flange_pose()
        return pos + rot @ np.array([0.0, 0.0, 0.155]), rot

    def true_sensor_wrench(self) -> np.ndarray:
        return np.zeros(6)


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture
def no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    assert not leaked, f"threads left running: {leaked}"


@pytest.fixture
def plant() -> FakePlant:
    return FakePlant(Q0)


@pytest.fixture
def emulator(plant: FakePlant) -> Iterator[TM5Emulator]:
    with TM5Emulator(plant, watchdog_cycles=6) as emu:
        yield emu
    # the port is really released: we can bind it again
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", emu.port))


def make_arm(emu: TM5Emulator, **overrides: Any) -> TM5ModbusArm:
    # 30 ms reply timeout: the emulator shares this process (and a busy CI machine).
    settings: dict[str, Any] = {"host": "127.0.0.1", "port": emu.port, "reconnect_initial_s": 0.02,
                                "reconnect_max_s": 0.1, "timeout_s": 0.03, **overrides}
    return TM5ModbusArm(TM5ModbusConfig(**settings), LIMITS, DT)


@pytest.fixture
def arm(emulator: TM5Emulator) -> Iterator[TM5ModbusArm]:
    a = make_arm(emulator)
    a.connect()
    yield a
    with contextlib.suppress(DriverError):  # a test may leave the link down: the stop then cannot reach it
        a.disconnect()
    assert a.lifecycle is Lifecycle.DISCONNECTED and not a.link_up


def wait_for(cond: Callable[[], bool], timeout: float = 1.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.002)


def read_until_ok(arm: TM5ModbusArm, timeout: float = 3.0) -> ArmState:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return arm.read_state()
        except LinkLostError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.005)


class WireWaits:
    """Counts the driver's waits on the wire: each link handed to a transaction and each connect attempt.
    With retries 0 every wait is bounded by `timeout_s`, so a count bounds how long a call can block
    whatever the machine's load (a stopwatch would measure the load instead)."""

    def __init__(self, arm: TM5ModbusArm, monkeypatch: pytest.MonkeyPatch) -> None:
        self.count = 0
        require_link, open_link = arm._require_link, arm._open_link

        def counting_require_link(may_reconnect: bool) -> object:
            client = require_link(may_reconnect)
            self.count += 1
            return client

        def counting_open_link() -> object:
            self.count += 1
            return open_link()

        monkeypatch.setattr(arm, "_require_link", counting_require_link)
        monkeypatch.setattr(arm, "_open_link", counting_open_link)

    def __call__(self, fn: Callable[[], object]) -> int:
        """Waits on the wire while `fn()` runs (its exceptions propagate)."""
        before = self.count
        try:
            fn()
        finally:
            self.waits = self.count - before
        return self.waits
