"""The torque model planning uses, and where planning's per-arm settings are kept: the prepared hybrid model (made on
a simulated cell when missing), its name (which keys every stored setting), and the settings' folder."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from app.cells import is_simulated
from app.sensing import PREPARE_SAMPLES, run_prepare
from app.tasks_registry import robot_for
from cell.config import CONFIG_DIR, CellConfig
from cell.model.robot import RobotModel
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")
NOMINAL = "nominal"  # --model nominal: the URDF's rigid body (P1), no prepared model needed
PLANS = CONFIG_DIR / "plans.yaml"  # the named paths and the planner settings `main.py plan` uses
ARTEFACTS = Path("artifacts/planning")  # bench planning's calibrations and policy, keyed by what they were made for


def planning_model(cfg: CellConfig, model: str | None, kind: str, plans_tcp_speed: float
                   ) -> tuple[RobotModel, Any, str, Any]:
    """What `plan` and `bench planning` plan with: `--model` (a saved model, `nominal`, or None: the prepared one,
    made first when missing, on the cell's config as given, as `run` makes it); then `cfg`'s TCP speed stop is
    raised to the plan file's limit, as the plans run (in place).  Returns the robot, the torque predictor, its
    name and toppra's part of it (`torque_model`)."""
    path = None if model == NOMINAL else model or prepared_model(cfg, kind)
    cfg.safety = replace(cfg.safety, max_tcp_speed=plans_tcp_speed)
    robot = robot_for(cfg, "wipe")
    return (robot, *torque_model(cfg, robot, path))


def torque_model(cfg: CellConfig, robot: RobotModel, path: str | None) -> tuple[Any, str, Any]:
    """The torque predictor the planner uses, its name and the part toppra takes as its constraint:
    a saved model artefact, or the nominal rigid body (P1)."""
    if path:
        from cell.model.dynamics.artefact import load_model  # the model lab's artefacts
        from cell.planning.constraints import toppra_terms

        model = load_model(Path(path), robot)
        return model.predict, model_name(model, path), toppra_terms(model)
    log.warning("--model %s: planning with the nominal rigid-body model (P1, no rotor inertia or friction); "
                "validation on the cell corrects the plan where it is wrong", NOMINAL)

    def p1(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    return p1, "P1 (nominal URDF)", None


def model_name(model: Any, path: str) -> str:
    """A saved model's name as planning knows it.  The name keys the calibrations and the policy stored for it,
    so it carries the saved files' content hash: a model trained again, on other data or with other settings, is
    another model."""
    from cell.sensing.virtual_sensor import model_identity

    return f"{model.meta.kind} ({path}, model {model_identity(Path(path))[:12]})"


def prepared_model_name(cfg: CellConfig, robot: RobotModel) -> str | None:
    """The name of the model `plan` uses on this cell (the wipe tool's prepared one), None while none is prepared:
    what `bench planning`'s stored settings must have been made for."""
    from cell.model.dynamics.artefact import load_model

    prepared = cfg.virtual_sensor.path("model", "wipe")
    if not (prepared / "model.json").exists():
        return None
    return model_name(load_model(prepared, robot), str(prepared))


def prepared_model(cfg: CellConfig, kind: str) -> str:
    """The wipe tool's prepared hybrid model: the plan's torque limits are the arm's own (rotor inertia,
    friction).  Missing on a simulated cell it is prepared now, on `cfg` as the cell's config gives it (its
    collection keeps to the cell's limits: a config changed for planning would collect another dataset than
    `run` does); on the real arm the command says how."""
    prepared = cfg.virtual_sensor.path("model", "wipe")
    if not (prepared / "model.json").exists():
        if not is_simulated(kind):
            raise ConfigError(f"plan: no prepared model at {prepared}: make it on this arm with `main.py prepare "
                              f"--tool wipe --cell {kind}`, or plan on the nominal rigid body with --model {NOMINAL}")
        log.warning("plan: no prepared model at %s; preparing it now on the simulated cell (`main.py prepare "
                    "--tool wipe`, once, a couple of minutes; --model %s plans on the nominal rigid body instead)",
                    prepared, NOMINAL)
        run_prepare(cfg, "wipe", "sim", None, PREPARE_SAMPLES, force=False)
    log.info("planning with the prepared hybrid model %s (--model to choose another)", prepared)
    return str(prepared)
