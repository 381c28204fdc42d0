"""Command bodies of the model lab and the virtual sensor: prepare, calibrate, collect, train, evaluate, import."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from app.cells import calibration_cells, cell_identity, cell_kind, open_cell
from app.common import emit, load_cell_config
from app.progress import heartbeat
from app.sensing import PREPARE_SAMPLES, plan_settings, run_prepare
from app.tasks_registry import robot_for
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")


def cmd_prepare(args: argparse.Namespace) -> int:
    cfg = load_cell_config(args)
    with heartbeat(f"prepare --tool {args.tool}"):
        out = run_prepare(cfg, args.tool, args.cell, args.seed, args.samples, args.force, fast_moves=args.fast_moves)
    emit(out, args.json)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from tasks.setup.calibrate import calibrate

    cfg = load_cell_config(args)
    robot = robot_for(cfg, args.tool)
    model_dir = Path(args.model) if args.model else cfg.virtual_sensor.for_tool(args.tool).path("model", args.tool)
    if not (model_dir / "model.json").exists():
        fix = f"`main.py prepare --tool {args.tool} --cell {args.cell}` (collects, trains the model and calibrates)"
        if args.model or args.cell != "sim":
            raise ConfigError(f"calibrate: no torque model at {model_dir}; make it with {fix}")
        # A first use on the simulated cell: the model comes first, and prepare calibrates after it.
        log.warning("calibrate: no torque model at %s; running %s on the simulated cell first", model_dir, fix)
        out = run_prepare(cfg, args.tool, "sim", args.seed, PREPARE_SAMPLES, force=False)
        if args.out is None:
            emit(out, args.json)
            return 0
    opener, applier = calibration_cells(cfg, args.cell, args.tool, robot, args.seed)
    out = calibrate(cfg, args.tool, robot, opener, applier, Path(args.model) if args.model else None,
                    Path(args.out) if args.out else None, cell_identity(cfg, args.cell, args.seed))
    # The tool's weight on the F/T sensor, from 9 static wrist postures about home (free space, unloaded).
    from tasks.setup.weigh_tool import identify_tool_gravity

    out["tool_gravity"] = identify_tool_gravity(
        cfg, args.tool, robot, opener,
        Path(args.out) if args.out else cfg.virtual_sensor.for_tool(args.tool).path("calibration", args.tool))
    emit(out, args.json)
    return 0


def cmd_collect(args: argparse.Namespace) -> int:
    from cell.model.specs import robot_by_name
    from tasks.lab.collect import collect

    cfg = load_cell_config(args)
    robot = robot_by_name(cfg)
    kind = cell_kind(cfg, args.cell)

    def opener() -> Any:
        return open_cell(cfg, kind, robot, args.seed, "free")

    out = collect(cfg, opener, Path(args.out), samples=args.samples, family=args.family,
                  fourier_share=args.fourier_share, test_trajectories=args.test_trajectories,
                  test_repeats=args.test_repeats, test_moves=args.test_moves,
                  excitation=args.excitation, seed=args.plan_seed, robot=args.robot,
                  fast_share=args.fast_share, fast_planner=plan_settings() if args.fast_share > 0 else None)
    emit(out, args.json)
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from tasks.lab.train import train

    with heartbeat(f"train {args.model} ({args.learner})"):
        out = train(load_cell_config(args), Path(args.data), Path(args.out), kind=args.model, samples=args.samples,
                    window=args.window, grouping=args.grouping, derivatives=args.derivatives,
                    nthread=args.nthread, seed=args.seed or 0, robot=args.robot, learner=args.learner)
    emit(out, args.json)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from tasks.lab.evaluate import DEFAULT_CURVE, evaluate

    curve = None if args.no_curve else args.curve if args.curve else DEFAULT_CURVE
    out = evaluate(load_cell_config(args), Path(args.data), Path(args.out), train_samples=args.train_samples,
                   large_samples=args.large_samples, curve=curve, nthread=args.nthread, seed=args.seed or 0,
                   max_trees=args.max_trees, robot=args.robot, lofo=args.lofo, learners=args.learners,
                   tuned=[Path(d) for d in args.tuned] if args.tuned else None, max_epochs=args.max_epochs)
    emit(out, args.json)
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from tasks.lab.import_ur10e import import_ur10e

    out = import_ur10e(Path(args.out), train=args.train, test=args.test, loaded=args.loaded,
                       max_gap_s=args.max_gap_s, payload_kg=args.payload_kg,
                       add_test=args.add_test)
    emit(out, args.json)
    return 0
