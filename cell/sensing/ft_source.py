"""Force sources for tasks: the physical F/T sensor behind the `ForceSource` seam the virtual sensor also fills."""

from __future__ import annotations

from drivers.interfaces import ArmState, ForceSensor, Wrench


class SensorForceSource:
    """The measured wrench from a `ForceSensor` (tared in free space by `rebias`)."""

    name = "sensor"

    def __init__(self, sensor: ForceSensor, tare_samples: int = 50) -> None:
        self.sensor = sensor
        self.tare_samples = tare_samples

    def read(self, state: ArmState) -> Wrench:
        return self.sensor.read()

    def rebias(self) -> None:
        self.sensor.tare(self.tare_samples)
