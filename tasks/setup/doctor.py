"""Bring-up checks of a cell's wiring: arm reachable, register map sane, robot-side program alive, sensor sound.

Every check is named, passes or fails, and says what to do when it fails.  The arm is never armed or
commanded here (only read), so the checks are safe with the arm in any state, except the one asked for by
name (`stream_stop`, route B: it turns the last wrist joint a few degrees); the sensor is tared and read at
rest.  A check whose precondition failed is `skipped` (its cause is the earlier failure).
"""

from __future__ import annotations

import logging
import math
import socket
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from drivers.errors import DriverError
from drivers.interfaces import JointLimits
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.ethernet_slave import SAFETY_ITEMS
from drivers.tm5.modbus import TM5ModbusArm
from drivers.tm5.table_check import check_arm
from drivers.wacoh.driver import WacohSensor

log = logging.getLogger(__name__)

Status = Literal["pass", "fail", "skipped"]
LIMIT_MARGIN_RAD = math.radians(2.0)  # a reading this far past a joint limit is no joint angle
HEARTBEAT_S = 0.5  # the robot counter must advance within this
# A command that takes longer than this many control periods to pass the Listen node's queue acts too late
# for the impedance loop closed through it.
LATENCY_BASE_PERIODS = 2  # the broadcast's age and the servo's interpolation, one period each
ROUND_TRIP_PERIODS = 4
RATE_WINDOW_S = 1.0  # the state stream is watched this long to measure its rate and jitter
# The measured rate may fall this much short of 1/period before the check fails: a one-second window
# over a polled counter counts a sample more or less at either end.
RATE_TOLERANCE = 0.95
TARE_DRIFT_N = 0.5  # |mean(last quarter) - mean(first quarter)| of the force after a tare
TARE_NOISE_N = 1.0  # standard deviation of |F| at rest
READ_LOSS = 0.02  # share of sensor reads that may come back empty or corrupted
SENSITIVITY_REL = 0.05  # the sensor's `p` within 5 % of the class's nominal values


@dataclass
class Check:
    name: str
    status: Status
    detail: str
    fix: str = ""


@dataclass
class DoctorSettings:
    period_s: float  # the control period the wire must keep up with
    slow_fraction: float = 0.8  # a step over this share of the period is late (the loop's own limit)
    timing_steps: int = 100
    tare_s: float = 2.0
    # The late tail (p95) a step may reach, in periods: 1 on a real cell (the robot side's jitter buffer
    # takes one period); the emulated cell's emulators share this machine's CPU, so it allows more.
    tail_periods: float = 1.0
    stream_stop: bool = False  # route B: run the check that moves the arm (asked for by name)


