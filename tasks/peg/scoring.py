"""Virtual-vs-measured wrench errors of a peg trial, scored over the insertion states (the bench; a run's summary
scores the same states through tasks/runner.py, under the same names)."""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.peg.states import INSERTION_STATES

WRENCH_AXES = ("mx", "my", "fz")  # the paper's 3-axis comparison: what the strategy reads
# Their mean absolute errors, named as every run's summary names them (tasks/runner.py virtual_vs_sensor).
ERROR_KEYS = ("virtual_vs_sensor_mx_mae_nm", "virtual_vs_sensor_my_mae_nm", "virtual_vs_sensor_fz_mae_n")


def wrench_abs_errors(states: Any, virtual: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """|virtual - measured| of (Mx, My, Fz), rows (n, 3), on the insertion states' samples where both
    sources read (a timed-out reading is no sample): (k, 3).  The bench and the run summary score this."""
    v, m = np.asarray(virtual, float).reshape(-1, 3), np.asarray(measured, float).reshape(-1, 3)
    rows = np.isin(np.asarray(states, dtype=object), INSERTION_STATES)
    rows &= np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(m), axis=1)
    return np.abs(v[rows] - m[rows])


def wrench_errors(table: Any) -> dict[str, Any]:
    """Virtual-vs-measured MAE of (Mx, My, Fz) over the insertion states, when the log has both."""
    d = table.to_pydict() if hasattr(table, "to_pydict") else table
    if "sensor_fz" not in d:
        return {}
    e = wrench_abs_errors(d["state"], np.column_stack([d[k] for k in WRENCH_AXES]),
                          np.column_stack([d[f"sensor_{k}"] for k in WRENCH_AXES]))
    out: dict[str, Any] = {"virtual_vs_sensor_samples": len(e)}
    for i, name in enumerate(ERROR_KEYS):
        out[name] = float(e[:, i].mean()) if len(e) else None
    return out
