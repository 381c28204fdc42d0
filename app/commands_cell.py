"""Command bodies that work a cell: `run` a task, `status`, `emulate` a device."""

from __future__ import annotations

import argparse
import json
import logging
import time
from typing import Any

import numpy as np

from app.cells import cell_kind, open_cell
from app.common import emit, load_cell_config, save_bench_summary
from app.sensing import ensure_virtual_artefacts, make_force_source, with_guard
from app.tasks_registry import TASKS, build_task, robot_for
from cell.config import load_config

log = logging.getLogger("tmcell")


def cmd_run(args: argparse.Namespace) -> int:
    cfg = load_cell_config(args)
    spec = TASKS[args.task]
    robot = robot_for(cfg, spec.tool)
    task, max_duration = build_task(args.task, cfg, robot, args.force_source)
    kind = cell_kind(cfg, args.cell)
    publisher = None
    if getattr(args, "publish", None):  # resolved here, once: an unknown host is refused before any work
        from cell.view.publish import WrenchPublisher, parse_endpoint

        publisher = WrenchPublisher(parse_endpoint(args.publish), robot.n)
    if args.force_source == "virtual":
        ensure_virtual_artefacts(cfg, spec.tool, kind, robot, args.seed)
    view = None
    if getattr(args, "view", False):
        from app.view import live_view

        view = live_view(robot, f"run-{args.task}", args.serve, args.force_source == "virtual",
                         args.bind)
    sinks = [s for s in (view, publisher) if s is not None]
    holder = open_cell(cfg, kind, robot, args.seed, spec.scene)
    try:
        cell = with_guard(cfg, spec.tool, make_force_source(cfg, args.force_source, spec.tool, holder.open(), robot),
                          robot)
        from tasks.runner import run_task

        summary = run_task(task, cell, cfg, robot, max_duration, record=not args.no_record,
                           extra_summary={"seed": args.seed}, view=_one_sink(sinks))
    finally:
        holder.close()
        if publisher is not None:
            publisher.close()
    emit(summary, args.json)
    if view is not None:
        from app.view import finish_view

        finish_view(view, args.serve)
    if summary["outcome"] == "interrupted":
        return 130
    save_bench_summary(summary, f"run-{args.task}", run_tags(kind, args.force_source), args)
    return 0 if summary["outcome"] == "done" else 1


def _one_sink(sinks: list[Any]) -> Any:
    """The loop's row consumer: none, the one asked for, or both (the live view and the publisher)."""
    if len(sinks) <= 1:
        return sinks[0] if sinks else None
    from cell.view.publish import RowSinks

    return RowSinks(sinks)


def run_tags(kind: str, force_source: str) -> list[str]:
    """The tags of a run's saved summary (`run-<task>[-<cell>][-sensor]`): the simulated cell and the virtual
    sensor are the defaults."""
    return ([kind] if kind != "sim" else []) + (["sensor"] if force_source == "sensor" else [])


WRENCH_WHERE = "at the F/T sensor face, sensor frame, untared"  # status reads the sensor as it is, no tare
AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")


def read_status(cell: Any, robot: Any) -> dict[str, Any]:
    """One reading of the arm and the F/T sensor, every value with its unit in its key."""
    state = cell.arm.read_state()
    wrench = cell.force.read(state)
    return {
        "cell": cell.kind,
        "lifecycle": cell.arm.lifecycle.value,
        "t": state.t,
        "q_deg": np.degrees(state.q).round(3).tolist(),
        "dq_deg_s": np.degrees(state.dq).round(3).tolist(),
        "tau_nm": np.round(state.tau, 3).tolist(),
        "status": {k: bool(v) for k, v in vars(state.status).items()},
        "tcp_m": np.round(robot.tcp_pose(state.q).translation, 4).tolist(),
        # The wrench's list keeps its key; where it was taken and in what frame is said beside it.
        "wrench": np.round(wrench.vector, 3).tolist(),
        "wrench_units": "N (Fx, Fy, Fz), N m (Mx, My, Mz)",
        "wrench_frame": "F/T sensor frame, at the sensor face; what the tool exerts (pressing down reads +Fz)",
        "wrench_tared": False,
        **modbus_cross_check(cell.arm),
    }


