"""TM5-700 controller emulator: the Modbus/TCP slave, its cycle and injected faults, running the robot-side program."""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.errors import ConfigError
from drivers.interfaces import ArmState
from drivers.tm5.contract import UserAreaLayout
from drivers.tm5.registers import (
    COIL_PLAY_PAUSE,
    COIL_STOP,
    DI_ERROR,
    DI_FIRST,
    USER_AREA_FIRST,
    USER_AREA_LAST,
    wrap_int32,
)
from sim.emulator_loop import EmulatorLoop
from sim.plant_api import PlantLike
from sim.tm5_program import LEASE_TIMEOUT_S, RobotProgramState, RobotSideProgram
from sim.tm_modbus_table import ControllerTable, close_server, start_server

log = logging.getLogger(__name__)

_HR_COUNT = USER_AREA_LAST - USER_AREA_FIRST + 1
_READ_HOLDING = {3, 23}
_WRITE_HOLDING = {6, 16, 23}
# pymodbus' non-shared bit blocks address bit b as register b // 16, bit b % 16: keep our bases aligned.
assert COIL_PLAY_PAUSE % 16 == 0 and COIL_STOP // 16 == COIL_PLAY_PAUSE // 16


# ------------------------------------------------------------------------------------------------
# Injected faults
# ------------------------------------------------------------------------------------------------
@dataclass
class EmulatorFaults:
    """Injected faults, as monotonic-clock deadlines (0 = off, inf = until cleared)."""

    link_down_until: float = 0.0  # no connections: existing ones were dropped, new ones are refused
    frozen_until: float = 0.0  # the robot-side program hangs: user area (counter) stops updating
    freeze_controller: bool = False  # ... and the controller's own registers (angles, poses, inputs) too
    delay_s: float = 0.0  # every reply is late by this much ...
    delay_until: float = 0.0  # ... until then
    exception_code: int = int(ExcCodes.DEVICE_FAILURE)  # Modbus exception replied to every request ...
    exceptions_until: float = 0.0  # ... until then
    estop_until: float = 0.0  # the E-stop input reads pressed (what a bring-up check must notice)

    def frozen(self, now: float) -> bool:
        return now < self.frozen_until

    def delay(self, now: float) -> float:
        return self.delay_s if now < self.delay_until else 0.0

    def exception(self, now: float) -> int | None:
        return self.exception_code if now < self.exceptions_until else None

    def estop(self, now: float) -> bool:
        return now < self.estop_until


class _Phase(enum.Enum):
    NEW = "new"
    RUNNING = "running"
    STOPPED = "stopped"


