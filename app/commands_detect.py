"""The `detect` command: the collision detector over a dataset's test trajectories (a real arm's logs)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from app.common import emit, load_cell_config
from cell.cliargs import NTHREAD, SEED, int_in


def cmd_detect(args: argparse.Namespace) -> int:
    from tasks.lab.detect import detect

    data = Path(args.data)
    out, runs = detect(load_cell_config(args), data, args.robot, Path(args.model) if args.model else None,
                       samples=args.samples, nthread=args.nthread, seed=args.seed or 0)
    if args.plot:
        from tasks.lab.detect_plot import plot_detections

        out["plot"] = str(plot_detections(runs, Path(args.plot), f"collision detector on {data.parent.name} "
                                          f"({args.robot}, test trajectories)"))
    emit(out, args.json)
    return 0


def add_detect_parser(sub: Any) -> None:
    """`detect --robot NAME --data DATASET.yaml [--model DIR] [--samples N] [--plot PNG] [--json]`."""
    dp = sub.add_parser("detect", help="the collision detector over a dataset's test trajectories (e.g. UR10e logs)")
    dp.add_argument("--robot", default="tm5-700", help="robot by name (config/robots/<name>/; default tm5-700)")
    dp.add_argument("--data", required=True, help="dataset manifest (dataset.yaml); its test split is checked")
    dp.add_argument("--model", default=None,
                    help="hybrid model folder: loaded when it holds one, else fitted on the training split and saved")
    dp.add_argument("--samples", type=int_in(100), default=None, help="training samples (default: all)")
    dp.add_argument("--plot", default=None, help="PNG: residual/threshold per joint over time, detections marked")
    dp.add_argument("--nthread", type=NTHREAD, default=2, help="XGBoost threads for the fit")
    dp.add_argument("--config", type=Path, default=None, help="cell config YAML (default config/cell.yaml)")
    dp.add_argument("--seed", type=SEED, default=None, help="fitting seed (default 0)")
    dp.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")
    dp.set_defaults(func=cmd_detect)
