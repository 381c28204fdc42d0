"""What the command bodies share: the cell config from --config and --plant, and printing a command's summary."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.figures import save_summary, summary_name
from cell.config import CellConfig, load_config
from drivers.configio import dumps_strict

log = logging.getLogger("tmcell")


def load_cell_config(args: argparse.Namespace) -> CellConfig:
    """The --config file, with the plant profile --plant (where the command takes one) in place of its own."""
    cfg = load_config(args.config)
    if getattr(args, "plant", None):
        cfg.plant = str(Path(args.plant).resolve())
    return cfg


def emit(out: dict[str, Any], as_json: bool) -> None:
    """The summary on stdout: one strict-JSON line, or `key: value` lines (a nested dict indented)."""
    if as_json:
        print(dumps_strict(out))
        return
    for key, value in out.items():
        if isinstance(value, dict):
            print(f"{key}:")
            for k, v in value.items():
                print(f"  {k}: {_fmt(v)}")
        else:
            print(f"{key}: {_fmt(value)}")


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def save_bench_summary(out: dict[str, Any], what: str, tags: Sequence[str], args: argparse.Namespace) -> None:
    """Save a command's summary for `main.py figures` (artifacts/bench/<what>[-tags][-seed<S>].json); the
    command's own result stands whether or not this works, so a failure is a warning."""
    plant = getattr(args, "plant", None)
    name = summary_name(what, [*tags, *([f"plant-{Path(plant).stem}"] if plant else [])], args.seed)
    try:
        path = save_summary(out, name)
    except (OSError, ValueError) as exc:
        log.warning("could not save the summary as %s.json: %s", name, exc)
        return
    log.info("summary saved to %s", path)
