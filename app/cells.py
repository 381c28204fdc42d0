"""The cell factory: the kinds of cell a command runs on (simulated, emulated, real), each opened from the config."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from cell.config import CellConfig, SceneKind, resolve
from cell.control.loop import OpenCell
from cell.model.robot import RobotModel
from drivers.errors import ConfigError


class CellHolder(Protocol):
    """An unopened cell: `open()` connects it, `close()` releases it (whether or not it opened)."""

    def open(self) -> OpenCell: ...

    def close(self) -> None: ...


# (cfg, tool, robot, seed) -> (opener of the calibration cell, holder -> the load applier on it)
CalibrationCells = Callable[[CellConfig, str, RobotModel, int | None], tuple[Callable[[], Any], Callable[[Any], Any]]]


@dataclass(frozen=True)
class CellKind:
    """One kind of cell: how to open it, which arm it is, and what it can do besides running tasks."""

    name: str
    open: Callable[[CellConfig, RobotModel, int | None, SceneKind | None], CellHolder]  # (cfg, robot, seed, scene)
    identity: Callable[[CellConfig, int | None], dict[str, Any]]  # (cfg, seed) -> which arm, for artefacts
    # A task's missing virtual-sensor artefacts are built on the simulated plant on the spot; a real arm's
    # must be made on that arm, by the operator's command.
    simulated: bool
    calibration: CalibrationCells | None = None  # None: no calibration on this kind
    check_plant: Callable[[CellConfig, int | None, str], None] | None = None  # (cfg, seed, tool): fail early


class RealCell:
    """The physical cell: drivers from config, paced by the wall clock."""

    def __init__(self, cfg: CellConfig, robot: RobotModel) -> None:
        from drivers.real_cell import open_drivers

        self.period = cfg.loop.period_s
        self.devices = open_drivers(cfg.devices.arm.settings, cfg.devices.sensor.settings, robot.limits,
                                    cfg.loop.period_s, f"{cfg.source}: devices")

    def open(self) -> OpenCell:
        from cell.control.loop import WallTicker
        from cell.sensing.ft_source import SensorForceSource

        d = self.devices
        assert d.sensor is not None and d.sensor_cfg is not None
        d.connect()
        return OpenCell(kind="real", arm=d.arm, force=SensorForceSource(d.sensor, d.sensor_cfg.tare_samples),
                        ticker=WallTicker(self.period))

    def close(self) -> None:
        self.devices.close()


def _open_sim(cfg: CellConfig, robot: RobotModel, seed: int | None, scene: SceneKind | None) -> CellHolder:
    from sim.cell import make_sim_cell

    return make_sim_cell(cfg, robot.limits, seed=seed, scene_kind=scene)


def _open_emulated(cfg: CellConfig, robot: RobotModel, seed: int | None, scene: SceneKind | None) -> CellHolder:
    from sim.emulated import EmulatedCell

    return EmulatedCell(cfg, robot.limits, seed=seed, scene_kind=scene)


def _open_real(cfg: CellConfig, robot: RobotModel, seed: int | None, scene: SceneKind | None) -> CellHolder:
    return RealCell(cfg, robot)


def _sim_identity(cfg: CellConfig, seed: int | None) -> dict[str, Any]:
    """A simulated arm is its plant profile (which fixes the specimen: friction-ripple phases, sensor
    offset); the run seed changes the noise only."""
    from sim.profile import load_profile

    path = resolve(cfg.plant)
    profile = load_profile(path)
    return {"kind": "sim", "plant": str(path), "plant_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "specimen_seed": profile.specimen_seed, "seed": seed if seed is not None else profile.seed}


def _real_identity(cfg: CellConfig, seed: int | None) -> dict[str, Any]:
    return {"kind": "real"}


def _sim_calibration(cfg: CellConfig, tool: str, robot: RobotModel,
                     seed: int | None) -> tuple[Callable[[], Any], Callable[[Any], Any]]:
    """The free scene with `tool` mounted, loaded by the scripted hand."""
    from sim.cell import make_sim_cell
    from sim.hand import ScriptedHand

    cal = cfg.virtual_sensor.calibration

    def sim_opener() -> Any:
        return make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="free", tool=tool)

    def hand(holder: Any) -> Any:
        return ScriptedHand(holder.plant, seed=seed or 0, max_force_n=cal.max_force_n,
                            max_lateral_n=cal.max_lateral_n, max_moment_nm=cal.max_moment_nm, load_s=cal.load_s)

    return sim_opener, hand


def _real_calibration(cfg: CellConfig, tool: str, robot: RobotModel,
                      seed: int | None) -> tuple[Callable[[], Any], Callable[[Any], Any]]:
    """The real cell, loaded by the operator prompted here (never by the driver)."""
    from tasks.setup.calibrate import OperatorLoads

    def real_opener() -> Any:
        return RealCell(cfg, robot)

    return real_opener, lambda holder: OperatorLoads()


def _check_sim_plant(cfg: CellConfig, seed: int | None, tool: str) -> None:
    from sim.cell import make_plant

    make_plant(cfg, seed, "free", tool)  # a bad plant profile fails here, before any planning


CELLS: dict[str, CellKind] = {kind.name: kind for kind in (
    CellKind("sim", _open_sim, _sim_identity, simulated=True, calibration=_sim_calibration,
             check_plant=_check_sim_plant),
    CellKind("emulated", _open_emulated, _sim_identity, simulated=True),
    CellKind("real", _open_real, _real_identity, simulated=False, calibration=_real_calibration),
)}
CELL_KINDS = tuple(CELLS)
CALIBRATION_KINDS = tuple(name for name, kind in CELLS.items() if kind.calibration is not None)


def cell_kind(cfg: CellConfig, requested: str | None) -> str:
    """--cell wins; otherwise the config's device kinds, which must agree."""
    if requested:
        return requested
    arm, sensor = cfg.devices.arm.kind, cfg.devices.sensor.kind
    if arm != sensor:
        raise ConfigError(f"{cfg.source}: devices.arm.kind ({arm}) and devices.sensor.kind ({sensor}) differ; "
                          "mixed cells are not supported yet")
    return arm


