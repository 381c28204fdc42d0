"""The `doctor` command: named bring-up checks of the real or emulated cell's arm and sensor, each with what to do."""

from __future__ import annotations

import argparse
import contextlib
import logging
from pathlib import Path
from typing import Any

from app.common import emit
from app.tasks_registry import robot_for
from cell.cliargs import SEED, float_in
from cell.config import load_config
from drivers.errors import ConfigError, DriverError
from tasks.setup.doctor import format_table

log = logging.getLogger("tmcell")
EMULATED_TAIL_PERIODS = 3.0  # the emulators share this machine's CPU (sim/emulated.py relaxes its timeouts alike)


def add_doctor_parser(sub: Any) -> None:
    """`doctor --cell real|emulated [--tare-s S] [--inject CMD]... [--stream-stop] [--json]`."""

    dr = sub.add_parser("doctor", help="bring-up checks of the arm and sensor wiring: named, pass/fail, what to do")
    dr.add_argument("--cell", choices=("real", "emulated"), default="real",
                    help="the real arm and sensor (devices.* in the config) or the emulated cell")
    dr.add_argument("--tare-s", type=float_in(0.2, 60), default=2.0, help="how long the sensor is watched at rest (s)")
    dr.add_argument("--inject", action="append", default=None, metavar="CMD",
                    help="emulated cell: a fault command for the emulator before the checks (repeatable; "
                         "e.g. 'freeze', 'estop', 'delay 20', 'sensor drop 0.5'; sim/serve_cell.py lists them)")
    dr.add_argument("--stream-stop", action="store_true",
                    help="TM Ethernet route: also measure what velocity mode does when the host stops streaming; "
                         "MOVES the last wrist joint about 4 degrees (tool clear, hand on the E-stop)")
    dr.add_argument("--config", type=Path, default=None, help="cell config YAML (default config/cell.yaml)")
    dr.add_argument("--seed", type=SEED, default=None, help="plant seed (emulated cell)")
    dr.add_argument("--json", action="store_true", help="print one JSON object as the last stdout line")
    dr.set_defaults(func=cmd_doctor)


def cmd_doctor(args: argparse.Namespace) -> int:
    from tasks.setup.doctor import Doctor, DoctorSettings, report

    cfg = load_config(args.config)
    robot = robot_for(cfg, "wipe")
    if args.inject and args.cell != "emulated":
        raise ConfigError("doctor --inject: faults can be injected into the emulated cell only (--cell emulated)")
    settings = DoctorSettings(period_s=cfg.loop.period_s, slow_fraction=cfg.loop.slow_cycle_fraction,
                              tare_s=args.tare_s,
                              tail_periods=EMULATED_TAIL_PERIODS if args.cell == "emulated" else 1.0,
                              stream_stop=args.stream_stop)
    holder: Any
    if args.cell == "emulated":
        from sim.emulated import EmulatedCell

        holder = EmulatedCell(cfg, robot.limits, seed=args.seed, scene_kind="free")
        arm, sensor = holder.arm, holder.sensor
    else:
        from drivers.real_cell import open_drivers

        holder = open_drivers(cfg.devices.arm.settings, cfg.devices.sensor.settings, robot.limits,
                              cfg.loop.period_s, f"{cfg.source}: devices")
        arm, sensor = holder.arm, holder.sensor
    try:
        for command in args.inject or []:
            try:
                holder.inject(command)
            except ValueError as exc:
                raise ConfigError(f"doctor --inject '{command}': {exc}") from None
        checks = Doctor(arm, sensor, robot.limits, settings).run()
    finally:
        for device in (arm, sensor):
            with contextlib.suppress(DriverError):
                if device is not None:
                    device.disconnect()
        holder.close()
    out = report(checks, args.cell)
    if args.json:
        emit(out, True)
    else:
        print(format_table(checks))
        print(f"doctor --cell {args.cell}: " + ("PASSED" if out["passed"] else f"FAILED ({', '.join(out['failed'])})"))
    return 0 if out["passed"] else 1
