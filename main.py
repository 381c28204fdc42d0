"""Command-line entry of the TM5-700 force-control cell: run tasks, check status, benchmark, emulate devices."""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cell.cliargs import COUNT, NTHREAD, PORT, SEED, float_in, int_in, int_list
from cell.config import CONFIG_DIR, TOOLS, CellConfig, check_home, check_task_force, load_config, resolve
from cell.configio import dumps_strict
from cell.robot import RobotModel, load_robot
from cell.signals import Terminated, received_sigterm, sigterm_as_interrupt
from drivers.errors import CellError, ConfigError

log = logging.getLogger("tmcell")

TASK_NAMES = ("wipe", "peg-in-hole")


# --------------------------------------------------------------------------------------- building
def robot_for(cfg: CellConfig, tool: str) -> RobotModel:
    tcp = cfg.robot.tcp_wipe if tool == "wipe" else cfg.robot.tcp_peg
    robot = load_robot(resolve(cfg.robot.urdf), tcp, cfg.robot.tool_mass, cfg.robot.tool_com)
    check_home(cfg, robot)
    return robot


def build_task(name: str, cfg: CellConfig, robot: RobotModel, force_source: str = "virtual") -> tuple[Any, float]:
    if name == "wipe":
        from tasks.wipe import WipeTask, load_wipe_config

        wcfg = load_wipe_config(cfg.tasks.get("wipe"), f"{cfg.source}: tasks.wipe")
        check_task_force(cfg, "wipe", wcfg.max_force_n)
        try:
            task = WipeTask(wcfg, robot, cfg.scene.table_height, cfg.loop.period_s, np.asarray(cfg.robot.home))
        except ValueError as exc:
            raise ConfigError(f"{cfg.source}: tasks.wipe: {exc}") from None
        return task, wcfg.max_duration_s
    if name == "peg-in-hole":
        from tasks.peg import PegInHoleTask
        from tasks.peg_config import load_peg_config

        pcfg = load_peg_config(cfg.tasks.get("peg"), f"{cfg.source}: tasks.peg", force_source)
        check_task_force(cfg, "peg", pcfg.max_force_n)
        try:
            task = PegInHoleTask(pcfg, robot, np.asarray(cfg.scene.hole_center, float), cfg.scene.table_height,
                                 cfg.loop.period_s, np.asarray(cfg.robot.home))
        except ValueError as exc:
            raise ConfigError(f"{cfg.source}: tasks.peg: {exc}") from None
        return task, pcfg.max_duration_s
    raise ConfigError(f"unknown task '{name}' (known: {', '.join(TASK_NAMES)})")


def cell_kind(cfg: CellConfig, requested: str | None) -> str:
    """--cell wins; otherwise the config's device kinds, which must agree."""
    if requested:
        return requested
    arm, sensor = cfg.devices.arm.kind, cfg.devices.sensor.kind
    if arm != sensor:
        raise ConfigError(f"{cfg.source}: devices.arm.kind ({arm}) and devices.sensor.kind ({sensor}) differ; "
                          "mixed cells are not supported yet")
    return arm


class RealCell:
    """The physical cell: drivers from config, paced by the wall clock."""

    def __init__(self, cfg: CellConfig, robot: RobotModel) -> None:
        from drivers.real_cell import make_real_devices

        self.period = cfg.loop.period_s
        self.devices = make_real_devices(cfg.devices.arm.settings, cfg.devices.sensor.settings, robot.limits,
                                         cfg.loop.period_s, f"{cfg.source}: devices")

    def open(self) -> Any:
        from cell.force import SensorForceSource
        from cell.loop import OpenCell, WallTicker

        d = self.devices
        assert d.sensor is not None and d.sensor_cfg is not None
        d.arm.connect()
        d.sensor.connect()
        return OpenCell(kind="real", arm=d.arm, force=SensorForceSource(d.sensor, d.sensor_cfg.tare_samples),
                        ticker=WallTicker(self.period))

    def close(self) -> None:
        self.devices.close()


def open_cell(cfg: CellConfig, kind: str, robot: RobotModel, seed: int | None, scene: str | None) -> Any:
    """Returns an object with .open() -> OpenCell and .close()."""
    if kind == "sim":
        from sim.cell import make_sim_cell

        return make_sim_cell(cfg, robot.limits, seed=seed, scene_kind=scene)
    if kind == "emulated":
        from sim.emulated import EmulatedCell

        return EmulatedCell(cfg, robot.limits, seed=seed, scene_kind=scene)
    if kind == "real":
        return RealCell(cfg, robot)
    raise ConfigError(f"unknown cell kind '{kind}' (sim, emulated, real)")


