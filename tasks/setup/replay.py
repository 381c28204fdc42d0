"""Replay: the virtual force sensor run again over a recorded run's joint data, scored as the run was."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from cell.config import CellConfig
from cell.data.recorder import read_log, verify_log
from cell.model.robot import RobotModel
from cell.sensing.virtual_sensor import build_virtual_source
from drivers.errors import ConfigError, DataError
from drivers.interfaces import ArmState
from tasks.peg.task import PegInHoleTask
from tasks.runner import virtual_vs_sensor
from tasks.wipe import WipeTask

log = logging.getLogger(__name__)

AXES = ("fx", "fy", "fz", "mx", "my", "mz")
FIGURE_PREFIX = "virtual_vs_sensor_"
TOUCH_KEYS = ("touches", "touch_virtual_peak_n", "touch_sensor_peak_n", "touch_peak_ratio")


def read_run(run_dir: Path) -> tuple[dict[str, Any], pa.Table]:
    """A recorded run's summary and step log; a folder that is not one is refused in one line."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: no such run folder (runs/<time>-<task>/ made by main.py run)")
    summary_path = run_dir / "summary.json"
    if not (run_dir / "log").is_dir() or not summary_path.exists():
        raise ConfigError(f"{run_dir}: not a recorded run (needs summary.json and log/ as main.py run writes them)")
    if not verify_log(run_dir):
        log.warning("%s: the recording predates step-log checksums: its parts are not verified", run_dir)
    try:
        summary = json.loads(summary_path.read_text())
        table = read_log(run_dir)
    except (OSError, ValueError, pa.ArrowException) as exc:
        raise DataError(f"{run_dir}: cannot read the recording: {exc}") from None
    except RecursionError:
        raise DataError(f"{summary_path}: nested too deeply to be a run's summary") from None
    if table.num_rows == 0:
        raise DataError(f"{run_dir}: the step log is empty")
    if not isinstance(summary, dict):
        raise DataError(f"{summary_path}: expected a JSON object, got {type(summary).__name__}")
    return summary, table


# What no recording of this arm can hold: joints this far past their limits (rad), this many times their
# speed and torque limits, and a wrench beyond this (N, N·m); NaN is allowed only where a reading was missing.
JOINT_MARGIN_RAD = 0.2
LIMIT_FACTOR = 3.0
MAX_WRENCH = 1e4


def _first_bad(ok: np.ndarray) -> int | None:
    bad = np.flatnonzero(~ok)
    return int(bad[0]) if bad.size else None


def check_ranges(run_dir: Path, table: pa.Table, joints: dict[str, np.ndarray], robot: RobotModel) -> None:
    """Refuse a step log holding physically impossible values (a damaged file read as numbers): one line
    naming the column, row and value."""
    lim = robot.limits
    if "t" not in table.column_names:
        raise DataError(f"{run_dir}: the step log has no column t")
    t = np.asarray(table.column("t").to_numpy(zero_copy_only=False), float)
    row = _first_bad(np.isfinite(t) & (t >= 0) & np.concatenate([[True], np.diff(t) >= 0]))
    if row is not None:
        raise DataError(f"{run_dir}: step log column t row {row}: {t[row]:g} s is not a time of the run "
                        "(finite, >= 0, not decreasing)")
    bounds = {"q": (lim.lower - JOINT_MARGIN_RAD, lim.upper + JOINT_MARGIN_RAD, "rad"),
              "dq": (-LIMIT_FACTOR * lim.velocity, LIMIT_FACTOR * lim.velocity, "rad/s"),
              "tau": (-LIMIT_FACTOR * lim.effort, LIMIT_FACTOR * lim.effort, "N·m")}
    for name, (lo, hi, unit) in bounds.items():
        values = joints[name]
        ok = np.isfinite(values) & (values >= lo) & (values <= hi)
        bad = np.argwhere(~ok)
        if bad.size:
            r, j = (int(v) for v in bad[0])
            raise DataError(f"{run_dir}: step log column {name}{j + 1} row {r}: {values[r, j]:g} {unit} is "
                            f"physically impossible for joint {j + 1} (outside [{lo[j]:.4g}, {hi[j]:.4g}] {unit})")
    for col in (c for c in table.column_names if c.removeprefix("sensor_") in AXES):
        values = np.asarray(table.column(col).to_numpy(zero_copy_only=False), float)
        row = _first_bad(np.isnan(values) | (np.abs(values) <= MAX_WRENCH))
        if row is not None:
            raise DataError(f"{run_dir}: step log column {col} row {row}: {values[row]:g} is physically "
                            f"impossible (|value| <= {MAX_WRENCH:g} N or N·m)")


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


