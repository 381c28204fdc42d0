"""TM5-700 controller emulator: the controller's Modbus/TCP slave and the robot-side program, driving a plant."""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusBaseServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.errors import ConfigError
from drivers.interfaces import ArmState, ArmStatus
from drivers.tm5_contract import UserAreaLayout
from drivers.tm5_registers import (
    COIL_PLAY_PAUSE,
    COIL_STOP,
    DI_COUNT,
    DI_ERROR,
    DI_ESTOP,
    DI_FIRST,
    DI_PAUSED,
    DI_RUNNING,
    IR_COUNT,
    IR_FIRST,
    IR_FLANGE_POSE,
    IR_JOINTS,
    IR_TOOL_POSE,
    USER_AREA_FIRST,
    USER_AREA_LAST,
    Command,
    RobotFlags,
    floats_to_regs,
    int32_to_regs,
    pose_to_regs,
    regs_to_floats,
    regs_to_int32,
    rpy_to_matrix,
    wrap_int32,
)
from sim.plant_api import PlantLike

log = logging.getLogger(__name__)

T = TypeVar("T")

_HR_COUNT = USER_AREA_LAST - USER_AREA_FIRST + 1
_READ_HOLDING = {3, 23}
_WRITE_HOLDING = {6, 16, 23}
# pymodbus' non-shared bit blocks address bit b as register b // 16, bit b % 16: keep our bases aligned.
assert DI_FIRST % 16 == 0 and COIL_PLAY_PAUSE % 16 == 0 and COIL_STOP // 16 == COIL_PLAY_PAUSE // 16


# ------------------------------------------------------------------------------------------------
# A trivial plant for the bench and `main.py emulate arm` without MuJoCo
# ------------------------------------------------------------------------------------------------
class KinematicPlant:
    """A documented stand-in satisfying `PlantLike`: every joint tracks its target as a first-order lag
    (time constant `tau_s`), the "measured torque" is a smooth gravity-like function of q (plus a damping
    term), and the flange/tool poses come from a toy planar-shoulder kinematic chain.  No contact, no
    sensor (the wrench is zero).  Good for wire tests and benchmarks, not for physics.  Starts at `HOME`
    (the cell's default home pose) unless given `q0`."""

    HOME = np.array([0.0, 0.0, math.pi / 2, 0.0, math.pi / 2, 0.0])

    def __init__(self, dt: float = 0.008, q0: np.ndarray | None = None, tau_s: float = 0.05,
                 tcp_offset_m: float = 0.155) -> None:
        self.dt = dt
        self.n_joints = 6
        self.q = self.HOME.copy() if q0 is None else np.array(q0, dtype=float)
        self.dq = np.zeros(6)
        self.target = self.q.copy()
        self.tau_s = tau_s
        self.tcp_offset_m = tcp_offset_m
        self.t = 0.0
        self.seq = 0
        self.holding = False
        self.status = ArmStatus()

    def step(self) -> None:
        alpha = 1.0 - math.exp(-self.dt / self.tau_s)
        q_new = self.q + alpha * (self.target - self.q)
        self.dq = (q_new - self.q) / self.dt
        self.q = q_new
        self.t += self.dt
        self.seq += 1

    def set_target(self, q: np.ndarray) -> None:
        if not self.holding:  # a protective stop ignores targets until released (like sim.plant.Plant)
            self.target = np.array(q, dtype=float)

    def hold(self) -> None:
        self.holding = True
        self.target = self.q.copy()
        self.status = ArmStatus(protective_stop=True)

    def release(self) -> None:
        self.holding = False
        self.target = self.q.copy()
        self.status = ArmStatus()

    def torque(self) -> np.ndarray:
        q = self.q
        gravity = np.array([0.0, 40.0 * math.cos(q[1]) + 12.0 * math.cos(q[1] + q[2]),
                            12.0 * math.cos(q[1] + q[2]), 1.5 * math.cos(q[1] + q[2] + q[3]),
                            0.4 * math.sin(q[4]), 0.0])
        return gravity + 2.0 * self.dq

    def measured_state(self) -> ArmState:
        return ArmState(t=self.t, q=self.q.copy(), dq=self.dq.copy(), tau=self.torque(), status=self.status,
                        seq=self.seq)

    def flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        q = self.q
        reach = 0.329 * math.cos(q[1]) + 0.312 * math.cos(q[1] + q[2])
        height = 0.146 + 0.329 * math.sin(q[1]) + 0.312 * math.sin(q[1] + q[2])
        pos = np.array([reach * math.cos(q[0]), reach * math.sin(q[0]), height])
        return pos, rpy_to_matrix(q[5], q[1] + q[2] + q[3] + q[4], q[0])

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        pos, rot = self.flange_pose()
        return pos + rot @ np.array([0.0, 0.0, self.tcp_offset_m]), rot

    def true_sensor_wrench(self) -> np.ndarray:
        return np.zeros(6)


