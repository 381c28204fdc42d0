"""Command-line entry of the TM5-700 force-control cell: run tasks, check status, benchmark, emulate devices."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from app.cells import CALIBRATION_KINDS, CELL_KINDS
from app.commands_bench import (
    BENCH_NAMES,
    COLLISION_FREE_S,
    COLLISION_IMPACTS,
    PEG_MAX_OFFSET_MM,
    PEG_MAX_TILT_DEG,
    PEG_TRIALS,
    cmd_bench,
)
from app.commands_cell import cmd_emulate, cmd_run, cmd_status
from app.commands_doctor import add_doctor_parser
from app.commands_figures import cmd_figures
from app.commands_lab import cmd_calibrate, cmd_collect, cmd_evaluate, cmd_import, cmd_prepare, cmd_train
from app.commands_plan import cmd_plan
from app.commands_planning import add_planning_options
from app.commands_replay import add_replay_parser
from app.commands_tune import add_learner_parsers
from app.sensing import FORCE_SOURCES, PREPARE_SAMPLES
from app.tasks_registry import TASK_NAMES
from app.view import add_view_options
from bench.figures import BENCH_DIR, FIGURES_PAGE
from cell.cliargs import COUNT, NTHREAD, PORT, SEED, float_in, int_in, int_list
from cell.config import CONFIG_DIR, REACTIONS, TOOLS
from cell.control.signals import Terminated, received_sigterm, sigterm_as_interrupt
from drivers.errors import CellError


# --------------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="main.py", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = p.add_subparsers(dest="command", required=True)

    def robot_option(sp: argparse.ArgumentParser, what: str = "") -> None:
        sp.add_argument("--robot", default="tm5-700",
                        help=f"{what}robot by name (config/robots/<name>/; default tm5-700, the cell's arm)")

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--config", type=Path, default=None, help="cell config YAML (default config/cell.yaml)")
        sp.add_argument("--seed", type=SEED, default=None, help="plant seed (default: the profile's)")
        sp.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")

    run = sub.add_parser("run", help="run a task on a cell")
    run.add_argument("task", choices=TASK_NAMES)
    run.add_argument("--cell", choices=CELL_KINDS, default=None,
                     help="default: devices.*.kind from the config")
    run.add_argument("--force-source", choices=FORCE_SOURCES, default="virtual",
                     help="virtual (default): the virtual force sensor, the F/T sensor logged as ground truth")
    run.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    run.add_argument("--no-record", action="store_true", help="do not write runs/<...>/")
    add_view_options(run, "the run as it happens")
    run.add_argument("--publish", metavar="HOST:PORT", help="send each step's wrench as a UDP JSON datagram")
    common(run)
    run.set_defaults(func=cmd_run)

    pr = sub.add_parser("prepare", help="make a tool ready for sensorless tasks: collect, train H1, calibrate")
    pr.add_argument("--tool", choices=TOOLS, default="wipe")
    pr.add_argument("--cell", choices=CALIBRATION_KINDS, default="sim")
    pr.add_argument("--samples", type=COUNT, default=PREPARE_SAMPLES, help="training samples to collect")
    pr.add_argument("--force", action="store_true", help="rebuild every artefact even if present and matching")
    pr.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    common(pr)
    pr.set_defaults(func=cmd_prepare)

    ca = sub.add_parser("calibrate", help="calibrate the virtual force sensor against the F/T sensor")
    ca.add_argument("--tool", choices=TOOLS, default="wipe")
    ca.add_argument("--cell", choices=CALIBRATION_KINDS, default="sim")
    ca.add_argument("--model", default=None, help="torque model artefact (default: virtual_sensor.model_dir)")
    ca.add_argument("--out", default=None, help="calibration folder (default: virtual_sensor.calibration_dir)")
    ca.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    common(ca)
    ca.set_defaults(func=cmd_calibrate)

    st = sub.add_parser("status", help="connect to the cell and print its state")
    st.add_argument("--cell", choices=CELL_KINDS, default=None)
    common(st)
    st.set_defaults(func=cmd_status)

    pl = sub.add_parser("plan", help="time-optimal plans under torque limits, executed and compared to a baseline")
    pl.add_argument("--plans", type=Path, default=CONFIG_DIR / "plans.yaml", help="paths and planner settings")
    pl.add_argument("--path", action="append", help="only this named path (repeatable)")
    pl.add_argument("--waypoints", default=None, help="'j1,..,j6; j1,..,j6; ...' in degrees instead of --plans paths")
    pl.add_argument("--model", default=None, help="torque model artefact, or 'nominal' (the URDF's rigid body); "
                    "default: the wipe tool's prepared model (prepared first on a simulated cell)")
    pl.add_argument("--cell", choices=CELL_KINDS, default=None)
    common(pl)
    pl.set_defaults(func=cmd_plan)

    co = sub.add_parser("collect", help="run excitation and test trajectories on a cell; write a dataset")
    co.add_argument("--cell", choices=CELL_KINDS, default=None)
    co.add_argument("--out", required=True, help="dataset folder (e.g. artifacts/data/default)")
    co.add_argument("--samples", type=COUNT, default=500_000, help="training samples to collect")
    co.add_argument("--family", choices=("mixed", "paper", "fourier"), default="mixed")
    co.add_argument("--fourier-share", type=float_in(0, 1, True, True), default=0.7,
                    help="mixed family: share of the training samples that are Fourier excitation")
    co.add_argument("--plan-seed", type=SEED, default=0,
                    help="seed of the planned trajectories (--seed is the plant's)")
    co.add_argument("--test-trajectories", type=int_in(0), default=6)
    co.add_argument("--test-repeats", type=COUNT, default=5)
    co.add_argument("--test-moves", type=COUNT, default=4)
    co.add_argument("--excitation", default=None, help="excitation config YAML")
    co.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    robot_option(co, "only tm5-700 (the simulated plant's arm): ")
    common(co)
    co.set_defaults(func=cmd_collect)

    tr = sub.add_parser("train", help="fit one model (P1, P2, D, H1, H2, H3) and save it")
    tr.add_argument("--data", required=True, help="dataset manifest (dataset.yaml)")
    tr.add_argument("--model", choices=("P1", "P2", "D", "H1", "H2", "H3"), default="H1")
    tr.add_argument("--out", required=True, help="model folder (e.g. artifacts/models/h1)")
    tr.add_argument("--samples", type=int_in(100), default=None)
    tr.add_argument("--window", type=int_in(1, 50), default=None)
    tr.add_argument("--grouping", choices=("own", "paper", "per_joint", "full"), default=None)
    tr.add_argument("--derivatives", choices=("zero_phase", "causal"), default="zero_phase")
    tr.add_argument("--nthread", type=NTHREAD, default=2)
    robot_option(tr, "the dataset's ")
    common(tr)
    tr.set_defaults(func=cmd_train)

    ev = sub.add_parser("evaluate", help="compare P1/P2/D/H1/H2/H3 on held-out trajectories")
    ev.add_argument("--data", required=True, help="dataset manifest (dataset.yaml)")
    ev.add_argument("--out", required=True, help="report folder (e.g. artifacts/eval/default)")
    ev.add_argument("--train-samples", type=int_in(100), default=24_000)
    ev.add_argument("--large-samples", type=int_in(100), default=500_000)
    ev.add_argument("--curve", type=int_list(100), default=None, help="learning-curve sizes, comma-separated")
    ev.add_argument("--no-curve", action="store_true")
    ev.add_argument("--lofo", action="store_true",
                    help="also leave each training file out in turn: P1, P2, H1 fitted on the others, scored on it")
    ev.add_argument("--max-trees", type=COUNT, default=None)
    ev.add_argument("--nthread", type=NTHREAD, default=2)
    ev.add_argument("--plant", default=None, help="plant profile whose noise floor the report cites")
    robot_option(ev, "the dataset's ")
    common(ev)
    ev.set_defaults(func=cmd_evaluate)
    add_learner_parsers(sub, common, robot_option, tr, ev)

    im = sub.add_parser("import", help="turn another robot's logs into a dataset (the public UR10e CSV logs)")
    im.add_argument("source", choices=("ur10e",), help="whose logs: ur10e (../shared/data/ur10e/README.md)")
    im.add_argument("--train", nargs="+", action="extend", metavar="PATH",
                    help="CSV files or folders for training (default: the unloaded harmonic runs)")
    im.add_argument("--test", nargs="+", action="extend", metavar="PATH",
                    help="CSV files or folders for testing (default: the joint-wise runs)")
    im.add_argument("--loaded", nargs="+", action="extend", metavar="PATH",
                    help="CSV files or folders recorded with the payload (default: the loaded harmonic runs)")
    im.add_argument("--out", required=True, help="dataset folder (e.g. artifacts/data/ur10e)")
    im.add_argument("--max-gap-s", type=float_in(0, 60, lo_open=True), default=0.05,
                    help="a time step longer than this starts a new trajectory (s)")
    im.add_argument("--payload-kg", type=float_in(0, 100), default=2.805,
                    help="payload of the --loaded logs (default: the published 2.805 kg of *harm50secLoad)")
    common(im)
    im.set_defaults(func=cmd_import)

    em = sub.add_parser("emulate", help="serve a device emulator on this machine until Ctrl+C")
    em.add_argument("device", choices=("arm", "sensor", "cell"),
                    help="cell: plant + arm + sensor emulators, endpoints as JSON on stdout, faults on stdin")
    em.add_argument("--port", type=PORT, default=5020, help="TCP port for the arm emulator (127.0.0.1)")
    em.add_argument("--kinematic", action="store_true", help="arm: a simple kinematic plant instead of MuJoCo")
    em.add_argument("--config", type=Path, default=None)
    em.add_argument("--seed", type=SEED, default=None)
    em.add_argument("--plant", default=None, help="plant profile YAML")
    em.add_argument("--scene", choices=("free", "table", "peg"), default=None)
    em.set_defaults(func=cmd_emulate)

    b = sub.add_parser("bench", help="benchmarks that print the project's measured figures")
    b.add_argument("what", choices=BENCH_NAMES)
    b.add_argument("--trials", type=COUNT, default=PEG_TRIALS, help="randomised insertions (bench peg-in-hole)")
    b.add_argument("--max-offset-mm", type=float_in(0, 20), default=PEG_MAX_OFFSET_MM,
                   help="hole offset drawn in +-this on x and y (bench peg-in-hole)")
    b.add_argument("--max-tilt-deg", type=float_in(0, 10), default=PEG_MAX_TILT_DEG,
                   help="hole tilt drawn in +-this about x and y (bench peg-in-hole)")
    b.add_argument("--peg-diameter-mm", type=float_in(1, 100, lo_open=True), default=None,
                   help="peg diameter (bench peg-in-hole; default: the plant profile's, 21.4)")
    b.add_argument("--force-source", choices=FORCE_SOURCES, default="virtual",
                   help="bench peg-in-hole: what the task regulates with")
    b.add_argument("--only", type=int_in(0), nargs="+", default=None, metavar="K",
                   help="bench peg-in-hole: run only these trial numbers (the same draws as in the full bench)")
    b.add_argument("--record", action="store_true",
                   help="bench peg-in-hole: log every trial run (runs/<date>-bench-peg/trial_NNN, as `run` logs)")
    add_view_options(b, "bench peg-in-hole, one trial (--only K)")
    b.add_argument("--impacts", type=COUNT, default=COLLISION_IMPACTS, help="scripted impacts (bench collision)")
    b.add_argument("--free-s", type=float_in(0, 3600), default=COLLISION_FREE_S,
                   help="simulated seconds of free motion for false alarms (bench collision)")
    b.add_argument("--reaction", choices=REACTIONS, default="stop", help="bench collision: the reaction to impacts")
    b.add_argument("--n", type=COUNT, default=500, help="samples (bench drivers)")
    b.add_argument("--data", default=None, help="dataset manifest (bench model)")
    b.add_argument("--model", default=None, help="model artefact (bench model; default: train an H1; bench planning: "
                   "default the prepared wipe model, 'nominal' the URDF's rigid body)")
    b.add_argument("--calls", type=COUNT, default=5000, help="single-sample predictions timed (bench model)")
    b.add_argument("--train-samples", type=int_in(100), default=24_000,
                   help="H1 training samples (bench model, no --model)")
    b.add_argument("--fit-samples", type=int_in(100), default=500_000,
                   help="samples for the timed XGBoost fit (bench model)")
    b.add_argument("--nthread", type=NTHREAD, default=2)
    b.add_argument("--plant", default=None, help="plant profile YAML (bench plant)")
    robot_option(b, "bench model: the dataset's ")
    add_planning_options(b)
    common(b)
    b.set_defaults(func=cmd_bench)

    add_replay_parser(sub)
    add_doctor_parser(sub)

    fi = sub.add_parser("figures", help="write docs/figures.md from the benchmarks' saved JSON summaries")
    fi.add_argument("--bench-dir", type=Path, default=BENCH_DIR, help=f"saved summaries (default {BENCH_DIR})")
    fi.add_argument("--out", type=Path, default=FIGURES_PAGE, help=f"the page to write (default {FIGURES_PAGE})")
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
    try:
        with sigterm_as_interrupt():
            code = int(args.func(args))
        return 143 if code == 130 and received_sigterm() else code
    except CellError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        if isinstance(exc, Terminated):
            print("terminated (SIGTERM): the arm was stopped", file=sys.stderr)
            return 143
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
