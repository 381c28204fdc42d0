"""Opens the real cell's drivers (TM5-700 over Modbus/TCP, WACOH over serial) from the cell config."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

from drivers.errors import DriverError
from drivers.interfaces import JointLimits
from drivers.tm5.contract import TM5ModbusConfig
from drivers.tm5.modbus import TM5ModbusArm
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor


@dataclass
class RealDevices:
    arm: TM5ModbusArm
    sensor: WacohSensor | None
    sensor_cfg: WacohConfig | None

    def close(self) -> None:
        for device in (self.arm, self.sensor):
            if device is not None:
                with contextlib.suppress(DriverError):
                    device.disconnect()


def make_real_devices(arm_settings: dict[str, Any], sensor_settings: dict[str, Any] | None, limits: JointLimits,
                      dt: float, where: str) -> RealDevices:
    """Drivers from the `devices.*.settings` mappings; the sensor is optional on a real cell."""
    arm = TM5ModbusArm(TM5ModbusConfig.from_dict(arm_settings, f"{where}.arm.settings"), limits, dt)
    if sensor_settings is None:
        return RealDevices(arm, None, None)
    scfg = WacohConfig.from_dict(sensor_settings, f"{where}.sensor.settings")
    return RealDevices(arm, WacohSensor(scfg), scfg)
