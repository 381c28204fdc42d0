"""The fixed-period control loop: read state -> estimate wrench -> detect collisions -> decide -> safety -> command
-> record.

The loop owns safety and shutdown: a safety limit, a driver fault, any exception or Ctrl+C stops the
arm and closes the recording before the loop returns (or re-raises an unexpected error).
"""

from __future__ import annotations

import gc
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from cell.collision.guard import CollisionStop, ContactGuard, Reaction
from cell.control.priority import raised_priority
from cell.control.safety import SafetyMonitor
from cell.control.signals import Terminated
from cell.data.recorder import Recorder
from drivers.errors import CellError, DriverError, SafetyStopError
from drivers.interfaces import Arm, ArmState, Lifecycle, Wrench

log = logging.getLogger(__name__)


class ForceSource(Protocol):
    """Where the task's tool wrench comes from: the F/T sensor, or (later) the virtual sensor."""

    name: str

    def read(self, state: ArmState) -> Wrench: ...

    def rebias(self) -> None:
        """Re-zero at the current state (arm at rest, no contact)."""


class Ticker(Protocol):
    """Paces the loop: lock-step with a simulator (advances it) or the wall clock (sleeps)."""

    def start(self) -> None: ...

    def wait(self) -> None: ...


@dataclass
class Observation:
    t: float  # s since the loop started
    cycle: int
    state: ArmState
    wrench: Wrench
    q_cmd: np.ndarray  # last target actually sent


@dataclass
class Command:
    q: np.ndarray  # joint-position target
    log: dict[str, float | str] = field(default_factory=dict)  # extra columns for the recording
    rebias_force: bool = False  # re-zero the force source before the next cycle


class Task(Protocol):
    name: str

    @property
    def done(self) -> bool: ...

    @property
    def state_name(self) -> str: ...

    def step(self, obs: Observation) -> Command: ...

    def abort(self, reason: str) -> None: ...

    def summary(self) -> dict[str, Any]: ...


@dataclass
class OpenCell:
    """The devices of a cell, opened and ready: what a task runs on."""

    kind: str
    arm: Arm
    force: ForceSource  # the source the task regulates with
    ticker: Ticker
    ground_truth: ForceSource | None = None  # the F/T sensor, when the task uses another source
    # Builds the collision guard for a task: (task name, its contact force limit [N]) -> guard.
    guard: Callable[[str, float], ContactGuard | None] | None = None

    def guard_for(self, task: Any, contact_limit_n: float) -> ContactGuard | None:
        """A fresh guard for `task` (`contact_limit_n` unless its collision settings name one), or None."""
        if self.guard is None:
            return None
        return self.guard(task.name, contact_limit_n)


class WallTicker:
    """Fixed-rate pacing: sleeps until the next period boundary; counts overruns.

    After an overrun the schedule is kept (the next cycle starts at once), so the host sends as many
    targets per second as the controller consumes and a jitter buffer on the robot side absorbs the
    lateness; only when more than `max_lag` periods behind does it give up and resynchronise.
    """

    def __init__(self, period: float, max_lag: int = 3) -> None:
        self.period = period
        self.max_lag = max_lag
        self.overruns = 0
        self.resyncs = 0
        self._next = 0.0

    def start(self) -> None:
        self._next = time.perf_counter() + self.period

    def wait(self) -> None:
        now = time.perf_counter()
        if now > self._next:
            self.overruns += 1
            if now - self._next > self.max_lag * self.period:
                self.resyncs += 1
                self._next = now + self.period
            else:
                self._next += self.period
            return
        time.sleep(self._next - now)
        self._next += self.period


@dataclass
class TimingStats:
    period: float
    slow_fraction: float
    samples: list[float] = field(default_factory=list)
    starts: list[float] = field(default_factory=list)  # perf_counter at each cycle's start

    def add(self, seconds: float) -> None:
        self.samples.append(seconds)

    def start(self, t0: float) -> None:
        self.starts.append(t0)

    def report(self) -> dict[str, float | int]:
        if not self.samples:
            return {"cycles": 0}
        a = np.asarray(self.samples) * 1e3
        slow = a > self.slow_fraction * self.period * 1e3
        return {
            "cycles": int(a.size),
            "compute_ms_p50": float(np.percentile(a, 50)),
            "compute_ms_p99": float(np.percentile(a, 99)),
            "compute_ms_max": float(a.max()),
            "slow_cycles": int(slow.sum()),
            "slow_cycle_threshold_ms": self.slow_fraction * self.period * 1e3,
            **self._periods(),
        }

    def _periods(self) -> dict[str, float]:
        """The time between cycle starts against the period: what a wall-clock cell's state samples and
        targets really were apart (in lock-step with a simulator, only the host's own pace)."""
        if len(self.starts) < 2:
            return {}
        p = np.diff(np.asarray(self.starts)) * 1e3
        jitter = np.abs(p - self.period * 1e3)
        return {"period_ms_p50": float(np.percentile(p, 50)), "period_ms_max": float(p.max()),
                "period_jitter_ms_p99": float(np.percentile(jitter, 99))}