# --------------------------------------------------------------------------------------- commands
# The tool each task runs with: its virtual sensor's model and calibration are that tool's.
TASK_TOOLS = {"wipe": "wipe", "peg-in-hole": "peg"}
TASK_SCENES = {"wipe": "table", "peg-in-hole": "peg"}  # the simulated fixture each task works on
PREPARE_SAMPLES = 40_000  # `prepare`'s default collection: about half a minute of simulated motion per 10k


def cell_identity(cfg: CellConfig, kind: str, seed: int | None) -> dict[str, Any]:
    """Which arm a calibration was made on: for a simulated one its plant profile (which fixes the
    specimen: friction-ripple phases, sensor offset) and the run seed (noise only)."""
    if kind == "real":
        return {"kind": "real"}
    import hashlib

    from sim.profile import load_profile

    path = resolve(cfg.plant)
    profile = load_profile(path)
    return {"kind": "sim", "plant": str(path), "plant_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "specimen_seed": profile.specimen_seed, "seed": seed if seed is not None else profile.seed}


def ensure_virtual_artefacts(cfg: CellConfig, tool: str, kind: str, robot: RobotModel,
                             seed: int | None = None) -> None:
    """The tool's model and calibration must be present and match: built on the spot for a simulated
    or emulated cell (same plant, logged), refused with the command to run for the real one."""
    from tasks.calibrate import artefacts_missing

    why = artefacts_missing(cfg, robot, tool)
    if not why:
        if kind != "real":
            _warn_other_plant(cfg, tool, seed)
        return
    if kind == "real":
        raise ConfigError(
            f"virtual force sensor for the {tool} tool: {why}; make it on the cell with "
            f"`main.py prepare --tool {tool} --cell real` (or `main.py calibrate --tool {tool} --cell real` when "
            f"the model exists), or run with --force-source sensor"
        )
    log.warning("virtual force sensor for the %s tool: %s; building it now with `main.py prepare --tool %s` "
                "on the simulated cell (once, a couple of minutes)", tool, why, tool)
    run_prepare(cfg, tool, "sim", None, PREPARE_SAMPLES, force=False)


def _warn_other_plant(cfg: CellConfig, tool: str, seed: int | None) -> None:
    from cell.virtual_sensor import read_calibration_doc

    made = read_calibration_doc(cfg.virtual_sensor.path("calibration", tool)).get("cell", {})
    here = cell_identity(cfg, "sim", seed)
    if made.get("kind") == "sim" and made.get("plant_sha256") != here["plant_sha256"]:
        log.warning("the %s tool's virtual sensor was made on plant profile %s, this run uses %s: another arm "
                    "(other friction, other ripple), expect larger force errors; `main.py prepare --tool %s --force` "
                    "rebuilds it for this one", tool, made.get("plant"), here["plant"], tool)


def make_force_source(cfg: CellConfig, source: str, tool: str, cell: Any, robot: RobotModel) -> Any:
    """The OpenCell a task runs on for --force-source: `sensor` keeps the F/T sensor in the loop;
    `virtual` regulates with the tool's virtual sensor and keeps the F/T sensor (when the cell has
    one) as the logged ground truth.  Every task builds its force source here."""
    if source == "sensor":
        return cell
    if source != "virtual":
        raise ConfigError(f"--force-source {source}: unknown (virtual or sensor)")
    from cell.virtual_sensor import build_virtual_source

    virtual = build_virtual_source(cfg.virtual_sensor, robot, tool, cfg.loop.period_s)
    log.info("force source: virtual sensor (%s) for the %s tool; the F/T sensor is logged as ground truth",
             virtual.label, tool)
    return replace(cell, force=virtual, ground_truth=cell.force)


def cmd_run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    if args.plant:
        cfg.plant = str(Path(args.plant).resolve())
    tool = TASK_TOOLS.get(args.task, "wipe")
    robot = robot_for(cfg, tool)
    task, max_duration = build_task(args.task, cfg, robot, args.force_source)
    kind = cell_kind(cfg, args.cell)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, tool, kind, robot, args.seed)
    holder = open_cell(cfg, kind, robot, args.seed, TASK_SCENES.get(args.task, "table"))
    try:
        cell = make_force_source(cfg, args.force_source, tool, holder.open(), robot)
        from tasks.runner import run_task

        summary = run_task(task, cell, cfg, robot, max_duration, record=not args.no_record,
                           extra_summary={"seed": args.seed})
    finally:
        holder.close()
    _emit(summary, args.json)
    if summary["outcome"] == "interrupted":
        return 130
    return 0 if summary["outcome"] == "done" else 1