def _kind(kind: str) -> CellKind:
    found = CELLS.get(kind)
    if found is None:
        raise ConfigError(f"unknown cell kind '{kind}' ({', '.join(CELL_KINDS)})")
    return found


def open_cell(cfg: CellConfig, kind: str, robot: RobotModel, seed: int | None, scene: SceneKind | None) -> CellHolder:
    return _kind(kind).open(cfg, robot, seed, scene)


def is_simulated(kind: str) -> bool:
    return _kind(kind).simulated


def cell_identity(cfg: CellConfig, kind: str, seed: int | None) -> dict[str, Any]:
    """Which arm a calibration was made on (recorded with it, compared before a task uses it)."""
    return _kind(kind).identity(cfg, seed)


def check_plant(cfg: CellConfig, kind: str, seed: int | None, tool: str) -> None:
    """Fails early on a cell whose plant cannot be built (a simulated cell's bad profile)."""
    check = _kind(kind).check_plant
    if check is not None:
        check(cfg, seed, tool)


def calibration_cells(cfg: CellConfig, kind: str, tool: str, robot: RobotModel,
                      seed: int | None) -> tuple[Callable[[], Any], Callable[[Any], Any]]:
    """(opener, load-applier factory) for calibrating on `kind`: the free scene with `tool` mounted
    and the scripted hand (sim), or the real cell and the operator prompted here (never the driver)."""
    cal = CELLS[kind].calibration if kind in CELLS else None
    if cal is None:
        raise ConfigError(f"--cell {kind}: calibration runs on the simulated cell (its scripted hand) or the real one")
    return cal(cfg, tool, robot, seed)
