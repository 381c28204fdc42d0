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
        # Called from the control loop: the readings it already took when the sensor keeps them, else new ones.
        if not self.sensor.tare_from_recent(self.tare_samples):
            self.sensor.tare(self.tare_samples)