def calibration_cells(cfg: CellConfig, kind: str, tool: str, robot: RobotModel,
                      seed: int | None) -> tuple[Any, Any]:
    """(opener, load-applier factory) for calibrating on `kind`: the free scene with `tool` mounted
    and the scripted hand (sim), or the real cell and the operator prompted here (never the driver)."""
    from tasks.calibrate import OperatorLoads

    if kind == "sim":
        from sim.cell import make_sim_cell
        from sim.hand import ScriptedHand

        cal = cfg.virtual_sensor.calibration

        def sim_opener() -> Any:
            return make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="free", tool=tool)

        def hand(holder: Any) -> Any:
            return ScriptedHand(holder.plant, seed=seed or 0, max_force_n=cal.max_force_n,
                                max_lateral_n=cal.max_lateral_n, max_moment_nm=cal.max_moment_nm, load_s=cal.load_s)

        return sim_opener, hand
    if kind == "real":
        def real_opener() -> Any:
            return RealCell(cfg, robot)

        return real_opener, lambda holder: OperatorLoads()
    raise ConfigError(f"--cell {kind}: calibration runs on the simulated cell (its scripted hand) or the real one")


def run_prepare(cfg: CellConfig, tool: str, kind: str, seed: int | None, samples: int, force: bool) -> dict[str, Any]:
    from tasks.calibrate import prepare

    robot = robot_for(cfg, tool)
    if kind == "sim":
        from sim.cell import make_plant

        make_plant(cfg, seed, "free", tool)  # a bad plant profile fails here, before any planning
    opener, applier = calibration_cells(cfg, kind, tool, robot, seed)
    return prepare(cfg, tool, robot, opener, opener, applier, samples=samples, force=force,
                   cell_info=cell_identity(cfg, kind, seed), working_posture=working_posture(cfg, tool, robot))


SWEEP_LIFT_M = 0.1  # the sweeps' centre: the task's start lifted this far (the collection keeps off the table)


def working_posture(cfg: CellConfig, tool: str, robot: RobotModel) -> np.ndarray:
    """Where `prepare` sweeps slowly: the joints of the tool's task start, with the tool lifted
    `SWEEP_LIFT_M` (the task's regime of postures and speeds, clear of the work surface)."""
    task, _ = build_task(next(t for t, k in TASK_TOOLS.items() if k == tool), cfg, robot)
    q0 = np.asarray(task.q_start, float)
    pose = robot.tcp_pose(q0)
    pose.translation = pose.translation + np.array([0.0, 0.0, SWEEP_LIFT_M])
    q, ok = robot.ik(pose, q0)
    if not ok:
        raise ConfigError(f"the {tool} tool's working posture lifted {SWEEP_LIFT_M} m is not reachable")
    return np.asarray(q, float)


def cmd_prepare(args: argparse.Namespace) -> int:
    cfg = _lab_config(args)
    out = run_prepare(cfg, args.tool, args.cell, args.seed, args.samples, args.force)
    _emit(out, args.json)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from tasks.calibrate import calibrate

    cfg = _lab_config(args)
    robot = robot_for(cfg, args.tool)
    opener, applier = calibration_cells(cfg, args.cell, args.tool, robot, args.seed)
    out = calibrate(cfg, args.tool, robot, opener, applier, Path(args.model) if args.model else None,
                    Path(args.out) if args.out else None, cell_identity(cfg, args.cell, args.seed))
    _emit(out, args.json)
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    robot = robot_for(cfg, "wipe")
    holder = open_cell(cfg, cell_kind(cfg, args.cell), robot, args.seed, None)
    try:
        cell = holder.open()
        state = cell.arm.read_state()
        wrench = cell.force.read(state)
        tcp = robot.tcp_pose(state.q).translation
        out = {
            "cell": cell.kind,
            "lifecycle": cell.arm.lifecycle.value,
            "t": state.t,
            "q_deg": np.degrees(state.q).round(3).tolist(),
            "dq_deg_s": np.degrees(state.dq).round(3).tolist(),
            "tau_nm": np.round(state.tau, 3).tolist(),
            "status": {k: bool(v) for k, v in vars(state.status).items()},
            "tcp_m": np.round(tcp, 4).tolist(),
            "wrench": np.round(wrench.vector, 3).tolist(),
        }
    finally:
        holder.close()
    _emit(out, args.json)
    return 0


