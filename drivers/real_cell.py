"""Opens the cell's drivers (TM5-700 over Modbus/TCP or TM's Ethernet Slave + Listen node, WACOH over serial)."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from drivers.configio import require
from drivers.errors import DriverError
from drivers.interfaces import JointLimits
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.modbus import TM5ModbusArm
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor

# `devices.arm.settings.protocol`: Modbus/TCP to a robot-side program (docs/robot-side-program.md), or TM's
# standard channels, the Ethernet Slave's broadcast for state and a Listen node for motion (no program).
PROTOCOLS = ("modbus", "tm-ethernet")


@dataclass
class CellDrivers:
    """The arm's and the sensor's drivers of one cell, not yet connected; the sensor is optional."""

    arm: TM5ModbusArm | TMEthernetArm
    sensor: WacohSensor | None
    sensor_cfg: WacohConfig | None

    def connect(self) -> None:
        """Connect the arm, then the sensor (the caller closes both on failure)."""
        self.arm.connect()
        if self.sensor is not None:
            self.sensor.connect()

    def close(self) -> None:
        for device in (self.arm, self.sensor):
            if device is not None:
                with contextlib.suppress(DriverError):
                    device.disconnect()


def arm_protocol(arm_settings: Mapping[str, Any], where: str) -> str:
    """The arm's protocol named by its settings (default modbus); ConfigError on another."""
    protocol = arm_settings.get("protocol", "modbus")
    require(protocol in PROTOCOLS, f"{where}.protocol", f"must be one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    return str(protocol)


def open_arm(settings: Mapping[str, Any], limits: JointLimits, dt: float, where: str, *,
             fixed: Mapping[str, Any] | None = None, min_timeout_s: float = 0.0,
             min_stale_s: float = 0.0) -> TM5ModbusArm | TMEthernetArm:
    """The arm's driver for its protocol, from `devices.arm.settings` (`fixed` laid over them)."""
    protocol = arm_protocol(settings, where)
    raw = {k: v for k, v in {**settings, **(fixed or {})}.items() if k != "protocol"}
    if protocol == "tm-ethernet":
        eth = TMEthernetConfig.from_dict(raw, where)
        if min_stale_s:
            # The Listen node's replies are as late as the table is stale there: the same allowance, and as
            # many unanswered scripts as fit in it.
            eth = replace(eth, stale_after_s=max(eth.stale_after_s, min_stale_s),
                          max_reply_age_s=max(eth.max_reply_age_s, min_stale_s),
                          max_unanswered_scripts=max(eth.max_unanswered_scripts, math.ceil(min_stale_s / dt)))
            eth.validate(where)
        eth.check_period(dt, where)
        return TMEthernetArm(eth, limits, dt)
    arm_cfg = TM5ModbusConfig.from_dict(raw, where)
    if min_timeout_s or min_stale_s:
        arm_cfg = replace(arm_cfg, timeout_s=max(arm_cfg.timeout_s, min_timeout_s),
                          stale_after_s=max(arm_cfg.stale_after_s, min_stale_s))
        arm_cfg.validate(where)
    arm_cfg.check_period(dt, where)
    return TM5ModbusArm(arm_cfg, limits, dt)


def open_drivers(arm_settings: Mapping[str, Any], sensor_settings: Mapping[str, Any] | None, limits: JointLimits,
                 dt: float, where: str, *, arm_fixed: Mapping[str, Any] | None = None,
                 sensor_fixed: Mapping[str, Any] | None = None, min_timeout_s: float = 0.0,
                 min_stale_s: float = 0.0) -> CellDrivers:
    """Drivers from the `devices.*.settings` mappings (ConfigError naming the key on bad settings).

    `arm_fixed`/`sensor_fixed` are settings the caller chooses itself (an emulator's address), laid over
    the config's; `min_timeout_s`/`min_stale_s` raise the reply timeouts and the stale limit to at least
    that much (emulators share the host's CPU, a real controller does not)."""
    arm = open_arm(arm_settings, limits, dt, f"{where}.arm.settings", fixed=arm_fixed,
                   min_timeout_s=min_timeout_s, min_stale_s=min_stale_s)
    if sensor_settings is None:
        return CellDrivers(arm, None, None)
    scfg = WacohConfig.from_dict({**sensor_settings, **(sensor_fixed or {})}, f"{where}.sensor.settings")
    if min_timeout_s:
        scfg = replace(scfg, timeout_s=max(scfg.timeout_s, min_timeout_s))
    return CellDrivers(arm, WacohSensor(scfg), scfg)
