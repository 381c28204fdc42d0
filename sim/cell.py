"""Opens the in-process simulated cell: plant, `SimArm`, `SimForceSensor` and the lock-step ticker."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cell.config import TOOLS, CellConfig, SceneKind, resolve
from cell.control.loop import OpenCell
from cell.sensing.ft_source import SensorForceSource
from drivers.errors import ConfigError
from drivers.interfaces import JointLimits
from drivers.real_cell import arm_protocol
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.velocity_loop import VelocityLoop
from sim.drivers import LockstepTicker, PacedTicker, SimArm, SimForceSensor
from sim.plant import Plant
from sim.profile import load_profile


@dataclass
class SimCell:
    plant: Plant
    arm: SimArm
    sensor: SimForceSensor
    clock: str = "auto"

    def open(self) -> OpenCell:
        self.arm.connect()
        self.sensor.connect()
        ticker = PacedTicker(self.plant) if self.clock == "wall" else LockstepTicker(self.plant)
        return OpenCell(kind="sim", arm=self.arm, force=SensorForceSource(self.sensor), ticker=ticker)

    def close(self) -> None:
        self.arm.disconnect()
        self.sensor.disconnect()


def make_plant(cfg: CellConfig, seed: int | None = None, scene_kind: SceneKind | None = None,
               tool: str | None = None) -> Plant:
    """The plant with the scene's fixtures; `tool` ("wipe", "peg") mounts that tool whatever the
    scene (default: the peg in the peg scene, the wiping tool elsewhere)."""
    profile = load_profile(resolve(cfg.plant))
    if seed is not None:
        profile = replace(profile, seed=seed)
    if abs(profile.sample_period_s - cfg.loop.period_s) > 1e-12:
        raise ConfigError(
            f"{cfg.source}: loop.period_s ({cfg.loop.period_s}) differs from the plant's sample_period_s "
            f"({profile.sample_period_s}); the simulated controller runs at one rate"
        )
    scene = cfg.scene if scene_kind is None else replace(cfg.scene, kind=scene_kind)
    if tool is not None and tool not in TOOLS:
        raise ConfigError(f"unknown tool '{tool}' ({' or '.join(TOOLS)})")
    return Plant(resolve(cfg.robot.urdf), profile, scene, np.asarray(cfg.robot.home, float), tool_kind=tool)


def make_sim_cell(
    cfg: CellConfig, limits: JointLimits, seed: int | None = None, scene_kind: SceneKind | None = None,
    tool: str | None = None,
) -> SimCell:
    plant = make_plant(cfg, seed, scene_kind, tool)
    arm = SimArm(plant, limits, velocity_streaming(cfg, limits))
    return SimCell(plant=plant, arm=arm, sensor=SimForceSensor(plant), clock=cfg.loop.clock)


def velocity_streaming(cfg: CellConfig, limits: JointLimits) -> VelocityLoop | None:
    """The host's velocity loop when the config's arm protocol streams speeds (TM's Ethernet route), with
    the config's gain and latency, so the simulated cell commands the plant as that route does."""
    where = f"{cfg.source}: devices.arm.settings"
    settings = cfg.devices.arm.settings
    if arm_protocol(settings, where) != "tm-ethernet":
        return None
    raw = {"host": "127.0.0.1", **{k: v for k, v in settings.items() if k != "protocol"}}
    eth = TMEthernetConfig.from_dict(raw, where)
    return VelocityLoop(limits, cfg.loop.period_s, eth.position_gain, eth.command_latency_periods)
