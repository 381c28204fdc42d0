"""The robot the model lab works on: the cell's arm (its URDF and nominal tool) or another robot's model."""

from __future__ import annotations

from typing import Any

from cell.config import CellConfig, resolve
from cell.model.robot import RobotModel, load_robot
from cell.model.specs import load_robot_spec, robot_model

CELL_ROBOT = "tm5-700"  # the cell's arm (and the simulated plant's): the lab's default --robot


def lab_robot(cfg: CellConfig, robot: str = CELL_ROBOT) -> RobotModel:
    """The nominal model the lab identifies against: for the cell's arm the cell config's URDF plus the
    nominal (wiping) tool; for another robot (`config/robots/<name>/`) its URDF with no tool."""
    if robot == CELL_ROBOT:
        return load_robot(resolve(cfg.robot.urdf), cfg.robot.tcp_wipe, cfg.robot.tool_mass, cfg.robot.tool_com)
    return robot_model(load_robot_spec(robot))


def lab_settings(robot: str = CELL_ROBOT) -> dict[str, Any]:
    """How the lab models a robot (TrainOptions fields): its robot.yaml `identification` and `learning`."""
    spec = load_robot_spec(robot)
    return {"identification": spec.identification, "coverage": spec.learning}