# ------------------------------------------------------------------------------------------------
# Faults and the robot-side program state
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

    def frozen(self, now: float) -> bool:
        return now < self.frozen_until

    def delay(self, now: float) -> float:
        return self.delay_s if now < self.delay_until else 0.0

    def exception(self, now: float) -> int | None:
        return self.exception_code if now < self.exceptions_until else None


# The robot-side program plays the host's targets about this many cycles behind the newest (a jitter
# buffer).  Its playback clock is elastic: it slows down (by at most RATE_STEP of the host's rate per
# cycle) when the buffer runs low, so a late host makes the arm ease off instead of overshooting and
# jumping back, and it catches up at up to MAX_RATE when the buffer is deeper than planned.
JITTER_DELAY_CYCLES = 2
RATE_STEP = 0.25
MAX_RATE = 1.25


@dataclass
class RobotProgramState:
    """What the robot-side program (docs/robot-side-program.md) remembers between its cycles."""

    counter: int = 0  # robot heartbeat, +1 per cycle (INT32, wraps)
    last_host_seq: int = 0  # the host registers start at 0: nothing to do until the host writes
    stalled_cycles: int = 0
    executing: bool = False
    held: bool = False  # latched protective hold (host STOP, bad targets, pause)
    watchdog: bool = False  # latched: host heartbeat stalled while tracking
    # Jitter buffer: targets received this tracking session, by host sequence number; the (fractional)
    # sequence position the servo plays, and how many sequence numbers it advances per cycle.
    received: dict[int, np.ndarray] = field(default_factory=dict)
    play_seq: float | None = None
    rate: float = 1.0

    @property
    def flags(self) -> RobotFlags:
        flags = RobotFlags(0)
        if self.watchdog:
            flags |= RobotFlags.WATCHDOG
        if self.executing:
            flags |= RobotFlags.EXECUTING
        if self.held:
            flags |= RobotFlags.HELD
        return flags


class _Phase(enum.Enum):
    NEW = "new"
    RUNNING = "running"
    STOPPED = "stopped"


