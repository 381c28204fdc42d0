"""The emulated cell's child process: the plant and both device emulators, endpoints on stdout, faults on stdin.

Run as `python -m sim.serve_cell --config C --plant P --scene S [--seed N]` (what `sim.emulated.EmulatedCell`
starts, and what `main.py emulate cell` runs in-process).  It prints one JSON line `{"port": ..., "tty": ...}`
and takes fault-injection commands on stdin, one per line, each answered by `{"ack": ...}` (or
`{"error": ...}`) once in effect: `drop_link 1.5`, `freeze 2`, `unfreeze`, `delay 20 1.0`, `exceptions 1.0`,
`estop [2]`, `clear`, `table_offset 5` (TM's channels: the Modbus table's joints read 5 deg off),
`sensor garbage 0.3`, `sensor split 0.5`, `sensor drop 0.2`, `sensor delay 12 [0.4]`,
`sensor clear`, `quit`.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from cell.config import CellConfig, SceneKind, load_config, resolve
from cell.control.priority import raised_priority
from drivers.errors import CellError
from drivers.real_cell import arm_protocol
from drivers.tm5.contract import UserAreaLayout
from sim.tm_ethernet_emulator import TMEthernetEmulator

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
SCENES: tuple[SceneKind, ...] = ("free", "table", "peg")


def child_command(cfg: CellConfig, seed: int | None, scene: SceneKind) -> tuple[list[str], dict[str, str]]:
    """(argv, environment) that start this module as the emulated cell's child process."""
    cmd = [sys.executable, "-m", "sim.serve_cell", "--config", cfg.source, "--plant", str(resolve(cfg.plant)),
           "--scene", scene]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    # The child runs from the caller's folder (a relative --config means the same file to both): the
    # project's root goes on its import path instead.
    path = os.environ.get("PYTHONPATH")
    env = {**os.environ, "PYTHONPATH": str(ROOT) if not path else f"{ROOT}{os.pathsep}{path}"}
    return cmd, env


def arm_emulator(cfg: CellConfig, plant: Any, port: int = 0, listen_port: int = 0,
                 broadcast_period_s: float | None = None, bind: str = "127.0.0.1", modbus_port: int = 0) -> Any:
    """The arm's emulator for the config's protocol on `plant` (not started): the Modbus controller running
    the robot-side program on `port`, or TM's Ethernet Slave (`port`), Listen node (`listen_port`) and the
    controller's Modbus table (`modbus_port`), whose broadcast runs at the plant's sample period unless
    `broadcast_period_s` says otherwise.  It listens on `bind` only (this machine unless said otherwise: an
    emulated arm takes commands from whoever connects)."""
    from sim.tm5_emulator import TM5Emulator

    if arm_protocol(cfg.devices.arm.settings, f"{cfg.source}: devices.arm.settings") == "tm-ethernet":
        # The command channel's latency sits in the Listen node's queue, where QueueTag (doctor) sees it.
        return TMEthernetEmulator(plant, host=bind, slave_port=port, listen_port=listen_port,
                                  period_s=broadcast_period_s or plant.dt, seed=plant.profile.seed,
                                  modbus_port=modbus_port, command_latency_cycles=plant.take_command_latency())
    return TM5Emulator(plant, host=bind, port=port, layout=UserAreaLayout.from_dict(
        cfg.devices.arm.settings.get("user_area", {}), f"{cfg.source}: devices.arm.settings.user_area"))


def arm_endpoint(arm_emu: Any) -> dict[str, int]:
    """Where a started arm emulator listens, as the host's `devices.arm.settings` name it."""
    if isinstance(arm_emu, TMEthernetEmulator):
        out = {"slave_port": arm_emu.slave_port, "listen_port": arm_emu.listen_port}
        if arm_emu.modbus_port is not None:
            out["modbus_port"] = arm_emu.modbus_port
        return out
    return {"port": arm_emu.port}


