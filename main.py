"""Command-line entry of the TM5-700 force-control cell: run tasks, check status, benchmark, emulate devices."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from app.cells import CALIBRATION_KINDS, CELL_KINDS
from app.commands_bench import add_bench_parser
from app.commands_cell import cmd_emulate, cmd_status
from app.commands_detect import add_detect_parser
from app.commands_doctor import add_doctor_parser
from app.commands_figures import cmd_figures
from app.commands_lab import cmd_calibrate, cmd_collect, cmd_evaluate, cmd_import, cmd_prepare, cmd_train
from app.commands_plan import cmd_plan
from app.commands_replay import add_replay_parser
from app.commands_taskfile import RUN_EXTRA_TASKS, add_taskfile_options, cmd_run_dispatch
from app.commands_tune import add_learner_parsers
from app.common import CliParser, add_nthread_option, add_plant_option, add_robot_option, emit, json_printed
from app.common import add_common_options as common
from app.progress import quiet_bars_off_terminal
from app.sensing import FORCE_SOURCES, PREPARE_SAMPLES
from app.tasks_registry import TASK_NAMES
from app.view import add_view_options
from bench.figures import BENCH_DIR, FIGURES_PAGE
from cell.cliargs import COUNT, PORT, SEED, float_in, int_in, int_list
from cell.config import CONFIG_DIR, TOOLS
from cell.control.signals import Terminated, received_sigterm, sigterm_as_interrupt
from drivers.errors import CellError

CELL_HELP = "which cell (default: devices.*.kind from the config)"
TOOL_HELP = "the tool mounted: wipe (the table wiper) or peg"


# --------------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="main.py", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a task on a cell")
    run.add_argument("task", choices=TASK_NAMES + RUN_EXTRA_TASKS,
                     help="the task: wipe (60 N along a path), peg-in-hole, task FILE.yaml (primitives), hand-guide")
    add_taskfile_options(run)
    run.add_argument("--cell", choices=CELL_KINDS, default=None, help=CELL_HELP)
    run.add_argument("--force-source", choices=FORCE_SOURCES, default="virtual",
                     help="virtual: the virtual force sensor, the F/T sensor logged as ground truth; sensor: the F/T")
    add_plant_option(run)
    run.add_argument("--no-record", action="store_true", help="do not write runs/<...>/")
    add_view_options(run, "the run as it happens")
    run.add_argument("--publish", metavar="HOST:PORT", help="send each step's wrench as a UDP JSON datagram "
                     "(N, N m, tool frame; default: none)")
    common(run)
    run.set_defaults(func=cmd_run_dispatch)

    pr = sub.add_parser("prepare", help="make a tool ready for sensorless tasks: collect, train H1, calibrate")
    pr.add_argument("--tool", choices=TOOLS, default="wipe", help=TOOL_HELP)
    pr.add_argument("--cell", choices=CALIBRATION_KINDS, default="sim", help="the cell to collect and calibrate on")
    pr.add_argument("--samples", type=COUNT, default=PREPARE_SAMPLES, help="training samples to collect (8 ms each)")
    pr.add_argument("--force", action="store_true", help="rebuild every artefact even if present and matching")
    pr.add_argument("--fast-moves", action="store_true",
                    help="add moves at `plan`'s speeds to the collection (docs/collision.md: what they change)")
    add_plant_option(pr)
    common(pr)
    pr.set_defaults(func=cmd_prepare)

    ca = sub.add_parser("calibrate", help="calibrate the virtual force sensor against the F/T sensor")
    ca.add_argument("--tool", choices=TOOLS, default="wipe", help=TOOL_HELP)
    ca.add_argument("--cell", choices=CALIBRATION_KINDS, default="sim", help="the cell to calibrate on")
    ca.add_argument("--model", default=None, help="torque model artefact (default: virtual_sensor.model_dir)")
    ca.add_argument("--out", default=None, help="calibration folder (default: virtual_sensor.calibration_dir)")
    add_plant_option(ca)
    common(ca)
    ca.set_defaults(func=cmd_calibrate)

    st = sub.add_parser("status", help="connect to the cell and print its state")
    st.add_argument("--cell", choices=CELL_KINDS, default=None, help=CELL_HELP)
    st.add_argument("--watch", action="store_true", help="refresh the state until Ctrl+C")
    st.add_argument("--interval", type=float_in(0.05, 3600), default=1.0, help="--watch: seconds between reads (s)")
    common(st)
    st.set_defaults(func=cmd_status)

    pl = sub.add_parser("plan", help="time-optimal plans under torque limits, executed and compared to baselines")
    pl.add_argument("--plans", type=Path, default=CONFIG_DIR / "plans.yaml", help="paths and planner settings YAML")
    pl.add_argument("--path", action="append", help="only this named path (repeatable; default: every path)")
    pl.add_argument("--waypoints", default=None, help="'j1,..,j6; j1,..,j6; ...' in degrees instead of --plans paths")
    pl.add_argument("--model", default=None, help="torque model artefact, or 'nominal' (the URDF's rigid body); "
                    "default: the wipe tool's prepared model (prepared first on a simulated cell)")
    pl.add_argument("--cell", choices=CELL_KINDS, default=None, help=CELL_HELP)
    common(pl)
    pl.set_defaults(func=cmd_plan)

    co = sub.add_parser("collect", help="run excitation and test trajectories on a cell; write a dataset")
    co.add_argument("--cell", choices=CELL_KINDS, default=None, help=CELL_HELP)
    co.add_argument("--out", required=True, help="dataset folder (e.g. artifacts/data/default)")
    co.add_argument("--samples", type=COUNT, default=500_000, help="training samples to collect (8 ms each)")
    co.add_argument("--family", choices=("mixed", "paper", "fourier"), default="mixed",
                    help="training excitation: the paper's configuration chain, Fourier, or both mixed")
    co.add_argument("--fourier-share", type=float_in(0, 1, True, True), default=0.7,
                    help="mixed family: share of the training samples that are Fourier excitation (0..1)")
    co.add_argument("--fast-share", type=float_in(0, 1, False, True), default=0.0,
                    help="extra share of moves timed as `plan` times them (config/plans.yaml), at its speeds")
    co.add_argument("--plan-seed", type=SEED, default=0, help="seed of the planned trajectories (--seed: the plant's)")
    co.add_argument("--test-trajectories", type=int_in(0), default=6, help="held-out test trajectories")
    co.add_argument("--test-repeats", type=COUNT, default=5, help="runs of each test trajectory")
    co.add_argument("--test-moves", type=COUNT, default=4, help="point-to-point moves per test trajectory")
    co.add_argument("--excitation", default=None, help="excitation config YAML (default: config/excitation.yaml)")
    add_plant_option(co)
    add_robot_option(co, "only tm5-700 (the simulated plant's arm): ")
    common(co)
    co.set_defaults(func=cmd_collect)

    tr = sub.add_parser("train", help="fit one model (P1, P2, D, H1, H2, H3) and save it")
    tr.add_argument("--data", required=True, help="dataset manifest (dataset.yaml)")
    tr.add_argument("--model", choices=("P1", "P2", "D", "H1", "H2", "H3"), default="H1", help="the model to fit")
    tr.add_argument("--out", required=True, help="model folder (e.g. artifacts/models/h1)")
    tr.add_argument("--samples", type=int_in(100), default=None, help="training samples (default: the model's)")
    tr.add_argument("--window", type=int_in(1, 50), default=None, help="input window (samples; default: the model's)")
    tr.add_argument("--grouping", choices=("own", "paper", "per_joint", "full"), default=None,
                    help="which joints each learned part sees (default: the model's)")
    tr.add_argument("--derivatives", choices=("zero_phase", "causal"), default="zero_phase",
                    help="velocity and acceleration filters: zero_phase (offline) or causal (as served)")
    add_nthread_option(tr)
    add_robot_option(tr, "the dataset's ")
    common(tr, "fitting seed (default 0)")
    tr.set_defaults(func=cmd_train)

    ev = sub.add_parser("evaluate", help="compare P1/P2/D/H1/H2/H3 on held-out trajectories")
    ev.add_argument("--data", required=True, help="dataset manifest (dataset.yaml)")
    ev.add_argument("--out", required=True, help="report folder (e.g. artifacts/eval/default)")
    ev.add_argument("--train-samples", type=int_in(100), default=24_000, help="training samples of each model")
    ev.add_argument("--large-samples", type=int_in(100), default=500_000, help="training samples of the large fits")
    ev.add_argument("--curve", type=int_list(100), default=None, help="learning-curve sizes, comma-separated "
                    "(default: evaluate's own)")
    ev.add_argument("--no-curve", action="store_true", help="skip the learning curve")
    ev.add_argument("--lofo", action="store_true",
                    help="also leave each training file out in turn: P1, P2, H1 fitted on the others, scored on it")
    ev.add_argument("--max-trees", type=COUNT, default=None, help="cap on XGBoost trees per joint (default: none)")
    add_nthread_option(ev)
    ev.add_argument("--plant", default=None, help="plant profile whose noise floor the report cites")
    add_robot_option(ev, "the dataset's ")
    common(ev, "fitting seed (default 0)")
    ev.set_defaults(func=cmd_evaluate)
    add_learner_parsers(sub, common, add_robot_option, tr, ev)

    im = sub.add_parser("import", help="turn another robot's logs into a dataset (the public UR10e CSV logs)")
    im.add_argument("source", choices=("ur10e",), help="whose logs: ur10e (../shared/data/ur10e/README.md)")
    im.add_argument("--train", nargs="+", action="extend", metavar="PATH",
                    help="CSV files or folders for training (default: the unloaded harmonic runs)")
    im.add_argument("--test", nargs="+", action="extend", metavar="PATH",
                    help="CSV files or folders for testing (default: the joint-wise runs)")
    im.add_argument("--loaded", nargs="+", action="extend", metavar="PATH",
                    help="CSV files or folders recorded with the payload (default: the loaded harmonic runs)")
    im.add_argument("--add-test", nargs="+", action="extend", metavar="PATH", help="more test CSV files or folders")
    im.add_argument("--out", required=True, help="dataset folder (e.g. artifacts/data/ur10e)")
    im.add_argument("--max-gap-s", type=float_in(0, 60, lo_open=True), default=0.05,
                    help="a time step longer than this starts a new trajectory (s)")
    im.add_argument("--payload-kg", type=float_in(0, 100), default=2.805,
                    help="payload of the --loaded logs (kg; default: the published 2.805 kg of *harm50secLoad)")
    common(im, "unused by the import (default: none)")
    im.set_defaults(func=cmd_import)

    em = sub.add_parser("emulate", help="serve a device emulator on this machine until Ctrl+C or SIGTERM")
    em.add_argument("device", choices=("arm", "sensor", "cell"),
                    help="cell: plant + arm + sensor emulators, endpoints as JSON on stdout, faults on stdin")
    em.add_argument("--port", type=PORT, default=5020,
                    help="TCP port of the arm emulator on 127.0.0.1 (0: any free; tm-ethernet: the Ethernet Slave's)")
    em.add_argument("--listen-port", type=PORT, default=0,
                    help="tm-ethernet: the Listen node's TCP port on 127.0.0.1 (0: any free)")
    em.add_argument("--broadcast-ms", type=float_in(1, 1000), default=None,
                    help="arm, tm-ethernet: the Ethernet Slave's broadcast period (ms; default: the plant's period)")
    em.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                    help="arm, cell: the address the arm listens on (default 127.0.0.1: this machine only)")
    em.add_argument("--kinematic", action="store_true", help="arm: a simple kinematic plant instead of MuJoCo")
    em.add_argument("--config", type=Path, default=None, help="cell config YAML (default: config/cell.yaml)")
    em.add_argument("--seed", type=SEED, default=None, help="plant and sensor noise seed (default: the profile's)")
    add_plant_option(em, "arm and cell")
    em.add_argument("--scene", choices=("free", "table", "peg"), default=None,
                    help="cell: what stands in the plant's workspace (default: the config's scene.kind)")
    em.set_defaults(func=cmd_emulate)

    add_bench_parser(sub)
    add_replay_parser(sub)
    add_doctor_parser(sub)
    add_detect_parser(sub)

    fi = sub.add_parser("figures", help="write docs/figures.md from the benchmarks' saved JSON summaries")
    fi.add_argument("--bench-dir", type=Path, default=BENCH_DIR, help="saved summaries")
    fi.add_argument("--out", type=Path, default=FIGURES_PAGE, help="the page to write")
    fi.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")
    fi.set_defaults(func=cmd_figures)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("transitions").setLevel(logging.WARNING)
    # pymodbus logs every failed connect at ERROR; the driver reports link loss itself.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    quiet_bars_off_terminal()
    json_printed(reset=True)
    try:
        with sigterm_as_interrupt():
            code = int(args.func(args))
        return 143 if code == 130 and received_sigterm() else code
    except CellError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        if getattr(args, "json", False) and not json_printed():
            # A repeated Ctrl+C can end the command before its summary: --json still ends in one JSON line.
            emit({"outcome": "interrupted", "reason": "terminated (SIGTERM)" if terminated
                  else "interrupted by the operator (Ctrl+C)"}, True)
        if terminated:
            print("terminated (SIGTERM): the arm was stopped", file=sys.stderr)
            return 143
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
