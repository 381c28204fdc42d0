"""The cell configuration (config/cell.yaml): robot, scene, loop, safety limits, devices, recording."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from cell.configio import load_dataclass, read_yaml, require, require_len

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "config"
DEFAULT_CONFIG = CONFIG_DIR / "cell.yaml"


def resolve(path: str, base: Path = CONFIG_DIR) -> Path:
    """Config paths are relative to config/ unless absolute."""
    p = Path(path)
    return p if p.is_absolute() else base / p


@dataclass
class RobotConfig:
    """The controller's nominal model of the arm and its tool."""

    urdf: str = "robots/tm5-700.urdf"
    home: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.5708, 0.0, 1.5708, 0.0])  # rad
    # Nominal tool as configured on the pendant: sensor + tool mass, COM and TCP in the flange frame.
    tool_mass: float = 1.4
    tool_com: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.11])
    tcp_wipe: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.155])
    tcp_peg: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.143])

    def validate(self, where: str) -> None:
        require_len(self.home, 6, f"{where}.home")
        for name in ("tool_com", "tcp_wipe", "tcp_peg"):
            require(len(getattr(self, name)) == 3, f"{where}.{name}", "must have 3 values (x, y, z) in m")
        require(0 <= self.tool_mass <= 6.0, f"{where}.tool_mass", "must lie in [0, 6] kg (rated payload)")


@dataclass
class SceneConfig:
    """Where the fixtures are, in the robot base frame [m].  The plant builds them; tasks aim at them."""

    kind: Literal["free", "table", "peg"] = "table"
    table_height: float = 0.05  # top surface z
    table_center: list[float] = field(default_factory=lambda: [0.45, -0.12])
    table_size: list[float] = field(default_factory=lambda: [0.6, 0.8])
    hole_center: list[float] = field(default_factory=lambda: [0.45, -0.12])
    hole_diameter: float = 0.0218
    hole_depth: float = 0.030

    def validate(self, where: str) -> None:
        require(len(self.table_center) == 2, f"{where}.table_center", "must have 2 values (x, y)")
        require(len(self.table_size) == 2, f"{where}.table_size", "must have 2 values (x, y)")
        require(len(self.hole_center) == 2, f"{where}.hole_center", "must have 2 values (x, y)")
        require(0.005 < self.hole_diameter < 0.1, f"{where}.hole_diameter", "must lie in (0.005, 0.1) m")
        require(0.005 < self.hole_depth < 0.2, f"{where}.hole_depth", "must lie in (0.005, 0.2) m")


@dataclass
class LoopConfig:
    period_s: float = 0.008
    clock: Literal["auto", "lockstep", "wall"] = "auto"  # auto: lockstep for sim, wall otherwise
    slow_cycle_fraction: float = 0.8  # a cycle whose compute takes more than this x period is 'slow'

    def validate(self, where: str) -> None:
        require(0.001 <= self.period_s <= 0.1, f"{where}.period_s", f"must lie in [0.001, 0.1] s, got {self.period_s}")
        require(0 < self.slow_cycle_fraction <= 1, f"{where}.slow_cycle_fraction", "must lie in (0, 1]")


@dataclass
class SafetyConfig:
    """Limits checked every control cycle; a breach stops the arm."""

    max_tool_force_n: float = 150.0
    max_tool_torque_nm: float = 10.0
    joint_torque_fraction: float = 0.9  # of the URDF effort limit
    joint_speed_fraction: float = 0.8  # of the URDF velocity limit
    workspace_min: list[float] = field(default_factory=lambda: [-0.8, -0.8, 0.0])
    workspace_max: list[float] = field(default_factory=lambda: [0.8, 0.8, 1.0])
    max_tcp_speed: float = 0.5  # m/s, commanded
    max_sensor_invalid_cycles: int = 3

    def validate(self, where: str) -> None:
        require(self.max_tool_force_n > 0, f"{where}.max_tool_force_n", "must be > 0")
        require(self.max_tool_torque_nm > 0, f"{where}.max_tool_torque_nm", "must be > 0")
        require(0 < self.joint_torque_fraction <= 1, f"{where}.joint_torque_fraction", "must lie in (0, 1]")
        require(0 < self.joint_speed_fraction <= 1, f"{where}.joint_speed_fraction", "must lie in (0, 1]")
        require(len(self.workspace_min) == 3, f"{where}.workspace_min", "must have 3 values")
        require(len(self.workspace_max) == 3, f"{where}.workspace_max", "must have 3 values")
        require(all(a < b for a, b in zip(self.workspace_min, self.workspace_max, strict=True)),
                f"{where}.workspace_min", "must be below workspace_max on every axis")
        require(self.max_tcp_speed > 0, f"{where}.max_tcp_speed", "must be > 0")


@dataclass
class DeviceConfig:
    """One device: `sim` (in-process plant), `emulated` (real driver against a local emulator) or `real`."""

    kind: Literal["sim", "emulated", "real"] = "sim"
    settings: dict[str, Any] = field(default_factory=dict)  # driver-specific; validated by the driver


@dataclass
class DevicesConfig:
    arm: DeviceConfig = field(default_factory=DeviceConfig)
    sensor: DeviceConfig = field(default_factory=DeviceConfig)


@dataclass
class RecordingConfig:
    directory: str = "runs"  # relative to the working directory
    chunk_rows: int = 250

    def validate(self, where: str) -> None:
        require(self.chunk_rows >= 1, f"{where}.chunk_rows", "must be >= 1")


@dataclass
class CellConfig:
    robot: RobotConfig = field(default_factory=RobotConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    devices: DevicesConfig = field(default_factory=DevicesConfig)
    plant: str = "plants/default.yaml"
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    tasks: dict[str, dict[str, Any]] = field(default_factory=dict)  # validated by each task

    source: str = ""  # file this was loaded from (not a config key)


def load_config(path: Path | None = None) -> CellConfig:
    path = Path(path) if path is not None else DEFAULT_CONFIG
    data = read_yaml(path)
    data.pop("source", None)
    cfg = load_dataclass(CellConfig, data, f"{path}:")
    cfg.source = str(path)
    return cfg
