"""TM5-700 over Modbus/TCP: the `TM5ModbusArm` driver, one state read and one target write per control cycle."""

from __future__ import annotations

import logging
import secrets
import socket
import time
from collections.abc import Callable

import numpy as np
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from drivers.errors import ConfigError, DriverError, LifecycleError, LinkLostError, ProtocolError, StaleDataError
from drivers.interfaces import Arm, ArmState, ArmStatus, JointLimits, Lifecycle, vector_text
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.contract import RobotSideStatus, token_text
from drivers.tm5.modbus_replies import ILLEGAL_DATA_ADDRESS, ModbusExceptionReply, exception_name, first_line
from drivers.tm5.registers import (
    COIL_STOP,
    DI_COUNT,
    DI_ERROR,
    DI_ESTOP,
    DI_FIRST,
    DI_PAUSED,
    DI_RUNNING,
    DI_RUNS,
    IR_COUNT,
    IR_FIRST,
    IR_FLANGE_POSE,
    IR_JOINTS,
    IR_TOOL_POSE,
    N_JOINTS,
    Command,
    RobotFlags,
    counter_delta,
    floats_to_regs,
    int32_to_regs,
    regs_to_floats,
    regs_to_int32,
    regs_to_pose,
    wrap_int32,
)

log = logging.getLogger(__name__)

_ROBOT_FLAGS_MASK = int(RobotFlags.WATCHDOG | RobotFlags.EXECUTING | RobotFlags.HELD)  # other bits: reserved

# A state read (three transactions) that takes longer than this many control periods (or than `timeout_s`, when
# that is longer) ends the cycle as stale: each transaction has its own timeout, but three slow ones in a row
# would keep the loop on data several periods old.
READ_BUDGET_PERIODS = 2.0


