"""`run task FILE.yaml` (a task file of primitives) and `run hand-guide` (sensorless hand guiding): the
`run` command's tasks that are not in the task registry."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import numpy as np

from app.cells import cell_kind, open_cell
from app.commands_cell import cmd_run, run_tags
from app.common import emit, load_cell_config, save_bench_summary
from app.sensing import ensure_virtual_artefacts, make_force_source, with_guard
from app.tasks_registry import robot_for
from cell.config import CellConfig
from cell.model.robot import RobotModel
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")

RUN_EXTRA_TASKS = ("task", "hand-guide")


def add_taskfile_options(run: argparse.ArgumentParser) -> None:
    """The `run` options of these two: the task file, and the file hand guiding teaches into."""
    run.add_argument("file", nargs="?", type=Path, default=None,
                     help="run task: the task file (YAML: docs/task-files.md)")
    run.add_argument("--teach", type=Path, default=None, metavar="FILE.yaml",
                     help="run hand-guide: record the taught poses into this task file")


def cmd_run_dispatch(args: argparse.Namespace) -> int:
    """`run`: a task file, hand guiding, or a registered task."""
    if args.task == "task":
        return cmd_run_taskfile(args)
    if args.task == "hand-guide":
        from app.commands_hand_guide import cmd_hand_guide

        return cmd_hand_guide(args)
    if getattr(args, "file", None) is not None or getattr(args, "teach", None) is not None:
        raise ConfigError(f"run {args.task}: a file and --teach are for `run task FILE` and `run hand-guide`")
    return cmd_run(args)


def load_checked(path: Path, cfg: CellConfig) -> tuple[Any, RobotModel]:
    """The task file, checked against the cell (limits, guarded speeds) and its arm (every pose reachable)."""
    from tasks.primitives.taskfile import load_task_file

    tf = load_task_file(path, cfg.collision.guarded, cfg.safety.max_tool_force_n)
    robot = robot_for(cfg, tf.header.tool)
    home = np.asarray(cfg.robot.home, float)
    lo, hi = np.asarray(cfg.safety.workspace_min), np.asarray(cfg.safety.workspace_max)
    for name, pose in tf.poses.items():
        line = tf.pose_lines.get(name, 1)
        if isinstance(pose, np.ndarray):
            lim = robot.limits
            if np.any(pose < lim.lower) or np.any(pose > lim.upper):
                raise ConfigError(f"{path}: line {line}: poses.{name}: a joint is outside its limits")
            continue
        if np.any(pose.translation < lo) or np.any(pose.translation > hi):
            raise ConfigError(f"{path}: line {line}: poses.{name}: {pose.translation.round(3).tolist()} is outside "
                              "the cell's workspace box (safety.workspace_min/max)")
        _, ok = robot.ik(pose, home)
        if not ok:
            raise ConfigError(f"{path}: line {line}: poses.{name}: {pose.translation.round(3).tolist()} is not "
                              f"reachable with the {tf.header.tool} tool")
    return tf, robot


def cmd_run_taskfile(args: argparse.Namespace) -> int:
    from tasks.primitives.runner import TaskFileTask
    from tasks.runner import run_task

    if args.file is None:
        raise ConfigError("run task: name the task file (main.py run task FILE.yaml)")
    cfg = load_cell_config(args)
    tf, robot = load_checked(args.file, cfg)
    task = TaskFileTask(tf, robot, cfg.loop.period_s)
    # The guard's table for this file (its contact steps and per-step reactions), under its run name.
    cfg.collision.tasks[task.name] = task.collision_settings()
    kind = cell_kind(cfg, args.cell)
    tool = tf.header.tool
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, tool, kind, robot, args.seed)
    holder = open_cell(cfg, kind, robot, args.seed, tf.header.scene)
    try:
        cell = with_guard(cfg, tool, make_force_source(cfg, args.force_source, tool, holder.open(), robot), robot)
        summary = run_task(task, cell, cfg, robot, tf.header.max_duration_s, record=not args.no_record,
                           extra_summary={"seed": args.seed})
        plant = getattr(holder, "plant", None)
        if plant is not None:
            summary.update(score_reports(task, plant))
    finally:
        holder.close()
    emit(summary, args.json)
    if summary["outcome"] == "interrupted":
        return 130
    save_bench_summary(summary, f"run-task-{tf.header.name}", run_tags(kind, args.force_source), args)
    return 0 if summary["outcome"] == "done" else 1


def score_reports(task: Any, plant: Any) -> dict[str, Any]:
    """On the simulated cell: each report that names a `truth` landmark, against where the plant has it."""
    from sim.landmarks import landmarks

    marks = landmarks(plant)
    out: dict[str, Any] = {}
    for step, prim in zip(task.steps, task.prims, strict=True):
        truth = getattr(step.params, "truth", None)
        if step.kind != "report" or truth is None or "point_m" not in prim.result:
            continue
        true = marks.get(truth)
        if true is None:
            out[step.params.name] = {"truth": truth, "error": f"no landmark '{truth}' in this scene"}
            continue
        got = np.asarray(prim.result["point_m"][:len(true)], float)
        err = got - np.asarray(true, float)
        out[step.params.name] = {"truth": truth, "true_m": true, "measured_m": got.tolist(),
                                 "error_mm": float(np.linalg.norm(err) * 1e3),
                                 "error_axes_mm": (err * 1e3).round(4).tolist()}
    return {"truth_scores": out} if out else {}
