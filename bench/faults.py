"""`main.py bench faults`: the fault-injection matrix over the emulated cell (real drivers, emulators):
per fault, whether the loop stopped the arm, how many control periods after the injection, and whether
the recording reads back."""

from __future__ import annotations

import contextlib
import logging
import math
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cell.config import CellConfig
from cell.control.loop import Command, ControlLoop, Observation
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.data.recorder import Recorder, read_log
from cell.model.robot import RobotModel
from drivers.errors import DriverError
from drivers.interfaces import Lifecycle
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.modbus import TM5ModbusArm
from sim.emulated import EmulatedCell

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Fault:
    """One row of the matrix: the emulator command and the stop it must cause within `budget_periods`."""

    name: str
    command: str
    expect: str  # the loop outcome that counts as detected: "fault" or "safety_stop"
    budget_periods: int
    words: str  # a word the stop's reason must contain (what was detected)


def fault_matrix(cfg: CellConfig, stale_after_s: float) -> list[Fault]:
    p = cfg.loop.period_s
    stale = int(math.ceil(stale_after_s / p)) + 3
    invalid = cfg.safety.max_sensor_invalid_cycles + 2
    return [
        Fault("link_loss", "drop_link 1.5", "fault", 2, "TM5"),
        Fault("stale_robot_data", "freeze 2", "fault", stale, "stale"),
        Fault("late_replies", "delay 50 1.0", "fault", 2, "TM5"),
        Fault("modbus_exceptions", "exceptions 1.0", "fault", 2, "TM5"),
        Fault("sensor_silent", "sensor drop 1.0", "safety_stop", invalid, "force"),
        Fault("sensor_garbage", "sensor garbage 1.0", "safety_stop", invalid, "force"),
        # Replies 80 ms late against the emulated cell's 50 ms sensor timeout: each answers an earlier
        # request, so every one is discarded as stale (`stale_records_discarded`), never taken as new, and
        # the readings go missing until the safety stop.
        Fault("sensor_late_replies", "sensor delay 80", "safety_stop", invalid, "force"),
        # Not an emulator command: another controller tries to arm the arm this run drives.  Detected when it
        # is refused naming the holder (the control lease) and this run goes on to its end undisturbed.
        Fault("second_host", SECOND_HOST, "done", 0, "held by another controller"),
    ]


SECOND_HOST = "second host"


class _SecondHost:
    """Another controller's driver arming the emulated arm, from its own thread (a refusal takes arm_timeout_s)."""

    def __init__(self, holder: EmulatedCell, robot: RobotModel, period_s: float) -> None:
        self.holder, self.robot, self.period_s = holder, robot, period_s
        self.refusal = ""
        self._thread: threading.Thread | None = None

    def inject(self, command: str) -> None:
        self._thread = threading.Thread(target=self._try_to_arm, name="second-host", daemon=True)
        self._thread.start()

    def _try_to_arm(self) -> None:
        config = self.holder.arm.config
        assert isinstance(config, TM5ModbusConfig), "the second-host case is the Modbus route's control lease"
        arm = TM5ModbusArm(config, self.robot.limits, self.period_s)
        try:
            arm.connect()
            arm.arm()
        except DriverError as exc:
            self.refusal = str(exc)
        finally:
            with contextlib.suppress(DriverError):
                arm.disconnect()

    def join(self) -> str:
        """The refusal's message ('' when it was not refused)."""
        if self._thread is not None:
            self._thread.join(10.0)
        return self.refusal


class _HoldAndInject:
    """Holds the arm still; at cycle `at` sends the fault command to the emulator process."""

    name = "fault-injection"

    def __init__(self, inject: Any, command: str, at: int, cycles: int) -> None:
        self.inject, self.command, self.at, self.cycles = inject, command, at, cycles
        self._done = False
        self.aborted = ""
        self.injected_cycle: int | None = None

    @property
    def done(self) -> bool:
        return self._done

    @property
    def state_name(self) -> str:
        return "hold"

    def step(self, obs: Observation) -> Command:
        if obs.cycle == self.at:
            self.inject(self.command)
            self.injected_cycle = obs.cycle
        if obs.cycle >= self.cycles:
            self._done = True
        return Command(q=obs.q_cmd, log={"injected": float(self.injected_cycle is not None)})

    def abort(self, reason: str) -> None:
        self.aborted = reason
        self._done = True

    def summary(self) -> dict[str, Any]:
        return {"outcome": "done"}


