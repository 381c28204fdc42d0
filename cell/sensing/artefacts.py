"""Whether a tool's virtual-sensor artefacts (torque model, calibration) are in place and made for this cell."""

from __future__ import annotations

from pathlib import Path

from cell.config import CellConfig
from cell.model.dynamics.artefact import load_model
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from cell.sensing.virtual_sensor import check_calibration, period_mismatch, read_calibration_doc
from drivers.errors import DataError


def calibration_matches(cfg: CellConfig, robot: RobotModel, tool: str, model_dir: Path, cal_dir: Path) -> str:
    """'' when the calibration at `cal_dir` fits this robot, tool and model; else why not."""
    try:
        model = load_model(model_dir, robot)
        if not isinstance(model, LearnedModel):
            return f"{model_dir} is not a hybrid model"
        check_calibration(read_calibration_doc(cal_dir), str(cal_dir), robot, tool, model_dir, model)
    except DataError as exc:
        return str(exc)
    return ""


def artefacts_missing(cfg: CellConfig, robot: RobotModel, tool: str) -> str:
    """'' when the tool's model and calibration are in place and match; else what is wrong."""
    vs = cfg.virtual_sensor
    model_dir, cal_dir = vs.path("model", tool), vs.path("calibration", tool)
    if not (model_dir / "model.json").exists():
        return f"no torque model at {model_dir}"
    if not (cal_dir / "calibration.json").exists():
        return f"no calibration at {cal_dir}"
    why = period_mismatch(model_dir, load_model(model_dir, robot).meta, cfg.loop.period_s)
    if why:
        return why
    return calibration_matches(cfg, robot, tool, model_dir, cal_dir)