def bench_peg_in_hole(args: argparse.Namespace) -> dict[str, Any]:
    """Randomised insertions on the simulated cell with the force source `run` would use for the peg."""
    from bench.peg import bench_peg
    from tasks.peg_config import load_peg_config

    cfg = load_config(args.config)
    if args.plant:
        cfg.plant = str(Path(args.plant).resolve())
    robot = robot_for(cfg, "peg")
    pcfg = load_peg_config(cfg.tasks.get("peg"), f"{cfg.source}: tasks.peg", args.force_source)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, "peg", "sim", robot)

    def wrap(cell: Any) -> Any:
        return make_force_source(cfg, args.force_source, "peg", cell, robot)

    if args.trials < 1 or args.max_offset_mm < 0 or args.max_tilt_deg < 0:
        raise ConfigError("bench peg-in-hole: --trials must be >= 1, --max-offset-mm and --max-tilt-deg >= 0")
    if args.only is not None and not all(0 <= k < args.trials for k in args.only):
        raise ConfigError(f"bench peg-in-hole: --only {args.only}: trial numbers must lie in 0..{args.trials - 1}")
    record = None
    if args.record:
        from cell.recorder import new_run_dir

        record = new_run_dir(Path(cfg.recording.directory), "bench-peg")
        log.info("recording every trial under %s", record)
    return bench_peg(cfg, robot, pcfg, args.trials, args.seed if args.seed is not None else 0,
                     only=args.only, record=record,
                     max_offset_m=args.max_offset_mm * 1e-3, max_tilt_deg=args.max_tilt_deg,
                     peg_diameter=args.peg_diameter_mm * 1e-3 if args.peg_diameter_mm else None,
                     wrap=wrap, force_source=args.force_source)


def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "peg-in-hole":
        out = bench_peg_in_hole(args)
    elif args.what == "sim":
        from bench.timing import bench_sim

        out = bench_sim(load_config(args.config), seed=args.seed)
    elif args.what == "drivers":
        from bench.timing import bench_drivers

        out = bench_drivers(args.n)
    elif args.what == "model":
        from tasks.lab_bench import bench_model

        if not args.data:
            raise ConfigError("bench model needs --data DATASET.yaml (make one with main.py collect)")
        out = bench_model(_lab_config(args), Path(args.data), Path(args.model) if args.model else None,
                              train_samples=args.train_samples, fit_samples=args.fit_samples,
                              calls=args.calls, nthread=args.nthread, robot=args.robot)
    elif args.what == "plant":
        from bench.characterise import characterise_plant

        cfg = load_config(args.config)
        if args.plant:
            cfg.plant = str(Path(args.plant).resolve())
        out = characterise_plant(cfg, seed=args.seed)
    elif args.what == "faults":
        from bench.faults import bench_faults

        cfg = load_config(args.config)
        out = bench_faults(cfg, robot_for(cfg, "wipe"))
        _emit(out, args.json)
        return 0 if out["failures"] == 0 else 1
    else:
        raise ConfigError(f"bench {args.what}: unknown benchmark")
    _emit(out, args.json)
    return 0


