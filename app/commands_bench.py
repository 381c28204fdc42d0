"""The `bench` command: the benchmark registry (name -> what it measures on which cell) and its dispatch."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.commands_planning import bench_planning_cmd, planning_tags
from app.common import emit, load_cell_config, save_bench_summary
from app.sensing import ensure_virtual_artefacts, make_force_source, with_guard
from app.tasks_registry import robot_for
from cell.config import load_config
from cell.control.loop import OpenCell
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")


# Defaults of the options that change a bench's figures (main.py's parser uses them): a run that departs from
# one saves its summary under a tagged name (`summary_name`), so it never overwrites the default's figures.
PEG_TRIALS = 50
PEG_MAX_OFFSET_MM = 2.0
PEG_MAX_TILT_DEG = 2.0
COLLISION_IMPACTS = 40
COLLISION_FREE_S = 600.0


def _no_tags(args: argparse.Namespace) -> list[str]:
    return []


def _peg_tags(args: argparse.Namespace) -> list[str]:
    tags = ["sensor"] if args.force_source == "sensor" else []
    if args.peg_diameter_mm:
        tags.append(f"d{args.peg_diameter_mm:g}mm")
    if args.trials != PEG_TRIALS:
        tags.append(f"{args.trials}trials")
    if args.max_offset_mm != PEG_MAX_OFFSET_MM:
        tags.append(f"offset{args.max_offset_mm:g}mm")
    if args.max_tilt_deg != PEG_MAX_TILT_DEG:
        tags.append(f"tilt{args.max_tilt_deg:g}deg")
    if args.only:
        tags.append("only" + "_".join(str(k) for k in args.only))
    return tags


def _collision_tags(args: argparse.Namespace) -> list[str]:
    tags = [args.reaction] if args.reaction != "stop" else []
    if args.impacts != COLLISION_IMPACTS:
        tags.append(f"{args.impacts}impacts")
    if args.free_s != COLLISION_FREE_S:
        tags.append(f"free{args.free_s:g}s")
    return tags


def _model_tags(args: argparse.Namespace) -> list[str]:
    return [args.robot] if args.robot != "tm5-700" else []


@dataclass(frozen=True)
class Bench:
    """One benchmark: `run(args)` -> its summary; `passed(summary)` false makes the command exit 1; `tags(args)`
    name the options that change its figures (in the saved summary's name)."""

    run: Callable[[argparse.Namespace], dict[str, Any]]
    passed: Callable[[dict[str, Any]], bool] = lambda out: True
    tags: Callable[[argparse.Namespace], list[str]] = _no_tags


def bench_peg_in_hole(args: argparse.Namespace) -> dict[str, Any]:
    """Randomised insertions on the simulated cell with the force source `run` would use for the peg."""
    from bench.peg import bench_peg
    from tasks.peg.config import load_peg_config

    cfg = load_cell_config(args)
    robot = robot_for(cfg, "peg")
    pcfg = load_peg_config(cfg.tasks.get("peg"), f"{cfg.source}: tasks.peg", args.force_source)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, "peg", "sim", robot)

    def wrap(cell: OpenCell) -> OpenCell:
        return with_guard(cfg, "peg", make_force_source(cfg, args.force_source, "peg", cell, robot), robot)

    if args.trials < 1 or args.max_offset_mm < 0 or args.max_tilt_deg < 0:
        raise ConfigError("bench peg-in-hole: --trials must be >= 1, --max-offset-mm and --max-tilt-deg >= 0")
    if args.only is not None and not all(0 <= k < args.trials for k in args.only):
        raise ConfigError(f"bench peg-in-hole: --only {args.only}: trial numbers must lie in 0..{args.trials - 1}")
    view = None
    if getattr(args, "view", False):
        from app.view import live_view

        view = live_view(robot, f"bench-peg-trial-{(args.only or [0])[0]}", args.serve, args.force_source == "virtual")
    record = None
    if args.record:
        from cell.data.recorder import new_run_dir

        record = new_run_dir(Path(cfg.recording.directory), "bench-peg")
        log.info("recording every trial under %s", record)
    out = bench_peg(cfg, robot, pcfg, args.trials, args.seed if args.seed is not None else 0,
                    only=args.only, record=record,
                    max_offset_m=args.max_offset_mm * 1e-3, max_tilt_deg=args.max_tilt_deg,
                    peg_diameter=args.peg_diameter_mm * 1e-3 if args.peg_diameter_mm else None,
                    wrap=wrap, force_source=args.force_source, view=view)
    if view is not None:
        from app.view import finish_view

        finish_view(view, args.serve)
    return out


