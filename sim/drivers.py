"""Simulated drivers: `SimArm` and `SimForceSensor` behind exactly the real interfaces, and the lock-step ticker."""

from __future__ import annotations

import numpy as np

from cell.control.loop import WallTicker
from drivers.interfaces import Arm, ArmState, ForceSensor, JointLimits, Wrench
from drivers.tm5.velocity_loop import VelocityLoop
from sim.plant import Plant


class SimArm(Arm):
    """The plant's arm through the `Arm` interface: a stop is the controller's protective stop.

    With `streaming` (TM's Ethernet route) it commands as the Listen node is commanded: the host's
    velocity loop turns each target into joint speeds and the controller integrates them into its servo
    target, from the measured joints when streaming starts; without, targets go straight to the servo.
    """

    def __init__(self, plant: Plant, limits: JointLimits, streaming: VelocityLoop | None = None) -> None:
        super().__init__(limits, plant.dt)
        self.plant = plant
        self.streaming = streaming
        self._q_cmd: np.ndarray | None = None

    def _connect(self) -> None:
        pass

    def _disconnect(self) -> None:
        pass

    def _arm(self) -> None:
        if self.plant.holding:
            self.plant.release()
        if self.streaming is not None:
            self.streaming.reset()
            self._q_cmd = None

    def _read_state(self) -> ArmState:
        return self.plant.measured_state()

    def _write_target(self, q: np.ndarray) -> None:
        if self.streaming is None:
            self.plant.set_target(q)
            return
        assert self._last_sent is not None
        q_meas = self.plant.measured_state().q
        v = self.streaming.speeds(q, self._last_sent, q_meas)
        if self._q_cmd is None:
            self._q_cmd = np.array(q_meas, dtype=float)
        self._q_cmd = self._q_cmd + v * self.dt
        self.plant.set_target(self._q_cmd)
        self.streaming.sent(v)

    def _stop(self) -> None:
        self.plant.hold()


class SimForceSensor(ForceSensor):
    """The WACOH model of the plant (offset, noise, quantisation, saturation), tared in software."""

    def __init__(self, plant: Plant) -> None:
        super().__init__()
        self.plant = plant
        self.bias = np.zeros(6)

    def _connect(self) -> None:
        pass

    def _disconnect(self) -> None:
        pass

    def _read(self) -> Wrench:
        w = self.plant.sensor_reading() - self.bias
        return Wrench(t=self.plant.t, force=w[:3], torque=w[3:])

    def _tare(self, samples: int) -> None:
        self.bias = np.mean([self.plant.sensor_reading() for _ in range(max(1, samples))], axis=0)


class LockstepTicker:
    """Advances the plant one control period per loop cycle: the loop runs as fast as it can."""

    def __init__(self, plant: Plant) -> None:
        self.plant = plant

    def start(self) -> None:
        pass

    def wait(self) -> None:
        self.plant.step()


class PacedTicker:
    """Advances the plant one period per cycle and sleeps to the wall clock: the sim at real speed."""

    def __init__(self, plant: Plant) -> None:

        self.plant = plant
        self.wall = WallTicker(plant.dt)

    @property
    def overruns(self) -> int:
        return self.wall.overruns

    def start(self) -> None:
        self.wall.start()

    def wait(self) -> None:
        self.plant.step()
        self.wall.wait()
