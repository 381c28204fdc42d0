"""The `replay` command: the virtual sensor again over a recorded run, with the run's config or another observer."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from app.common import emit
from app.tasks_registry import TASKS, robot_for
from cell.config import load_config
from drivers.errors import ConfigError


def cmd_replay(args: argparse.Namespace) -> int:
    from tasks.setup.replay import read_run, replay

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
                    summary.get("force_source") == "virtual", args.bind)
    return 0


def add_replay_parser(sub: Any) -> None:
    """`replay RUN_DIR [--observer] [--mapping] [--model] [--calibration] [--config] [--view] [--json]`."""
    from app.view import add_view_options

    rp = sub.add_parser("replay", help="the virtual sensor again over a recorded run's joint data, scored as the run")
    rp.add_argument("run_dir", help="a recorded run (runs/<time>-<task>/)")
    rp.add_argument("--observer", choices=("kalman", "momentum"), default=None, help="default: the run's config")
    rp.add_argument("--mapping", choices=("jacobian", "learned", "contact"), default=None,
                    help="default: the run's config")
    rp.add_argument("--model", default=None, help="torque model artefact (default: the run config's)")
    rp.add_argument("--calibration", default=None, help="calibration folder (default: the run config's)")
    rp.add_argument("--config", type=Path, default=None, help="cell config (default: the run's config.yaml)")
    add_view_options(rp, "the recording and the replayed wrench")
    rp.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")
    rp.set_defaults(func=cmd_replay)
