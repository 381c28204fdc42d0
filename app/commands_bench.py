"""The `bench` command: the benchmark registry (name -> what it measures on which cell) and its dispatch."""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from app.commands_planning import add_planning_options, bench_planning_cmd, planning_tags
from app.common import (
    add_common_options,
    add_nthread_option,
    add_plant_option,
    add_robot_option,
    emit,
    load_cell_config,
    save_bench_summary,
)
from app.progress import heartbeat
from app.sensing import FORCE_SOURCES, ensure_virtual_artefacts, make_force_source, with_guard
from app.tasks_registry import robot_for
from bench.machine import cpu_model, machine_load, reference_ms
from cell.cliargs import COUNT, float_in, int_in
from cell.collision.config import REACTIONS
from cell.config import check_task_speeds, load_config
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


def _peg_setup(args: argparse.Namespace) -> tuple[Any, Any, Any, Callable[[OpenCell], OpenCell]]:
    """(cell config, robot, peg config, the cell's force source and guard) as `bench peg-in-hole` runs them."""
    from tasks.peg.config import load_peg_config

    cfg = load_cell_config(args)
    robot = robot_for(cfg, "peg")
    pcfg = load_peg_config(cfg.tasks.get("peg"), f"{cfg.source}: tasks.peg", args.force_source)

    def wrap(cell: OpenCell) -> OpenCell:
        return with_guard(cfg, "peg", make_force_source(cfg, args.force_source, "peg", cell, robot), robot)

    return cfg, robot, pcfg, wrap


# What a worker process needs of the command line to build the same set-up (plain data: it is pickled).
_PEG_RECIPE = ("config", "plant", "force_source", "peg_diameter_mm")


def _peg_worker_setup(recipe: dict[str, Any]) -> tuple[Any, ...]:
    return _peg_setup(argparse.Namespace(**recipe))


def _peg_worker_trial(setup: tuple[Any, ...], job: tuple[Any, float | None]) -> Any:
    from bench.peg import run_trial

    cfg, robot, pcfg, wrap = setup
    draw, peg_diameter = job
    return run_trial(cfg, robot, pcfg, draw.offset, draw.tilt, draw.seed, peg_diameter, wrap, index=draw.index)


def bench_peg_in_hole(args: argparse.Namespace) -> dict[str, Any]:
    """Randomised insertions on the simulated cell with the force source `run` would use for the peg."""
    from bench.peg import TrialDraw, bench_peg

    cfg, robot, pcfg, wrap = _peg_setup(args)
    check_task_speeds(cfg, "peg", pcfg)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, "peg", "sim", robot)
    if args.trials < 1 or args.max_offset_mm < 0 or args.max_tilt_deg < 0:
        raise ConfigError("bench peg-in-hole: --trials must be >= 1, --max-offset-mm and --max-tilt-deg >= 0")
    if args.only is not None and not all(0 <= k < args.trials for k in args.only):
        raise ConfigError(f"bench peg-in-hole: --only {args.only}: trial numbers must lie in 0..{args.trials - 1}")
    view = None
    if getattr(args, "view", False):
        from app.view import live_view

        view = live_view(robot, f"bench-peg-trial-{(args.only or [0])[0]}", args.serve, args.force_source == "virtual",
                         args.bind)
    record = None
    if args.record:
        from cell.data.recorder import new_run_dir

        record = new_run_dir(Path(cfg.recording.directory), "bench-peg")
        log.info("recording every trial under %s", record)
    peg_diameter = args.peg_diameter_mm * 1e-3 if args.peg_diameter_mm else None
    jobs = min(args.jobs, len(args.only) if args.only is not None else args.trials)
    runner = None
    if jobs > 1 and view is None and record is None:
        from app.trial_pool import run_pooled

        recipe = {key: getattr(args, key, None) for key in _PEG_RECIPE}

        def runner(draws: list[TrialDraw]) -> Any:
            return run_pooled([(d, peg_diameter) for d in draws], jobs, _peg_worker_setup, recipe, _peg_worker_trial)
    out = bench_peg(cfg, robot, pcfg, args.trials, args.seed if args.seed is not None else 0,
                    only=args.only, record=record,
                    max_offset_m=args.max_offset_mm * 1e-3, max_tilt_deg=args.max_tilt_deg,
                    peg_diameter=peg_diameter, wrap=wrap, force_source=args.force_source, view=view, runner=runner)
    out["jobs"] = jobs if runner is not None else 1
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