def modbus_cross_check(arm: Any) -> dict[str, Any]:
    """On TM's channels, `modbus_cross_check`: the controller's own Modbus table against the Ethernet Slave's
    (None when devices.arm.settings.modbus_port is null, `error` when it cannot be read); nothing elsewhere."""
    from drivers.errors import DriverError
    from drivers.tm5.ethernet import TMEthernetArm
    from drivers.tm5.table_check import check_arm

    if not isinstance(arm, TMEthernetArm):
        return {}
    if arm.config.modbus_port is None:
        return {"modbus_cross_check": None}
    try:
        return {"modbus_cross_check": check_arm(arm).as_dict()}
    except DriverError as exc:  # a reading command reports what it could not read, and reads on
        return {"modbus_cross_check": {"error": str(exc)}}


def format_status(out: dict[str, Any]) -> str:
    """The human reading: each quantity labelled with its unit, the wrench with where and how it was taken."""
    def row(values: list[float], fmt: str = "8.3f") -> str:
        return " ".join(format(v, fmt) for v in values)

    w = out["wrench"]
    flags = ", ".join(k for k, v in out["status"].items() if v) or "none"
    return "\n".join([
        f"cell: {out['cell']}   lifecycle: {out['lifecycle']}   t: {out['t']:.3f} s   status flags: {flags}",
        f"joints q [deg]:        {row(out['q_deg'])}",
        f"joint speeds [deg/s]:  {row(out['dq_deg_s'])}",
        f"joint torques [N m]:   {row(out['tau_nm'])}",
        f"TCP position [m] (base frame): {row(out['tcp_m'], '.4f')}",
        f"wrench {WRENCH_WHERE}: " + "  ".join(f"{a} {v:.3f} {'N' if a[0] == 'F' else 'N m'}"
                                              for a, v in zip(AXES, w, strict=True)),
        *_cross_check_line(out),
    ])


def _cross_check_line(out: dict[str, Any]) -> list[str]:
    if "modbus_cross_check" not in out:
        return []
    check = out["modbus_cross_check"]
    if check is None:
        return ["Modbus cross-check: off (devices.arm.settings.modbus_port is null)"]
    if "error" in check:
        return [f"Modbus cross-check: cannot read: {check['error']}"]
    flags = "; flags differ: " + "; ".join(check["differing_flags"]) if check["differing_flags"] else ""
    return [f"Modbus cross-check ({check['endpoint']}): {'agrees' if check['agrees'] else 'DISAGREES'}, joints "
            f"off the Ethernet Slave's by at most {check['max_joint_diff_deg']:.3f} deg{flags}"]


def cmd_status(args: argparse.Namespace) -> int:

    cfg = load_config(args.config)
    robot = robot_for(cfg, "wipe")
    holder = open_cell(cfg, cell_kind(cfg, args.cell), robot, args.seed, None)
    try:
        cell = holder.open()
        while True:
            out = read_status(cell, robot)
            if args.json:
                emit(out, True)
            else:
                print(format_status(out), flush=True)
            if not args.watch:
                break
            time.sleep(args.interval)  # Ctrl+C ends the watch (exit 130), the cell closed below
            if not args.json:
                print(flush=True)
    finally:
        holder.close()
    return 0


def _emulate_arm(args: argparse.Namespace) -> int:
    """The arm alone on the config's protocol, on the MuJoCo plant (or a kinematic stand-in)."""
    from sim.cell import make_plant
    from sim.kinematic_plant import KinematicPlant
    from sim.serve_cell import arm_emulator, arm_endpoint

    cfg = load_cell_config(args)
    plant = KinematicPlant() if args.kinematic else make_plant(cfg, args.seed, "free")
    period = args.broadcast_ms / 1000.0 if args.broadcast_ms else None
    with arm_emulator(cfg, plant, args.port, args.listen_port, period, args.bind) as emu:
        log.info("arm emulator on %s %s; Ctrl+C or SIGTERM stops it", args.bind, arm_endpoint(emu))
        print(json.dumps(arm_endpoint(emu)), flush=True)
        try:
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:
            log.info("arm emulator: stopping")
    return 0


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve one device emulator until Ctrl+C or SIGTERM (for standard tools or a second process); a closed
    stdin does not end it."""
    if args.device == "cell":
        from sim.serve_cell import serve_cell

        cfg = load_cell_config(args)
        return serve_cell(cfg, args.seed, args.scene or cfg.scene.kind, args.port, args.listen_port,
                          until_signal=True, bind=args.bind)
    if args.device == "arm":
        return _emulate_arm(args)
    from sim.wacoh_emulator import emulate_sensor_main

    return emulate_sensor_main(args.seed or 0)
