"""Robots by name: `config/robots/<name>/` holds a robot's URDF and its `robot.yaml`, loaded strictly here."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pinocchio as pin

from cell.collision.config import DetectorSettings
from cell.config import CONFIG_DIR, CellConfig, resolve
from cell.model.dynamics.rigid_body import IdentificationConfig
from cell.model.dynamics.uncertainty import CoverageConfig
from cell.model.robot import RobotModel, ToolSpec, load_robot
from drivers.configio import join, load_dataclass, read_yaml, require
from drivers.errors import ConfigError

ROBOTS_DIR = CONFIG_DIR / "robots"
SPEC_FILE = "robot.yaml"
CELL_ROBOT = "tm5-700"  # the cell's arm (and the simulated plant's): the model lab's default robot

TorqueSource = Literal["current", "torque"]


@dataclass
class DriveFile:
    """robot.yaml `drive`: how the logged joint torque is obtained."""

    torque_constants_nm_per_a: list[float] | None = None  # joint torque = motor current x gain (joints 1..n)
    torque_source: TorqueSource = "torque"  # "current": tau = gain x motor current; "torque": logged as such

    def validate(self, where: str) -> None:
        gains = self.torque_constants_nm_per_a
        require(self.torque_source != "current" or gains is not None, join(where, "torque_constants_nm_per_a"),
                "is required when torque_source is 'current'")
        if gains is not None:
            require(all(g > 0 for g in gains), join(where, "torque_constants_nm_per_a"),
                    f"must all be > 0 N·m/A, got {gains}")


@dataclass
class RobotFile:
    """config/robots/<name>/robot.yaml as written (paths relative to its folder)."""

    name: str
    urdf: str
    flange_frame: str
    joints: int
    description: str
    drive: DriveFile = field(default_factory=DriveFile)
    # How the model lab identifies this arm's P2 (cell/model/dynamics/rigid_body.py IdentificationConfig).
    identification: IdentificationConfig = field(default_factory=IdentificationConfig)
    # How a hybrid's learned residual is trusted (cell/model/dynamics/uncertainty.py CoverageConfig).
    learning: CoverageConfig = field(default_factory=CoverageConfig)
    # The collision detector's settings on this arm (cell/config.py DetectorSettings; main.py detect).
    collision: DetectorSettings | None = None

    def validate(self, where: str) -> None:
        self.identification.validate(join(where, "identification"))
        self.learning.validate(join(where, "learning"))
        require(self.joints >= 1, join(where, "joints"), f"must be >= 1, got {self.joints}")
        gains = self.drive.torque_constants_nm_per_a
        if gains is not None:
            require(len(gains) == self.joints, join(where, "drive.torque_constants_nm_per_a"),
                    f"must have {self.joints} values (one per joint), got {len(gains)}")


@dataclass(frozen=True)
class RobotSpec:
    """A robot known by name: its URDF, end-effector frame, joint count and drive facts."""

    name: str
    folder: Path
    urdf: Path
    flange_frame: str
    joints: int
    description: str
    torque_constants: tuple[float, ...] | None  # N·m/A per joint, when torques come from motor currents
    torque_source: TorqueSource
    identification: IdentificationConfig = field(default_factory=IdentificationConfig)
    learning: CoverageConfig = field(default_factory=CoverageConfig)
    collision: DetectorSettings | None = None  # the detector's settings on this arm, when it has its own


def available_robots(robots_dir: Path = ROBOTS_DIR) -> list[str]:
    """Names of the robots with a `robot.yaml` under `robots_dir`, sorted."""
    if not robots_dir.is_dir():
        return []
    return sorted(p.name for p in robots_dir.iterdir() if (p / SPEC_FILE).is_file())


def load_robot_spec(name: str, robots_dir: Path = ROBOTS_DIR) -> RobotSpec:
    """The robot `name` from `<robots_dir>/<name>/robot.yaml`: unknown or missing keys, a name or joint
    count that disagrees with the folder or the URDF, or a missing flange frame are one-line ConfigErrors."""
    known = available_robots(robots_dir)
    if name not in known:
        raise ConfigError(f"unknown robot '{name}' (available: {', '.join(known) or 'none'})")
    folder = robots_dir / name
    path = folder / SPEC_FILE
    where = f"{path}:"
    spec = load_dataclass(RobotFile, read_yaml(path), where)
    require(spec.name == name, join(where, "name"), f"is '{spec.name}' but the folder is '{name}'")
    urdf = Path(spec.urdf) if Path(spec.urdf).is_absolute() else folder / spec.urdf
    require(urdf.is_file(), join(where, "urdf"), f"names {urdf}, which does not exist")
    try:
        model = pin.buildModelFromUrdf(str(urdf))
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"{urdf}: cannot load URDF: {str(exc).splitlines()[0]}") from None
    require(model.nv == spec.joints, join(where, "joints"), f"is {spec.joints} but {urdf.name} has {model.nv} joints")
    # Datasets and model artefacts carry the URDF's robot name: it must be this robot's name.
    require(model.name == name, join(where, "name"), f"is '{name}' but {urdf.name} names its robot '{model.name}'")
    require(model.existFrame(spec.flange_frame), join(where, "flange_frame"),
            f"'{spec.flange_frame}' is not a frame of {urdf.name}")
    gains = spec.drive.torque_constants_nm_per_a
    return RobotSpec(
        name=name, folder=folder, urdf=urdf, flange_frame=spec.flange_frame, joints=spec.joints,
        description=spec.description.strip(), torque_constants=None if gains is None else tuple(gains),
        torque_source=spec.drive.torque_source, identification=spec.identification,
        learning=spec.learning, collision=spec.collision,
    )


def robot_model(spec: RobotSpec, tool: ToolSpec | None = None) -> RobotModel:
    """The nominal model of `spec`'s arm with `tool` mounted (none: a zero-mass tool, the TCP at the flange)."""
    return RobotModel(spec.urdf, tool or ToolSpec(tcp_offset=np.zeros(3)), spec.flange_frame)


def cell_robot(cfg: CellConfig, tcp: list[float] | None = None) -> RobotModel:
    """The cell's arm: the cell config's URDF with its tool's mass, centre of mass and TCP (`tcp`, default the
    nominal wiping tool's)."""
    arm = cfg.robot
    return load_robot(resolve(arm.urdf), arm.tcp_wipe if tcp is None else tcp, arm.tool_mass, arm.tool_com)


def robot_by_name(cfg: CellConfig, name: str = CELL_ROBOT) -> RobotModel:
    """The nominal model the model lab identifies against: for the cell's arm `cell_robot(cfg)`; for another
    robot (`config/robots/<name>/`) its URDF with no tool."""
    if name == CELL_ROBOT:
        return cell_robot(cfg)
    return robot_model(load_robot_spec(name))
