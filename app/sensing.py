"""The force a task regulates with: the F/T sensor, or the tool's virtual sensor (its artefacts made ready first)."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np

from app.cells import calibration_cells, cell_identity, check_plant, is_simulated
from app.tasks_registry import robot_for, working_posture
from cell.config import CONFIG_DIR, CellConfig
from cell.control.loop import OpenCell
from cell.model.robot import RobotModel
from cell.planning.config import PlannerConfig
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")

FORCE_SOURCES = ("virtual", "sensor")
PREPARE_SAMPLES = 40_000  # `prepare`'s default collection: about half a minute of simulated motion per 10k


def make_force_source(cfg: CellConfig, source: str, tool: str, cell: OpenCell, robot: RobotModel) -> OpenCell:
    """The OpenCell a task runs on for --force-source: `sensor` keeps the F/T sensor in the loop;
    `virtual` regulates with the tool's virtual sensor and keeps the F/T sensor (when the cell has
    one) as the logged ground truth.  Every task builds its force source here."""
    cell = with_tool_gravity(cfg, tool, cell, robot)
    if source == "sensor":
        return cell
    if source != "virtual":
        raise ConfigError(f"--force-source {source}: unknown (virtual or sensor)")
    from cell.sensing.virtual_sensor import build_virtual_source

    virtual = build_virtual_source(cfg.virtual_sensor, robot, tool, cfg.loop.period_s)
    log.info("force source: virtual sensor (%s) for the %s tool; the F/T sensor is logged as ground truth",
             virtual.label, tool)
    return replace(cell, force=virtual, ground_truth=cell.force)


def with_tool_gravity(cfg: CellConfig, tool: str, cell: OpenCell, robot: RobotModel) -> OpenCell:
    """The F/T sensor less the tool's weight when `calibrate` identified it (`tool_gravity.json` in the tool's
    calibration folder): it then reads the contact alone in any pose, not only in the pose of its tare."""
    from cell.sensing.tool_gravity import FILE, GravityCompensatedSource, load

    folder = cfg.virtual_sensor.for_tool(tool).path("calibration", tool)
    if not (folder / FILE).exists():
        return cell
    tg = load(folder)
    log.info("F/T sensor: the %s tool's weight compensated (%.3f kg, %s)", tool, tg.mass_kg, folder / FILE)
    return replace(cell, force=GravityCompensatedSource(cell.force, tg, robot))


def with_guard(cfg: CellConfig, tool: str, cell: OpenCell, robot: RobotModel) -> OpenCell:
    """The cell with collision detection for its tasks (`collision` in the config) on the tool's hybrid
    model.  Without a model: refused on the real cell (it would run blind to collisions), a warning on a
    simulated one.  `collision.enabled: false` turns it off."""
    if not cfg.collision.enabled:
        log.warning("collision detection is off (collision.enabled: false)")
        return cell
    model_dir = cfg.virtual_sensor.path("model", tool)
    if not (model_dir / "model.json").exists():
        if not is_simulated(cell.kind):
            raise ConfigError(f"collision detection for the {tool} tool needs its model ({model_dir}); make it with "
                              f"`main.py prepare --tool {tool} --cell real`, or set collision.enabled: false")
        log.warning("collision detection off for this run: no model for the %s tool at %s (main.py prepare --tool %s)",
                    tool, model_dir, tool)
        return cell
    from cell.collision.guard import build_guard
    from cell.sensing.virtual_sensor import VirtualForceSource, load_observer_model

    # On the virtual sensor's own model the detector shares its observers' model evaluation (one per period).
    force = cell.force
    step = (force.model_step if isinstance(force, VirtualForceSource) and force.model_dir == model_dir.resolve()
            else None)
    model = step.model if step is not None else load_observer_model(model_dir, robot, cfg.loop.period_s)
    point = np.asarray(cfg.virtual_sensor.wrench_point, float)

    def factory(task: str, contact_limit_n: float) -> Any:
        return build_guard(cfg.collision, model, robot, cfg.loop.period_s, task, contact_limit_n, point,
                           over_wire=cell.kind != "sim", model_step=step)

    return replace(cell, guard=factory)


def plan_settings() -> PlannerConfig:
    """The planner settings `plan` times its moves with (config/plans.yaml), its TCP speed stop included."""
    from tasks.setup.plan import load_plan_file

    return load_plan_file(CONFIG_DIR / "plans.yaml").planner


def run_prepare(cfg: CellConfig, tool: str, kind: str, seed: int | None, samples: int, force: bool,
                fast_moves: bool = False) -> dict[str, Any]:
    """Collect, train the causal H1 and calibrate for `tool` on a `kind` cell (each step skipped when done);
    `fast_moves`: the collection adds moves timed as `plan` times them."""
    from tasks.setup.prepare import prepare

    robot = robot_for(cfg, tool)
    check_plant(cfg, kind, seed, tool)
    opener, applier = calibration_cells(cfg, kind, tool, robot, seed)
    return prepare(cfg, tool, robot, opener, opener, applier, samples=samples, force=force,
                   cell_info=cell_identity(cfg, kind, seed), working_posture=working_posture(cfg, tool, robot),
                   fast_planner=plan_settings() if fast_moves else None)


def ensure_virtual_artefacts(cfg: CellConfig, tool: str, kind: str, robot: RobotModel,
                             seed: int | None = None) -> None:
    """The tool's model and calibration must be present and match: built on the spot for a simulated
    or emulated cell (same plant, logged), refused with the command to run for the real one."""
    from cell.sensing.artefacts import artefacts_missing

    why = artefacts_missing(cfg, robot, tool)
    simulated = is_simulated(kind)
    if not why:
        if simulated:
            _warn_other_plant(cfg, tool, seed)
        return
    if not simulated:
        raise ConfigError(
            f"virtual force sensor for the {tool} tool: {why}; make it on the cell with "
            f"`main.py prepare --tool {tool} --cell real` (or `main.py calibrate --tool {tool} --cell real` when "
            f"the model exists), or run with --force-source sensor"
        )
    log.warning("virtual force sensor for the %s tool: %s; building it now with `main.py prepare --tool %s` "
                "on the simulated cell (once, a couple of minutes)", tool, why, tool)
    run_prepare(cfg, tool, "sim", None, PREPARE_SAMPLES, force=False)


def _warn_other_plant(cfg: CellConfig, tool: str, seed: int | None) -> None:
    from cell.sensing.virtual_sensor import read_calibration_doc

    made = read_calibration_doc(cfg.virtual_sensor.path("calibration", tool)).get("cell", {})
    here = cell_identity(cfg, "sim", seed)
    if made.get("kind") == "sim" and made.get("plant_sha256") != here["plant_sha256"]:
        log.warning("the %s tool's virtual sensor was made on plant profile %s, this run uses %s: another arm "
                    "(other friction, other ripple), expect larger force errors; `main.py prepare --tool %s --force` "
                    "rebuilds it for this one", tool, made.get("plant"), here["plant"], tool)
