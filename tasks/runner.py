"""Runs one task on an opened cell: safety, control loop, recording, summary and plot."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cell.config import CellConfig
from cell.control.loop import ControlLoop, ForceSource, OpenCell, Task
from cell.control.safety import SafetyMonitor
from cell.control.signals import interrupts_deferred
from cell.data.recorder import Recorder, new_run_dir, read_log
from cell.model.robot import RobotModel
from cell.view.report import plot_force_run
from drivers.configio import to_plain
from drivers.interfaces import ArmState, Wrench
from tasks.base import SETUP_STATES

log = logging.getLogger(__name__)

# A touch: the F/T sensor's force over this (N) in a touch state; samples this close (periods) are one touch,
# and the virtual sensor's peak is looked for from TOUCH_BEFORE periods before it to TOUCH_AFTER after (the
# joint torques reach the controller a period late and the observer takes a few more to follow).
TOUCH_N = 5.0
TOUCH_GAP = 5
TOUCH_BEFORE, TOUCH_AFTER = 2, 8
# The virtual sensor sees a touch when its peak is within this factor of the F/T sensor's.
TOUCH_RATIO_BAND = (0.5, 2.0)


class GroundTruthTap:
    """Wraps the ground-truth F/T source: pairs each cycle's measured wrench with the virtual one the
    task used that cycle (the loop reads the task's source first), the task's state, and whether the F/T
    sensor has been zeroed yet (its tare)."""

    def __init__(self, truth: ForceSource, virtual: ForceSource, task: Task) -> None:
        self.truth = truth
        self.virtual = virtual
        self.task = task
        self.name = truth.name
        self.states: list[str] = []
        self.tared: list[bool] = []
        self.measured: list[np.ndarray] = []
        self.estimated: list[np.ndarray] = []
        self._tared = False

    def read(self, state: ArmState) -> Wrench:
        w = self.truth.read(state)
        last = getattr(self.virtual, "last", None)
        if last is not None:
            self.states.append(self.task.state_name)
            self.tared.append(self._tared)
            self.measured.append(w.vector)
            self.estimated.append(last.vector)
        return w

    def rebias(self) -> None:
        self.truth.rebias()
        self._tared = True

    def summary(self, task_summary: dict[str, Any]) -> dict[str, Any]:
        """Virtual against measured, and the measured force against the setpoint, on the working samples."""
        if not self.measured:
            return {}
        working, touching = working_states(self.task), tuple(getattr(self.task, "touch_states", ()))
        # The states scored go into the summary: `replay` scores the recording over the same ones.
        return {"scored_states": list(working), "touch_states": list(touching),
                **virtual_vs_sensor(self.states, np.asarray(self.measured), np.asarray(self.estimated), working,
                                    task_summary, self.tared, touch_states=touching)}


def working_states(task: Any) -> tuple[str, ...]:
    """The states a task declares as working (tasks/base.py MachineTask.working_states)."""
    return tuple(getattr(task, "working_states", ()))


def touches(force: np.ndarray, touching: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) sample of each touch: the F/T force over TOUCH_N where `touching` allows, samples
    within TOUCH_GAP periods joined (a stiff contact bounces: the force drops to zero between impacts)."""
    out: list[tuple[int, int]] = []
    for i in np.flatnonzero(touching & (force > TOUCH_N)):
        if out and i - out[-1][1] <= TOUCH_GAP:
            out[-1] = (out[-1][0], int(i))
        else:
            out.append((int(i), int(i)))
    return out


def touch_figures(states: Sequence[str] | np.ndarray, meas: np.ndarray, est: np.ndarray, touch_states: Sequence[str],
                  tared: np.ndarray) -> dict[str, Any]:
    """How much of each touch the virtual sensor saw: its peak pressing force (Fz, along the tool, as the
    tasks read a touch) over the F/T sensor's, at the touches in the task's touch states after the tare.
    `touch_peak_ratio` compares the largest of each; a ratio outside TOUCH_RATIO_BAND is named in `warnings`."""
    if not touch_states:
        return {}
    f_meas = np.nan_to_num(meas[:, 2], nan=-np.inf)
    f_est = np.nan_to_num(est[:, 2], nan=-np.inf)
    found = touches(f_meas, np.isin(np.asarray(states), list(touch_states)) & tared)
    if not found:
        return {"touches": 0}
    n = len(f_meas)
    v_peak = max(float(np.max(f_est[max(0, a - TOUCH_BEFORE):min(n, b + TOUCH_AFTER + 1)])) for a, b in found)
    s_peak = max(float(np.max(f_meas[a:b + 1])) for a, b in found)
    ratio = v_peak / s_peak
    out: dict[str, Any] = {"touches": len(found), "touch_virtual_peak_n": v_peak, "touch_sensor_peak_n": s_peak,
                           "touch_peak_ratio": ratio}
    lo, hi = TOUCH_RATIO_BAND
    if not lo <= ratio <= hi:
        out["warnings"] = [f"the virtual sensor saw {ratio:.2f} of the touches' peak force ({v_peak:.1f} N against "
                           f"the F/T sensor's {s_peak:.1f} N; within {lo:g}-{hi:g} expected)"]
    return out


def virtual_vs_sensor(states: Sequence[str], meas: np.ndarray, est: np.ndarray,
                      working: Sequence[str], task_summary: dict[str, Any],
                      tared: Sequence[bool] | np.ndarray | None = None,
                      touch_states: Sequence[str] = ()) -> dict[str, Any]:
    """The run's virtual-vs-sensor figures from per-cycle states (as the force sources read), measured and
    estimated wrenches (n, 6), the task's working states and whether the F/T sensor was zeroed yet; `replay`
    calls it on a recording to score another observer or mapping.

    Names: `virtual_vs_sensor_*` is the estimate's error (virtual against the F/T sensor), over the working
    states after the tare; `force_tracking_*` is the regulated force's error against its setpoint as the
    F/T sensor measured it (`force_tracking_virtual_mae_n`: as the virtual sensor in the loop saw it)."""
    st = np.asarray(states)
    done_tare = np.ones(len(st), bool) if tared is None else np.asarray(tared, bool)
    rows = np.isin(st, list(working)) & done_tare
    # A missing reading (NaN: a timed-out read of either source) is no sample.
    rows &= np.all(np.isfinite(meas), axis=1) & np.all(np.isfinite(est), axis=1)
    out: dict[str, Any] = {"virtual_vs_sensor_samples": int(rows.sum())}
    if rows.any():
        err = est[rows] - meas[rows]
        out.update({
            "virtual_vs_sensor_fz_mae_n": float(np.mean(np.abs(err[:, 2]))),
            "virtual_vs_sensor_fz_mean_error_n": float(np.mean(err[:, 2])),
            "virtual_vs_sensor_fz_std_n": float(np.std(err[:, 2])),
            "virtual_vs_sensor_mx_mae_nm": float(np.mean(np.abs(err[:, 3]))),
            "virtual_vs_sensor_my_mae_nm": float(np.mean(np.abs(err[:, 4]))),
        })
    out.update(touch_figures(st, meas, est, touch_states, done_tare))
    setpoint = task_summary.get("force_setpoint_n")
    if rows.any() and setpoint is not None and "force_tracking_mae_n" in task_summary:
        # With the virtual sensor in the loop the task scores what it saw; the cell's figure is
        # what the F/T sensor measured against the setpoint.
        e = meas[rows, 2] - float(setpoint)
        out.update(force_tracking_virtual_mae_n=task_summary["force_tracking_mae_n"],
                   force_tracking_mae_n=float(np.mean(np.abs(e))), force_tracking_std_n=float(np.std(e)),
                   force_tracking_max_abs_error_n=float(np.max(np.abs(e))), force_mean_n=float(np.mean(meas[rows, 2])))
    if "peak_force_n" in task_summary:
        # Likewise the peak: the task's is what its force source read, the cell's what the sensor felt
        # (after the tare, outside the set-up states, as the peg bench scores it).
        working_now = ~np.isin(st, SETUP_STATES) & done_tare & np.all(np.isfinite(meas[:, :3]), axis=1)
        if working_now.any():
            out.update(virtual_peak_force_n=task_summary["peak_force_n"],
                       peak_force_n=float(np.max(np.linalg.norm(meas[working_now, :3], axis=1))))
    return out


def expect_touches(force: Any, task: Any) -> None:
    """Tell a virtual sensor when `task` expects a touch (its `touch_states`): it reads fast there.  The
    state is the one the task is in as the loop reads the force, before the task's step."""
    touching = tuple(getattr(task, "touch_states", ()))
    if hasattr(force, "contact_expected") and touching:
        force.contact_expected = lambda: task.state_name in touching


def force_limits(task: Any, cfg: CellConfig) -> dict[str, list[tuple[str, float]]]:
    """The limits the plot and the Rerun view draw, by wrench axis: the task's own (its `max_force_n` on Fz,
    `max_moment_nm` on Mx and My) and the cell's safety limits (tool force and torque)."""
    out: dict[str, list[tuple[str, float]]] = {"fz": [], "mx": [], "my": []}
    tcfg = getattr(task, "cfg", None)
    force, moment = getattr(tcfg, "max_force_n", None), getattr(tcfg, "max_moment_nm", None)
    if force is not None:
        out["fz"].append(("task limit", float(force)))
    if moment is not None:
        for axis in ("mx", "my"):
            out[axis].append(("task limit", float(moment)))
    out["fz"].append(("cell limit", float(cfg.safety.max_tool_force_n)))
    for axis in ("mx", "my"):
        out[axis].append(("cell limit", float(cfg.safety.max_tool_torque_nm)))
    return out


def run_task(
    task: Task,
    cell: OpenCell,
    cfg: CellConfig,
    robot: RobotModel,
    max_duration_s: float,
    record: bool = True,
    extra_summary: dict[str, Any] | None = None,
    view: Any | None = None,
) -> dict[str, Any]:
    """Run `task` on `cell`; `view` (a cell.rerun_view.RunView) streams the rows live as they are logged."""
    recorder = None
    run_dir: Path | None = None
    if record:
        run_dir = new_run_dir(Path(cfg.recording.directory), task.name)
        recorder = Recorder(run_dir, cfg.recording.chunk_rows)
        recorder.write_config(to_plain(cfg))
        log.info("recording to %s", run_dir)
    safety = SafetyMonitor(cfg.safety, robot, cfg.loop.period_s)
    expect_touches(cell.force, task)
    tap = GroundTruthTap(cell.ground_truth, cell.force, task) if cell.ground_truth is not None else None
    guard = cell.guard_for(task, cfg.safety.max_tool_force_n)
    loop = ControlLoop(
        cell.arm, cell.force, task, safety, cell.ticker, recorder, cfg.loop.period_s, max_duration_s,
        cfg.loop.slow_cycle_fraction, ground_truth=tap, guard=guard, on_row=view.row if view is not None else None,
    )
    result = loop.run()
    # The arm is stopped: an interrupt now waits for the summary and the plot.
    with interrupts_deferred():
        summary: dict[str, Any] = dict(task.summary())
        if result.outcome != "done":
            summary["outcome"] = "failed" if result.outcome == "failed" else result.outcome
            summary["reason"] = summary.get("reason") or result.reason
        summary.update(
            cell=cell.kind,
            force_source=cell.force.name,
            cycles=result.cycles,
            sim_time_s=result.sim_time_s,
            wall_time_s=result.wall_time_s,
            real_time_factor=result.sim_time_s / result.wall_time_s if result.wall_time_s > 0 else None,
            timing=result.timing,
            safety_stop=result.outcome in ("safety_stop", "collision"),
            collision=result.collision if result.collision is not None else {"enabled": False},
        )
        if tap is not None:
            figures = tap.summary(summary)
            warnings = list(summary.get("warnings", [])) + list(figures.pop("warnings", []))
            summary.update(figures)
            if warnings:
                summary["warnings"] = warnings
                for w in warnings:
                    log.warning("%s", w)
        source_summary = getattr(cell.force, "summary", None)
        if callable(source_summary):
            summary.update(source_summary())
        if extra_summary:
            summary.update(extra_summary)
        if view is not None:
            outcome, reason = str(summary.get("outcome", "")), str(summary.get("reason") or "")
            view.event(f"outcome: {outcome}" + (f" ({reason})" if reason else ""), warn=outcome != "done")
        if recorder is not None and run_dir is not None:
            summary["run_dir"] = str(run_dir)
            limits = force_limits(task, cfg)
            if recorder.rows_written:
                try:
                    table = read_log(run_dir)
                    # A task may summarise its own log (e.g. virtual-vs-measured wrench errors) and draw
                    # its own figure; the default is the normal force against its setpoint.
                    log_summary = getattr(task, "log_summary", None)
                    if callable(log_summary):
                        summary.update(log_summary(table))
                    plot = getattr(task, "plot_run", None)
                    title = f"{task.name} on the {cell.kind} cell: {summary['outcome']}"
                    if callable(plot):
                        png = plot(table, run_dir / "plot.png", title, limits)
                    else:
                        png = plot_force_run(table, run_dir / "plot.png", title, force_label=(
                            "Fz virtual sensor (in the loop)" if cell.force.name == "virtual"
                            else "Fz used by the controller"), limits=limits)
                    summary["plot"] = str(png)
                except Exception as exc:  # a plot must never lose the recording or the summary
                    log.error("could not draw the plot: %s", exc)
                _write_rrd(run_dir, robot, summary, limits)
            recorder.write_summary(summary)
    return summary


def _write_rrd(run_dir: Path, robot: RobotModel, summary: dict[str, Any],
               limits: dict[str, list[tuple[str, float]]]) -> None:
    """The step log's Rerun copy beside it (`recording.rrd`), named in the summary."""
    try:
        from cell.view.rerun_view import write_rrd

        summary["rerun"] = str(write_rrd(run_dir, read_log(run_dir), robot, summary, limits))
    except Exception as exc:  # the Rerun copy must never lose the recording or the summary
        log.error("could not write the Rerun recording: %s", exc)
