"""The emulated cell: the *real* drivers over loopback against emulators that follow the MuJoCo plant.

The plant and both emulators run in their own process (`main.py emulate cell`), as the robot and the
sensor are separate machines: the host's control loop then does not share an interpreter with them.
That process prints one JSON line `{"port": ..., "tty": ...}` and takes fault-injection commands on
stdin, one per line, each answered by `{"ack": ...}` (or `{"error": ...}`) once in effect:
`drop_link 1.5`, `freeze 2`, `unfreeze`, `delay 20 1.0`, `exceptions 1.0`, `estop [2]`, `clear`,
`sensor garbage 0.3`, `sensor split 0.5`, `sensor drop 0.2`, `sensor delay 12 [0.4]`, `sensor clear`, `quit`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import select
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

from cell.config import CellConfig, SceneKind, resolve
from cell.control.loop import OpenCell, WallTicker
from cell.sensing.ft_source import SensorForceSource
from drivers.errors import ConfigError, DriverError, LinkLostError
from drivers.interfaces import JointLimits
from drivers.tm5.contract import TM5ModbusConfig, UserAreaLayout
from drivers.tm5.modbus import TM5ModbusArm
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor

log = logging.getLogger(__name__)

MAIN = Path(__file__).resolve().parents[1] / "main.py"
START_TIMEOUT_S = 30.0

# Settings the emulated cell chooses itself (where the emulators listen); the rest come from config.
_ARM_OWNED = ("host", "port")
_SENSOR_OWNED = ("port",)
# The emulators share this machine's CPU with the host (a real controller and sensor do not), so a
# reply may come late when the machine is busy: allow this much before calling the link lost.  A
# dropped connection is still noticed at once, and frozen data by its own stale limit.
EMULATED_MIN_TIMEOUT_S = 0.05
EMULATED_MIN_STALE_S = 0.1


def _settings(raw: dict[str, Any], owned: tuple[str, ...], where: str) -> dict[str, Any]:
    clash = [k for k in owned if k in raw]
    if clash:
        raise ConfigError(f"{where}.{clash[0]} is chosen by the emulated cell; remove it or use --cell real")
    return dict(raw)


class EmulatedCell:
    """Starts `main.py emulate cell` in a child process, then connects the real drivers to it."""

    def __init__(self, cfg: CellConfig, limits: JointLimits, seed: int | None = None,
                 scene_kind: SceneKind | None = None) -> None:
        where = f"{cfg.source}: devices"
        arm_raw = _settings(cfg.devices.arm.settings, _ARM_OWNED, f"{where}.arm.settings")
        sensor_raw = _settings(cfg.devices.sensor.settings, _SENSOR_OWNED, f"{where}.sensor.settings")
        UserAreaLayout.from_dict(arm_raw.get("user_area", {}), f"{where}.arm.settings.user_area")
        self.period = cfg.loop.period_s
        cmd = [sys.executable, str(MAIN), "-q", "emulate", "cell", "--config", cfg.source,
               "--plant", str(resolve(cfg.plant)),
               "--scene", scene_kind or cfg.scene.kind]
        if seed is not None:
            cmd += ["--seed", str(seed)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        try:
            endpoint = self._read_endpoint()
            arm_timeout = max(float(arm_raw.get("timeout_s", 0.0)), EMULATED_MIN_TIMEOUT_S)
            sensor_timeout = max(float(sensor_raw.get("timeout_s", 0.0)), EMULATED_MIN_TIMEOUT_S)
            stale = max(float(arm_raw.get("stale_after_s", 0.0)), EMULATED_MIN_STALE_S)
            arm_cfg = TM5ModbusConfig.from_dict(
                {**arm_raw, "host": "127.0.0.1", "port": endpoint["port"], "timeout_s": arm_timeout,
                 "stale_after_s": stale}, f"{where}.arm.settings")
            self.sensor_cfg = WacohConfig.from_dict(
                {**sensor_raw, "port": endpoint["tty"], "timeout_s": sensor_timeout}, f"{where}.sensor.settings")
        except BaseException:
            self._stop_process()
            raise
        self.arm = TM5ModbusArm(arm_cfg, limits, cfg.loop.period_s)
        self.sensor = WacohSensor(self.sensor_cfg)
        log.info("emulated cell: arm on 127.0.0.1:%d, sensor on %s (pid %d)", endpoint["port"], endpoint["tty"],
                 self.proc.pid)

    def _read_endpoint(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        line: list[str] = []
        reader = threading.Thread(target=lambda: line.append(self.proc.stdout.readline()), daemon=True)  # type: ignore[union-attr]
        reader.start()
        reader.join(START_TIMEOUT_S)
        if not line:
            raise LinkLostError(f"the cell emulator did not report its endpoints within {START_TIMEOUT_S:.0f} s")
        if not line[0].strip():
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=2)
            raise LinkLostError(f"the cell emulator exited before it started (exit code {self.proc.poll()}); "
                                "its error is printed above")
        return json.loads(line[0])

    def inject(self, command: str, timeout_s: float = 2.0) -> None:
        """Send one fault-injection command to the emulator process and wait until it is in effect."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(command.strip() + "\n")
        self.proc.stdin.flush()
        if command.strip() == "quit":
            return
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        reply = self.proc.stdout.readline() if ready else ""
        if not reply.strip():
            raise LinkLostError(f"the cell emulator did not acknowledge '{command.strip()}'")
        ack = json.loads(reply)
        if "error" in ack:
            raise ValueError(f"the cell emulator refused '{command.strip()}': {ack['error']}")

    def open(self) -> OpenCell:
        self.arm.connect()
        self.sensor.connect()
        return OpenCell(kind="emulated", arm=self.arm,
                        force=SensorForceSource(self.sensor, self.sensor_cfg.tare_samples),
                        ticker=WallTicker(self.period))

    def close(self) -> None:
        for device in (getattr(self, "arm", None), getattr(self, "sensor", None)):
            if device is not None:
                with contextlib.suppress(DriverError):
                    device.disconnect()
        self._stop_process()

    def _stop_process(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.inject("quit")
                assert self.proc.stdin is not None
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        for stream in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(OSError, ValueError):
                if stream is not None:
                    stream.close()


def serve_cell(cfg: CellConfig, seed: int | None, scene: SceneKind) -> int:
    """`main.py emulate cell`: plant + TM5 emulator + WACOH emulator until stdin closes or says quit."""
    from sim.cell import make_plant
    from sim.tm5_emulator import TM5Emulator
    from sim.wacoh_emulator import FaultConfig, WacohEmulator

    if not sys.stdin.isatty():
        # Driven by a host through a pipe: a terminal's Ctrl+C is for the host, which stops the arm
        # through us and then closes our stdin.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    layout = UserAreaLayout.from_dict(cfg.devices.arm.settings.get("user_area", {}),
                                      f"{cfg.source}: devices.arm.settings.user_area")
    plant = make_plant(cfg, seed, scene)
    sensor_faults = FaultConfig()
    with TM5Emulator(plant, layout=layout) as arm_emu, \
            WacohEmulator(plant.true_sensor_wrench, seed=plant.profile.seed, faults=sensor_faults) as sensor_emu:
        print(json.dumps({"port": arm_emu.port, "tty": sensor_emu.tty_path}), flush=True)
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
    return 0


# Fault commands: name -> (least, most arguments); every argument a finite number >= 0 (seconds,
# milliseconds or a probability), checked whole: a malformed one is refused, never skipped (which would
# change the command's meaning, e.g. `delay 20 -1` read as `delay 20`: for ever).
ARM_COMMANDS = {"drop_link": (1, 1), "freeze": (0, 1), "unfreeze": (0, 0), "delay": (1, 2), "exceptions": (0, 1),
                "estop": (0, 1), "clear": (0, 0)}
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
    else:
        arm_emu.clear_faults()
