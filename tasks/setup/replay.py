"""Replay: the virtual force sensor run again over a recorded run's joint data, scored as the run was."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from cell.config import CellConfig
from cell.data.recorder import read_log
from cell.model.robot import RobotModel
from cell.sensing.virtual_sensor import build_virtual_source
from drivers.errors import ConfigError, DataError
from drivers.interfaces import ArmState
from tasks.runner import REGULATED_STATES, virtual_vs_sensor

log = logging.getLogger(__name__)

AXES = ("fx", "fy", "fz", "mx", "my", "mz")
FIGURE_PREFIX = "virtual_vs_sensor_"


def read_run(run_dir: Path) -> tuple[dict[str, Any], pa.Table]:
    """A recorded run's summary and step log; a folder that is not one is refused in one line."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: no such run folder (runs/<time>-<task>/ made by main.py run)")
    summary_path = run_dir / "summary.json"
    if not (run_dir / "log").is_dir() or not summary_path.exists():
        raise ConfigError(f"{run_dir}: not a recorded run (needs summary.json and log/ as main.py run writes them)")
    try:
        summary = json.loads(summary_path.read_text())
        table = read_log(run_dir)
    except (OSError, ValueError, pa.ArrowException) as exc:
        raise DataError(f"{run_dir}: cannot read the recording: {exc}") from None
    if table.num_rows == 0:
        raise DataError(f"{run_dir}: the step log is empty")
    return summary, table


def joint_columns(table: pa.Table, n: int) -> dict[str, np.ndarray]:
    """q, dq, tau as (rows, n) arrays from the log's q1..qn, dq1.., tau1.. columns."""
    out = {}
    for name in ("q", "dq", "tau"):
        cols = [f"{name}{i + 1}" for i in range(n)]
        missing = [c for c in cols if c not in table.column_names]
        if missing:
            raise DataError(f"the step log has no column {missing[0]} (a recording of a {n}-joint arm?)")
        out[name] = np.column_stack([table.column(c).to_numpy(zero_copy_only=False) for c in cols]).astype(float)
    return out


def measured_wrench(table: pa.Table, force_source: str) -> np.ndarray:
    """The F/T sensor's wrench per row: `sensor_*` when the virtual sensor was in the loop, else the loop's own."""
    prefix = "sensor_" if force_source == "virtual" else ""
    cols = [prefix + a for a in AXES]
    if any(c not in table.column_names for c in cols):
        raise DataError("the recording has no F/T sensor columns (a run on a cell without the sensor): "
                        "nothing to score the virtual sensor against")
    return np.column_stack([np.asarray(table.column(c).to_numpy(zero_copy_only=False), float) for c in cols])


def read_states(table: pa.Table) -> list[str]:
    """The task state each cycle's force reading was taken in; recordings from before `state_read` was logged
    give the previous row's state (the same except on the cycle a guard's reaction changed it)."""
    if "state_read" in table.column_names:
        return [str(s) for s in table.column("state_read").to_pylist()]
    after = [str(s) for s in table.column("state").to_pylist()]
    log.warning("the recording predates the `state_read` column: scoring on the previous cycle's state")
    return after[:1] + after[:-1]


def replay(cfg: CellConfig, robot: RobotModel, tool: str, task_name: str, run_dir: Path,
           observer: str | None = None, mapping: str | None = None, model_dir: Path | None = None,
           calibration_dir: Path | None = None) -> tuple[dict[str, Any], np.ndarray]:
    """Run the virtual sensor over the run's joint data (re-zeroed where the run re-zeroed its force source)
    and score it against the recorded F/T wrench as the run did; the run's own figures beside.  Returns the
    report and the replayed wrench per row (rows, 6)."""
    summary, table = read_run(run_dir)
    source = build_virtual_source(cfg.virtual_sensor, robot, tool, cfg.loop.period_s, observer, mapping,
                                  model_dir, calibration_dir)
    joints = joint_columns(table, robot.n)
    meas = measured_wrench(table, str(summary.get("force_source", "virtual")))
    if "force_rebias" in table.column_names:
        rebias = np.asarray(table.column("force_rebias").to_pylist(), bool)
    else:
        log.warning("the recording predates the `force_rebias` column: replaying without the run's re-zeroing")
        rebias = np.zeros(table.num_rows, bool)
    t = np.asarray(table.column("t").to_numpy(zero_copy_only=False), float)
    est = np.empty((table.num_rows, 6))
    for k in range(table.num_rows):
        state = ArmState(t=float(t[k]), q=joints["q"][k], dq=joints["dq"][k], tau=joints["tau"][k], seq=k)
        est[k] = source.read(state).vector
        if rebias[k]:
            source.rebias()
    regulated = REGULATED_STATES.get(task_name)
    figures = virtual_vs_sensor(read_states(table), meas, est, regulated, {})
    run_figures = {k: v for k, v in summary.items() if k.startswith(FIGURE_PREFIX)}
    diff = {k: abs(float(figures[k]) - float(v)) for k, v in run_figures.items()
            if k in figures and v is not None and k != FIGURE_PREFIX + "samples"}
    out: dict[str, Any] = {"run_dir": str(run_dir), "task": task_name, "cell": summary.get("cell"),
                           "virtual_sensor": source.label, "run_virtual_sensor": summary.get("virtual_sensor"),
                           "rows": table.num_rows, **figures,
                           "run": run_figures, "max_abs_difference": max(diff.values()) if diff else None}
    out.update(source.summary())
    return out, est
