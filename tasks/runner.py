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

# The states in which a task regulates its force: where virtual and measured are scored (tasks may
# declare `regulated_states` themselves; without either, every sample in contact counts).
REGULATED_STATES: dict[str, tuple[str, ...]] = {"wipe": ("wipe",)}
CONTACT_N = 5.0


class GroundTruthTap:
    """Wraps the ground-truth F/T source: pairs each cycle's measured wrench with the virtual one the
    task used that cycle (the loop reads the task's source first) and the task's state."""

    def __init__(self, truth: ForceSource, virtual: ForceSource, task: Task) -> None:
        self.truth = truth
        self.virtual = virtual
        self.task = task
        self.name = truth.name
        self.states: list[str] = []
        self.measured: list[np.ndarray] = []
        self.estimated: list[np.ndarray] = []

    def read(self, state: ArmState) -> Wrench:
        w = self.truth.read(state)
        last = getattr(self.virtual, "last", None)
        if last is not None:
            self.states.append(self.task.state_name)
            self.measured.append(w.vector)
            self.estimated.append(last.vector)
        return w

    def rebias(self) -> None:
        self.truth.rebias()

    def summary(self, task_summary: dict[str, Any]) -> dict[str, Any]:
        """Virtual against measured, and the measured force against the setpoint, on regulated samples."""
        if not self.measured:
            return {}
        regulated = getattr(self.task, "regulated_states", REGULATED_STATES.get(self.task.name))
        return virtual_vs_sensor(self.states, np.asarray(self.measured), np.asarray(self.estimated), regulated,
                                 task_summary)


def virtual_vs_sensor(states: Sequence[str], meas: np.ndarray, est: np.ndarray,
                      regulated: Sequence[str] | None, task_summary: dict[str, Any]) -> dict[str, Any]:
    """The run's virtual-vs-sensor figures from per-cycle states (as the force sources read), measured and
    estimated wrenches (n, 6); `replay` calls it on a recording to score another observer or mapping."""
    if regulated:
        rows = np.isin(np.asarray(states), list(regulated))
    else:
        rows = np.linalg.norm(meas[:, :3], axis=1) > CONTACT_N
    # A missing reading (NaN: a timed-out read of either source) is no sample.
    rows &= np.all(np.isfinite(meas), axis=1) & np.all(np.isfinite(est), axis=1)
    if not rows.any():
        return {"virtual_vs_sensor_samples": 0}
    err = est[rows] - meas[rows]
    out: dict[str, Any] = {
        "virtual_vs_sensor_samples": int(rows.sum()),
        "virtual_vs_sensor_fz_mae_n": float(np.mean(np.abs(err[:, 2]))),
        "virtual_vs_sensor_fz_mean_error_n": float(np.mean(err[:, 2])),
        "virtual_vs_sensor_fz_std_n": float(np.std(err[:, 2])),
        "virtual_vs_sensor_mx_mae_nm": float(np.mean(np.abs(err[:, 3]))),
        "virtual_vs_sensor_my_mae_nm": float(np.mean(np.abs(err[:, 4]))),
    }
    setpoint = task_summary.get("force_setpoint_n")
    if setpoint is not None and "force_mae_n" in task_summary:
        # With the virtual sensor in the loop the task scores what it saw; the cell's figure is
        # what the F/T sensor measured against the setpoint.
        e = meas[rows, 2] - float(setpoint)
        out.update(virtual_force_mae_n=task_summary["force_mae_n"], force_mae_n=float(np.mean(np.abs(e))),
                   force_std_n=float(np.std(e)), force_max_abs_error_n=float(np.max(np.abs(e))),
                   force_mean_n=float(np.mean(meas[rows, 2])))
    if "peak_force_n" in task_summary:
        # Likewise the peak: the task's is what its force source read, the cell's what the sensor felt
        # (from the first contact on, as the peg bench scores it).
        working = ~np.isin(np.asarray(states), SETUP_STATES) & np.all(np.isfinite(meas[:, :3]), axis=1)
        if working.any():
            out.update(virtual_peak_force_n=task_summary["peak_force_n"],
                       peak_force_n=float(np.max(np.linalg.norm(meas[working, :3], axis=1))))
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
            summary.update(tap.summary(summary))
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
                        png = plot(table, run_dir / "plot.png", title)
                    else:
                        png = plot_force_run(table, run_dir / "plot.png", title, force_label=(
                            "Fz virtual sensor (in the loop)" if cell.force.name == "virtual"
                            else "Fz used by the controller"))
                    summary["plot"] = str(png)
                except Exception as exc:  # a plot must never lose the recording or the summary
                    log.error("could not draw the plot: %s", exc)
                _write_rrd(run_dir, robot, summary)
            recorder.write_summary(summary)
    return summary


def _write_rrd(run_dir: Path, robot: RobotModel, summary: dict[str, Any]) -> None:
    """The step log's Rerun copy beside it (`recording.rrd`), named in the summary."""
    try:
        from cell.view.rerun_view import write_rrd

        summary["rerun"] = str(write_rrd(run_dir, read_log(run_dir), robot, summary))
    except Exception as exc:  # the Rerun copy must never lose the recording or the summary
        log.error("could not write the Rerun recording: %s", exc)
