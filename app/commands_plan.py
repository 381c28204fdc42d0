"""The `plan` command: time-optimal plans under the torque model's limits, validated on a cell."""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from app.cells import cell_kind, open_cell
from app.common import emit, save_bench_summary
from app.sensing import with_guard
from app.tasks_registry import robot_for
from cell.config import CellConfig, load_config
from cell.robot import RobotModel
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")


def torque_model(cfg: CellConfig, robot: RobotModel, path: str | None) -> tuple[Any, str, Any]:
    """The torque predictor the planner uses, its name and the part toppra takes as its constraint:
    a saved model artefact, or the nominal rigid body (P1)."""
    if path:
        from cell.dynamics.artefact import load_model  # the model lab's artefacts
        from cell.planner import toppra_terms

        model = load_model(Path(path), robot)
        return model.predict, f"{model.meta.kind} ({path})", toppra_terms(model)
    log.warning("no --model and no prepared model (main.py prepare): planning with the nominal rigid-body model "
                "(P1, no rotor inertia or friction); validation on the cell corrects the plan where it is wrong")

    def p1(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    return p1, "P1 (nominal URDF)", None


def cmd_plan(args: argparse.Namespace) -> int:
    from cell.collision import CollisionChecker
    from tasks.plan import load_plan_file, parse_waypoints, run_plans

    cfg = load_config(args.config)
    plan_file = load_plan_file(args.plans)
    if args.waypoints:
        plan_file = replace(plan_file, paths={"cli": parse_waypoints(args.waypoints)})
    only = args.path or None
    if only:
        unknown = [p for p in only if p not in plan_file.paths]
        if unknown:
            raise ConfigError(f"{args.plans}: no path named '{unknown[0]}' (known: {', '.join(plan_file.paths)})")
    cfg.safety = replace(cfg.safety, max_tcp_speed=plan_file.max_tcp_speed)
    robot = robot_for(cfg, "wipe")
    model_path = args.model
    if model_path is None:
        prepared = cfg.virtual_sensor.path("model", "wipe")
        if (prepared / "model.json").exists():
            model_path = str(prepared)
            log.info("planning with the prepared hybrid model %s (--model to choose another)", prepared)
    predictor, model_name, terms = torque_model(cfg, robot, model_path)
    collisions = CollisionChecker(robot, replace(cfg.scene, kind="free"))

    def open_for_plan() -> tuple[Any, Any]:
        holder = open_cell(cfg, cell_kind(cfg, args.cell), robot, args.seed, "free")
        try:
            return with_guard(cfg, "wipe", holder.open(), robot), holder
        except BaseException:
            holder.close()
            raise

    out = run_plans(cfg, robot, predictor, model_name, plan_file, open_for_plan, collisions,
                    Path(cfg.recording.directory) / "plans", only, terms)
    emit(out, args.json)
    tags = (["waypoints"] if args.waypoints else []) + [f"path-{name}" for name in only or []]
    save_bench_summary(out, "plan", tags, args)
    return 0