@dataclass
class LoopResult:
    outcome: str  # "done", "failed", "safety_stop", "collision", "fault", "interrupted", "timeout", "error"
    reason: str
    cycles: int
    sim_time_s: float
    wall_time_s: float
    timing: dict[str, float | int]
    collision: dict[str, Any] | None = None  # the contact guard's summary, when one ran


class ControlLoop:
    def __init__(
        self,
        arm: Arm,
        force: ForceSource,
        task: Task,
        safety: SafetyMonitor,
        ticker: Ticker,
        recorder: Recorder | None,
        period: float,
        max_duration_s: float,
        slow_fraction: float = 0.8,
        ground_truth: ForceSource | None = None,
        guard: ContactGuard | None = None,
        on_row: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        self.arm = arm
        self.force = force
        self.task = task
        self.safety = safety
        self.ticker = ticker
        self.recorder = recorder
        self.period = period
        self.max_cycles = int(round(max_duration_s / period))
        self.timing = TimingStats(period, slow_fraction)
        self.ground_truth = ground_truth
        self.guard = guard
        self.on_row = on_row  # a live view of the rows (--view); it sees what the recording gets
        self._state_at_read = ""

    def run(self) -> LoopResult:
        """Run the task to its end; on a wall clock at raised priority where the OS permits it (the cell's driver
        threads too), with what the process held before it out of the garbage collector's way."""
        if not isinstance(self.ticker, WallTicker):
            return self._run()
        # A full collection walks every object the process holds (a long-lived process: thousands of model
        # arrays and more), which can take longer than a period; frozen, the loop's collections walk only
        # what it made itself.
        gc.freeze()
        try:
            with raised_priority(other_threads=True):
                return self._run()
        finally:
            gc.unfreeze()

    def _run(self) -> LoopResult:
        outcome, reason = "done", ""
        cycle = 0
        wall0 = time.perf_counter()
        q_cmd: np.ndarray | None = None
        state: ArmState | None = None
        wrench: Wrench | None = None
        truth: Wrench | None = None
        reaction: Reaction | None = None
        reaction_reason = ""
        try:
            self.arm.arm()
            q_cmd = self.arm.last_sent
            assert q_cmd is not None
            self.ticker.start()
            while not self.task.done or reaction is not None:
                if cycle >= self.max_cycles and reaction is None:
                    outcome, reason = "timeout", f"task did not finish within {self.max_cycles * self.period:.1f} s"
                    self.task.abort(reason)
                    break
                t0 = time.perf_counter()
                self.timing.start(t0)
                state = self.arm.read_state()
                # The state the force sources read in (the row's `state` is the one after the step):
                # `replay` scores its virtual-vs-sensor figures on it, as the run did.
                self._state_at_read = self.task.state_name
                wrench = self.force.read(state)
                truth = self.ground_truth.read(state) if self.ground_truth is not None else None
                obs = Observation(t=cycle * self.period, cycle=cycle, state=state, wrench=wrench, q_cmd=q_cmd)
                # The collision detector first: a collision that also trips a limit is reported as one.
                if self.guard is not None:
                    if reaction is None:
                        det = self.guard.observe(state, obs.t, cycle, self.task.state_name)
                        if det is not None:
                            reaction = self.guard.react(det, state)  # a stop raises CollisionStop
                            if reaction is not None:
                                reaction_reason = det.describe()
                                self.task.abort(f"{reaction_reason}: {reaction.kind}")
                                if reaction.stop_first:
                                    self.arm.stop()  # the controller's brake acts now; the reaction moves at rest
                    else:
                        self.guard.detector.update(state)
                if reaction is not None and reaction.braking(state):
                    # Stopped on purpose: nothing is sent (the state's status reports the stop) until at rest.
                    self._record(obs, Command(q=q_cmd, log={"reaction": "brake"}), q_cmd, False, truth,
                                 time.perf_counter() - t0)
                    cycle += 1
                    self.ticker.wait()
                    continue
                if reaction is not None and reaction.stop_first and self.arm.lifecycle is not Lifecycle.ARMED:
                    self.arm.arm()  # the stop is acknowledged: the reaction's own motion starts from rest
                    # A new motion: the commanded-speed check starts from here, not from the last target before
                    # the stop.
                    self.safety = SafetyMonitor(self.safety.cfg, self.safety.robot, self.safety.dt)
                    state = self.arm.read_state()  # its status read before the stop was acknowledged
                self.safety.check_state(state, truth if truth is not None else wrench)
                if reaction is not None:
                    assert self.guard is not None
                    cmd = Command(q=reaction.step(state, self.guard.reaction_force(state)),
                                  log={"reaction": reaction.kind})
                else:
                    cmd = self.task.step(obs)
                    if self.task.done:
                        self._record(obs, replace(cmd, rebias_force=False), q_cmd, False, truth,
                                     time.perf_counter() - t0)
                        break
                self.safety.check_command(cmd.q)
                sent = self.arm.send_target(cmd.q)
                q_cmd = sent.q
                if self.guard is not None:
                    self.guard.commanded(q_cmd)
                if cmd.rebias_force:
                    self.force.rebias()
                    if self.guard is not None:
                        self.guard.rebias()
                    if self.ground_truth is not None:
                        self.ground_truth.rebias()
                compute = time.perf_counter() - t0
                self.timing.add(compute)
                self._record(obs, cmd, q_cmd, sent.clipped, truth, compute)
                cycle += 1
                if reaction is not None and reaction.done:
                    outcome, reason = "collision", f"{reaction_reason}: {reaction.describe()}"
                    break
                self.ticker.wait()
            if outcome == "done" and self.task.summary().get("outcome") == "failed":
                outcome, reason = "failed", str(self.task.summary().get("reason", ""))
        except SafetyStopError as exc:
            outcome, reason = ("collision" if isinstance(exc, CollisionStop) else "safety_stop"), exc.reason
            self.task.abort(f"safety stop: {exc.reason}")
            log.error("safety stop: %s", exc.reason)
            if state is not None and wrench is not None and q_cmd is not None:  # the tripping sample
                obs = Observation(t=cycle * self.period, cycle=cycle, state=state, wrench=wrench, q_cmd=q_cmd)
                self._record(obs, Command(q=q_cmd), q_cmd, False, truth, 0.0)
        except DriverError as exc:
            outcome, reason = "fault", f"{exc.kind}: {exc}"
            self.task.abort(f"driver fault: {exc}")
            log.error("driver fault: %s", exc)
        except CellError as exc:
            outcome, reason = "error", str(exc)
            self.task.abort(str(exc))
            log.error("%s", exc)
        except KeyboardInterrupt as exc:
            outcome = "interrupted"
            reason = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted by the operator (Ctrl+C)"
            self.task.abort(reason)
            log.warning("interrupted: stopping the arm")
        finally:
            self._shutdown()
        timing = self.timing.report()
        if timing.get("slow_cycles"):
            log.warning(
                "%d of %d cycles took longer than %.1f ms to compute (p99 %.2f ms, max %.2f ms)",
                timing["slow_cycles"], timing["cycles"], timing["slow_cycle_threshold_ms"],
                timing["compute_ms_p99"], timing["compute_ms_max"],
            )
        overruns = getattr(self.ticker, "overruns", 0)
        if overruns:
            log.warning("the loop missed %d period deadlines", overruns)
        return LoopResult(
            outcome=outcome,
            reason=reason,
            cycles=cycle,
            sim_time_s=cycle * self.period,
            wall_time_s=time.perf_counter() - wall0,
            timing={**timing, "missed_deadlines": overruns, "resyncs": getattr(self.ticker, "resyncs", 0)},
            collision=self.guard.summary() if self.guard is not None else None,
        )

    def _shutdown(self, attempts: int = 3) -> None:
        for attempt in range(1, attempts + 1):
            try:
                self.arm.stop()
                break
            except Exception as exc:  # the arm's own watchdog stops it if we cannot reach it
                if attempt == attempts:
                    log.error("could not command a stop (%d attempts): %s", attempts, exc)
                else:
                    time.sleep(self.period)
        if self.recorder is not None:
            self.recorder.close()

    def _record(
        self,
        obs: Observation,
        cmd: Command,
        q_cmd: np.ndarray,
        clipped: bool,
        truth: Wrench | None,
        compute: float,
    ) -> None:
        if self.recorder is None and self.on_row is None:
            return
        s = obs.state
        row: dict[str, Any] = {"t": obs.t, "cycle": obs.cycle, "state": self.task.state_name,
                               "state_read": self._state_at_read, "force_rebias": bool(cmd.rebias_force)}
        for i in range(len(s.q)):
            row[f"q{i + 1}"] = float(s.q[i])
        for i in range(len(s.q)):
            row[f"dq{i + 1}"] = float(s.dq[i])
        for i in range(len(s.q)):
            row[f"tau{i + 1}"] = float(s.tau[i])
        for i in range(len(s.q)):
            row[f"q_cmd{i + 1}"] = float(q_cmd[i])
        row["clipped"] = clipped
        for k, v in zip(("fx", "fy", "fz", "mx", "my", "mz"), obs.wrench.vector, strict=True):
            row[k] = float(v)
        if truth is not None:
            for k, v in zip(("fx", "fy", "fz", "mx", "my", "mz"), truth.vector, strict=True):
                row[f"sensor_{k}"] = float(v)
        row.update(cmd.log)
        if self.guard is not None:
            row.update(self.guard.log_columns())
        row["compute_ms"] = compute * 1e3
        if self.recorder is not None:
            self.recorder.append(row)
        if self.on_row is not None:
            try:
                self.on_row(row)
            except Exception as exc:  # a viewer gone away must not stop the arm mid-task
                log.warning("live view stopped: %s", exc)
                self.on_row = None