# ------------------------------------------------------------------------------------------------
# The emulator
# ------------------------------------------------------------------------------------------------
class TM5Emulator(EmulatorLoop):
    """A TM5-700 controller on 127.0.0.1: Modbus/TCP slave (input registers 7001-7036, discrete inputs
    7200-7208, coils 7104/7105, holding 9000-9999) and the robot-side program, driving `plant`.

    A pymodbus server and the cycle task share one asyncio loop in a background thread, so register
    accesses and cycles never interleave.  Each cycle (every `plant.dt / time_scale` wall seconds): read
    the host block, act on it (targets, stop, acknowledge, watchdog), `plant.step()`, publish the
    controller registers and the robot->host block.  `time_scale > 1` runs the plant faster than wall time.
    """

    def __init__(self, plant: PlantLike, layout: UserAreaLayout | None = None, host: str = "127.0.0.1",
                 port: int = 0, time_scale: float = 1.0, watchdog_cycles: int = 10,
                 history: int = 2048, lease_timeout_s: float = LEASE_TIMEOUT_S) -> None:
        if not (time_scale > 0 and math.isfinite(time_scale)):
            raise ValueError(f"time_scale must be positive, got {time_scale!r}")
        if watchdog_cycles < 1:
            raise ValueError(f"watchdog_cycles must be >= 1, got {watchdog_cycles}")
        if not (lease_timeout_s > 0 and math.isfinite(lease_timeout_s)):
            raise ValueError(f"lease_timeout_s must be positive, got {lease_timeout_s!r}")
        super().__init__("tm5-emulator", "TM5 emulator")
        self.plant = plant
        self.layout = layout if layout is not None else UserAreaLayout()
        self.layout.validate("layout")
        self.host = host
        self.time_scale = time_scale
        self.faults = EmulatorFaults()
        self.project_running = True
        self.paused = False
        self.cycles = 0
        self.stop_coil_writes: list[bool] = []  # every value written to coil 7105, in order
        self._requested_port = port
        self._port: int | None = None
        self._table = ControllerTable()
        self._hr = [0] * _HR_COUNT
        self._robot = RobotSideProgram(plant, self.layout, self._hr, watchdog_cycles, lease_timeout_s)
        self._history: OrderedDict[int, ArmState] = OrderedDict()
        self._history_len = history
        self._history_lock = threading.Lock()
        self._device = self._make_device()
        self._server: ModbusTcpServer | None = None
        self._relisten: asyncio.Task[None] | None = None
        self._phase = _Phase.NEW
        self._cycle_failed = False
        self._publish_controller()  # sensible registers before the first cycle

    # ----------------------------------------------------------------------------- lifecycle
    @property
    def port(self) -> int:
        if self._port is None:
            raise RuntimeError("the emulator is not started")
        return self._port

    def start(self) -> int:
        """Start serving; returns the bound port.  Raises ConfigError when the address cannot be bound."""
        if self._phase is not _Phase.NEW:
            raise RuntimeError(f"the emulator is {self._phase.value}; create a new one")
        self._phase = _Phase.RUNNING
        error = self._start_loop()
        if error is not None:
            self._phase = _Phase.STOPPED
            raise ConfigError(f"TM5 emulator cannot listen on {self.host}:{self._requested_port} ({error})") from error
        log.debug("TM5 emulator serving Modbus/TCP on %s:%d", self.host, self.port)
        return self.port

    def stop(self) -> None:
        """Stop the cycle task, close every connection and the listener, join the thread."""
        if self._phase is not _Phase.RUNNING:
            return
        self._phase = _Phase.STOPPED
        self._stop_loop()

    def __enter__(self) -> TM5Emulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----------------------------------------------------------------------------- fault injection
    def drop_link(self, seconds: float) -> None:
        """Close every client connection now and refuse new ones for `seconds` (then listen again)."""
        self._run_coroutine(self._drop_link(seconds))

    def freeze(self, seconds: float | None = None, *, controller: bool = False) -> None:
        """The robot-side program hangs (counter and user area stop updating) for `seconds` (None: until
        `unfreeze`).  `controller=True` freezes the controller's angles/poses/inputs as well."""
        until = math.inf if seconds is None else time.monotonic() + seconds
        self._set_faults(frozen_until=until, freeze_controller=controller)

    def unfreeze(self) -> None:
        self._set_faults(frozen_until=0.0, freeze_controller=False)

    def delay_replies(self, ms: float, seconds: float | None = None) -> None:
        """Every reply is `ms` late for `seconds` (None: until cleared)."""
        until = math.inf if seconds is None else time.monotonic() + seconds
        self._set_faults(delay_s=ms / 1000.0, delay_until=until)

    def inject_exceptions(self, seconds: float | None = None, code: int = ExcCodes.DEVICE_FAILURE) -> None:
        """Answer every request with Modbus exception `code` for `seconds` (None: until cleared)."""
        until = math.inf if seconds is None else time.monotonic() + seconds
        self._set_faults(exception_code=int(code), exceptions_until=until)

    def serve_documented_inputs_only(self, on: bool = True) -> None:
        """Refuse (exception 2) a discrete-input read that covers the undocumented 7203, 7205-7207."""
        self._table.documented_inputs_only = on

    def press_estop(self, seconds: float | None = None) -> None:
        """The E-stop input reads pressed for `seconds` (None: until cleared)."""
        self._set_faults(estop_until=math.inf if seconds is None else time.monotonic() + seconds)

    def clear_faults(self) -> None:
        """Clear register faults (a dropped link comes back on its own schedule)."""
        self._set_faults(frozen_until=0.0, freeze_controller=False, delay_s=0.0, delay_until=0.0,
                         exceptions_until=0.0, estop_until=0.0)

    def restart_project(self) -> None:
        """The operator presses play after a stop coil: the robot-side program runs again (still held)."""
        def restart() -> None:
            self.project_running = True
            self.paused = False
        self._call(restart)

    # ----------------------------------------------------------------------------- observation
    @property
    def program(self) -> RobotProgramState:
        """What the robot-side program remembers between its cycles."""
        return self._robot.state

    @property
    def robot_counter(self) -> int:
        return self.program.counter

    def published_state(self, counter: int) -> ArmState | None:
        """The plant state published with robot counter value `counter` (recent history only)."""
        with self._history_lock:
            return self._history.get(wrap_int32(counter))

    def host_block(self) -> tuple[int, np.ndarray, int]:
        """(host seq, targets [deg], command) as currently in the registers."""
        return self._robot.host_block()

    # ----------------------------------------------------------------------------- loop thread
    async def _bind(self) -> None:
        await self._listen(self._requested_port)

    def _serve(self) -> list[asyncio.Task[None]]:
        return [asyncio.create_task(self._run_cycles(), name="tm5-emulator-cycle")]

    async def _close(self) -> None:
        if self._relisten is not None:
            self._relisten.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._relisten
        await self._close_server()

    async def _listen(self, port: int) -> None:
        self._server, self._port = await start_server(self._device, self.host, port,
                                                      trace_pdu=self._table.screen_request)

    async def _close_server(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            await close_server(server)

    async def _drop_link(self, seconds: float) -> None:
        self.faults.link_down_until = time.monotonic() + seconds
        await self._close_server()
        if self._relisten is not None:
            self._relisten.cancel()
        self._relisten = asyncio.create_task(self._listen_again(seconds), name="tm5-emulator-relisten")

    async def _listen_again(self, seconds: float) -> None:
        await asyncio.sleep(seconds)
        for attempt in range(50):
            try:
                await self._listen(self.port)
                self.faults.link_down_until = 0.0
                log.info("TM5 emulator listening again on %s:%d", self.host, self.port)
                return
            except RuntimeError:
                if attempt == 0:
                    log.warning("TM5 emulator: port %d busy, retrying", self.port)
                await asyncio.sleep(0.05)
        log.error("TM5 emulator could not listen again on %s:%d", self.host, self.port)

    async def _run_cycles(self) -> None:
        period = self.plant.dt / self.time_scale
        deadline = time.monotonic()
        while True:
            try:
                self._cycle()
            except Exception:  # noqa: BLE001 - a broken plant is a controller error, not a dead server
                log.exception("TM5 emulator: cycle failed; the controller reports an error from now on")
                self._cycle_failed = True
                self._table.di[DI_ERROR - DI_FIRST] = True
                return
            deadline += period
            delay = deadline - time.monotonic()
            if delay < -period:  # fell behind (debugger, overloaded machine): skip, do not burst
                deadline = time.monotonic()
                delay = 0.0
            await asyncio.sleep(max(delay, 0.0))

    def _set_faults(self, **changes: Any) -> None:
        def apply() -> None:
            self.faults = replace(self.faults, **changes)
        self._call(apply)

    # ----------------------------------------------------------------------------- one cycle
    def _cycle(self) -> None:
        now = time.monotonic()
        frozen = self.faults.frozen(now)
        program_runs = self.project_running and not self.paused and not frozen
        if program_runs:
            self._robot.act_on_host_block()
        self.plant.step()
        self.cycles += 1
        if not (frozen and self.faults.freeze_controller):
            self._publish_controller()
        if program_runs:
            self._publish_user_area()

    def _publish_controller(self) -> None:
        """The controller's own registers: joint angles, poses, status inputs."""
        st = self.plant.measured_state()
        self._table.publish(self.plant, st.q, error=st.status.error or self._cycle_failed,
                            running=st.status.project_running and self.project_running,
                            paused=st.status.paused or self.paused,
                            estop=st.status.estop or self.faults.estop(time.monotonic()))

    def _publish_user_area(self) -> None:
        st = self._robot.publish()
        with self._history_lock:
            self._history[self.program.counter] = st
            while len(self._history) > self._history_len:
                self._history.popitem(last=False)

    # ----------------------------------------------------------------------------- Modbus data model
    def _make_device(self) -> SimDevice:
        """Non-shared blocks (coils, discrete inputs, holding, input).  Our own images are the truth: the
        access hook copies them into pymodbus' registers before every read and takes every write."""
        return SimDevice(
            0,  # device id 0 answers every unit id, as the controller does not care which one is used
            simdata=(
                [SimData(COIL_PLAY_PAUSE, count=2, values=False, datatype=DataType.BITS)],
                self._table.discrete_inputs_block(),
                [SimData(USER_AREA_FIRST, count=_HR_COUNT, values=0, datatype=DataType.REGISTERS)],
                self._table.input_registers_block(),
            ),
            action=self._on_access,
        )

    async def _on_access(self, function_code: int, start: int, address: int, count: int, registers: list[int],
                         values: list[int] | list[bool] | None) -> ExcCodes | None:
        now = time.monotonic()
        delay = self.faults.delay(now)
        if delay > 0:
            await asyncio.sleep(delay)
        code = self.faults.exception(now)
        if code is not None:
            return ExcCodes(code)
        if self._table.serve_read(function_code, start, address, count, registers):
            return None
        if function_code in (1, 5, 15):
            if values:
                if address <= COIL_STOP < address + len(values):
                    self.stop_coil_writes.append(bool(values[COIL_STOP - address]))
                self._on_coils(address, [bool(v) for v in values])
            registers[COIL_PLAY_PAUSE // 16 - start] = 0  # momentary: coils read back as released
        elif values and function_code in _WRITE_HOLDING:
            i = address - USER_AREA_FIRST
            self._hr[i:i + len(values)] = [int(v) for v in values]
        elif function_code in _READ_HOLDING:
            i = address - USER_AREA_FIRST
            registers[address - start:address - start + count] = self._hr[i:i + count]
        return None

    def _on_coils(self, address: int, values: list[bool]) -> None:
        for i, on in enumerate(values):
            coil = address + i
            if not on:
                continue
            if coil == COIL_STOP:
                log.info("TM5 emulator: stop coil %d: project stopped", COIL_STOP)
                self._robot.hold("project stopped")
                self.project_running = False
            elif coil == COIL_PLAY_PAUSE:
                self.paused = not self.paused
                if self.paused:
                    self._robot.hold("project paused")
                log.info("TM5 emulator: play/pause coil %d: paused=%s", COIL_PLAY_PAUSE, self.paused)