# ------------------------------------------------------------------------------------------------
# The emulator
# ------------------------------------------------------------------------------------------------
class TM5Emulator:
    """A TM5-700 controller on 127.0.0.1: Modbus/TCP slave (input registers 7001-7036, discrete inputs
    7200-7208, coils 7104/7105, holding 9000-9999) and the robot-side program, driving `plant`.

    A pymodbus server and the cycle task share one asyncio loop in a background thread, so register
    accesses and cycles never interleave.  Each cycle (every `plant.dt / time_scale` wall seconds): read
    the host block, act on it (targets, stop, acknowledge, watchdog), `plant.step()`, publish the
    controller registers and the robot->host block.  `time_scale > 1` runs the plant faster than wall time.
    """

    def __init__(self, plant: PlantLike, layout: UserAreaLayout | None = None, host: str = "127.0.0.1",
                 port: int = 0, time_scale: float = 1.0, watchdog_cycles: int = 10,
                 history: int = 2048) -> None:
        if not (time_scale > 0 and math.isfinite(time_scale)):
            raise ValueError(f"time_scale must be positive, got {time_scale!r}")
        if watchdog_cycles < 1:
            raise ValueError(f"watchdog_cycles must be >= 1, got {watchdog_cycles}")
        self.plant = plant
        self.layout = layout if layout is not None else UserAreaLayout()
        self.layout.validate("layout")
        self.host = host
        self.time_scale = time_scale
        self.watchdog_cycles = watchdog_cycles
        self.faults = EmulatorFaults()
        self.program = RobotProgramState()
        self.project_running = True
        self.paused = False
        self.cycles = 0
        self._requested_port = port
        self._port: int | None = None
        self._ir = [0] * IR_COUNT
        self._di = [False] * DI_COUNT
        self._hr = [0] * _HR_COUNT
        self._history: OrderedDict[int, ArmState] = OrderedDict()
        self._history_len = history
        self._history_lock = threading.Lock()
        self._device = self._make_device()
        self._server: ModbusTcpServer | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._relisten: asyncio.Task[None] | None = None
        self._ready = threading.Event()
        self._startup_error: BaseException | None = None
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
        self._thread = threading.Thread(target=self._thread_main, name="tm5-emulator", daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError("the emulator thread did not start within 10 s")
        if self._startup_error is not None:
            self._thread.join(5.0)
            self._phase = _Phase.STOPPED
            raise ConfigError(f"TM5 emulator cannot listen on {self.host}:{self._requested_port} "
                              f"({self._startup_error})") from self._startup_error
        log.debug("TM5 emulator serving Modbus/TCP on %s:%d", self.host, self.port)
        return self.port

    def stop(self) -> None:
        """Stop the cycle task, close every connection and the listener, join the thread."""
        if self._phase is not _Phase.RUNNING:
            return
        self._phase = _Phase.STOPPED
        loop, ev, thread = self._loop, self._stop_event, self._thread
        if loop is not None and ev is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop may just have finished on its own
                loop.call_soon_threadsafe(ev.set)
        if thread is not None:
            thread.join(10.0)
            if thread.is_alive():
                log.error("TM5 emulator thread did not stop within 10 s")

    def __enter__(self) -> TM5Emulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----------------------------------------------------------------------------- fault injection
    def drop_link(self, seconds: float) -> None:
        """Close every client connection now and refuse new ones for `seconds` (then listen again)."""
        self._in_loop(self._drop_link(seconds))

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

    def clear_faults(self) -> None:
        """Clear register faults (a dropped link comes back on its own schedule)."""
        self._set_faults(frozen_until=0.0, freeze_controller=False, delay_s=0.0, delay_until=0.0,
                         exceptions_until=0.0)

    def restart_project(self) -> None:
        """The operator presses play after a stop coil: the robot-side program runs again (still held)."""
        def restart() -> None:
            self.project_running = True
            self.paused = False
        self._in_loop_sync(restart)

    # ----------------------------------------------------------------------------- observation
    @property
    def robot_counter(self) -> int:
        return self.program.counter

    def published_state(self, counter: int) -> ArmState | None:
        """The plant state published with robot counter value `counter` (recent history only)."""
        with self._history_lock:
            return self._history.get(wrap_int32(counter))

    def host_block(self) -> tuple[int, np.ndarray, int]:
        """(host seq, targets [deg], command) as currently in the registers."""
        lay = self.layout
        seq = regs_to_int32(self._hr_slice(lay.host_seq, 2))
        targets = regs_to_floats(self._hr_slice(lay.targets, 12))
        return seq, targets, self._hr_slice(lay.command, 1)[0]

    # ----------------------------------------------------------------------------- loop thread
    def _thread_main(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - report startup failures to start(); log the rest
            if not self._ready.is_set():
                self._startup_error = exc
            else:
                log.exception("TM5 emulator loop crashed")
        finally:
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        try:
            await self._listen(self._requested_port)
        except Exception as exc:  # noqa: BLE001 - handed to start()
            self._startup_error = exc
            self._ready.set()
            return
        cycle = asyncio.create_task(self._run_cycles(), name="tm5-emulator-cycle")
        self._ready.set()
        try:
            await self._stop_event.wait()
        finally:
            cycle.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await cycle
            if self._relisten is not None:
                self._relisten.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._relisten
            await self._close_server()

    async def _listen(self, port: int) -> None:
        server = ModbusTcpServer(self._device, address=(self.host, port))
        await server.serve_forever(background=True)  # RuntimeError when the address cannot be bound
        listener: Any = server.transport
        self._port = int(listener.sockets[0].getsockname()[1])
        self._server = server

    async def _close_server(self) -> None:
        server, self._server = self._server, None
        if server is None:
            return
        await server.shutdown()  # closes the listener and every client connection
        if ModbusBaseServer.active_server is server:  # pymodbus' class-level reference would keep us alive
            ModbusBaseServer.active_server = None
        for _ in range(3):  # let the transports run their connection_lost callbacks (sockets closed)
            await asyncio.sleep(0)

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
                self._di[DI_ERROR - DI_FIRST] = True
                return
            deadline += period
            delay = deadline - time.monotonic()
            if delay < -period:  # fell behind (debugger, overloaded machine): skip, do not burst
                deadline = time.monotonic()
                delay = 0.0
            await asyncio.sleep(max(delay, 0.0))

    def _in_loop(self, coro: Coroutine[Any, Any, T]) -> T:
        loop = self._loop
        if self._phase is not _Phase.RUNNING or loop is None:
            coro.close()
            raise RuntimeError("the emulator is not running")
        return asyncio.run_coroutine_threadsafe(coro, loop).result(5.0)

    def _in_loop_sync(self, fn: Callable[[], None]) -> None:
        """Run `fn` on the loop thread (or directly when not running) and wait for it."""
        if self._phase is not _Phase.RUNNING or self._loop is None:
            fn()
            return

        async def run() -> None:
            fn()
        self._in_loop(run())

    def _set_faults(self, **changes: Any) -> None:
        def apply() -> None:
            self.faults = replace(self.faults, **changes)
        self._in_loop_sync(apply)

    # ----------------------------------------------------------------------------- one cycle
    def _cycle(self) -> None:
        now = time.monotonic()
        frozen = self.faults.frozen(now)
        program_runs = self.project_running and not self.paused and not frozen
        if program_runs:
            self._robot_program_inputs()
        self.plant.step()
        self.cycles += 1
        if not (frozen and self.faults.freeze_controller):
            self._publish_controller()
        if program_runs:
            self._publish_user_area()

    def _robot_program_inputs(self) -> None:
        """The robot-side program's input half: heartbeat, command word, targets, watchdog."""
        prog, lay = self.program, self.layout
        seq = regs_to_int32(self._hr_slice(lay.host_seq, 2))
        command = self._hr_slice(lay.command, 1)[0]
        advanced = seq != prog.last_host_seq
        if advanced:
            prog.last_host_seq, prog.stalled_cycles = seq, 0
        else:
            prog.stalled_cycles += 1

        if command == Command.STOP:
            self._hold("host command STOP", asked=True)
        elif command == Command.TRACK:
            if prog.held or prog.watchdog:
                return  # latched: targets are ignored until the host acknowledges with IDLE
            if advanced:
                targets = np.radians(regs_to_floats(self._hr_slice(lay.targets, 12)))
                if not np.all(np.isfinite(targets)):
                    self._hold(f"non-finite joint targets {targets!r}")
                    return
                if not prog.executing:
                    prog.received.clear()
                    prog.play_seq = float(seq - JITTER_DELAY_CYCLES)
                    prog.rate = 1.0
                prog.received[seq] = targets
                prog.executing = True
            elif prog.executing and prog.stalled_cycles >= self.watchdog_cycles:
                self._hold(f"host heartbeat stalled for {prog.stalled_cycles} cycles", watchdog=True)
                return
            if prog.executing:
                self._play_next()
        elif command == Command.IDLE:
            prog.executing = False
            if advanced and (prog.held or prog.watchdog or self.plant.measured_state().status.protective_stop):
                self._release()
        else:
            self._hold(f"unknown host command {command}")

    def _play_next(self) -> None:
        """Hand the servo one target per cycle from the jitter buffer, on an elastic clock: the
        playback rate (host sequence numbers per cycle) moves by at most RATE_STEP per cycle, never
        faster than it can still brake to a stop at the newest stored target (half a cycle of
        tolerance), and up to MAX_RATE while the buffer is deeper than planned.  A skipped sequence is
        interpolated; a host that stops sending makes the arm ease to a stop at its last target (the
        watchdog latches a hold if it stays silent)."""
        prog = self.program
        assert prog.play_seq is not None
        if not prog.received:
            return
        newest = max(prog.received)
        ahead = newest - prog.play_seq
        # Brake-able rate r: r + (r - s) + (r - 2s) + ... ~ r^2 / (2 s) + r / 2 <= ahead + 0.5.
        s, d = RATE_STEP, max(ahead + 0.5, 0.0)
        brake = math.sqrt(2.0 * s * d + s * s / 4.0) - s / 2.0
        want = MAX_RATE if ahead > JITTER_DELAY_CYCLES + 0.5 else 1.0
        rate = max(min(want, prog.rate + s), prog.rate - s)  # ease towards the wanted rate
        prog.rate = max(0.0, min(rate, brake))  # but never past what still stops at the newest target
        prog.play_seq = min(prog.play_seq + prog.rate, float(newest))
        pos = prog.play_seq
        known = sorted(prog.received)
        below = [k for k in known if k <= pos]
        above = [k for k in known if k >= pos]
        if not below:
            return  # nothing to play yet (the buffer starts ahead of the arm)
        a = below[-1]
        b = above[0] if above else a
        target = prog.received[a] if b == a else (
            prog.received[a] + (prog.received[b] - prog.received[a]) * (pos - a) / (b - a))
        for k in [k for k in known if k < a - 4]:
            del prog.received[k]
        self.plant.set_target(target)

    def _hold(self, why: str, *, watchdog: bool = False, asked: bool = False) -> None:
        prog = self.program
        if not (prog.held or prog.watchdog):
            # A hold the host did not ask for is news to it (the host sees only the protective-stop flag).
            log.log(logging.INFO if asked else logging.WARNING, "TM5 emulator robot-side program: hold (%s)", why)
            self.plant.hold()
        prog.executing = False
        if watchdog:
            prog.watchdog = True
        else:
            prog.held = True

    def _release(self) -> None:
        """Host acknowledged with IDLE: clear the latches and stand still at the current position."""
        release = getattr(self.plant, "release", None)
        if callable(release):
            release()  # a plant whose hold() latches (sim.plant.Plant, KinematicPlant) needs releasing
        else:
            self.plant.set_target(self.plant.measured_state().q)
        self.program.held = self.program.watchdog = False
        log.info("TM5 emulator robot-side program: released by host IDLE")

    def _publish_controller(self) -> None:
        """The controller's own registers: joint angles, poses, status inputs."""
        st = self.plant.measured_state()
        ir = self._ir
        j = IR_JOINTS - IR_FIRST
        ir[j:j + 12] = floats_to_regs(np.degrees(st.q), allow_nonfinite=True)
        f = IR_FLANGE_POSE - IR_FIRST
        ir[f:f + 12] = pose_to_regs(*self.plant.flange_pose(), allow_nonfinite=True)
        t = IR_TOOL_POSE - IR_FIRST
        ir[t:t + 12] = pose_to_regs(*self.plant.tool_pose(), allow_nonfinite=True)
        di = self._di
        di[0] = True  # 7200: robot link up
        di[DI_ERROR - DI_FIRST] = st.status.error or self._cycle_failed
        di[DI_RUNNING - DI_FIRST] = st.status.project_running and self.project_running
        di[DI_PAUSED - DI_FIRST] = st.status.paused or self.paused
        di[DI_ESTOP - DI_FIRST] = st.status.estop

    def _publish_user_area(self) -> None:
        """The robot-side program's output half: counter, torque (mN·m), speed (deg/s), status, echo."""
        st = self.plant.measured_state()
        prog, lay = self.program, self.layout
        prog.counter = wrap_int32(prog.counter + 1)
        flags = prog.flags | (RobotFlags.HELD if st.status.protective_stop else RobotFlags(0))
        self._hr_put(lay.robot_counter, int32_to_regs(prog.counter))
        self._hr_put(lay.torque, floats_to_regs(np.asarray(st.tau) * 1000.0, allow_nonfinite=True))
        self._hr_put(lay.speed, floats_to_regs(np.degrees(st.dq), allow_nonfinite=True))
        self._hr_put(lay.robot_status, [int(flags)])
        self._hr_put(lay.host_seq_echo, int32_to_regs(prog.last_host_seq))
        with self._history_lock:
            self._history[prog.counter] = st
            while len(self._history) > self._history_len:
                self._history.popitem(last=False)

    def _hr_slice(self, address: int, count: int) -> list[int]:
        i = address - USER_AREA_FIRST
        return self._hr[i:i + count]

    def _hr_put(self, address: int, regs: list[int]) -> None:
        i = address - USER_AREA_FIRST
        self._hr[i:i + len(regs)] = regs

    # ----------------------------------------------------------------------------- Modbus data model
    def _make_device(self) -> SimDevice:
        """Non-shared blocks (coils, discrete inputs, holding, input).  Our own images are the truth: the
        access hook copies them into pymodbus' registers before every read and takes every write."""
        return SimDevice(
            0,  # device id 0 answers every unit id, as the controller does not care which one is used
            simdata=(
                [SimData(COIL_PLAY_PAUSE, count=2, values=False, datatype=DataType.BITS)],
                [SimData(DI_FIRST, count=DI_COUNT, values=False, datatype=DataType.BITS)],
                [SimData(USER_AREA_FIRST, count=_HR_COUNT, values=0, datatype=DataType.REGISTERS)],
                [SimData(IR_FIRST, count=IR_COUNT, values=0, datatype=DataType.REGISTERS)],
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
        if function_code == 4:
            registers[address - start:address - start + count] = self._ir[address - IR_FIRST:address - IR_FIRST + count]
        elif function_code == 2:
            registers[DI_FIRST // 16 - start] = sum(1 << i for i, bit in enumerate(self._di) if bit)
        elif function_code in (1, 5, 15):
            if values:
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
                self._hold("project stopped")
                self.project_running = False
            elif coil == COIL_PLAY_PAUSE:
                self.paused = not self.paused
                if self.paused:
                    self._hold("project paused")
                log.info("TM5 emulator: play/pause coil %d: paused=%s", COIL_PLAY_PAUSE, self.paused)


def emulate_arm_main(port: int, plant: PlantLike | None = None, host: str = "127.0.0.1") -> int:
    """Serve a TM5-700 emulator for `plant` (default: KinematicPlant) until Ctrl+C; returns the exit code."""
    emulator = TM5Emulator(plant if plant is not None else KinematicPlant(), host=host, port=port)
    bound = emulator.start()
    log.info("TM5-700 emulator listening on %s:%d (Modbus/TCP, unit id any); Ctrl+C to stop", host, bound)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        log.info("TM5 emulator: interrupted, shutting down")
    finally:
        emulator.stop()
    return 0