class Doctor:
    """Runs the checks in order on the devices given (either may be None when the cell has none)."""

    def __init__(self, arm: TM5ModbusArm | TMEthernetArm | None, sensor: WacohSensor | None, limits: JointLimits,
                 settings: DoctorSettings) -> None:
        self.arm, self.sensor, self.limits, self.s = arm, sensor, limits, settings
        self.checks: list[Check] = []

    def run(self) -> list[Check]:
        has_sensor = self.sensor is not None
        alive = self._tm_ethernet_checks() if isinstance(self.arm, TMEthernetArm) else self._modbus_checks()
        self._step("state_rate", self._state_rate, (
            "the arm's state arrives slower than the control loop needs it: set loop.period_s to the measured "
            "period (TM's Ethernet Slave broadcasts every ~15.6 ms: config/tm-ethernet.yaml), or make the "
            "robot-side program's cycle keep loop.period_s (docs/real-cell.md)"), run=alive)
        self._step("estop_and_errors", self._status, (
            "release the E-stop, clear the controller's error in TMflow and start the project; a protective stop "
            "of the robot-side program (its watchdog's latched hold) is released when a host arms the arm"),
            run=alive)
        if isinstance(self.arm, TMEthernetArm):
            node = self._step("listen_node", self._listen_node, (
                "start the project in TMflow and let its flow reach the Listen node (a project with a Listen "
                "node, Setting > Connection > Listen node enabled; docs/real-cell.md route B)"), run=alive)
            self._step("command_round_trip", self._round_trip, (
                "the Listen node answers slowly: a direct cable, no other client on port 5890, project speed "
                "100 %; a node that cannot keep up with the loop's rate: a longer loop.period_s, or (knowing the "
                "commands then act later) devices.arm.settings.max_unanswered_scripts / max_reply_age_s "
                "(docs/real-cell.md)"), run=node)
            self._step("stream_stop", self._stream_stop, (
                "velocity mode keeps the last streamed speed when the host falls silent: a killed host or a pulled "
                "cable leaves the arm moving (the driver caps each speed so that 0.1 s of it stays in the joint "
                "range, no more).  Keep the E-stop in reach, set TMflow's safety speed limits to the cell's work, "
                "or use route A, whose robot-side program stops on a stalled heartbeat (docs/real-cell.md)"),
                run=node and self.s.stream_stop, skip_reason=None if not node or self.s.stream_stop else (
                    "not run: it moves the arm (the last wrist joint, about 4 degrees): `doctor --stream-stop` "
                    "with the tool clear and a hand on the E-stop"))
        elif self.s.stream_stop and self.arm is not None:
            self.checks.append(Check("stream_stop", "skipped", (
                "not run: the Modbus route streams no speeds; its robot-side program stops the arm when the host's "
                "heartbeat stalls (docs/robot-side-program.md)")))
        port = self._step("sensor_port", self._sensor_connect, (
            "check devices.sensor.settings.port (the device exists, your user may open it: dialout group), "
            "the baud rate, and that the sensor is powered; a USB adapter's latency timer over the reply timeout: "
            "set it to 1 ms (docs/real-cell.md, section 3)"), run=has_sensor)
        self._step("sensor_sensitivities", self._sensitivities, (
            "enter the calibration sheet's sensitivities in devices.sensor.settings.sensitivities, or replace "
            "a sensor whose reply is off its class"), run=port)
        self._step("sensor_tare_stability", self._tare, (
            "keep the tool still and unloaded, let the sensor warm up (15 min), check the cable's strain relief; "
            "a drifting sensor needs re-taring before each contact (tasks do it in their tare state)"), run=port)
        self._step("sensor_line", self._line, (
            "the serial line loses or corrupts records: a shorter or shielded cable, a grounded sensor, a USB "
            "adapter with low latency (FTDI latency_timer 1 ms), or a lower baud rate"), run=port)
        self._step("control_step_timing", self._timing, (
            "the wire is too slow for the control period: a direct cable (no switch or Wi-Fi), power saving off "
            "on the host, a quieter machine, or a longer loop.period_s"), run=alive)
        return self.checks

    def _modbus_checks(self) -> bool:
        """The Modbus route's first checks; True when the robot-side program's counter advances."""
        reach = self._step("arm_reachable", self._reachable, (
            "check the cable and the controller's address (devices.arm.settings.host/port) and that its "
            "Modbus TCP server is on (TMflow: Setting > Connection > Modbus)"), run=self.arm is not None)
        connected = self._step("modbus_connect", self._connect, (
            "check devices.arm.settings.unit_id and that nothing else holds the controller's Modbus connection"),
            run=reach)
        mapped = self._step("register_map", self._register_map, (
            "the registers do not read as TM5-700 joint data: check the controller's firmware register map and "
            "devices.arm.settings.user_area against the robot-side program (docs/robot-side-program.md)"),
            run=connected)
        return self._step("robot_program_heartbeat", self._heartbeat, (
            "start the robot-side program on the controller and check it is not paused or stalled "
            "(docs/robot-side-program.md)"), run=mapped)

    def _tm_ethernet_checks(self) -> bool:
        """TM's channels' first checks; True when the Ethernet Slave streams a readable table."""
        reach = self._step("arm_reachable", self._reachable, (
            "check the cable and devices.arm.settings.host, and that the Ethernet Slave is enabled (TMflow: "
            "Setting > Connection > Ethernet Slave, Data Table Setting: import TM's "
            "Data_Table_Setting_TM_ROS_Default.xml)"))
        table = self._step("slave_table", self._slave_table, (
            "set the Ethernet Slave's Communication Mode to BINARY and its transmit table to TM's "
            "Data_Table_Setting_TM_ROS_Default.xml (or tick Joint_Angle, Joint_Speed, Joint_Torque and "
            f"{', '.join(SAFETY_ITEMS)} by hand)"), run=reach)
        self._step("project_speed", self._project_speed, (
            "set the project speed to 100 % in TMflow (Auto mode): below it the controller scales the streamed "
            "joint speeds and the host's position loop, which assumes them as sent, lags and overshoots"), run=table)
        data = self._step("joint_data", self._register_map, (
            "the table's joint items do not read as TM5-700 joint data (degrees, deg/s, mN·m): check the items "
            "and their types in the Data Table Setting"), run=table)
        off = isinstance(self.arm, TMEthernetArm) and self.arm.config.modbus_port is None
        self._step("modbus_cross_check", self._modbus_cross_check, (
            "unreadable: turn on the controller's Modbus TCP server (TMflow: Setting > Connection > Modbus) and "
            "check devices.arm.settings.modbus_port (TM's is 502); disagreeing joints: another machine answers on "
            "that port, or the Ethernet Slave's table is not this controller's joints (check its Joint_Angle "
            "item); the E-stop flag alone disagreeing on a healthy arm: register 7208's meaning is uncertain "
            "(docs tm5-700.md section 3); or set modbus_port: null to go without the cross-check (arming too)"),
            run=data and not off, skip_reason=(
                "not run: devices.arm.settings.modbus_port is null (no Modbus table to cross-check against)"
                if off else None))
        return data

    # ------------------------------------------------------------------------------------ plumbing
    def _step(self, name: str, fn: Callable[[], str], fix: str, run: bool = True,
              skip_reason: str | None = None) -> bool:
        if not run:
            no_sensor = name.startswith("sensor_") and self.sensor is None
            self.checks.append(Check(name, "skipped", skip_reason or (
                "not run: this cell has no F/T sensor" if no_sensor else "not run: an earlier check failed")))
            return False
        try:
            detail = fn()
            self.checks.append(Check(name, "pass", detail))
            return True
        except (DriverError, OSError, AssertionError, ValueError) as exc:
            self.checks.append(Check(name, "fail", f"{type(exc).__name__}: {exc}" if not isinstance(
                exc, AssertionError) else str(exc), fix))
            log.debug("doctor: %s failed: %s", name, exc)
            return False

    # ------------------------------------------------------------------------------------ the arm
    def _reachable(self) -> str:
        assert self.arm is not None
        cfg = self.arm.config
        host, port = cfg.host, cfg.slave_port if isinstance(cfg, TMEthernetConfig) else cfg.port
        t0 = time.perf_counter()
        with socket.create_connection((host, port), timeout=2.0):
            pass
        return f"{host}:{port} accepts TCP connections ({(time.perf_counter() - t0) * 1e3:.1f} ms)"

    def _slave_table(self) -> str:
        assert isinstance(self.arm, TMEthernetArm)
        self.arm.connect()  # refuses a STRING or JSON table, or one without the joint items, saying what to change
        table = self.arm.latest_table
        assert table is not None, "no data table arrived"
        missing = table.missing_safety_items
        detail = f"binary table, {len(table.items)} items, joint angles, speeds and torques present"
        assert not missing, (f"{detail}; missing {', '.join(missing)}: the cell cannot see the controller's stops "
                             "and refuses to arm")
        return f"{detail}, and {', '.join(SAFETY_ITEMS)}"

    def _project_speed(self) -> str:
        assert isinstance(self.arm, TMEthernetArm)
        self.arm.read_state()
        table = self.arm.latest_table
        assert table is not None, "no data table arrived"
        if table.project_speed is None:
            return "Project_Speed is not in the table: unchecked"
        assert table.project_speed == 100, f"Project_Speed is {table.project_speed} %, not 100 %"
        return "Project_Speed 100 %"

    def _modbus_cross_check(self) -> str:
        assert isinstance(self.arm, TMEthernetArm)
        check = check_arm(self.arm)
        assert check.agrees, check.summary()
        return check.summary()

    def _listen_node(self) -> str:
        assert isinstance(self.arm, TMEthernetArm)
        status = self.arm.probe_listen_node()
        assert status.in_node, "TMSTA 00 answers false: the project is not in its Listen node"
        return f"the project is in its Listen node ({status.message!r})"

    def _round_trip(self) -> str:
        assert isinstance(self.arm, TMEthernetArm)
        ms = self.arm.command_round_trip() * 1e3
        periods = ms / (self.s.period_s * 1e3)
        detail = f"QueueTag to done in {ms:.1f} ms ({periods:.1f} control periods)"
        assert ms <= ROUND_TRIP_PERIODS * self.s.period_s * 1e3, (
            f"{detail}: over {ROUND_TRIP_PERIODS} periods, commands would act too late for force control")
        # The velocity loop predicts across the queue's periods plus the table's age and the servo's
        # interpolation (one period each): counted short, a contact force rings.  A round trip takes one
        # period without any queue (the tag runs on the next servo cycle), so only the periods beyond count.
        needed = LATENCY_BASE_PERIODS + max(0, int(np.ceil(periods - 1.5)))
        have = self.arm.config.command_latency_periods
        assert have >= needed, (f"{detail}: devices.arm.settings.command_latency_periods is {have}, this arm "
                                f"needs {needed} (2 + the round trip's periods beyond its first)")
        # The replies to scripts streamed at the loop's rate: the driver stops the arm when more than
        # max_unanswered_scripts are outstanding or the oldest is older than max_reply_age_s.
        cfg = self.arm.config
        lag = self.arm.script_reply_lag(period_s=self.s.period_s)
        streamed = f"{lag.sent} scripts at {1 / self.s.period_s:.0f} Hz: {lag.summary()}"
        assert lag.answered == lag.sent, f"{detail}; {streamed}: the Listen node left scripts unanswered"
        assert lag.max_unanswered <= cfg.max_unanswered_scripts and lag.max_s <= cfg.max_reply_age_s, (
            f"{detail}; {streamed}: over max_unanswered_scripts {cfg.max_unanswered_scripts} or max_reply_age_s "
            f"{cfg.max_reply_age_s * 1e3:.0f} ms, the driver would stop the arm at this rate")
        return f"{detail}; command_latency_periods {have} covers it; {streamed}"

    def _stream_stop(self) -> str:
        assert isinstance(self.arm, TMEthernetArm)
        probe = self.arm.stream_stop_probe()
        assert probe.moved, (f"{probe.summary()}: the streamed speed did not reach the joint (project paused, "
                             "or below 100 % project speed?)")
        assert probe.stopped_after_s is not None, probe.summary()
        return probe.summary()

    def _connect(self) -> str:
        assert isinstance(self.arm, TM5ModbusArm)
        self.arm.connect()
        return f"Modbus unit {self.arm.config.unit_id} answers"

    def _register_map(self) -> str:
        assert self.arm is not None
        state = self.arm.read_state()
        lo, hi = self.limits.lower - LIMIT_MARGIN_RAD, self.limits.upper + LIMIT_MARGIN_RAD
        bad = [j + 1 for j in range(len(state.q)) if not lo[j] <= state.q[j] <= hi[j]]
        assert not bad, (f"joint angles {np.degrees(state.q).round(1).tolist()} deg: joint {bad[0]} lies outside "
                         "its limits (another register map or unit)")
        torque_bad = [j + 1 for j in range(len(state.tau)) if abs(state.tau[j]) > 1.5 * self.limits.effort[j]]
        assert not torque_bad, (f"joint torques {np.round(state.tau, 1).tolist()} N·m: joint {torque_bad[0]} above "
                                "1.5x its rated torque (another register map or unit)")
        return f"joints {np.degrees(state.q).round(1).tolist()} deg within limits, torques plausible"

    def _heartbeat(self) -> str:
        assert self.arm is not None
        first = self.arm.read_state()
        deadline = time.monotonic() + HEARTBEAT_S
        while time.monotonic() < deadline:
            time.sleep(self.s.period_s)
            last = self.arm.read_state()
            if last.seq != first.seq:
                # Its rate is the state_rate check's to measure.
                return f"robot counter advancing ({first.seq} -> {last.seq})"
        raise AssertionError(f"robot counter stuck at {first.seq} for {HEARTBEAT_S:.1f} s: the robot-side "
                             "program is not running")

    def _state_rate(self) -> str:
        assert self.arm is not None
        rate, jitter_ms, samples = measure_state_rate(self.arm.read_state, RATE_WINDOW_S,
                                                      min(0.001, self.s.period_s / 4))
        need = 1.0 / self.s.period_s
        detail = (f"state at {rate:.1f} Hz ({samples} samples in {RATE_WINDOW_S:g} s, interval p95 - p50 "
                  f"{jitter_ms:.1f} ms); loop.period_s {self.s.period_s * 1e3:g} ms needs {need:.1f} Hz")
        assert rate >= RATE_TOLERANCE * need, detail
        return detail

    def _status(self) -> str:
        assert self.arm is not None
        st = self.arm.read_state().status
        held = (self._tm_held() if isinstance(self.arm, TMEthernetArm) else
                "protective stop (robot-side program holding)")
        problems = [what for what, on in (("E-stop pressed", st.estop), ("controller error", st.error),
                                          (held, st.protective_stop),
                                          ("project not running", not st.project_running),
                                          ("project paused", st.paused)) if on]
        assert not problems, "; ".join(problems)
        return "no E-stop, no error, project running"

    def _tm_held(self) -> str:
        """What makes TM's table read as a protective stop."""
        assert isinstance(self.arm, TMEthernetArm)
        table = self.arm.latest_table
        if table is None:
            return "protective stop"
        missing = table.missing_safety_items
        why = [w for w, on in (("Safeguard_A triggered", table.safeguard is True),
                               ("Robot_Link 0", table.robot_link is False),
                               (f"table lacks {', '.join(missing)}", bool(missing))) if on]
        return f"protective stop ({'; '.join(why)})" if why else "protective stop"

    def _timing(self) -> str:
        assert self.arm is not None
        steps = []
        for _ in range(self.s.timing_steps):
            t0 = time.perf_counter()
            self.arm.read_state()
            if self.sensor is not None and self.sensor.connected:
                self.sensor.read()
            steps.append(time.perf_counter() - t0)
        ms = np.asarray(steps) * 1e3
        budget = self.s.slow_fraction * self.s.period_s * 1e3
        p50, p95 = float(np.percentile(ms, 50)), float(np.percentile(ms, 95))
        tail = self.s.tail_periods * self.s.period_s * 1e3
        detail = (f"state and wrench read in p50 {p50:.2f} ms (limit {budget:.1f}), p95 {p95:.2f} ms (limit "
                  f"{tail:g} ms)")
        # The median must leave the loop its compute budget; an occasional late step is absorbed by the
        # robot side's jitter buffer, so the tail is held to `tail_periods`.
        assert p50 <= budget and p95 <= tail, detail
        return detail

    # ------------------------------------------------------------------------------------ the sensor
    def _sensor_connect(self) -> str:
        assert self.sensor is not None
        self._before = self.sensor.counters()
        self.sensor.connect()
        cfg = self.sensor.config
        detail = f"{cfg.port} answers ({cfg.mode} mode)"
        if cfg.mode == "poll":
            # What a lost reply costs depends on it (docs/real-cell.md, section 3): one reading, or ~0.1 s.
            detail += (", record number steps by one per reply" if self.sensor.counter_steps_by_one else
                       ", record number does not step by one per reply (a lost reply costs ~0.1 s of readings)")
        timer = self.sensor.adapter_latency_ms()
        if timer is not None:
            # A USB adapter holds a short reply back up to its latency timer: longer than the reply timeout, a
            # read finds nothing in time.
            detail += f", USB adapter latency timer {timer} ms"
            assert timer * 1e-3 <= cfg.timeout_s, (
                f"{detail}, longer than the {cfg.timeout_s * 1e3:g} ms reply timeout (the port did not take the "
                "low-latency request)")
        return detail

    def _sensitivities(self) -> str:
        assert self.sensor is not None
        have = np.asarray(self.sensor.sensitivities.as_array(), float)
        nominal = np.asarray(self.sensor.config.nominal_sensitivities.as_array(), float)
        worst = float(np.max(np.abs(have / nominal - 1.0)))
        values = f"{np.round(have, 3).tolist()} against nominal {np.round(nominal, 1).tolist()}"
        assert worst <= SENSITIVITY_REL, f"sensitivities {values}: {worst:.0%} off"
        source = self.sensor.sensitivities_source
        note = "" if source == "sensor" else " (the sensor did not answer `p`: the configured values are used)"
        return f"{values}, within {worst:.1%}{note}"

    def _tare(self) -> str:
        assert self.sensor is not None
        self.sensor.tare(self.sensor.config.tare_samples)
        forces = []
        deadline = time.monotonic() + self.s.tare_s
        while time.monotonic() < deadline:
            forces.append(self.sensor.read().force)
            time.sleep(self.s.period_s)
        f = np.asarray(forces)
        ok = np.all(np.isfinite(f), axis=1)
        assert ok.mean() >= 0.5, f"{int((~ok).sum())} of {len(f)} readings empty: no stable reading to judge"
        f = f[ok]
        q = max(1, len(f) // 4)
        drift = float(np.linalg.norm(f[-q:].mean(axis=0) - f[:q].mean(axis=0)))
        noise = float(np.std(np.linalg.norm(f, axis=1)))
        offset = float(np.linalg.norm(f.mean(axis=0)))
        detail = (f"over {self.s.tare_s:g} s after a tare: drift {drift:.2f} N (limit {TARE_DRIFT_N}), noise "
                  f"{noise:.2f} N (limit {TARE_NOISE_N}), mean |F| {offset:.2f} N")
        assert drift <= TARE_DRIFT_N and noise <= TARE_NOISE_N and offset <= TARE_DRIFT_N + 2 * noise, detail
        return detail

    def _line(self) -> str:
        assert self.sensor is not None
        before = getattr(self, "_before", {})
        if not any(c.name == "sensor_tare_stability" and c.status == "pass" for c in self.checks):
            # The tare's window failed early: read for the same time so the line has records to judge.
            deadline = time.monotonic() + self.s.tare_s
            while time.monotonic() < deadline:
                self.sensor.read()
        after = self.sensor.counters()
        lost = {k: after[k] - before.get(k, 0) for k in ("records_rejected", "timeouts", "records_stale")}
        good = after["records_ok"] - before.get("records_ok", 0)
        total = good + lost["records_rejected"] + lost["timeouts"]
        share = (lost["records_rejected"] + lost["timeouts"]) / total if total else 1.0
        detail = (f"{good} good records, {lost['records_rejected']} corrupted, {lost['timeouts']} timed out "
                  f"({share:.1%} lost; limit {READ_LOSS:.0%})")
        assert total > 0 and share <= READ_LOSS, detail
        return detail


def measure_state_rate(read: Callable[[], Any], window_s: float, poll_s: float) -> tuple[float, float, int]:
    """(rate in Hz, interval jitter p95 - p50 in ms, samples) of a state stream whose `seq` counts the
    device's samples: polled for `window_s`, the rate from the counter's advance between its first and last
    change (a device that sends several samples at once advances it by several)."""
    last = read().seq
    changes: list[tuple[float, int]] = []
    deadline = time.monotonic() + window_s
    while time.monotonic() < deadline:
        state = read()
        if state.seq != last:
            changes.append((time.monotonic(), state.seq))
            last = state.seq
        time.sleep(poll_s)
    if len(changes) < 2:
        raise AssertionError(f"the state counter advanced {len(changes)} time(s) in {window_s:g} s: no stream")
    t = np.array([c[0] for c in changes])
    seq = np.array([c[1] for c in changes], dtype=float)
    samples = int(seq[-1] - seq[0])
    rate = samples / max(float(t[-1] - t[0]), 1e-9)
    per_sample = np.diff(t) / np.maximum(np.diff(seq), 1.0)
    jitter_ms = float(np.percentile(per_sample, 95) - np.percentile(per_sample, 50)) * 1e3
    return rate, jitter_ms, samples


def format_table(checks: list[Check]) -> str:
    """The checks as a plain-text table: name, PASS / FAIL / SKIPPED, what was seen; a failed check's fix
    on the line below it."""
    width = max(len(c.name) for c in checks) if checks else 10
    lines = [f"{'check':<{width}}  {'result':<7}  detail", f"{'-' * width}  {'-' * 7}  {'-' * 40}"]
    for c in checks:
        lines.append(f"{c.name:<{width}}  {c.status.upper():<7}  {c.detail}")
        if c.status == "fail" and c.fix:
            lines.append(f"{'':<{width}}  {'':<7}  what to do: {c.fix}")
    return "\n".join(lines)


def report(checks: list[Check], cell: str) -> dict[str, Any]:
    """The doctor's summary: passed, the failing checks' names, every check."""
    failed = [c.name for c in checks if c.status == "fail"]
    return {"cell": cell, "passed": not failed, "failed": failed,
            "skipped": [c.name for c in checks if c.status == "skipped"],
            "checks": [{**asdict(c), "passed": c.status == "pass"} for c in checks]}
