"""What the command bodies share: the cell config from --config and --plant, and printing a command's summary."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.figures import save_summary, summary_name
from cell.cliargs import NTHREAD, SEED
from cell.config import CellConfig, load_config
from drivers.configio import dumps_strict

log = logging.getLogger("tmcell")


def load_cell_config(args: argparse.Namespace) -> CellConfig:
    """The --config file, with the plant profile --plant (where the command takes one) in place of its own."""
    cfg = load_config(args.config)
    if getattr(args, "plant", None):
        cfg.plant = str(Path(args.plant).resolve())
    return cfg


_json_printed = False


def json_printed(reset: bool = False) -> bool:
    """Whether `emit` printed a JSON line in this command (`reset`: start a new command)."""
    global _json_printed
    printed = _json_printed
    if reset:
        _json_printed = False
    return printed


def emit(out: dict[str, Any], as_json: bool) -> None:
    """The summary on stdout: one strict-JSON line, or `key: value` lines (a nested dict indented)."""
    global _json_printed
    if as_json:
        print(dumps_strict(out), flush=True)
        _json_printed = True
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
    config = getattr(args, "config", None)
    # Another config (another loop period, protocol or plant) measures another cell: its own file, never a
    # figure of the default cell's row.
    other = [f"config-{Path(config).stem}"] if config is not None and Path(config).stem != "cell" else []
    name = summary_name(what, [*tags, *other, *([f"plant-{Path(plant).stem}"] if plant else [])], args.seed)
    try:
        path = save_summary(out, name)
    except (OSError, ValueError) as exc:
        log.warning("could not save the summary as %s.json: %s", name, exc)
        return
    log.info("summary saved to %s", path)


# ---------------------------------------------------------------------------------------------- the parser
def _shows_default(action: argparse.Action) -> bool:
    """Whether an option's help should name its default: not for a flag, nor for None (the help says what
    an absent value means), nor when the help already gives it."""
    default = action.default
    if default is None or default is argparse.SUPPRESS or isinstance(default, bool) or not action.help:
        return False
    if not action.option_strings and action.nargs not in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
        return False
    text = action.help
    return "%(default)" not in text and not ("default" in text and str(default) in text)


class HelpFormatter(argparse.HelpFormatter):
    """Every option's help ends with "(default: X)" where it has a value to show and does not name it."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help
        if text and _shows_default(action):
            text += " (default: %(default)s)"
        return text


class CliParser(argparse.ArgumentParser):
    """The CLI's parser: the help formatter above; the sub-commands' parsers are of this class too."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def add_common_options(sp: argparse.ArgumentParser, seed_help: str = "plant noise seed (default: the profile's)",
                       config: bool = True) -> None:
    """--config, --seed and --json, the options most commands share."""
    if config:
        sp.add_argument("--config", type=Path, default=None, help="cell config YAML (default: config/cell.yaml)")
    sp.add_argument("--seed", type=SEED, default=None, help=seed_help)
    sp.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")


def add_robot_option(sp: argparse.ArgumentParser, what: str = "") -> None:
    sp.add_argument("--robot", default="tm5-700",
                    help=f"{what}robot by name (config/robots/<name>/; default tm5-700, the cell's arm)")


def add_plant_option(sp: argparse.ArgumentParser, what: str = "sim cells") -> None:
    sp.add_argument("--plant", default=None, help=f"plant profile YAML ({what}; default: the config's)")


def add_nthread_option(sp: argparse.ArgumentParser, default: int = 2, what: str = "XGBoost threads") -> None:
    sp.add_argument("--nthread", type=NTHREAD, default=default, help=what)