def bench_faults(cfg: CellConfig, robot: RobotModel, inject_at: int = 60, cycles: int = 400,
                 only: list[str] | None = None) -> dict[str, Any]:
    """Each fault on a fresh emulated cell: `detected` (the expected stop, for the expected reason),
    `detection_periods` (cycles from the injection to the stop), `within_budget`, `arm_stopped`
    (not left ARMED), `recording_ok` (the step log reads back, every cycle in it).  The injection is a
    line to the emulator process, in effect once acknowledged, within the cycle that sends it."""
    probe = EmulatedCell(cfg, robot.limits, scene_kind="free")
    stale_after = probe.arm.config.stale_after_s
    probe.close()
    matrix = [f for f in fault_matrix(cfg, stale_after) if only is None or f.name in only]
    rows: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench-faults-") as tmp:
        for fault in tqdm(matrix, desc="bench faults", unit="fault"):
            holder = EmulatedCell(cfg, robot.limits, scene_kind="free")
            second = _SecondHost(holder, robot, cfg.loop.period_s) if fault.command == SECOND_HOST else None
            try:
                cell = holder.open()
                task = _HoldAndInject(second.inject if second else holder.inject, fault.command, inject_at, cycles)
                run_dir = Path(tmp) / fault.name
                rec = Recorder(run_dir, chunk_rows=16)
                loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s),
                                   cell.ticker, rec, cfg.loop.period_s, cycles * cfg.loop.period_s + 10.0)
                t0 = time.perf_counter()
                result = loop.run()
                wall = time.perf_counter() - t0
                raise_if_interrupted(result.outcome)
                arm_state = holder.arm.lifecycle
                stale = getattr(holder.sensor, "records_stale", None)
                refusal = second.join() if second else ""
            finally:
                holder.close()
            try:
                rows_logged = read_log(run_dir).num_rows
            except Exception:  # the point is whether it reads: any failure is a "no"
                rows_logged = -1
            after = result.cycles - inject_at if task.injected_cycle is not None else None
            detected = result.outcome == fault.expect and fault.words.lower() in result.reason.lower()
            if second is not None:  # nothing to stop: the refusal is the detection
                after, detected = None, result.outcome == fault.expect and fault.words in refusal
            within = bool(detected and (second is not None or (after is not None and after <= fault.budget_periods)))
            rows[fault.name] = {
                "command": fault.command, "outcome": result.outcome, "reason": result.reason,
                "detected": detected, "detection_periods": after,
                "detection_ms": None if after is None else round(after * cfg.loop.period_s * 1000, 1),
                "budget_periods": fault.budget_periods,
                "within_budget": within,
                "arm_stopped": arm_state is not Lifecycle.ARMED,
                # every cycle logged, plus the sample that tripped a safety stop
                "recording_ok": rows_logged in (result.cycles, result.cycles + 1),
                "stale_records_discarded": stale,
                "wall_s": round(wall, 2),
                **({"refusal": refusal} if second is not None else {}),
            }
            log.info("fault %s: %s after %s periods (%s)", fault.name, result.outcome, after, result.reason)
    failures = [k for k, r in rows.items()
                if not (r["detected"] and r["within_budget"] and r["arm_stopped"] and r["recording_ok"])]
    link = rows.get("link_loss", {})
    return {"faults": rows, "failures": len(failures), "failed": failures,
            "all_detected": all(r["detected"] for r in rows.values()),
            "link_loss_detection_periods": link.get("detection_periods"),
            "max_detection_ms": max((r["detection_ms"] or 0.0) for r in rows.values()) if rows else None,
            "inject_at_cycle": inject_at, "period_ms": cfg.loop.period_s * 1000,
            "detection_periods_median": float(np.median([r["detection_periods"] for r in rows.values()
                                                         if r["detection_periods"] is not None] or [np.nan]))}