HOLD_OUT_EVERY = 4  # a dataset without a test split: every 4th trajectory is held out for the timing


def held_out_dataset(manifest: Path, folder: Path) -> tuple[Path, int]:
    """`manifest` itself when it lists test files; else a dataset in `folder` whose test split is every
    HOLD_OUT_EVERY-th trajectory of the training files (whole trajectories, by their `traj` id; whole files
    when a file has none) and whose training split is the rest.  Returns (manifest, trajectories held out)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from cell.data.dataset import load_manifest, manifest_files
    from drivers.configio import read_yaml

    if load_manifest(manifest).test:
        return manifest, 0
    files = manifest_files(manifest, "train")
    folder.mkdir(parents=True, exist_ok=True)
    train: list[str] = []
    test: list[str] = []
    held = 0
    for i, path in enumerate(files):
        table = pq.read_table(path)
        if "traj" not in table.column_names:
            (test if i % HOLD_OUT_EVERY == HOLD_OUT_EVERY - 1 else train).append(str(path.resolve()))
            held += i % HOLD_OUT_EVERY == HOLD_OUT_EVERY - 1
            continue
        ids = sorted(set(table.column("traj").to_pylist()))
        out = ids[HOLD_OUT_EVERY - 1::HOLD_OUT_EVERY] or ids[-1:]
        if len(out) == len(ids):  # one trajectory: nothing would be left to train on
            train.append(str(path.resolve()))
            continue
        mask = pc.is_in(table.column("traj"), value_set=pa.array(out))
        for part, rows in (("test", mask), ("train", pc.invert(mask))):
            target = folder / f"{part}_{i:03d}.parquet"
            pq.write_table(table.filter(rows), target)
            (test if part == "test" else train).append(target.name)
        held += len(out)
    if not test:
        raise ConfigError(f"{manifest}: no test split and too few trajectories to hold one out")
    doc = dict(read_yaml(manifest))
    doc.update(train=train, test=test, loaded=[str((manifest.parent / f).resolve()) for f in doc.get("loaded") or []])
    derived = folder / "dataset.yaml"
    derived.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return derived, held


def _bench_model(args: argparse.Namespace) -> dict[str, Any]:

    from tasks.lab.bench import bench_model

    if not args.data:
        raise ConfigError("bench model needs --data DATASET.yaml (made by main.py prepare or collect)")
    with tempfile.TemporaryDirectory(prefix="bench-model-") as tmp:
        data, held = held_out_dataset(Path(args.data), Path(tmp))
        if held:
            log.info("%s has no test split: %d trajectories of its training split held out for the timing",
                     args.data, held)
        with heartbeat("bench model"):  # its H1 fit and the timed fit show no count
            out = bench_model(load_cell_config(args), data, Path(args.model) if args.model else None,
                              train_samples=args.train_samples, fit_samples=args.fit_samples,
                              calls=args.calls, nthread=args.nthread, robot=args.robot)
    return {**out, "held_out_trajectories": held}


def _bench_faults(args: argparse.Namespace) -> dict[str, Any]:
    from bench.faults import bench_faults

    cfg = load_config(args.config)
    return bench_faults(cfg, robot_for(cfg, "wipe"))


def _bench_collision(args: argparse.Namespace) -> dict[str, Any]:
    """Scripted impacts and free motion on the simulated cell, the peg tool's hybrid model detecting; the free
    motion includes the plans `bench planning` makes and the tasks' own runs."""
    from app.planning_model import ARTEFACTS, prepared_model_name
    from bench.collision import bench_collision
    from bench.collision_plans import bench_planners
    from cell.sensing.virtual_sensor import load_observer_model

    cfg = load_cell_config(args)
    robot = robot_for(cfg, "peg")
    ensure_virtual_artefacts(cfg, "peg", "sim", robot)
    model = load_observer_model(cfg.virtual_sensor.path("model", "peg"), robot, cfg.loop.period_s)
    planners = None
    if args.free_s > 0:
        # `bench planning`'s stored settings count here only when made for the model `plan` uses now.
        planners = bench_planners(robot, cfg, model, ARTEFACTS, prepared_model_name(cfg, robot_for(cfg, "wipe")))
    return bench_collision(cfg, robot, model, impacts=args.impacts, seed=args.seed if args.seed is not None else 0,
                           free_s=args.free_s, reaction=args.reaction, planners=planners,
                           task_run=_collision_task_run(cfg) if args.free_s > 0 else None)


