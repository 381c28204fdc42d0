"""`run hand-guide [--teach FILE.yaml]` and `bench hand-guide`: sensorless hand guiding."""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from typing import Any

import numpy as np
import yaml

from app.cells import cell_kind, open_cell
from app.commands_cell import run_tags
from app.common import emit, load_cell_config, save_bench_summary
from app.sensing import ensure_virtual_artefacts, make_force_source, with_guard
from app.tasks_registry import robot_for
from cell.collision.config import TaskContactSafety
from cell.config import CellConfig
from cell.control.loop import OpenCell
from cell.model.robot import RobotModel
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")

TOOL = "wipe"  # guided with the wiping tool mounted (its virtual sensor)
# On the simulated cell the scripted hand places the tool at three points, resting at each (what --teach records).
DEMO_PATH = [[0.0, 0.0, 0.0], [0.0, 0.15, 0.0], [0.08, 0.15, -0.05], [0.08, 0.0, -0.05]]


def _wrapper(cfg: CellConfig, robot: RobotModel, force_source: str) -> Any:
    """The cell as hand guiding runs on it: its force source (the virtual sensor with the guiding's own
    settings, `tasks.hand_guide.virtual_sensor`) and the collision guard (the cell's settings)."""
    from tasks.hand_guide import guiding_sensor, load_hand_guide_config

    where = f"{cfg.source}: tasks.hand_guide"
    hcfg = load_hand_guide_config(cfg.tasks.get("hand_guide"), where)
    sensor = guiding_sensor(cfg.virtual_sensor, TOOL, hcfg.virtual_sensor, f"{where}.virtual_sensor")
    guiding = replace(cfg, virtual_sensor=sensor)

    def wrap(cell: OpenCell) -> OpenCell:
        return with_guard(cfg, TOOL, make_force_source(guiding, force_source, TOOL, cell, robot), robot)

    return wrap


def _inertia(cfg: CellConfig, robot: RobotModel, force_source: str) -> Any:
    """The arm's Cartesian inertia from the tool's hybrid model (rotors included), with which the task predicts
    the virtual sensor's read-back of its own commanded acceleration; None for the F/T sensor (no read-back)."""
    if force_source != "virtual":
        return None
    from cell.sensing.virtual_sensor import load_observer_model
    from tasks.hand_guide import model_inertia

    return model_inertia(robot, load_observer_model(cfg.virtual_sensor.path("model", TOOL), robot, cfg.loop.period_s))


def cmd_hand_guide(args: argparse.Namespace) -> int:
    from tasks.hand_guide import taught_task_file

    if args.file is not None:
        raise ConfigError("run hand-guide takes no task file (--teach FILE.yaml writes one)")
    if args.teach is not None and args.teach.suffix not in (".yaml", ".yml"):
        raise ConfigError(f"--teach {args.teach}: must name a .yaml file")
    cfg = load_cell_config(args)
    robot = robot_for(cfg, TOOL)
    kind = cell_kind(cfg, args.cell)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, TOOL, kind, robot, args.seed)
    if kind == "sim":
        from bench.hand_guide import guided_run, hand_guide_figures
        from sim.hand_guide import HandScript

        script = HandScript(path=DEMO_PATH, speed_mps=0.05, pause_s=1.5, settle_s=1.5, release_s=2.0)
        summary, hand, task = guided_run(cfg, robot, script, args.seed, _wrapper(cfg, robot, args.force_source),
                                         record=not args.no_record, inertia=_inertia(cfg, robot, args.force_source),
                                         readback=args.force_source == "virtual")
        figures = hand_guide_figures(hand, task, summary)
        summary.update({k: v for k, v in figures.items() if k not in summary})
    else:
        from tasks.hand_guide import HandGuideTask, load_hand_guide_config
        from tasks.runner import run_task

        hcfg = load_hand_guide_config(cfg.tasks.get("hand_guide"), f"{cfg.source}: tasks.hand_guide")
        if args.force_source != "virtual":
            hcfg.inertia_readback = 0.0  # the F/T sensor reads no commanded acceleration back
        try:
            task = HandGuideTask(hcfg, robot, cfg.loop.period_s, np.asarray(cfg.robot.home, float),
                                 inertia=_inertia(cfg, robot, args.force_source))
        except ValueError as exc:
            raise ConfigError(f"{cfg.source}: tasks.hand_guide: {exc}") from None
        cfg.collision.tasks[task.name] = TaskContactSafety(contact_states=["guide"])
        holder = open_cell(cfg, kind, robot, args.seed, "free")
        try:
            log.warning("hand guiding: take the tool after the tare; Ctrl+C ends (keep a hand on the E-stop)")
            summary = run_task(task, _wrapper(cfg, robot, args.force_source)(holder.open()), cfg, robot,
                               hcfg.duration_s + 60.0, record=not args.no_record, extra_summary={"seed": args.seed})
        finally:
            holder.close()
    summary["taught"] = task.taught
    if args.teach is not None:
        doc = taught_task_file(task.taught, [180.0, 0.0, 0.0], TOOL, args.teach.stem.lower().replace(" ", "-")[:40])
        args.teach.parent.mkdir(parents=True, exist_ok=True)
        args.teach.write_text("# Taught by hand guiding (main.py run hand-guide --teach).\n"
                              + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
        summary["teach_file"] = str(args.teach)
        log.info("%d taught poses written to %s", len(task.taught), args.teach)
    emit(summary, args.json)
    if summary["outcome"] == "interrupted":
        return 130
    save_bench_summary(summary, "run-hand-guide", run_tags(kind, args.force_source), args)
    return 0 if summary["outcome"] == "done" else 1


def bench_hand_guide_cmd(args: argparse.Namespace) -> dict[str, Any]:
    from bench.hand_guide import bench_hand_guide

    cfg = load_cell_config(args)
    robot = robot_for(cfg, TOOL)
    ensure_virtual_artefacts(cfg, TOOL, "sim", robot, args.seed)
    return bench_hand_guide(cfg, robot, args.seed, _wrapper(cfg, robot, "virtual"),
                            inertia=_inertia(cfg, robot, "virtual"))
