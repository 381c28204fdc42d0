"""The emulated cell: the *real* drivers over loopback against emulators that follow the MuJoCo plant.

The plant and both emulators run in their own process (`python -m sim.serve_cell`, which lists the
fault-injection commands), as the robot and the sensor are separate machines: the host's control loop
then does not share an interpreter with them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import select
import subprocess
import threading
from typing import Any

from cell.config import CellConfig, SceneKind
from cell.control.loop import OpenCell, WallTicker
from cell.sensing.ft_source import SensorForceSource
from drivers.errors import ConfigError, LinkLostError
from drivers.interfaces import JointLimits
from drivers.real_cell import CellDrivers, arm_protocol, open_drivers
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.contract import UserAreaLayout
from sim.serve_cell import child_command

log = logging.getLogger(__name__)

START_TIMEOUT_S = 30.0

# Settings the emulated cell chooses itself (where the emulators listen); the rest come from config.
_ARM_OWNED = ("host", "port", "slave_port", "listen_port", "modbus_port")
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
    """Starts the cell emulator (`sim.serve_cell`) in a child process, then connects the real drivers to it."""

    def __init__(self, cfg: CellConfig, limits: JointLimits, seed: int | None = None,
                 scene_kind: SceneKind | None = None) -> None:
        where = f"{cfg.source}: devices"
        arm_raw = _settings(cfg.devices.arm.settings, _ARM_OWNED, f"{where}.arm.settings")
        sensor_raw = _settings(cfg.devices.sensor.settings, _SENSOR_OWNED, f"{where}.sensor.settings")
        protocol = arm_protocol(arm_raw, f"{where}.arm.settings")
        if protocol == "modbus":
            UserAreaLayout.from_dict(arm_raw.get("user_area", {}), f"{where}.arm.settings.user_area")
        self.period = cfg.loop.period_s
        cmd, env = child_command(cfg, seed, scene_kind or cfg.scene.kind)
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
                                     env=env)
        try:
            endpoint = self._read_endpoint()
            self.drivers: CellDrivers = open_drivers(
                arm_raw, sensor_raw, limits, cfg.loop.period_s, where,
                arm_fixed={"host": "127.0.0.1", **{k: v for k, v in endpoint.items() if k != "tty"}},
                sensor_fixed={"port": endpoint["tty"]},
                min_timeout_s=EMULATED_MIN_TIMEOUT_S, min_stale_s=EMULATED_MIN_STALE_S)
        except BaseException:
            self._stop_process()
            raise
        self.arm = self.drivers.arm
        assert self.drivers.sensor is not None and self.drivers.sensor_cfg is not None
        self.sensor, self.sensor_cfg = self.drivers.sensor, self.drivers.sensor_cfg
        log.info("emulated cell: arm (%s) on %s, sensor on %s (pid %d)", protocol, self.arm.endpoint,
                 endpoint["tty"], self.proc.pid)

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

    @property
    def arm_endpoint(self) -> tuple[str, int]:
        """Where the arm emulator listens (another host's driver may connect there too): its Modbus port, or
        the Ethernet Slave's on TM's channels."""
        cfg = self.arm.config
        return cfg.host, cfg.port if isinstance(cfg, TM5ModbusConfig) else cfg.slave_port

    def open(self) -> OpenCell:
        self.drivers.connect()
        return OpenCell(kind="emulated", arm=self.arm,
                        force=SensorForceSource(self.sensor, self.sensor_cfg.tare_samples),
                        ticker=WallTicker(self.period))

    def close(self) -> None:
        drivers = getattr(self, "drivers", None)
        if drivers is not None:
            drivers.close()
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
