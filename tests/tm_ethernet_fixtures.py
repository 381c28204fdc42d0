"""Helpers of the TM Ethernet tests: the emulator on a kinematic plant, the driver on it, a bounded wait.

The modules define their `emulator` / `arm` fixtures themselves: the names are the Modbus tests' too (their
fixtures are the suite's plugins), and a module's own fixture is the one its tests get."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from drivers.interfaces import JointLimits
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_config import TMEthernetConfig
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator

DT = 0.008
LIMITS = JointLimits(lower=np.full(6, -2 * math.pi), upper=np.full(6, 2 * math.pi), velocity=np.full(6, math.pi),
                     effort=np.full(6, 150.0))


def wait_for(cond: Callable[[], bool], timeout: float = 3.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)


def start(plant: KinematicPlant, **kw: Any) -> TMEthernetEmulator:
    emu = TMEthernetEmulator(plant, **kw)
    emu.start()
    return emu


def make_arm(emu: TMEthernetEmulator, **overrides: Any) -> TMEthernetArm:
    cfg = TMEthernetConfig(host="127.0.0.1", slave_port=emu.slave_port, listen_port=emu.listen_port,
                           connect_timeout_s=2.0, **overrides)
    return TMEthernetArm(cfg, LIMITS, DT)


def connected(emu: TMEthernetEmulator, **overrides: Any) -> Iterator[TMEthernetArm]:
    """A module's `arm` fixture body: the driver connected to `emu`, disconnected after the test."""
    arm = make_arm(emu, **overrides)
    arm.connect()
    try:
        yield arm
    finally:
        arm.disconnect()