def torque_model(cfg: CellConfig, robot: RobotModel, path: str | None) -> tuple[Any, str, Any]:
    """The torque predictor the planner uses, its name and the part toppra takes as its constraint:
    a saved model artefact, or the nominal rigid body (P1)."""
    if path:
        from cell.dynamics.artefact import load_model  # the model lab's artefacts
        from cell.planner import toppra_terms

        model = load_model(Path(path), robot)
        return model.predict, f"{model.meta.kind} ({path})", toppra_terms(model)
    log.warning("no --model and no prepared model (main.py prepare): planning with the nominal rigid-body model "
                "(P1, no rotor inertia or friction); validation on the cell corrects the plan where it is wrong")

    def p1(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return np.array([robot.rnea(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])

    return p1, "P1 (nominal URDF)", None


def cmd_plan(args: argparse.Namespace) -> int:
    from cell.collision import CollisionChecker
    from tasks.plan import load_plan_file, parse_waypoints, run_plans

    cfg = load_config(args.config)
    plan_file = load_plan_file(args.plans)
    if args.waypoints:
        plan_file = replace(plan_file, paths={"cli": parse_waypoints(args.waypoints)})
    only = args.path or None
    if only:
        unknown = [p for p in only if p not in plan_file.paths]
        if unknown:
            raise ConfigError(f"{args.plans}: no path named '{unknown[0]}' (known: {', '.join(plan_file.paths)})")
    cfg.safety = replace(cfg.safety, max_tcp_speed=plan_file.max_tcp_speed)
    robot = robot_for(cfg, "wipe")
    model_path = args.model
    if model_path is None:
        prepared = cfg.virtual_sensor.path("model", "wipe")
        if (prepared / "model.json").exists():
            model_path = str(prepared)
            log.info("planning with the prepared hybrid model %s (--model to choose another)", prepared)
    predictor, model_name, terms = torque_model(cfg, robot, model_path)
    collisions = CollisionChecker(robot, replace(cfg.scene, kind="free"))

    def open_for_plan() -> tuple[Any, Any]:
        holder = open_cell(cfg, cell_kind(cfg, args.cell), robot, args.seed, "free")
        try:
            return holder.open(), holder
        except BaseException:
            holder.close()
            raise

    out = run_plans(cfg, robot, predictor, model_name, plan_file, open_for_plan, collisions,
                    Path(cfg.recording.directory) / "plans", only, terms)
    _emit(out, args.json)
    return 0


def _lab_config(args: argparse.Namespace) -> CellConfig:
    cfg = load_config(args.config)
    if getattr(args, "plant", None):
        cfg.plant = str(Path(args.plant).resolve())
    return cfg


def cmd_collect(args: argparse.Namespace) -> int:
    from tasks import lab

    cfg = _lab_config(args)
    robot = lab.lab_robot(cfg)
    kind = cell_kind(cfg, args.cell)

    def opener() -> Any:
        return open_cell(cfg, kind, robot, args.seed, "free")

    out = lab.collect(cfg, opener, Path(args.out), samples=args.samples, family=args.family,
                      fourier_share=args.fourier_share, test_trajectories=args.test_trajectories,
                      test_repeats=args.test_repeats, test_moves=args.test_moves,
                      excitation=args.excitation, seed=args.plan_seed, robot=args.robot)
    _emit(out, args.json)
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from tasks import lab

    out = lab.train(_lab_config(args), Path(args.data), Path(args.out), kind=args.model, samples=args.samples,
                    window=args.window, grouping=args.grouping, derivatives=args.derivatives,
                    nthread=args.nthread, seed=args.seed or 0, robot=args.robot)
    _emit(out, args.json)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from tasks import lab

    curve = None if args.no_curve else args.curve if args.curve else lab.DEFAULT_CURVE
    out = lab.evaluate(_lab_config(args), Path(args.data), Path(args.out), train_samples=args.train_samples,
                       large_samples=args.large_samples, curve=curve, nthread=args.nthread, seed=args.seed or 0,
                       max_trees=args.max_trees, robot=args.robot, lofo=args.lofo)
    _emit(out, args.json)
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from tasks.import_ur10e import import_ur10e

    out = import_ur10e(Path(args.out), train=args.train, test=args.test, loaded=args.loaded,
                       max_gap_s=args.max_gap_s, payload_kg=args.payload_kg)
    _emit(out, args.json)
    return 0


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve one device emulator until Ctrl+C (for standard tools or a second process)."""
    if args.device == "cell":
        from sim.emulated import serve_cell

        cfg = load_config(args.config)
        if args.plant:
            cfg.plant = str(Path(args.plant).resolve())
        return serve_cell(cfg, args.seed, args.scene or cfg.scene.kind)
    if args.device == "arm":
        from sim.tm5_emulator import emulate_arm_main

        plant = None
        if not args.kinematic:
            from sim.cell import make_plant

            plant = make_plant(load_config(args.config), args.seed, "free")
        return emulate_arm_main(args.port, plant)
    from sim.wacoh_emulator import emulate_sensor_main

    return emulate_sensor_main(args.seed or 0)


def _emit(out: dict[str, Any], as_json: bool) -> None:
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
    run.add_argument("--cell", choices=("sim", "emulated", "real"), default=None,
                     help="default: devices.*.kind from the config")
    run.add_argument("--force-source", choices=("virtual", "sensor"), default="virtual",
                     help="virtual (default): the virtual force sensor, the F/T sensor logged as ground truth")
    run.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    run.add_argument("--no-record", action="store_true", help="do not write runs/<...>/")
    common(run)
    run.set_defaults(func=cmd_run)

    pr = sub.add_parser("prepare", help="make a tool ready for sensorless tasks: collect, train H1, calibrate")
    pr.add_argument("--tool", choices=TOOLS, default="wipe")
    pr.add_argument("--cell", choices=("sim", "real"), default="sim")
    pr.add_argument("--samples", type=COUNT, default=PREPARE_SAMPLES, help="training samples to collect")
    pr.add_argument("--force", action="store_true", help="rebuild every artefact even if present and matching")
    pr.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    common(pr)
    pr.set_defaults(func=cmd_prepare)

    ca = sub.add_parser("calibrate", help="calibrate the virtual force sensor against the F/T sensor")
    ca.add_argument("--tool", choices=TOOLS, default="wipe")
    ca.add_argument("--cell", choices=("sim", "real"), default="sim")
    ca.add_argument("--model", default=None, help="torque model artefact (default: virtual_sensor.model_dir)")
    ca.add_argument("--out", default=None, help="calibration folder (default: virtual_sensor.calibration_dir)")
    ca.add_argument("--plant", default=None, help="plant profile YAML (sim cells)")
    common(ca)
    ca.set_defaults(func=cmd_calibrate)

    st = sub.add_parser("status", help="connect to the cell and print its state")
    st.add_argument("--cell", choices=("sim", "emulated", "real"), default=None)
    common(st)
    st.set_defaults(func=cmd_status)

    pl = sub.add_parser("plan", help="time-optimal plans under torque limits, executed and compared to a baseline")
    pl.add_argument("--plans", type=Path, default=CONFIG_DIR / "plans.yaml", help="paths and planner settings")
    pl.add_argument("--path", action="append", help="only this named path (repeatable)")
    pl.add_argument("--waypoints", default=None, help="'j1,..,j6; j1,..,j6; ...' in degrees instead of --plans paths")
    pl.add_argument("--model", default=None, help="torque model artefact (default: nominal rigid body)")
    pl.add_argument("--cell", choices=("sim", "emulated", "real"), default=None)
    common(pl)
    pl.set_defaults(func=cmd_plan)

    co = sub.add_parser("collect", help="run excitation and test trajectories on a cell; write a dataset")
    co.add_argument("--cell", choices=("sim", "emulated", "real"), default=None)
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
    b.add_argument("what", choices=("sim", "plant", "drivers", "model", "peg-in-hole", "faults"))
    b.add_argument("--trials", type=COUNT, default=50, help="randomised insertions (bench peg-in-hole)")
    b.add_argument("--max-offset-mm", type=float_in(0, 20), default=2.0,
                   help="hole offset drawn in +-this on x and y (bench peg-in-hole)")
    b.add_argument("--max-tilt-deg", type=float_in(0, 10), default=2.0,
                   help="hole tilt drawn in +-this about x and y (bench peg-in-hole)")
    b.add_argument("--peg-diameter-mm", type=float_in(1, 100, lo_open=True), default=None,
                   help="peg diameter (bench peg-in-hole; default: the plant profile's, 21.4)")
    b.add_argument("--force-source", choices=("virtual", "sensor"), default="virtual",
                   help="bench peg-in-hole: what the task regulates with")
    b.add_argument("--only", type=int_in(0), nargs="+", default=None, metavar="K",
                   help="bench peg-in-hole: run only these trial numbers (the same draws as in the full bench)")
    b.add_argument("--record", action="store_true",
                   help="bench peg-in-hole: log every trial run (runs/<date>-bench-peg/trial_NNN, as `run` logs)")
    b.add_argument("--n", type=COUNT, default=500, help="samples (bench drivers)")
    b.add_argument("--data", default=None, help="dataset manifest (bench model)")
    b.add_argument("--model", default=None, help="model artefact (bench model; default: train an H1)")
    b.add_argument("--calls", type=COUNT, default=5000, help="single-sample predictions timed (bench model)")
    b.add_argument("--train-samples", type=int_in(100), default=24_000,
                   help="H1 training samples (bench model, no --model)")
    b.add_argument("--fit-samples", type=int_in(100), default=500_000,
                   help="samples for the timed XGBoost fit (bench model)")
    b.add_argument("--nthread", type=NTHREAD, default=2)
    b.add_argument("--plant", default=None, help="plant profile YAML (bench plant)")
    robot_option(b, "bench model: the dataset's ")
    common(b)
    b.set_defaults(func=cmd_bench)
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