class TM5ModbusArm(Arm):
    """The TM5-700 through its Modbus/TCP slave plus the robot-side program of docs/robot-side-program.md.

    Per cycle: `read_state` = 3 reads (input registers 7001-7036, discrete inputs 7200-7208, the robot->host
    user block); `send_target` = 1 write (the host->robot user block).  Units are converted here only.
    A controller that refuses the discrete-input block (its undocumented addresses 7203, 7205-7207) is read
    on the documented addresses alone from then on (three more reads a cycle).
    The link is a sync pymodbus client with `retries=0`, so a dead link costs at most `timeout_s`, and a state
    read as a whole at most READ_BUDGET_PERIODS control periods (then StaleDataError).
    Every write carries this driver's random `token`: the robot side acts on one token at a time (the
    control lease, renewed by every write), so a second host cannot arm an arm another one drives.
    """

    def __init__(self, config: TM5ModbusConfig, limits: JointLimits, dt: float, speed_scale: float = 1.0) -> None:
        super().__init__(limits, dt, speed_scale)
        config.validate()
        config.check_period(dt)
        if limits.n != N_JOINTS:
            raise ConfigError(f"the TM5-700 has {N_JOINTS} joints, the joint limits describe {limits.n}")
        self.config = config
        self._layout = config.user_area
        self._client: ModbusTcpClient | None = None
        self._down_reason = "not connected"
        self._backoff_s = config.reconnect_initial_s
        self._stop_failed = False  # the last stop attempt raised: the next one may reconnect
        self._next_attempt = 0.0
        self._host_seq = 0
        self.token = 1 + secrets.randbelow(0xFFFFFFFF)  # nonzero: a zero token claims nothing
        self._counter_raw: int | None = None
        self._counter_seen_at = 0.0
        self._new_stale_window = False
        self._seq = 0
        self._last_q: np.ndarray | None = None
        self._flange_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._tool_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._robot_side: RobotSideStatus | None = None
        self._warned_untested = False
        self._di_by_runs = False  # the controller refused the block read: read the documented runs
        self._read_budget_s = max(READ_BUDGET_PERIODS * dt, config.timeout_s)

    # ----------------------------------------------------------------------------- public extras
    @property
    def endpoint(self) -> str:
        return f"{self.config.host}:{self.config.port}"

    @property
    def link_up(self) -> bool:
        return self._client is not None and self._client.connected

    @property
    def robot_side(self) -> RobotSideStatus | None:
        """Robot-side program status from the last successful read."""
        return self._robot_side

    @property
    def last_flange_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(position [m], rotation) of the flange from the last `read_state` (no extra transaction)."""
        return self._flange_pose

    @property
    def last_tool_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(position [m], rotation) of the TCP from the last `read_state` (no extra transaction)."""
        return self._tool_pose

    def read_tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Fresh TCP pose in the current base (input registers 7025-7036): (position [m], rotation matrix)."""
        return self._read_pose(IR_TOOL_POSE, "tool pose")

    def read_flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Fresh flange pose in the current base (input registers 7001-7012)."""
        return self._read_pose(IR_FLANGE_POSE, "flange pose")

    def reconnect(self, timeout_s: float | None = None) -> None:
        """Re-open the link now, retrying with exponential backoff for up to `timeout_s` (default
        `arm_timeout_s`).  Does not leave FAULT: commanding still needs `arm()`.  Raises LinkLostError."""
        with self._lock:
            if self.lifecycle is Lifecycle.DISCONNECTED:
                raise LifecycleError("cannot reconnect: the arm is not connected (call connect())")
            self._reconnect_blocking(self.config.arm_timeout_s if timeout_s is None else timeout_s)

    # ----------------------------------------------------------------------------- wire: lifecycle
    def _connect(self) -> None:
        if not self._warned_untested:
            log.warning("TM5ModbusArm %s: the real-hardware path is UNTESTED on a physical arm (it has only run "
                        "against sim.tm5_emulator); keep a hand on the E-stop", self.endpoint)
            self._warned_untested = True
        # A first contact may be slow (a controller just booted, a busy machine): keep trying for
        # arm_timeout_s before giving up, as arming does.
        # A refused connection (nobody listening) fails at once.
        deadline = time.monotonic() + self.config.arm_timeout_s
        while True:
            self._next_attempt = 0.0
            self._open_link()
            try:
                # Start our heartbeat right after whatever the robot last acted upon, so a restarted
                # host never repeats a sequence number the robot-side program would ignore.
                self._host_seq = self._read_robot_block().host_seq_echo
                return
            except DriverError:
                self._close_link("connect failed")
                if time.monotonic() >= deadline:
                    raise
                time.sleep(self.config.reconnect_initial_s)

    def _disconnect(self) -> None:
        self._close_link("disconnected")
        self._client = None

    def _arm(self) -> None:
        """Get the link back if needed, then the IDLE handshake: the robot-side program must echo our new
        host sequence (which also clears its latched stop / watchdog trip) within `arm_timeout_s`."""
        deadline = time.monotonic() + self.config.arm_timeout_s
        if not self.link_up:
            self._reconnect_blocking(self.config.arm_timeout_s)
        echo = self._await_lease(deadline).host_seq_echo
        if 0 < counter_delta(echo, self._host_seq) < 0x80000000:
            # Another host wrote since we last did: number on from its sequence, or our IDLE might repeat
            # a number the robot side already acted upon (and never be acted upon itself).
            self._host_seq = echo
        q = self._read_joints()
        seq = self._write_host_block(Command.IDLE, q)
        first_counter: int | None = None
        while True:
            rs = self._read_robot_block()
            first_counter = rs.counter if first_counter is None else first_counter
            if self._held_by_other(rs):
                raise self._held_error(rs, "arm is held by another controller")
            if rs.host_seq_echo == seq and rs.lease_holder == self.token:
                # Armed on a working link: a stop that failed before this is moot, so a fault's first stop
                # again never waits on the link (it would double the time a lost link takes to report).
                self._stop_failed = False
                return
            if time.monotonic() >= deadline:
                break
            time.sleep(0.002)  # a robot cycle is several ms: poll gently
        if rs.counter == first_counter:
            raise StaleDataError(
                f"TM5 {self.endpoint}: robot counter at {self._layout.robot_counter} stuck at {rs.counter}: "
                "the robot-side program is not running (see docs/robot-side-program.md)"
            )
        raise ProtocolError(
            f"TM5 {self.endpoint}: robot-side program did not acknowledge host sequence {seq} and grant this "
            f"host control within {self.config.arm_timeout_s:g} s (echo at {self._layout.host_seq_echo} reads "
            f"{rs.host_seq_echo}, lease holder {token_text(rs.lease_holder)}); does its register layout match "
            "devices.arm.user_area?"
        )

    def _await_lease(self, deadline: float) -> RobotSideStatus:
        """Write nothing while another host holds control: wait, up to `deadline`, for its lease to lapse
        (a host that stopped or vanished), then raise naming the holder.  A write would be refused anyway,
        and it would cost the holder a cycle of its targets."""
        while True:
            rs = self._read_robot_block()
            if not self._held_by_other(rs):
                return rs
            if time.monotonic() >= deadline:
                raise self._held_error(rs, "arm is held by another controller")
            time.sleep(0.005)

    def _held_by_other(self, rs: RobotSideStatus) -> bool:
        return rs.lease_holder not in (0, self.token)

    def _held_error(self, rs: RobotSideStatus, what: str) -> LifecycleError:
        return LifecycleError(f"TM5 {self.endpoint}: {what} (token {token_text(rs.lease_holder)}, renewed "
                              f"{rs.lease_age_s * 1000:.0f} ms ago; this host is {token_text(self.token)})")

    def _stop(self) -> None:
        # A first stop never waits on the link: a dead one fails at once (the robot's watchdog stops the arm
        # then; a fault's stop must not add a connect to the time a lost link takes to detect).  A stop
        # retried after a failed one may open the link again -- one connect attempt, bounded by timeout_s --
        # so a stop whose reply was lost gets through on a fresh link.
        retry, self._stop_failed = self._stop_failed, True
        q = self._last_sent if self._last_sent is not None else self._last_q
        self._write_host_block(Command.STOP, q, may_reconnect=retry)
        if self.config.stop_coil:
            self._call("write coil", COIL_STOP, lambda c, dev: c.write_coil(COIL_STOP, True, device_id=dev),
                       may_reconnect=retry)
            # A pulse: the coil released again, so that a controller acting on its rising edge sees the next
            # stop too.  The stop itself has gone out; a link failing now is reported by the next cycle.
            try:
                self._call("release coil", COIL_STOP,
                           lambda c, dev: c.write_coil(COIL_STOP, False, device_id=dev), may_reconnect=False)
            except DriverError as exc:
                log.warning("TM5 %s: stop coil %d set, its release failed: %s", self.endpoint, COIL_STOP, exc)
        self._stop_failed = False

    # ----------------------------------------------------------------------------- wire: data
    def _read_state(self) -> ArmState:
        layout = self._layout
        t0 = time.monotonic()
        ir = self._read_registers("input", IR_FIRST, IR_COUNT)
        self._within_budget(t0, "the discrete inputs")
        di = self._read_status_inputs(t0)
        self._within_budget(t0, "the robot-side block")
        rb_start, rb_count = layout.robot_block
        hr = self._read_registers("holding", rb_start, rb_count)
        t = time.monotonic()

        q_deg = self._finite(regs_to_floats(ir[IR_JOINTS - IR_FIRST:IR_JOINTS - IR_FIRST + 12]), "joint angles",
                             IR_JOINTS)
        tau_mnm = self._finite(regs_to_floats(hr[layout.slice_in("torque", rb_start)]), "joint torque",
                               layout.torque)
        dq_deg = self._finite(regs_to_floats(hr[layout.slice_in("speed", rb_start)]), "joint speed", layout.speed)
        robot = self._decode_robot_block(hr, rb_start)
        if self.lifecycle is Lifecycle.ARMED and self._held_by_other(robot):
            # Our lease lapsed (no write for the robot side's lease timeout) and another host took it.
            raise self._held_error(robot, "control was taken by another controller")
        self._flange_pose = regs_to_pose(ir[0:12])
        self._tool_pose = regs_to_pose(ir[IR_TOOL_POSE - IR_FIRST:IR_TOOL_POSE - IR_FIRST + 12])
        self._check_counter(robot.counter, t)

        q = np.radians(q_deg)
        self._last_q = q
        status = ArmStatus(
            error=di[DI_ERROR - DI_FIRST],
            estop=di[DI_ESTOP - DI_FIRST],
            project_running=di[DI_RUNNING - DI_FIRST],
            paused=di[DI_PAUSED - DI_FIRST],
            protective_stop=bool(robot.flags & (RobotFlags.WATCHDOG | RobotFlags.HELD)),
        )
        return ArmState(t=t, q=q, dq=np.radians(dq_deg), tau=tau_mnm / 1000.0, status=status, seq=self._seq)

    def _write_target(self, q: np.ndarray) -> None:
        self._write_host_block(Command.TRACK, q, may_reconnect=False)

    # ----------------------------------------------------------------------------- helpers
    def _within_budget(self, t0: float, next_read: str) -> None:
        """StaleDataError when the state read begun at `t0` has used its budget before reading `next_read`."""
        spent = time.monotonic() - t0
        if spent > self._read_budget_s:
            raise StaleDataError(
                f"TM5 {self.endpoint}: reading the state took {spent * 1000:.1f} ms before {next_read} (limit "
                f"{self._read_budget_s * 1000:.1f} ms, {READ_BUDGET_PERIODS:g} control periods): the link is too "
                "slow for the control period")

    def _read_status_inputs(self, t0: float) -> list[bool]:
        """Discrete inputs 7200-7208: one block read, or the documented runs once the controller refused it
        (the undocumented addresses then read False)."""
        if not self._di_by_runs:
            try:
                return self._read_bits(DI_FIRST, DI_COUNT)
            except ModbusExceptionReply as exc:
                if exc.code != ILLEGAL_DATA_ADDRESS:
                    raise
                self._di_by_runs = True
                log.warning("TM5 %s: the controller refuses discrete inputs %d-%d as one block (illegal data "
                            "address): reading the documented ones (%s) apiece from now on", self.endpoint,
                            DI_FIRST, DI_FIRST + DI_COUNT - 1,
                            ", ".join(f"{a}-{a + n - 1}" if n > 1 else str(a) for a, n in DI_RUNS))
        bits = [False] * DI_COUNT
        for i, (address, count) in enumerate(DI_RUNS):
            if i:
                self._within_budget(t0, f"discrete input {address}")
            bits[address - DI_FIRST:address - DI_FIRST + count] = self._read_bits(address, count)
        return bits

    def _read_pose(self, address: int, what: str) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            if self.lifecycle is Lifecycle.DISCONNECTED:
                raise LifecycleError(f"cannot read the {what}: the arm is not connected")
            try:
                regs = self._read_registers("input", address, 12)
            except (LinkLostError, StaleDataError) as exc:
                self.fault(str(exc))
                raise
            pos, rot = regs_to_pose(regs)
            self._finite(np.concatenate([pos, rot.ravel()]), what, address)
            return pos, rot

    def _finite(self, values: np.ndarray, what: str, address: int) -> np.ndarray:
        if not np.all(np.isfinite(values)):
            raise ProtocolError(f"TM5 {self.endpoint}: {what} at {address} holds non-finite values "
                                f"{vector_text(values)}")
        return values

    def _decode_robot_block(self, hr: list[int], start: int) -> RobotSideStatus:
        lay = self._layout
        rs = RobotSideStatus(
            counter=regs_to_int32(hr[lay.slice_in("robot_counter", start)]),
            flags=RobotFlags(hr[lay.slice_in("robot_status", start)][0] & _ROBOT_FLAGS_MASK),
            host_seq_echo=regs_to_int32(hr[lay.slice_in("host_seq_echo", start)]),
            lease_holder=regs_to_int32(hr[lay.slice_in("lease_holder", start)]) & 0xFFFFFFFF,
            lease_age_s=hr[lay.slice_in("lease_age_ms", start)][0] / 1000.0,
        )
        self._robot_side = rs
        return rs

    def _read_robot_block(self) -> RobotSideStatus:
        start, count = self._layout.robot_block
        return self._decode_robot_block(self._read_registers("holding", start, count), start)

    def _read_joints(self) -> np.ndarray:
        regs = self._read_registers("input", IR_JOINTS, 12)
        q = np.radians(self._finite(regs_to_floats(regs), "joint angles", IR_JOINTS))
        self._last_q = q
        return q

    def _check_counter(self, counter: int, t: float) -> None:
        """Unwrap the robot counter into ArmState.seq and raise StaleDataError when it stops advancing."""
        if self._counter_raw is None:
            self._counter_raw, self._counter_seen_at = counter, t
            self._seq = counter & 0xFFFFFFFF
            return
        step = counter_delta(counter, self._counter_raw)
        if step or self._new_stale_window:
            self._seq += step
            self._counter_raw, self._counter_seen_at = counter, t
            self._new_stale_window = False
            return
        stuck = t - self._counter_seen_at
        if stuck > self.config.stale_after_s:
            raise StaleDataError(
                f"TM5 {self.endpoint}: robot counter at {self._layout.robot_counter} stuck at {counter} for "
                f"{stuck * 1000:.0f} ms (limit {self.config.stale_after_s * 1000:.0f} ms): robot-side program "
                "stalled or stopped"
            )

    def _write_host_block(self, command: Command, q_rad: np.ndarray | None, *, may_reconnect: bool = False) -> int:
        """One FC16 write of host seq + targets + command; returns the host sequence used."""
        lay = self._layout
        start, count = lay.host_block
        regs = [0] * count
        seq = wrap_int32(self._host_seq + 1)
        targets = np.zeros(N_JOINTS) if q_rad is None else np.degrees(np.asarray(q_rad, dtype=float))
        try:
            regs[lay.slice_in("targets", start)] = floats_to_regs(targets)
        except ValueError as exc:
            raise ProtocolError(f"TM5 {self.endpoint}: cannot encode joint targets: {exc}") from None
        regs[lay.slice_in("host_seq", start)] = int32_to_regs(seq)
        regs[lay.slice_in("command", start)] = [int(command)]
        regs[lay.slice_in("host_token", start)] = int32_to_regs(wrap_int32(self.token))
        # The number is used up once sent, reply or not: a write whose reply was lost may have reached the
        # robot-side program, which ignores a number it already acted upon (a re-arm reusing it would
        # never clear the latched stop).
        self._host_seq = seq
        self._call("write holding", start, lambda c, dev: c.write_registers(start, regs, device_id=dev),
                   may_reconnect=may_reconnect)
        return seq

    def _read_registers(self, kind: str, address: int, count: int) -> list[int]:
        def read(c: ModbusTcpClient, dev: int) -> ModbusPDU:
            if kind == "input":
                return c.read_input_registers(address, count=count, device_id=dev)
            return c.read_holding_registers(address, count=count, device_id=dev)

        rr = self._call(f"read {kind}", address, read, may_reconnect=True)
        regs = list(rr.registers)
        if len(regs) != count:
            raise ProtocolError(f"TM5 {self.endpoint}: read {kind} {address}: asked {count} registers, "
                                f"got {len(regs)}")
        return regs

    def _read_bits(self, address: int, count: int) -> list[bool]:
        rr = self._call("read discrete inputs", address,
                        lambda c, dev: c.read_discrete_inputs(address, count=count, device_id=dev),
                        may_reconnect=True)
        bits = list(rr.bits)
        if len(bits) < count:
            raise ProtocolError(f"TM5 {self.endpoint}: read discrete inputs {address}: asked {count} bits, "
                                f"got {len(bits)}")
        return [bool(b) for b in bits[:count]]

    def _call(self, op: str, address: int, fn: Callable[[ModbusTcpClient, int], ModbusPDU], *,
              may_reconnect: bool) -> ModbusPDU:
        """One Modbus transaction; every failure becomes LinkLostError (link closed) or ProtocolError."""
        client = self._require_link(may_reconnect)
        try:
            rr = fn(client, self.config.unit_id)
        except ConnectionException as exc:
            raise self._link_lost(f"{op} {address}: connection lost ({first_line(exc)})") from None
        except ModbusIOException as exc:
            # No (matching) reply in time.  Close the socket: a late reply must not be taken for the next one.
            raise self._link_lost(f"{op} {address}: no valid reply within {self.config.timeout_s * 1000:.0f} ms "
                                  f"({first_line(exc)})") from None
        except (ModbusException, OSError) as exc:
            raise self._link_lost(f"{op} {address}: {type(exc).__name__}: {first_line(exc)}") from None
        if rr is None:
            raise self._link_lost(f"{op} {address}: no reply")
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            raise ModbusExceptionReply(f"TM5 {self.endpoint}: {op} {address}: Modbus exception reply code {code} "
                                       f"({exception_name(code)})", code if isinstance(code, int) else None)
        return rr

    def _require_link(self, may_reconnect: bool) -> ModbusTcpClient:
        if self._client is not None and self._client.connected:
            return self._client
        now = time.monotonic()
        if may_reconnect and now >= self._next_attempt:
            return self._open_link()
        wait = max(0.0, self._next_attempt - now)
        hint = f"; next reconnect attempt in {wait * 1000:.0f} ms" if may_reconnect else ""
        raise LinkLostError(f"TM5 {self.endpoint}: link is down ({self._down_reason}){hint}")

    def _open_link(self) -> ModbusTcpClient:
        """One connect attempt (bounded by timeout_s); on failure schedule the next one with backoff."""
        if self._client is None:
            # retries=0: one try per transaction so a dead link costs at most timeout_s per call.
            self._client = ModbusTcpClient(self.config.host, port=self.config.port, timeout=self.config.timeout_s,
                                           retries=0, name="tm5")
        client = self._client
        if not client.connect():
            now = time.monotonic()
            self._down_reason = f"connect to {self.endpoint} failed"
            self._next_attempt = now + self._backoff_s
            self._backoff_s = min(2 * self._backoff_s, self.config.reconnect_max_s)
            raise LinkLostError(f"TM5 {self.endpoint}: cannot connect (next attempt in "
                                f"{(self._next_attempt - now) * 1000:.0f} ms)")
        if client.socket is not None:
            # Request/reply of a few dozen bytes: never let Nagle hold a request back.
            client.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._backoff_s = self.config.reconnect_initial_s
        self._new_stale_window = True  # a new link starts a new staleness window; seq keeps unwrapping
        log.info("TM5 %s: link up", self.endpoint)
        return client

    def _reconnect_blocking(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._require_link(may_reconnect=True)
                return
            except LinkLostError:
                now = time.monotonic()
                if now >= deadline:
                    raise
                time.sleep(min(max(self._next_attempt - now, 0.001), deadline - now))

    def _link_lost(self, reason: str) -> LinkLostError:
        self._close_link(reason)
        self._next_attempt = time.monotonic()  # the first retry may be immediate; failures then back off
        log.warning("TM5 %s: link lost: %s", self.endpoint, reason)
        return LinkLostError(f"TM5 {self.endpoint}: {reason}")

    def _close_link(self, reason: str) -> None:
        self._down_reason = reason
        if self._client is not None:
            self._client.close()

