"""The robot-side program (docs/robot-side-program.md) as the TM5 emulator runs it: commands, playback, holds."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from drivers.interfaces import ArmState
from drivers.tm5.contract import UserAreaLayout
from drivers.tm5.registers import (
    USER_AREA_FIRST,
    Command,
    RobotFlags,
    floats_to_regs,
    int32_to_regs,
    regs_to_floats,
    regs_to_int32,
    wrap_int32,
)
from sim.plant_api import PlantLike

log = logging.getLogger(__name__)

# The robot-side program plays the host's targets about this many cycles behind the newest (a jitter
# buffer).  Its playback clock is elastic: it slows down (by at most RATE_STEP of the host's rate per
# cycle) when the buffer runs low, so a late host makes the arm ease off instead of overshooting and
# jumping back, and it catches up at up to MAX_RATE when the buffer is deeper than planned.
JITTER_DELAY_CYCLES = 2
RATE_STEP = 0.25
MAX_RATE = 1.25
# The control lease expires when its holder has not renewed it for this long (robot time): long
# enough to ride out a reconnect, short enough that a crashed host's successor is not kept waiting.
LEASE_TIMEOUT_S = 0.5
LEASE_AGE_MAX_MS = 0xFFFF


@dataclass
class RobotProgramState:
    """What the robot-side program (docs/robot-side-program.md) remembers between its cycles."""

    counter: int = 0  # robot heartbeat, +1 per cycle (INT32, wraps)
    last_host_seq: int = 0  # the host registers start at 0: nothing to do until the host writes
    last_command: int = int(Command.IDLE)  # the holder's last command word, as acted upon
    stalled_cycles: int = 0
    executing: bool = False
    held: bool = False  # latched protective hold (host STOP, bad targets, pause)
    watchdog: bool = False  # latched: host heartbeat stalled while tracking
    # The control lease: the token (unsigned 32-bit, 0: free) of the one host whose writes are acted
    # upon, cycles since it last renewed, and how many writes of other hosts were refused.
    lease_token: int = 0
    lease_age_cycles: int = 0
    refused_writes: int = 0
    last_refused: tuple[int, int] | None = None
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


class RobotSideProgram:
    """One cycle of the robot-side program over the user-area registers `hr` (9000-9999, the image the
    Modbus server serves): `act_on_host_block` before the plant steps, `publish` after it."""

    def __init__(self, plant: PlantLike, layout: UserAreaLayout, hr: list[int], watchdog_cycles: int,
                 lease_timeout_s: float = LEASE_TIMEOUT_S) -> None:
        self.plant = plant
        self.layout = layout
        self.watchdog_cycles = watchdog_cycles
        self.lease_cycles = max(1, round(lease_timeout_s / plant.dt))
        self.state = RobotProgramState()
        self._hr = hr

    def host_block(self) -> tuple[int, np.ndarray, int]:
        """(host seq, targets [deg], command) as currently in the registers."""
        lay = self.layout
        seq = regs_to_int32(self._hr_slice(lay.host_seq, 2))
        targets = regs_to_floats(self._hr_slice(lay.targets, 12))
        return seq, targets, self._hr_slice(lay.command, 1)[0]

    def act_on_host_block(self) -> None:
        """The input half: control lease, heartbeat, command word, targets, watchdog."""
        prog, lay = self.state, self.layout
        seq = regs_to_int32(self._hr_slice(lay.host_seq, 2))
        command = self._hr_slice(lay.command, 1)[0]
        if not self._holder_wrote(seq, regs_to_int32(self._hr_slice(lay.host_token, 2)) & 0xFFFFFFFF):
            # Another host's write (or one without a token) is refused whole, a STOP included: the
            # cycle runs as if the holder had not written (the E-stop and the stop coil stop any arm).
            seq, command = prog.last_host_seq, prog.last_command
        prog.last_command = command
        advanced = seq != prog.last_host_seq
        if advanced:
            prog.last_host_seq, prog.stalled_cycles = seq, 0
        else:
            prog.stalled_cycles += 1

        if command == Command.STOP:
            self.hold("host command STOP", asked=True)
        elif command == Command.TRACK:
            if prog.held or prog.watchdog:
                return  # latched: targets are ignored until the host acknowledges with IDLE
            if advanced:
                targets = np.radians(regs_to_floats(self._hr_slice(lay.targets, 12)))
                if not np.all(np.isfinite(targets)):
                    self.hold(f"non-finite joint targets {targets!r}")
                    return
                if not prog.executing:
                    prog.received.clear()
                    prog.play_seq = float(seq - JITTER_DELAY_CYCLES)
                    prog.rate = 1.0
                prog.received[seq] = targets
                prog.executing = True
            elif prog.executing and prog.stalled_cycles >= self.watchdog_cycles:
                self.hold(f"host heartbeat stalled for {prog.stalled_cycles} cycles", watchdog=True)
                return
            if prog.executing:
                self._play_next()
        elif command == Command.IDLE:
            prog.executing = False
            if advanced and (prog.held or prog.watchdog or self.plant.measured_state().status.protective_stop):
                self.release()
        else:
            self.hold(f"unknown host command {command}")

    def _holder_wrote(self, seq: int, token: int) -> bool:
        """Age, expire, grant or renew the control lease; whether the block in the registers is the holder's."""
        prog = self.state
        prog.lease_age_cycles += 1
        if prog.lease_token and prog.lease_age_cycles > self.lease_cycles:
            log.info("TM5 emulator robot-side program: lease of host 0x%08x expired", prog.lease_token)
            prog.lease_token = 0
        fresh = seq != prog.last_host_seq
        if prog.lease_token == 0 and token != 0 and fresh:
            log.info("TM5 emulator robot-side program: control granted to host 0x%08x", token)
            prog.lease_token, prog.lease_age_cycles = token, 0
        if token == 0 or token != prog.lease_token:
            if fresh and prog.last_refused != (token, seq):
                prog.refused_writes += 1
                prog.last_refused = (token, seq)
                log.warning("TM5 emulator robot-side program: write of host 0x%08x refused (held by 0x%08x)",
                            token, prog.lease_token)
            return False
        if fresh:
            prog.lease_age_cycles = 0
        return True

    @property
    def lease_age_ms(self) -> int:
        """Time since the holder last renewed its lease, as published (0 when nobody holds it)."""
        prog = self.state
        if not prog.lease_token:
            return 0
        return min(LEASE_AGE_MAX_MS, round(prog.lease_age_cycles * self.plant.dt * 1000.0))

    def _play_next(self) -> None:
        """Hand the servo one target per cycle from the jitter buffer, on an elastic clock: the
        playback rate (host sequence numbers per cycle) moves by at most RATE_STEP per cycle, never
        faster than it can still brake to a stop at the newest stored target (half a cycle of
        tolerance), and up to MAX_RATE while the buffer is deeper than planned.  A skipped sequence is
        interpolated; a host that stops sending makes the arm ease to a stop at its last target (the
        watchdog latches a hold if it stays silent)."""
        prog = self.state
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

    def hold(self, why: str, *, watchdog: bool = False, asked: bool = False) -> None:
        prog = self.state
        if not (prog.held or prog.watchdog):
            # A hold the host did not ask for is news to it (the host sees only the protective-stop flag).
            log.log(logging.INFO if asked else logging.WARNING, "TM5 emulator robot-side program: hold (%s)", why)
            self.plant.hold()
        prog.executing = False
        if watchdog:
            prog.watchdog = True
        else:
            prog.held = True

    def release(self) -> None:
        """Host acknowledged with IDLE: clear the latches and stand still at the current position."""
        release = getattr(self.plant, "release", None)
        if callable(release):
            release()  # a plant whose hold() latches (sim.plant.Plant, KinematicPlant) needs releasing
        else:
            self.plant.set_target(self.plant.measured_state().q)
        self.state.held = self.state.watchdog = False
        log.info("TM5 emulator robot-side program: released by host IDLE")

    def publish(self) -> ArmState:
        """The output half: counter, torque (mN·m), speed (deg/s), status, echo; returns the state published."""
        st = self.plant.measured_state()
        prog, lay = self.state, self.layout
        prog.counter = wrap_int32(prog.counter + 1)
        flags = prog.flags | (RobotFlags.HELD if st.status.protective_stop else RobotFlags(0))
        self._hr_put(lay.robot_counter, int32_to_regs(prog.counter))
        self._hr_put(lay.torque, floats_to_regs(np.asarray(st.tau) * 1000.0, allow_nonfinite=True))
        self._hr_put(lay.speed, floats_to_regs(np.degrees(st.dq), allow_nonfinite=True))
        self._hr_put(lay.robot_status, [int(flags)])
        self._hr_put(lay.host_seq_echo, int32_to_regs(prog.last_host_seq))
        self._hr_put(lay.lease_holder, int32_to_regs(wrap_int32(prog.lease_token)))
        self._hr_put(lay.lease_age_ms, [self.lease_age_ms])
        return st

    def _hr_slice(self, address: int, count: int) -> list[int]:
        i = address - USER_AREA_FIRST
        return self._hr[i:i + count]

    def _hr_put(self, address: int, regs: list[int]) -> None:
        i = address - USER_AREA_FIRST
        self._hr[i:i + len(regs)] = regs