def _collision_task_run(cfg: Any) -> Any:
    """(task, seed, payload error kg) -> the task's run summary on the simulated cell with the virtual sensor, the
    guard recording only (every reaction `monitor`), the tool carrying the payload error."""
    from dataclasses import replace

    from app.cells import open_cell
    from app.tasks_registry import TASKS, build_task
    from bench.collision_cell import set_payload_error
    from tasks.runner import run_task

    tasks = {k: replace(v, reactions={}) for k, v in cfg.collision.tasks.items()}
    mcfg = replace(cfg, collision=replace(cfg.collision, reaction="monitor", tasks=tasks))

    def run(name: str, seed: int, payload_kg: float) -> dict[str, Any]:
        spec = TASKS[name]
        robot = robot_for(mcfg, spec.tool)
        ensure_virtual_artefacts(mcfg, spec.tool, "sim", robot)
        task, max_duration = build_task(name, mcfg, robot, "virtual")
        holder = open_cell(mcfg, "sim", robot, seed, spec.scene)
        try:
            set_payload_error(holder.plant, payload_kg, reset=True)  # type: ignore[attr-defined]
            cell = with_guard(mcfg, spec.tool, make_force_source(mcfg, "virtual", spec.tool, holder.open(), robot),
                              robot)
            return run_task(task, cell, mcfg, robot, max_duration, record=False)
        finally:
            holder.close()

    return run


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


def _bench_hand_guide(args: argparse.Namespace) -> dict[str, Any]:
    from app.commands_hand_guide import bench_hand_guide_cmd

    return bench_hand_guide_cmd(args)


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
    # Exit 1 when a hand-guiding figure misses its target or the push did not stop the arm.
    "hand-guide": Bench(_bench_hand_guide, passed=lambda out: out["passed"]),
}
BENCH_NAMES = tuple(BENCHES)


BENCH_HELP = {
    "sim": "real-time factor of the simulated plant and the controller in lock-step",
    "plant": "the simulated plant's error budget (P1, ideal P2, noise floor)",
    "drivers": "one Modbus state read and target write, one serial wrench read, over loopback",
    "model": "serving speed of the hybrid model, the fit time, the virtual sensor's step",
    "peg-in-hole": "randomised insertions on the simulated cell",
    "faults": "the fault-injection matrix on the emulated cell with the real drivers",
    "collision": "scripted impacts and free motion: detections, delays, false alarms",
    "tool-gravity": "the tool's weight on the F/T sensor, identified and compensated",
    "peg-sim": "the simulator at tight peg fits: bore, contact give, wedging, cost",
    "planning": "four planners on named and random paths, each plan run on the plant",
    "hand-guide": "sensorless hand guiding: a simulated hand along a 0.4 m path, release, a push over the limit",
}
DRAW_SEED = "seed of the random draws and the plant's noise (default 0)"


