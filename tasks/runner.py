"""Runs one task on an opened cell: safety, control loop, recording, summary and plot."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from cell.config import CellConfig
from cell.configio import to_plain
from cell.loop import ControlLoop, OpenCell, Task
from cell.recorder import Recorder, new_run_dir, read_log
from cell.report import plot_force_run
from cell.robot import RobotModel
from cell.safety import SafetyMonitor

log = logging.getLogger(__name__)


def run_task(
    task: Task,
    cell: OpenCell,
    cfg: CellConfig,
    robot: RobotModel,
    max_duration_s: float,
    record: bool = True,
    extra_summary: dict[str, Any] | None = None,
) -> dict[str, Any]:
    recorder = None
    run_dir: Path | None = None
    if record:
        run_dir = new_run_dir(Path(cfg.recording.directory), task.name)
        recorder = Recorder(run_dir, cfg.recording.chunk_rows)
        recorder.write_config(to_plain(cfg))
        log.info("recording to %s", run_dir)
    safety = SafetyMonitor(cfg.safety, robot, cfg.loop.period_s)
    loop = ControlLoop(
        cell.arm, cell.force, task, safety, cell.ticker, recorder, cfg.loop.period_s, max_duration_s,
        cfg.loop.slow_cycle_fraction, ground_truth=cell.ground_truth,
    )
    result = loop.run()
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
        safety_stop=result.outcome == "safety_stop",
    )
    if extra_summary:
        summary.update(extra_summary)
    if recorder is not None and run_dir is not None:
        summary["run_dir"] = str(run_dir)
        if recorder.rows_written:
            try:
                png = plot_force_run(read_log(run_dir), run_dir / "plot.png",
                                     f"{task.name} on the {cell.kind} cell: {summary['outcome']}")
                summary["plot"] = str(png)
            except Exception as exc:  # a plot must never lose the recording or the summary
                log.error("could not draw the plot: %s", exc)
        recorder.write_summary(summary)
    return summary
