"""Command bodies that work a cell: `run` a task, `status`, `emulate` a device."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from app.cells import cell_kind, open_cell
from app.common import emit, load_cell_config, save_bench_summary
from app.sensing import ensure_virtual_artefacts, make_force_source, with_guard
from app.tasks_registry import TASKS, build_task, robot_for
from cell.config import load_config


def cmd_run(args: argparse.Namespace) -> int:
    cfg = load_cell_config(args)
    spec = TASKS[args.task]
    robot = robot_for(cfg, spec.tool)
    task, max_duration = build_task(args.task, cfg, robot, args.force_source)
    kind = cell_kind(cfg, args.cell)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, spec.tool, kind, robot, args.seed)
    view = None
    if getattr(args, "view", False):
        from app.view import live_view

        view = live_view(robot, f"run-{args.task}", args.serve, args.force_source == "virtual")
    publisher = None
    if getattr(args, "publish", None):
        from cell.view.publish import WrenchPublisher, parse_endpoint

        publisher = WrenchPublisher(parse_endpoint(args.publish), robot.n)
    sinks = [s for s in (view, publisher) if s is not None]
    holder = open_cell(cfg, kind, robot, args.seed, spec.scene)
    try:
        cell = with_guard(cfg, spec.tool, make_force_source(cfg, args.force_source, spec.tool, holder.open(), robot),
                          robot)
        from tasks.runner import run_task

        summary = run_task(task, cell, cfg, robot, max_duration, record=not args.no_record,
                           extra_summary={"seed": args.seed}, view=_one_sink(sinks))
    finally:
        holder.close()
        if publisher is not None:
            publisher.close()
    emit(summary, args.json)
    if view is not None:
        from app.view import finish_view

        finish_view(view, args.serve)
    if summary["outcome"] == "interrupted":
        return 130
    save_bench_summary(summary, f"run-{args.task}", run_tags(kind, args.force_source), args)
    return 0 if summary["outcome"] == "done" else 1


def _one_sink(sinks: list[Any]) -> Any:
    """The loop's row consumer: none, the one asked for, or both (the live view and the publisher)."""
    if len(sinks) <= 1:
        return sinks[0] if sinks else None
    from cell.view.publish import RowSinks

    return RowSinks(sinks)


def run_tags(kind: str, force_source: str) -> list[str]:
    """The tags of a run's saved summary (`run-<task>[-<cell>][-sensor]`): the simulated cell and the virtual
    sensor are the defaults."""
    return ([kind] if kind != "sim" else []) + (["sensor"] if force_source == "sensor" else [])


def cmd_status(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    robot = robot_for(cfg, "wipe")
    holder = open_cell(cfg, cell_kind(cfg, args.cell), robot, args.seed, None)
    try:
        cell = holder.open()
        state = cell.arm.read_state()
        wrench = cell.force.read(state)
        tcp = robot.tcp_pose(state.q).translation
        out = {
            "cell": cell.kind,
            "lifecycle": cell.arm.lifecycle.value,
            "t": state.t,
            "q_deg": np.degrees(state.q).round(3).tolist(),
            "dq_deg_s": np.degrees(state.dq).round(3).tolist(),
            "tau_nm": np.round(state.tau, 3).tolist(),
            "status": {k: bool(v) for k, v in vars(state.status).items()},
            "tcp_m": np.round(tcp, 4).tolist(),
            "wrench": np.round(wrench.vector, 3).tolist(),
        }
    finally:
        holder.close()
    emit(out, args.json)
    return 0


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve one device emulator until Ctrl+C (for standard tools or a second process)."""
    if args.device == "cell":
        from sim.emulated import serve_cell

        cfg = load_cell_config(args)
        return serve_cell(cfg, args.seed, args.scene or cfg.scene.kind)
    if args.device == "arm":
        from sim.tm5_emulator import emulate_arm_main

        plant = None
        if not args.kinematic:
            from sim.cell import make_plant

            plant = make_plant(load_config(args.config), args.seed, "free")
        return emulate_arm_main(args.port, plant)
    from sim.wacoh_emulator import emulate_sensor_main

    return emulate_sensor_main(args.seed or 0)