def scored_states(summary: dict[str, Any], task_name: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The working and touch states the run was scored over (its summary names them; a recording from before
    it did takes the task's own declaration)."""

    task = {"wipe": WipeTask, "peg-in-hole": PegInHoleTask}.get(task_name)
    working = summary.get("scored_states", getattr(task, "working_states", ()))
    touching = summary.get("touch_states", getattr(task, "touch_states", ()))
    return tuple(str(s) for s in working), tuple(str(s) for s in touching)


def replay(cfg: CellConfig, robot: RobotModel, tool: str, task_name: str, run_dir: Path,
           observer: str | None = None, mapping: str | None = None, model_dir: Path | None = None,
           calibration_dir: Path | None = None) -> tuple[dict[str, Any], np.ndarray]:
    """Run the virtual sensor over the run's joint data (re-zeroed where the run re-zeroed its force source)
    and score it against the recorded F/T wrench as the run did; the run's own figures beside.  Returns the
    report and the replayed wrench per row (rows, 6)."""
    summary, table = read_run(run_dir)
    joints = joint_columns(table, robot.n)
    check_ranges(run_dir, table, joints, robot)
    source = build_virtual_source(cfg.virtual_sensor, robot, tool, cfg.loop.period_s, observer, mapping,
                                  model_dir, calibration_dir)
    meas = measured_wrench(table, str(summary.get("force_source", "virtual")))
    if "force_rebias" in table.column_names:
        rebias = np.asarray(table.column("force_rebias").to_pylist(), bool)
    else:
        log.warning("the recording predates the `force_rebias` column: replaying without the run's re-zeroing")
        rebias = np.zeros(table.num_rows, bool)
    t = np.asarray(table.column("t").to_numpy(zero_copy_only=False), float)
    working, touching = scored_states(summary, task_name)
    states = read_states(table)
    # The run's own sensor read fast where its task expected a touch (the state it was in at the read).
    row = [0]
    source.contact_expected = lambda: states[row[0]] in touching
    est = np.empty((table.num_rows, 6))
    for k in range(table.num_rows):
        row[0] = k
        state = ArmState(t=float(t[k]), q=joints["q"][k], dq=joints["dq"][k], tau=joints["tau"][k], seq=k)
        est[k] = source.read(state).vector
        if rebias[k]:
            source.rebias()
    # The F/T sensor is zeroed at the run's first re-zeroing (its tare): before it, nothing is scored.
    tared = np.concatenate([[False], np.cumsum(rebias)[:-1] > 0])
    figures = virtual_vs_sensor(states, meas, est, working, {}, tared, touch_states=touching)
    figures.pop("warnings", None)
    run_figures = {k: v for k, v in summary.items() if k.startswith(FIGURE_PREFIX) or k in TOUCH_KEYS}
    diff = {k: abs(float(figures[k]) - float(v)) for k, v in run_figures.items()
            if k in figures and v is not None and k not in (FIGURE_PREFIX + "samples", "touches")}
    out: dict[str, Any] = {"run_dir": str(run_dir), "task": task_name, "cell": summary.get("cell"),
                           "virtual_sensor": source.label, "run_virtual_sensor": summary.get("virtual_sensor"),
                           "rows": table.num_rows, **figures,
                           "run": run_figures, "max_abs_difference": max(diff.values()) if diff else None}
    out.update(source.summary())
    return out, est