def _bench_sim(args: argparse.Namespace) -> dict[str, Any]:
    from bench.timing import bench_sim

    return bench_sim(load_config(args.config), seed=args.seed)


def _bench_plant(args: argparse.Namespace) -> dict[str, Any]:
    from bench.characterise import characterise_plant

    return characterise_plant(load_cell_config(args), seed=args.seed)


def _bench_drivers(args: argparse.Namespace) -> dict[str, Any]:
    from bench.timing import bench_drivers

    return bench_drivers(args.n)


def _bench_model(args: argparse.Namespace) -> dict[str, Any]:
    from tasks.lab.bench import bench_model

    if not args.data:
        raise ConfigError("bench model needs --data DATASET.yaml (make one with main.py collect)")
    return bench_model(load_cell_config(args), Path(args.data), Path(args.model) if args.model else None,
                       train_samples=args.train_samples, fit_samples=args.fit_samples,
                       calls=args.calls, nthread=args.nthread, robot=args.robot)


def _bench_faults(args: argparse.Namespace) -> dict[str, Any]:
    from bench.faults import bench_faults

    cfg = load_config(args.config)
    return bench_faults(cfg, robot_for(cfg, "wipe"))


def _bench_collision(args: argparse.Namespace) -> dict[str, Any]:
    """Scripted impacts and free motion on the simulated cell, the peg tool's hybrid model detecting."""
    from bench.collision import bench_collision
    from cell.sensing.virtual_sensor import load_observer_model

    cfg = load_cell_config(args)
    robot = robot_for(cfg, "peg")
    ensure_virtual_artefacts(cfg, "peg", "sim", robot)
    model = load_observer_model(cfg.virtual_sensor.path("model", "peg"), robot)
    return bench_collision(cfg, robot, model, impacts=args.impacts, seed=args.seed if args.seed is not None else 0,
                           free_s=args.free_s, reaction=args.reaction)


def _bench_tool_gravity(args: argparse.Namespace) -> dict[str, Any]:
    from bench.tool_gravity import bench_tools

    cfg = load_cell_config(args)
    return bench_tools(cfg, {tool: robot_for(cfg, tool) for tool in ("wipe", "peg")}, poses=9,
                       seed=args.seed if args.seed is not None else 0)


def _bench_peg_sim(args: argparse.Namespace) -> dict[str, Any]:
    """The simulator at tight peg fits (bench/peg_sim.py): bore, contact give, wedging vs geometry, cost."""
    from bench.peg_sim import measure, plot

    data = measure()
    out = Path("artifacts/bench")
    out.mkdir(parents=True, exist_ok=True)
    log.info("peg-sim figure: %s", plot(data, out / "peg-sim.png"))
    return data


BENCHES: dict[str, Bench] = {
    "sim": Bench(_bench_sim),
    "plant": Bench(_bench_plant),
    "drivers": Bench(_bench_drivers),
    "model": Bench(_bench_model, tags=_model_tags),
    "peg-in-hole": Bench(bench_peg_in_hole, tags=_peg_tags),
    "faults": Bench(_bench_faults, passed=lambda out: out["failures"] == 0),
    # Exit 1 when an impact went undetected or free motion raised an alarm.
    "collision": Bench(_bench_collision, passed=lambda out: not out["missed"] and out["false_alarms"] == 0,
                       tags=_collision_tags),
    # Exit 1 when a compensated free-space force exceeds the target (0.5 N).
    "tool-gravity": Bench(_bench_tool_gravity, passed=lambda out: out["passed"]),
    # Exit 1 when a plan of ours (the hybrid model's TOPP-RA) exceeded a torque limit on the plant.
    "peg-sim": Bench(_bench_peg_sim),
    "planning": Bench(bench_planning_cmd, passed=lambda out: out["torque_violations"]["model"] == 0,
                      tags=planning_tags),
}
BENCH_NAMES = tuple(BENCHES)


def cmd_bench(args: argparse.Namespace) -> int:
    chosen = BENCHES.get(args.what)
    if chosen is None:
        raise ConfigError(f"bench {args.what}: unknown benchmark")
    if getattr(args, "view", False) and args.what != "peg-in-hole":
        raise ConfigError(f"bench {args.what}: --view shows one trial of bench peg-in-hole only")
    if getattr(args, "view", False) and len(args.only if args.only is not None else range(args.trials)) != 1:
        raise ConfigError("bench peg-in-hole --view shows one trial: add --only K (or --trials 1)")
    out = chosen.run(args)
    emit(out, args.json)
    save_bench_summary(out, args.what, chosen.tags(args), args)
    return 0 if chosen.passed(out) else 1