def serve_cell(cfg: CellConfig, seed: int | None, scene: SceneKind, port: int = 0, listen_port: int = 0,
               until_signal: bool = False, bind: str = "127.0.0.1") -> int:
    """Plant + arm emulator (listening on `bind`) + WACOH emulator; returns the exit code.  As the emulated
    cell's child it lives until its stdin closes or says quit (its host owns it); with `until_signal`
    (`main.py emulate cell`, run by hand or by a service manager) until Ctrl+C, SIGTERM or `quit`, a closed
    stdin ending only the fault commands."""
    from sim.cell import make_plant
    from sim.wacoh_emulator import FaultConfig, WacohEmulator

    if not until_signal and not sys.stdin.isatty():
        # Driven by a host through a pipe: a terminal's Ctrl+C is for the host, which stops the arm
        # through us and then closes our stdin.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    plant = make_plant(cfg, seed, scene)
    sensor_faults = FaultConfig()
    quit_asked = threading.Event()
    # The emulated controller and sensor stand for machines with their own CPUs: on a shared host they run at
    # the control loop's priority (where permitted), so a busy machine starves neither side of the wire.
    with raised_priority(), arm_emulator(cfg, plant, port, listen_port, bind=bind) as arm_emu, \
            WacohEmulator(plant.true_sensor_wrench, seed=plant.profile.seed, faults=sensor_faults) as sensor_emu:

        def fault_commands() -> None:
            for line in sys.stdin:
                words = line.split()
                if not words:
                    continue
                if words[0] == "quit":
                    break
                try:
                    _apply(words, arm_emu, sensor_faults)
                    print(json.dumps({"ack": line.strip()}), flush=True)
                except (ValueError, IndexError, AttributeError) as exc:
                    print(json.dumps({"error": f"{exc}"}), flush=True)
            else:
                if until_signal:
                    log.info("emulate cell: stdin closed; serving on until Ctrl+C or SIGTERM")
                    return
            quit_asked.set()

        print(json.dumps({**arm_endpoint(arm_emu), "tty": sensor_emu.tty_path}), flush=True)
        if not until_signal:
            fault_commands()
            return 0
        log.info("emulated cell: arm on 127.0.0.1 %s, sensor on %s; Ctrl+C or SIGTERM stops it",
                 arm_endpoint(arm_emu), sensor_emu.tty_path)
        threading.Thread(target=fault_commands, name="emulate-faults", daemon=True).start()
        try:
            while not quit_asked.wait(0.5):
                pass
        except KeyboardInterrupt:  # Ctrl+C, or SIGTERM delivered as one (main.py): the normal end
            log.info("emulate cell: stopping")
    return 0


# Fault commands: name -> (least, most arguments); every argument a finite number >= 0 (seconds,
# milliseconds or a probability), checked whole: a malformed one is refused, never skipped (which would
# change the command's meaning, e.g. `delay 20 -1` read as `delay 20`: for ever).
ARM_COMMANDS = {"drop_link": (1, 1), "freeze": (0, 1), "unfreeze": (0, 0), "delay": (1, 2), "exceptions": (0, 1),
                "estop": (0, 1), "clear": (0, 0), "table_offset": (1, 1), "safeguard": (0, 1), "listen_lag": (1, 1),
                "vjog_timeout": (1, 1)}
SENSOR_COMMANDS = {"garbage": (1, 1), "split": (1, 1), "drop": (1, 1), "delay": (1, 2), "clear": (0, 0)}


def _numbers(words: list[str], bounds: tuple[int, int], what: str, probability: bool = False) -> list[float]:
    least, most = bounds
    if not least <= len(words) <= most:
        span = str(least) if least == most else f"{least} to {most}"
        raise ValueError(f"{what} takes {span} argument(s), got {len(words)}")
    out = []
    for w in words:
        try:
            v = float(w)
        except ValueError:
            raise ValueError(f"{what}: {w!r} is not a number") from None
        if not math.isfinite(v) or v < 0 or (probability and v > 1):
            raise ValueError(f"{what}: {w} must be a finite number >= 0{' and <= 1' if probability else ''}")
        out.append(v)
    return out