def _bench_options(name: str, b: argparse.ArgumentParser) -> None:
    """The options of `bench NAME`: its own, and of the shared ones only those it reads."""
    if name == "peg-in-hole":
        b.add_argument("--trials", type=COUNT, default=PEG_TRIALS, help="randomised insertions")
        b.add_argument("--max-offset-mm", type=float_in(0, 20), default=PEG_MAX_OFFSET_MM,
                       help="hole offset drawn in +-this on x and y (mm)")
        b.add_argument("--max-tilt-deg", type=float_in(0, 10), default=PEG_MAX_TILT_DEG,
                       help="hole tilt drawn in +-this about x and y (degrees)")
        b.add_argument("--peg-diameter-mm", type=float_in(1, 100, lo_open=True), default=None,
                       help="peg diameter (mm; default: the plant profile's, 21.4)")
        b.add_argument("--force-source", choices=FORCE_SOURCES, default="virtual",
                       help="what the task regulates with: the virtual force sensor or the F/T sensor")
        b.add_argument("--only", type=int_in(0), nargs="+", default=None, metavar="K",
                       help="run only these trial numbers (the same draws as in the full bench; default: all)")
        b.add_argument("--record", action="store_true",
                       help="log every trial run (runs/<date>-bench-peg/trial_NNN, as `run` logs)")
        b.add_argument("--jobs", type=COUNT, default=os.cpu_count() or 1,
                       help="trials run at once, one worker process each (default: the machine's cores); "
                       "the figures do not depend on it, only the wall time (--record and --view run one)")
        from app.view import add_view_options

        add_view_options(b, "one trial (--only K)")
    elif name == "collision":
        b.add_argument("--impacts", type=COUNT, default=COLLISION_IMPACTS, help="scripted impacts")
        b.add_argument("--free-s", type=float_in(0, 3600), default=COLLISION_FREE_S,
                       help="simulated seconds of free motion watched for false alarms (s)")
        b.add_argument("--reaction", choices=REACTIONS, default="stop", help="the reaction to a detected impact")
    elif name == "drivers":
        b.add_argument("--n", type=COUNT, default=500, help="timed samples of each exchange")
    elif name == "model":
        b.add_argument("--data", default=None, help="dataset manifest (dataset.yaml) from `prepare` or `collect`; "
                       "without a test split, trajectories of the training split are held out")
        b.add_argument("--model", default=None, help="model artefact folder (default: train an H1 on --data)")
        b.add_argument("--calls", type=COUNT, default=5000, help="single-sample predictions timed")
        b.add_argument("--train-samples", type=int_in(100), default=24_000,
                       help="H1 training samples (without --model)")
        b.add_argument("--fit-samples", type=int_in(100), default=500_000, help="samples of the timed XGBoost fit")
        add_nthread_option(b)
        add_robot_option(b, "the dataset's ")
    elif name == "planning":
        b.add_argument("--model", default=None, help="torque model artefact, or 'nominal' (the URDF's rigid body; "
                       "default: the prepared wipe model)")
        add_planning_options(b)
    seeded = {"sim": "plant noise seed (default: the profile's)", "plant": "plant noise seed (default: the profile's)",
              "peg-in-hole": DRAW_SEED, "collision": DRAW_SEED, "tool-gravity": DRAW_SEED,
              "planning": "seed of the random paths and the plant's noise (default 0)",
              "hand-guide": "plant noise seed (default: the profile's)"}
    if name in ("plant", "peg-in-hole", "collision", "tool-gravity", "planning", "model"):
        add_plant_option(b)
    if name in seeded:
        add_common_options(b, seeded[name])
    else:  # these read no seed; model and faults read the cell config
        if name in ("model", "faults"):
            b.add_argument("--config", type=Path, default=None, help="cell config YAML (default: config/cell.yaml)")
        b.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")
        b.set_defaults(seed=None)


def add_bench_parser(sub: argparse._SubParsersAction) -> None:
    """`bench NAME [options]`: one sub-command per benchmark, each with only the options it reads."""
    b = sub.add_parser("bench", help="benchmarks that print the project's measured figures",
                       description="Each benchmark prints its summary and saves it under artifacts/bench/; "
                       "`main.py bench NAME --help` lists its options.")
    names = b.add_subparsers(dest="what", required=True, metavar="NAME", parser_class=type(b))
    for name in BENCH_NAMES:
        one = names.add_parser(name, help=BENCH_HELP[name], description=BENCH_HELP[name])
        _bench_options(name, one)
    b.set_defaults(func=cmd_bench)


# What every bench's summary adds about its run: its wall time, the load averages before and after, the cores,
# the processor and the time of a fixed piece of work on it (bench/machine.py: a machine's own speed).
BENCH_CONTEXT_KEYS = ("bench_wall_s", "load_avg_before", "load_avg_after", "cpu_count", "cpu_model",
                      "machine_reference_ms")


def cmd_bench(args: argparse.Namespace) -> int:
    chosen = BENCHES.get(args.what)
    if chosen is None:
        raise ConfigError(f"bench {args.what}: unknown benchmark")
    if getattr(args, "view", False) and len(args.only if args.only is not None else range(args.trials)) != 1:
        raise ConfigError("bench peg-in-hole --view shows one trial: add --only K (or --trials 1)")
    t0, load_before, reference = time.perf_counter(), machine_load(), reference_ms()
    out = chosen.run(args)
    # Every bench says how long it took, what else the cores were doing and how fast the machine is: a slow run
    # from a busy or a slow machine.
    context = (round(time.perf_counter() - t0, 2), load_before, machine_load(), os.cpu_count(), cpu_model(),
               reference)
    for key, value in zip(BENCH_CONTEXT_KEYS, context, strict=True):
        out.setdefault(key, value)
    emit(out, args.json)
    save_bench_summary(out, args.what, chosen.tags(args), args)
    return 0 if chosen.passed(out) else 1
