"""TM5-700 emulator on TM's channels: the Ethernet Slave broadcast, a Listen node, the Modbus table; with faults."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import random
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer

from drivers.errors import ConfigError, ProtocolError
from drivers.interfaces import ArmState
from drivers.tm5.ethernet_slave import (
    MODE_BINARY,
    MODE_JSON,
    MODE_STRING,
    encode_items,
    encode_state_items,
    encode_svr,
    parse_items,
)
from drivers.tm5.tm_packet import FrameError, TMFramer, TMPacket, encode_packet
from sim.emulator_loop import EmulatorLoop
from sim.plant_api import PlantLike
from sim.tm_listen_node import ListenNode
from sim.tm_modbus_table import ControllerTable, close_server, start_server, table_device

log = logging.getLogger(__name__)

TableMode = Literal["binary", "string", "json"]
_MODES = {"binary": MODE_BINARY, "string": MODE_STRING, "json": MODE_JSON}
DEFAULT_PERIOD_S = 0.0156  # the broadcast period seen on a real controller (about 64 Hz)
_SPLIT_GAP_S = 0.002  # between the pieces of a split write, so the client reads them apart


@dataclass
class TMEthernetFaults:
    """Injected faults: deadlines on the monotonic clock (0 = off, inf = until cleared) and per-packet odds."""

    silent_until: float = 0.0  # no broadcast, connections stay open
    link_down_until: float = 0.0  # every connection dropped, new ones closed at once
    estop_until: float = 0.0  # ESTOP reads 1, the arm holds
    error_until: float = 0.0  # Robot_Error reads 1, the arm holds
    safeguard_until: float = 0.0  # Safeguard_A reads 1 (a protective stop), the arm holds
    drop_probability: float = 0.0  # a broadcast packet is lost
    corrupt_probability: float = 0.0  # a broadcast packet's checksum is wrong
    modbus_offset_deg: float = 0.0  # the Modbus table's joint angles read this much off (a table that disagrees)

    def validate(self) -> None:
        for name in ("drop_probability", "corrupt_probability"):
            p = getattr(self, name)
            if not (isinstance(p, int | float) and 0.0 <= p <= 1.0):
                raise ConfigError(f"TM Ethernet emulator: {name} must lie in [0, 1], got {p!r}")


class TMEthernetEmulator(EmulatorLoop):
    """A TM5-700 on 127.0.0.1: Ethernet Slave (`$TMSVR` table every `period_s`), Listen node (`$TMSCT`,
    `$TMSTA`) and the controller's own Modbus table (joint angles, poses, status inputs; read-only; None for
    `modbus_port` serves none), all on port 0 by default, on one asyncio loop in a background thread with the
    servo cycle.  The Modbus table is taken from the plant when it is read.

    Each servo cycle (`plant.dt / time_scale` wall seconds) runs the Listen node's due statements,
    integrates the streamed joint speed into the plant's target and steps the plant.  The broadcast runs on
    its own clock.  `coalesce` packets go out in one write, each write in `split` pieces; `mode` and `items`
    (names of the table's items, None = all) shape the table, to exercise a client's refusals.
    `script_interval_s` > 0 makes the Listen node take that long per packet, answering and acting when done:
    each reply comes that late, and packets sent faster queue behind each other (the lag users see above ~15 Hz).
    """

    def __init__(self, plant: PlantLike, host: str = "127.0.0.1", slave_port: int = 0, listen_port: int = 0,
                 period_s: float = DEFAULT_PERIOD_S, time_scale: float = 1.0, coalesce: int = 1, split: int = 1,
                 mode: TableMode = "binary", items: Sequence[str] | None = None, command_latency_cycles: int = 0,
                 node_message: str = "Listen1", vjog_timeout_s: float | None = None, seed: int = 0,
                 modbus_port: int | None = 0, script_interval_s: float = 0.0) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ConfigError(f"TM Ethernet emulator: period_s must be positive, got {period_s!r}")
        if not (time_scale > 0 and math.isfinite(time_scale)):
            raise ConfigError(f"TM Ethernet emulator: time_scale must be positive, got {time_scale!r}")
        if coalesce < 1 or split < 1 or command_latency_cycles < 0:
            raise ConfigError(f"TM Ethernet emulator: coalesce and split must be >= 1 and command_latency_cycles "
                              f">= 0, got {coalesce}, {split}, {command_latency_cycles}")
        if mode not in _MODES:
            raise ConfigError(f"TM Ethernet emulator: mode must be one of {list(_MODES)}, got {mode!r}")
        _check_interval(script_interval_s)
        super().__init__("tm-ethernet-emulator", "TM Ethernet emulator")
        self.plant = plant
        self.host = host
        self.period_s = period_s
        self.time_scale = time_scale
        self.coalesce = coalesce
        self.split = split
        self.mode: TableMode = mode
        self.items = None if items is None else tuple(items)
        self.faults = TMEthernetFaults()
        self.node = ListenNode(node_message, command_latency_cycles, vjog_timeout_s)
        self.script_interval_s = script_interval_s
        self.project_speed = 100  # % (Project_Speed in the table)
        self.broadcasts = 0
        self.modbus_reads = 0  # requests served from the controller's Modbus table
        self.published: deque[ArmState] = deque(maxlen=256)
        self.cycles = 0
        self._rng = random.Random(seed)
        self._ports = (slave_port, listen_port)
        self._bound: tuple[int, int] | None = None
        self._modbus_requested = modbus_port
        self._modbus_bound: int | None = None
        self._table = ControllerTable()
        self._slave_clients: set[asyncio.StreamWriter] = set()
        self._listen_clients: set[asyncio.StreamWriter] = set()
        self._pending: list[bytes] = []
        self._holding = False
        self._servers: list[asyncio.Server] = []
        self._modbus: ModbusTcpServer | None = None

    # ----------------------------------------------------------------------------- lifecycle
    @property
    def slave_port(self) -> int:
        return self._require_bound()[0]

    @property
    def listen_port(self) -> int:
        return self._require_bound()[1]

    @property
    def modbus_port(self) -> int | None:
        """Where the controller's Modbus table is served (None: not served)."""
        self._require_bound()
        return self._modbus_bound

    def start(self) -> tuple[int, int]:
        """Serve; returns (slave port, listen port).  ConfigError when an address cannot be bound."""
        if self.started:
            raise RuntimeError("the emulator was started already; create a new one")
        error = self._start_loop()
        if error is not None:
            ports = (*self._ports, self._modbus_requested)
            raise ConfigError(f"TM Ethernet emulator cannot listen on {self.host}:{ports} ({error})")
        return self._require_bound()

    def stop(self) -> None:
        self._stop_loop()

    def __enter__(self) -> TMEthernetEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----------------------------------------------------------------------------- faults and the node
    def go_silent(self, seconds: float | None = None) -> None:
        """Stop broadcasting for `seconds` (None: until cleared); connections stay open."""
        self._set(silent_until=_until(seconds))

    def drop_link(self, seconds: float) -> None:
        """Close every connection now and close new ones at once for `seconds`."""
        self._set(link_down_until=_until(seconds))
        self._call(self._close_all)

    def press_estop(self, seconds: float | None = None) -> None:
        self._set(estop_until=_until(seconds))

    def trigger_safeguard(self, seconds: float | None = None) -> None:
        """Safeguard_A reads 1 (the safeguard input: a protective stop) for `seconds`; the arm holds."""
        self._set(safeguard_until=_until(seconds))

    def set_items(self, items: Sequence[str] | None) -> None:
        """The table carries only these items from the next broadcast on (None: all of them)."""
        names = None if items is None else tuple(items)

        def apply() -> None:
            self.items = names
        self._call(apply)

    def set_script_interval(self, seconds: float) -> None:
        """The Listen node takes `seconds` per packet from now on (0: answers at once)."""
        _check_interval(seconds)

        def apply() -> None:
            self.script_interval_s = seconds
        self._call(apply)

    def set_vjog_timeout(self, seconds: float | None) -> None:
        """Velocity mode zeroes the streamed speed `seconds` after the last SetContinueVJog from now on (None: it
        keeps the last speed, the default: no public source says which the controller does)."""
        if seconds is not None:
            _check_interval(seconds)

        def apply() -> None:
            self.node.vjog_timeout_s = seconds
        self._call(apply)

    def set_project_speed(self, percent: int) -> None:
        """Project_Speed reads `percent` from the next broadcast on (TMflow: 5-100 in steps of 5)."""
        if not (isinstance(percent, int) and 5 <= percent <= 100):
            raise ConfigError(f"TM Ethernet emulator: project speed must be an integer in 5-100 %, got {percent!r}")

        def apply() -> None:
            self.project_speed = percent
        self._call(apply)

    def raise_error(self, seconds: float | None = None) -> None:
        """Robot_Error reads 1 (with Error_Code) for `seconds`."""
        self._set(error_until=_until(seconds))

    def set_fault_rates(self, drop: float = 0.0, corrupt: float = 0.0) -> None:
        """Odds per broadcast packet of being lost or sent with a wrong checksum, each in [0, 1]."""
        TMEthernetFaults(drop_probability=drop, corrupt_probability=corrupt).validate()
        self._set(drop_probability=drop, corrupt_probability=corrupt)

    def offset_modbus_joints(self, deg: float) -> None:
        """The Modbus table's joint angles read `deg` off the broadcast's on every joint (0: agree again)."""
        if not math.isfinite(deg):
            raise ValueError(f"the Modbus joint offset must be finite, got {deg!r}")
        self._set(modbus_offset_deg=deg)

    def clear_faults(self) -> None:
        self._set(silent_until=0.0, link_down_until=0.0, estop_until=0.0, error_until=0.0, safeguard_until=0.0,
                  drop_probability=0.0, corrupt_probability=0.0, modbus_offset_deg=0.0)

    def enter_node(self) -> None:
        """The flow reaches the Listen node: connected clients get the entry message."""
        def enter() -> None:
            self.node.enter()
            self._write_all(self._listen_clients, self.node.entry_packet())
        self._call(enter)

    def leave_node(self) -> None:
        """The flow leaves the node: scripts get CPERR F1, TMSTA 00 answers false, streaming stops."""
        self._call(self.node.leave)

    # ----------------------------------------------------------------------------- loop thread
    async def _bind(self) -> None:
        slave = await asyncio.start_server(self._on_slave_client, self.host, self._ports[0])
        self._servers.append(slave)
        listen = await asyncio.start_server(self._on_listen_client, self.host, self._ports[1])
        self._servers.append(listen)
        if self._modbus_requested is not None:  # pymodbus raises RuntimeError when it cannot bind
            self._modbus, self._modbus_bound = await start_server(table_device(self._table, self._on_modbus),
                                                                  self.host, self._modbus_requested)
        self._bound = (slave.sockets[0].getsockname()[1], listen.sockets[0].getsockname()[1])

    def _serve(self) -> list[asyncio.Task[None]]:
        return [asyncio.create_task(self._servo()), asyncio.create_task(self._broadcast())]

    async def _close(self) -> None:
        for server in self._servers:
            server.close()
        self._close_all()
        for server in self._servers:
            await server.wait_closed()
        if self._modbus is not None:
            await close_server(self._modbus)

    async def _on_slave_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._link_down():
            writer.close()
            return
        self._slave_clients.add(writer)
        try:
            while await reader.read(4096):  # the client sends nothing we act on; EOF ends it
                pass
        except OSError:
            pass
        finally:
            self._slave_clients.discard(writer)
            writer.close()

    async def _on_listen_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._link_down():
            writer.close()
            return
        self._listen_clients.add(writer)
        framer = TMFramer("TM emulator Listen node")
        loop = asyncio.get_running_loop()
        next_free = 0.0  # when the node is done with the packets it took so far (script_interval_s > 0)
        try:
            while chunk := await reader.read(65536):
                framer.feed(chunk)
                while True:
                    try:
                        packet = framer.next_packet()
                    except FrameError as exc:  # the framer skipped past it: the next `$` may start a good one
                        log.info("TM emulator Listen node: %s", exc)
                        writer.write(encode_packet("CPERR", exc.cperr_code))
                        continue
                    if packet is None:
                        break
                    now = loop.time()
                    if self.script_interval_s <= 0 and next_free <= now:
                        self._answer(writer, packet)
                    else:  # answered when done, after the packets before it
                        next_free = max(now, next_free) + self.script_interval_s
                        loop.call_at(next_free, self._answer, writer, packet)
        except OSError:
            pass
        finally:
            self._listen_clients.discard(writer)
            writer.close()

    def _answer(self, writer: asyncio.StreamWriter, packet: TMPacket) -> None:
        try:
            replies = self.node.handle(packet)
        except ProtocolError as exc:
            log.info("TM emulator Listen node: %s", exc)
            replies = [encode_packet("CPERR", "01")]
        if not writer.is_closing():
            for reply in replies:
                writer.write(reply)

    def _close_all(self) -> None:
        for writer in [*self._slave_clients, *self._listen_clients]:
            writer.close()
        self._slave_clients.clear()
        self._listen_clients.clear()

    async def _on_modbus(self, function_code: int, start: int, address: int, count: int, registers: list[int],
                         values: list[int] | list[bool] | None) -> ExcCodes | None:
        """Reads of the table get the plant as it is now; the controller's coils and user area belong to
        route A's program, which this emulator does not run."""
        if function_code in (2, 4):
            self.modbus_reads += 1
            now = time.monotonic()
            st = self.plant.measured_state()
            self._table.publish(self.plant, st.q, error=self._error(now) or st.status.error,
                                running=st.status.project_running, paused=st.status.paused,
                                estop=self._estop(now) or st.status.estop,
                                joint_offset_deg=self.faults.modbus_offset_deg)
        if self._table.serve_read(function_code, start, address, count, registers):
            return None
        return ExcCodes.ILLEGAL_FUNCTION

    # ----------------------------------------------------------------------------- servo and broadcast
    async def _servo(self) -> None:
        await _every(self.plant.dt / self.time_scale, self._servo_cycle, "the servo cycle")
        self.faults.error_until = math.inf  # the plant failed: the controller reports an error from now on

    def _servo_cycle(self) -> None:
        now = time.monotonic()
        stopped = self._estop(now) or self._error(now) or now < self.faults.safeguard_until
        if stopped and not self._holding:
            self.node.stop_now()
            self.plant.hold()
            self._holding = True
        elif not stopped and self._holding:
            release = getattr(self.plant, "release", None)
            if callable(release):
                release()
            self._holding = False
        target = self.node.servo_target(self.plant.measured_state().q, self.plant.dt)
        if target is not None and not stopped:
            self.plant.set_target(target)
        self.plant.step()
        self.cycles += 1

    async def _broadcast(self) -> None:
        await _every(self.period_s / self.time_scale, self._broadcast_one, "the broadcast")

    def _broadcast_one(self) -> None:
        now = time.monotonic()
        if now < self.faults.silent_until or self._link_down(now):
            return
        st = self.plant.measured_state()
        tid = str(self.broadcasts % 10)
        self.broadcasts += 1
        self.published.append(st)
        faults = self.faults
        if faults.drop_probability and self._rng.random() < faults.drop_probability:
            return
        packet = encode_packet("TMSVR", encode_svr(tid, _MODES[self.mode], self._content(st, now)))
        if faults.corrupt_probability and self._rng.random() < faults.corrupt_probability:
            wrong = (int(packet[-4:-2], 16) ^ 0x5A) & 0xFF
            packet = packet[:-4] + f"{wrong:02X}".encode("ascii") + b"\r\n"
        self._pending.append(packet)
        if len(self._pending) >= self.coalesce:
            data, self._pending = b"".join(self._pending), []
            for writer in list(self._slave_clients):
                asyncio.get_running_loop().create_task(self._write_split(writer, data))

    def _content(self, st: ArmState, now: float) -> bytes:
        error = self._error(now) or st.status.error
        items = encode_state_items(
            st.q, st.dq, st.tau, robot_error=error, estop=self._estop(now) or st.status.estop,
            project_run=st.status.project_running, project_pause=st.status.paused,
            safeguard=now < self.faults.safeguard_until, error_code=0x0A if error else 0,
            project_speed=self.project_speed)
        if self.items is not None:
            items = [(name, value) for name, value in items if name in self.items]
        if self.mode == "binary":
            return encode_items(items)
        decoded = parse_items(encode_items(items))
        values = {name: _plain(name, raw) for name, raw in decoded.items()}
        if self.mode == "json":
            return json.dumps([{"Item": k, "Value": v} for k, v in values.items()]).encode()
        return "\r\n".join(f"{k}={_string(v)}" for k, v in values.items()).encode()

    async def _write_split(self, writer: asyncio.StreamWriter, data: bytes) -> None:
        pieces = self.split
        size = max(1, math.ceil(len(data) / pieces))
        for i in range(0, len(data), size):
            if writer.is_closing():
                return
            writer.write(data[i:i + size])
            if i + size < len(data):
                await asyncio.sleep(_SPLIT_GAP_S)

    # ----------------------------------------------------------------------------- helpers
    def _estop(self, now: float) -> bool:
        return now < self.faults.estop_until

    def _error(self, now: float) -> bool:
        return now < self.faults.error_until

    def _link_down(self, now: float | None = None) -> bool:
        return (time.monotonic() if now is None else now) < self.faults.link_down_until

    def _write_all(self, writers: set[asyncio.StreamWriter], data: bytes) -> None:
        for writer in list(writers):
            if not writer.is_closing():
                writer.write(data)

    def _set(self, **changes: float) -> None:
        def apply() -> None:
            for name, value in changes.items():
                setattr(self.faults, name, value)
        self._call(apply)

    def _require_bound(self) -> tuple[int, int]:
        if self._bound is None:
            raise RuntimeError("the emulator is not started")
        return self._bound


def _check_interval(seconds: float) -> None:
    if not (isinstance(seconds, int | float) and math.isfinite(seconds) and seconds >= 0):
        raise ConfigError(f"TM Ethernet emulator: script_interval_s must be >= 0 s, got {seconds!r}")


def _until(seconds: float | None) -> float:
    return math.inf if seconds is None else time.monotonic() + seconds


async def _every(period: float, fn: Callable[[], None], what: str) -> None:
    """Call `fn` every `period` wall seconds; after a stall skip ahead rather than burst.  A failing call ends
    the loop (logged once): the connections stay up, so the client sees the silence or the error flag."""
    deadline = time.monotonic()
    while True:
        try:
            fn()
        except Exception:  # noqa: BLE001 - a broken plant is the controller's failure, not the server's
            log.exception("TM Ethernet emulator: %s failed; it stops from now on", what)
            return
        deadline += period
        delay = deadline - time.monotonic()
        if delay < -period:
            deadline = time.monotonic()
            delay = 0.0
        await asyncio.sleep(max(delay, 0.0))


def _plain(name: str, raw: bytes) -> object:
    if name.startswith("Joint_"):
        return [round(float(x), 4) for x in np.frombuffer(raw, dtype="<f4")]
    value = int.from_bytes(raw, "little", signed=len(raw) > 1)
    return bool(value) if len(raw) == 1 else value


def _string(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "{" + ",".join(str(v) for v in value) + "}"
    return str(value)
