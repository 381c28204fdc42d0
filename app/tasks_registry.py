"""The task registry: each task's tool, simulated scene and config section, and how to build it from the cell config."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.config import CellConfig, SceneKind, check_home, check_task_force, check_task_speeds
from cell.control.guarded import check_speeds
from cell.model.robot import RobotModel
from cell.model.specs import cell_robot
from drivers.errors import ConfigError

SWEEP_LIFT_M = 0.1  # the sweeps' centre: the task's start lifted this far (the collection keeps off the table)


@dataclass(frozen=True)
class TaskSpec:
    """One task the CLI can run: `build(cfg, robot, section, force_source)` -> (task, max duration in s)."""

    name: str
    tool: str  # the tool mounted: the task's virtual sensor uses that tool's model and calibration
    scene: SceneKind  # the simulated fixture the task works on
    section: str  # its settings: `tasks.<section>` in the cell config
    build: Callable[[CellConfig, RobotModel, str, str], tuple[Any, float]]


def _build_wipe(cfg: CellConfig, robot: RobotModel, section: str, force_source: str) -> tuple[Any, float]:
    from tasks.wipe import WipeTask, load_wipe_config

    where = f"{cfg.source}: tasks.{section}"
    wcfg = load_wipe_config(cfg.tasks.get(section), where)
    check_task_force(cfg, section, wcfg.max_force_n)
    check_task_speeds(cfg, section, wcfg)
    check_speeds(cfg.collision.guarded, {"approach_speed_mps": wcfg.approach_speed_mps}, wcfg.max_force_n, where)
    try:
        task = WipeTask(wcfg, robot, cfg.scene.table_height, cfg.loop.period_s, np.asarray(cfg.robot.home))
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return task, wcfg.max_duration_s


def peg_head_on_speeds(p: Any) -> dict[str, float]:
    """The peg's speeds toward a face it may meet head-on (cell/control/guarded.py), wedges in the bore included.
    Not bounded: the survey's moves between touch points (above the nominal face by more than its tilt
    allows), and the free feed deeper than a peg can wedge (mu x D, `wedge_friction`), where the walls
    are sliding contacts."""
    return {name: getattr(p, name) for name in (
        "approach_speed_mps", "slow_speed_mps", "survey_speed_mps", "slide_slow_speed_mps", "chord_speed_mps",
        "entry_speed_mps", "centre_speed_mps", "wedge_speed_mps", "tight_insert_speed_mps")}


def _build_peg(cfg: CellConfig, robot: RobotModel, section: str, force_source: str) -> tuple[Any, float]:
    from tasks.peg.config import load_peg_config
    from tasks.peg.task import PegInHoleTask

    where = f"{cfg.source}: tasks.{section}"
    pcfg = load_peg_config(cfg.tasks.get(section), where, force_source)
    check_task_force(cfg, section, pcfg.max_force_n)
    check_task_speeds(cfg, section, pcfg)
    check_speeds(cfg.collision.guarded, peg_head_on_speeds(pcfg), pcfg.max_force_n, where)
    try:
        task = PegInHoleTask(pcfg, robot, np.asarray(cfg.scene.hole_center, float), cfg.scene.table_height,
                             cfg.loop.period_s, np.asarray(cfg.robot.home))
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return task, pcfg.max_duration_s


TASKS: dict[str, TaskSpec] = {spec.name: spec for spec in (
    TaskSpec("wipe", tool="wipe", scene="table", section="wipe", build=_build_wipe),
    TaskSpec("peg-in-hole", tool="peg", scene="peg", section="peg", build=_build_peg),
)}
TASK_NAMES = tuple(TASKS)
TASK_TOOLS = {name: spec.tool for name, spec in TASKS.items()}


def build_task(name: str, cfg: CellConfig, robot: RobotModel, force_source: str = "virtual") -> tuple[Any, float]:
    spec = TASKS.get(name)
    if spec is None:
        raise ConfigError(f"unknown task '{name}' (known: {', '.join(TASK_NAMES)})")
    return spec.build(cfg, robot, spec.section, force_source)


def robot_for(cfg: CellConfig, tool: str) -> RobotModel:
    """The cell's arm with `tool` mounted (its TCP), the config's home checked against it."""
    tcp = cfg.robot.tcp_wipe if tool == "wipe" else cfg.robot.tcp_peg
    robot = cell_robot(cfg, tcp)
    check_home(cfg, robot)
    return robot


def working_posture(cfg: CellConfig, tool: str, robot: RobotModel) -> np.ndarray:
    """Where `prepare` sweeps slowly: the joints of the tool's task start, with the tool lifted
    `SWEEP_LIFT_M` (the task's regime of postures and speeds, clear of the work surface)."""
    task, _ = build_task(next(t for t, k in TASK_TOOLS.items() if k == tool), cfg, robot)
    q0 = np.asarray(task.q_start, float)
    pose = robot.tcp_pose(q0)
    pose.translation = pose.translation + np.array([0.0, 0.0, SWEEP_LIFT_M])
    q, ok = robot.ik(pose, q0)
    if not ok:
        raise ConfigError(f"the {tool} tool's working posture lifted {SWEEP_LIFT_M} m is not reachable")
    return np.asarray(q, float)