def _apply(words: list[str], arm_emu: Any, sensor_faults: Any) -> None:
    head = words[0]
    if head == "sensor":
        if len(words) < 2 or words[1] not in SENSOR_COMMANDS:
            raise ValueError(f"sensor fault must be one of {', '.join(SENSOR_COMMANDS)}")
        kind = words[1]
        if kind == "delay":  # `sensor delay MS [PROBABILITY]`: replies late by MS, with that probability
            ms = _numbers(words[2:3], (1, 1), "sensor delay")[0]
            prob = _numbers(words[3:], (0, 1), "sensor delay", probability=True)
            sensor_faults.reply_delay_s = ms / 1000.0
            sensor_faults.reply_delay_prob = prob[0] if prob else 1.0
            return
        p = _numbers(words[2:], SENSOR_COMMANDS[kind], f"sensor {kind}", probability=True)
        if kind == "garbage":
            sensor_faults.garbage_prob = p[0]
        elif kind == "split":
            sensor_faults.split_prob = p[0]
        elif kind == "drop":
            sensor_faults.drop_reply_prob = p[0]
        else:
            sensor_faults.garbage_prob = sensor_faults.split_prob = sensor_faults.drop_reply_prob = 0.0
            sensor_faults.reply_delay_s = 0.0
        return
    if head not in ARM_COMMANDS:
        raise ValueError(f"unknown command '{head}' (known: {', '.join([*ARM_COMMANDS, 'sensor', 'quit'])})")
    args = _numbers(words[1:], ARM_COMMANDS[head], head)
    if isinstance(arm_emu, TMEthernetEmulator):
        _apply_tm_ethernet(head, args, arm_emu)
        return
    if head == "drop_link":
        arm_emu.drop_link(args[0])
    elif head == "freeze":
        arm_emu.freeze(args[0] if args else None)
    elif head == "unfreeze":
        arm_emu.unfreeze()
    elif head == "delay":
        arm_emu.delay_replies(args[0], args[1] if len(args) > 1 else None)
    elif head == "exceptions":
        arm_emu.inject_exceptions(args[0] if args else None)
    elif head == "estop":
        arm_emu.press_estop(args[0] if args else None)
    elif head in ("table_offset", "safeguard", "listen_lag", "vjog_timeout"):
        raise ValueError(f"'{head}' is for TM's channels (the Ethernet Slave, its Listen node and the Modbus table "
                         "beside them); this emulator serves Modbus alone")
    else:
        arm_emu.clear_faults()


def _apply_tm_ethernet(head: str, args: list[float], arm_emu: Any) -> None:
    """The arm's fault commands on TM's channels: a frozen robot side is a silent broadcast there; late
    replies and Modbus exceptions have no counterpart."""
    if head == "drop_link":
        arm_emu.drop_link(args[0])
    elif head == "freeze":
        arm_emu.go_silent(args[0] if args else None)
    elif head == "estop":
        arm_emu.press_estop(args[0] if args else None)
    elif head == "table_offset":
        arm_emu.offset_modbus_joints(args[0])
    elif head == "safeguard":  # Safeguard_A reads 1: a protective stop
        arm_emu.trigger_safeguard(args[0] if args else None)
    elif head == "listen_lag":  # `listen_lag MS`: the Listen node takes MS per packet (its replies fall behind)
        arm_emu.set_script_interval(args[0] / 1000.0)
    elif head == "vjog_timeout":  # `vjog_timeout MS`: velocity mode stops MS after the last speed (0: keeps it)
        arm_emu.set_vjog_timeout(args[0] / 1000.0 if args[0] > 0 else None)
    elif head in ("unfreeze", "clear"):
        arm_emu.clear_faults()
        arm_emu.set_script_interval(0.0)
    else:
        raise ValueError(f"'{head}' has no counterpart on TM's Ethernet Slave and Listen node")


def main(argv: list[str] | None = None) -> int:
    """The child process's entry: arguments, logging, then `serve_cell`; a bad config is one line on stderr."""
    p = argparse.ArgumentParser(prog="python -m sim.serve_cell", description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, required=True, help="cell config YAML")
    p.add_argument("--plant", default=None, help="plant profile YAML (default: the config's)")
    p.add_argument("--scene", choices=SCENES, default=None, help="default: the config's")
    p.add_argument("--seed", type=int, default=None, help="plant seed")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # the drivers report link loss themselves
    try:
        cfg = load_config(args.config)
        if args.plant:
            cfg.plant = str(Path(args.plant).resolve())
        return serve_cell(cfg, args.seed, args.scene or cfg.scene.kind)
    except CellError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
