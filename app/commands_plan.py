"""The `plan` command: time-optimal plans under the torque model's limits, validated on a cell."""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from app.cells import cell_kind, open_cell
from app.common import emit, save_bench_summary
from app.planning_model import ARTEFACTS, planning_model
from app.sensing import with_guard
from cell.config import CellConfig, load_config
from cell.model.robot import RobotModel
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")


def kinematic_baseline(cfg: CellConfig, robot: RobotModel, predictor: Any, pcfg: Any, collisions: Any, kind: str,
                       seed: int | None, store: Path) -> tuple[Any, str]:
    """The calibrated kinematic planner (TOPP-RA with speed and acceleration limits only, the accelerations
    calibrated once per arm on the plant by `bench planning`), or None and why not: without a calibration
    made for this arm and these planner settings there is no honest kinematic figure to give.  `store`: the
    folder `bench planning` keeps its calibrations in."""

    from app.cells import cell_identity
    from bench.planning_calibration import kinematic_calibration_key
    from cell.planning.baselines import KinematicPlanner

    path = store / "kinematic.json"
    if not path.exists():
        return None, f"not calibrated (no {path}; `main.py bench planning` calibrates it on a simulated cell)"
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return None, f"not calibrated ({path} unreadable: {exc})"
    key = kinematic_calibration_key({k: v for k, v in cell_identity(cfg, kind, seed).items() if k != "seed"}, pcfg)
    if not isinstance(stored, dict) or stored.get("key") != json.loads(json.dumps(key)):
        return None, f"not calibrated for this arm or these planner settings ({path} was made for others)"
    acc = np.minimum(stored["acceleration_limits"], pcfg.acceleration_limits).tolist()
    return (KinematicPlanner(robot, predictor, replace(pcfg, acceleration_limits=acc), collisions),
            f"calibrated ({path}, fraction {stored.get('fraction')})")


def add_kinematic_comparison(out: dict[str, Any], baseline: tuple[Any, str], paths: dict[str, Any], cfg: CellConfig,
                             robot: RobotModel, open_for_plan: Any) -> None:
    """Each path's optimised time against the calibrated kinematic planner's, executed once on the same cell
    (`improvement_vs_kinematic_pct`), beside the uniform baseline's (`improvement_vs_uniform_pct`)."""
    from cell.control.signals import raise_if_interrupted
    from cell.planning.planner import PlanningError
    from tasks.setup.plan import execute

    planner, status = baseline
    out["kinematic_baseline"] = status
    gains = []
    for name, row in out["paths"].items():
        row["kinematic_s"] = row["improvement_vs_kinematic_pct"] = None
        if planner is None:
            row["improvement_vs_kinematic_pct"] = "not calibrated"
            continue
        try:
            traj = planner.plan(np.radians(np.asarray(paths[name], float)))
        except PlanningError as exc:
            row["kinematic_outcome"] = f"plan_failed: {exc}"
            continue
        summary = execute(traj, cfg, robot, open_for_plan)
        raise_if_interrupted(summary["outcome"])
        row["kinematic_outcome"] = summary["outcome"]
        if summary["outcome"] == "done" and summary.get("elapsed_s") and row["optimized_s"]:
            row["kinematic_s"] = summary["elapsed_s"]
            row["improvement_vs_kinematic_pct"] = 100.0 * (1.0 - row["optimized_s"] / summary["elapsed_s"])
            gains.append(row["improvement_vs_kinematic_pct"])
    complete = planner is not None and len(gains) == len(out["paths"])
    out["mean_improvement_vs_kinematic_pct"] = float(np.mean(gains)) if complete else (
        "not calibrated" if planner is None else None)
    out["min_improvement_vs_kinematic_pct"] = min(gains) if complete else out["mean_improvement_vs_kinematic_pct"]


def cmd_plan(args: argparse.Namespace) -> int:
    from cell.collision.geometry import CollisionChecker
    from tasks.setup.plan import load_plan_file, parse_waypoints, run_plans

    cfg = load_config(args.config)
    plan_file = load_plan_file(args.plans)
    if args.waypoints:
        plan_file = replace(plan_file, paths={"cli": parse_waypoints(args.waypoints)})
    only = args.path or None
    if only:
        unknown = [p for p in only if p not in plan_file.paths]
        if unknown:
            raise ConfigError(f"{args.plans}: no path named '{unknown[0]}' (known: {', '.join(plan_file.paths)})")
    robot, predictor, model_name, terms = planning_model(cfg, args.model, cell_kind(cfg, args.cell),
                                                         plan_file.max_tcp_speed)
    collisions = CollisionChecker.for_scene(robot, replace(cfg.scene, kind="free"))

    def open_for_plan() -> tuple[Any, Any]:
        holder = open_cell(cfg, cell_kind(cfg, args.cell), robot, args.seed, "free")
        try:
            return with_guard(cfg, "wipe", holder.open(), robot), holder
        except BaseException:
            holder.close()
            raise

    out = run_plans(cfg, robot, predictor, model_name, plan_file, open_for_plan, collisions,
                    Path(cfg.recording.directory) / "plans", only, terms)
    kind = cell_kind(cfg, args.cell)
    add_kinematic_comparison(out, kinematic_baseline(cfg, robot, predictor, plan_file.planner, collisions, kind,
                                                     args.seed, ARTEFACTS), plan_file.paths, cfg, robot, open_for_plan)
    emit(out, args.json)
    tags = (["waypoints"] if args.waypoints else []) + [f"path-{name}" for name in only or []]
    save_bench_summary(out, "plan", tags, args)
    return 0
