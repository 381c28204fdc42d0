"""Fixtures of the WACOH driver tests: emulators on pseudo-terminals, the sensors opened on them, true wrenches."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from drivers.wacoh.codec import Sensitivities
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor
from sim.wacoh_emulator import REAL_UNIT_SENSITIVITIES, WacohEmulator

S = REAL_UNIT_SENSITIVITIES.as_array()
# A calibration sheet told apart from the emulator's (within the default band of the nominal values): the
# emulator's `p` replies do not match it, so a sensor configured with it always uses it.
FALLBACK = Sensitivities(force=(32.5, 32.6, 32.7), moment=(1620.0, 1625.0, 1630.0))
# What a sensor without a calibration sheet falls back to: the model's nominal values.
NOMINAL = Sensitivities()
BIG_OFFSET = np.array([600.0, -640.0, 655.0, -500.0, 420.0, -655.0])  # LSB, near the +-655 limit
# Fault-free tests check values, not timing: a generous timeout keeps a loaded CI box from turning a
# scheduling stall into a NaN they would (rightly) fail on.
SLACK_TIMEOUT_S = 0.25


class Source:
    """The true wrench the emulator reports; logs every value it hands out."""

    def __init__(self, value: np.ndarray | None = None, fresh_each_call: bool = False, seed: int = 1) -> None:
        self.value = np.zeros(6) if value is None else np.asarray(value, dtype=float)
        self.fresh_each_call = fresh_each_call
        self.rng = np.random.default_rng(seed)
        self.produced: list[np.ndarray] = []
        self.lock = threading.Lock()
        self._open = threading.Event()  # cleared by `hold`: the emulator waits here before its next record
        self._open.set()
        self._waiting = threading.Event()

    def hold(self, timeout_s: float = 10.0) -> None:
        """Stop the emulator before its next record; returns once it waits (every earlier record written)."""
        self._open.clear()
        if not self._waiting.wait(timeout_s):
            raise TimeoutError("the emulator did not ask for another record")

    def release(self) -> None:
        self._waiting.clear()
        self._open.set()

    def __call__(self) -> np.ndarray:
        if not self._open.is_set():
            self._waiting.set()
            self._open.wait()
        with self.lock:
            if self.fresh_each_call:
                self.value = random_wrench(self.rng)
            self.produced.append(self.value.copy())
            return self.value.copy()


def random_wrench(rng: np.random.Generator) -> np.ndarray:
    """Well inside the range even with a 655 LSB offset (+-100 N, +-2 N·m)."""
    return np.concatenate([rng.uniform(-100, 100, 3), rng.uniform(-2, 2, 3)])


def close_to(reading: np.ndarray, truth: np.ndarray, lsb: float, sens: np.ndarray = S) -> bool:
    """Within `lsb` counts on every channel (quantisation and tare error budget).

    `sens` is what the driver divides by: when a faulty line garbled `p` it is the configured fallback,
    and a true load then reads scaled by S_emulator / S_driver.
    """
    expected = truth * S / sens
    return bool(np.all(np.abs(reading - expected) <= lsb / sens + 1e-9))


EmulatorFactory = Callable[..., WacohEmulator]


@pytest.fixture
def make_emulator() -> Iterator[EmulatorFactory]:
    started: list[WacohEmulator] = []

    def factory(*args: Any, **kwargs: Any) -> WacohEmulator:
        emulator = WacohEmulator(*args, **kwargs)
        emulator.start()
        started.append(emulator)
        return emulator

    yield factory
    for emulator in started:
        emulator.stop()


@pytest.fixture
def sensors() -> Iterator[list[WacohSensor]]:
    opened: list[WacohSensor] = []
    yield opened
    for sensor in opened:
        sensor.disconnect()


def connect(sensors: list[WacohSensor], emulator: WacohEmulator, **settings: object) -> WacohSensor:
    cfg = WacohConfig.from_dict({"port": emulator.tty_path, **settings}, "test")
    sensor = WacohSensor(cfg)
    sensors.append(sensor)
    sensor.connect()
    return sensor
