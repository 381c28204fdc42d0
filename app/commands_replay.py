"""The `replay` command: the virtual sensor again over a recorded run, with the run's config or another observer."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.common import emit
from app.tasks_registry import TASKS, robot_for
from cell.config import load_config
from drivers.errors import ConfigError


def cmd_replay(args: argparse.Namespace) -> int:
    from tasks.replay import read_run, replay

    run_dir = Path(args.run_dir)
    summary, _ = read_run(run_dir)
    task = str(summary.get("task", ""))
    if task not in TASKS:
        raise ConfigError(f"{run_dir / 'summary.json'}: task '{task}' is not one replay knows "
                          f"({', '.join(TASKS)})")
    # The run's own resolved config: the same period, virtual-sensor settings and artefact paths it ran with.
    cfg = load_config(args.config if args.config else run_dir / "config.yaml")
    robot = robot_for(cfg, TASKS[task].tool)
    out, est = replay(cfg, robot, TASKS[task].tool, task, run_dir, args.observer, args.mapping,
                 Path(args.model) if args.model else None, Path(args.calibration) if args.calibration else None)
    emit(out, args.json)
    if args.view:
        from app.view import view_replay

        view_replay(run_dir, robot, est, str(out["virtual_sensor"]), args.serve,
                    summary.get("force_source") == "virtual")
    return 0
