"""`main.py import ur10e`: the public UR10e joint-current logs (CSV) as a model-lab dataset (docs/dataset.md).

The logs (`../shared/data/ur10e/README.md`): CSV without a header, 31 columns per row: time stamp,
q1..q6 (rad), qd1..qd6 (rad/s, measured), motor currents i1..i6 (A), commanded currents (A),
commanded torques (N·m).  Each source file becomes one Parquet file `<out>/<split>/<stem>.parquet` with
`t` (zero-based), `q1..q6`, `dq1..dq6` (the measured speeds), `tau1..tau6` (motor current x the drive
gains of `config/robots/ur10e/robot.yaml`) and `traj`; files of the `loaded` split also carry the
payload (`payload_kg`; `payload_com_x..z` NaN: its centre of mass is not published).

Malformed rows are dropped and counted, never repaired: a wrong column count, a field that is not a
number or not finite, and time stamps out of order (both rows of every adjacent pair whose time does
not increase, repeated until the kept times increase strictly: which row of such a pair is wrong is
not guessed).  A time step longer than `max_gap_s` starts a new trajectory; the manifest records
`max_gap_s`, so the loader splits at the same gaps only (the logs' 12-34 ms jitter on a 10 ms median
is not a gap).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from cell.config import ROOT
from cell.data.dataset import PAYLOAD_COM
from cell.model.specs import RobotSpec, load_robot_spec
from drivers.configio import json_default
from drivers.errors import ConfigError, DataError

log = logging.getLogger(__name__)

ROBOT = "ur10e"
N_JOINTS = 6
N_COLUMNS = 31  # time, q1..6, qd1..6, i1..6, commanded currents 1..6, commanded torques 1..6
Q_COLS = slice(1, 7)
DQ_COLS = slice(7, 13)
CURRENT_COLS = slice(13, 19)
DEFAULT_MAX_GAP_S = 0.05
LOADED_PAYLOAD_KG = 2.805  # the loaded harmonic runs (*harm50secLoad), from the data's README
SPLITS = ("train", "test", "loaded")


def shared_data_root() -> Path:
    """Where the public logs live: `<project>/../shared/data/ur10e` (from the project root, not the cwd)."""
    return ROOT.parent / "shared" / "data" / "ur10e"


def default_sources(root: Path) -> dict[str, list[Path]]:
    """train: the unloaded harmonic runs; test: the joint-wise runs; loaded: the loaded harmonic runs."""
    harm = sorted((root / "identification").glob("*harm*.csv"))
    return {
        "train": [p for p in harm if "Load" not in p.name],
        "test": sorted((root / "jointwise").glob("*.csv")),
        "loaded": [p for p in harm if "Load" in p.name],
    }


def expand_paths(paths: Sequence[str | Path], option: str) -> list[Path]:
    """CSV files and folders (every `*.csv` inside, sorted) as a list of files."""
    out: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if p.is_dir():
            found = sorted(p.glob("*.csv"))
            if not found:
                raise ConfigError(f"{option} {p}: no *.csv files in this folder")
            out.extend(found)
        elif p.is_file():
            out.append(p)
        else:
            raise ConfigError(f"{option} {p}: no such file or folder")
    return out


# ------------------------------------------------------------------------------------------ parsing
@dataclass
class ParsedLog:
    """The valid rows of one CSV log and what was dropped."""

    path: Path
    values: np.ndarray  # (N, 31) valid rows
    lines: np.ndarray  # (N,) their 1-based line numbers
    total_rows: int  # rows in the file (blank last line excluded)
    dropped: dict[str, int]  # reason -> count
    first_bad_line: int | None

    @property
    def rows_dropped(self) -> int:
        return sum(self.dropped.values())


def parse_row(line: str) -> tuple[list[float] | None, str]:
    """One CSV line as 31 finite numbers, or (None, reason)."""
    fields = line.split(",")
    if len(fields) != N_COLUMNS:
        return None, "column count"
    try:
        values = [float(f) for f in fields]
    except ValueError:
        return None, "not a number"
    if not all(math.isfinite(v) for v in values):
        return None, "not finite"
    return values, ""


def increasing_time(t: np.ndarray) -> np.ndarray:
    """Mask of the rows whose time stamps increase strictly: both rows of every adjacent pair out of
    order are dropped (which one is wrong is not guessed), repeated until the rest increases."""
    keep = np.ones(len(t), bool)
    while True:
        idx = np.flatnonzero(keep)
        bad = np.diff(t[idx]) <= 0
        if not bad.any():
            return keep
        drop = np.zeros(len(idx), bool)
        drop[:-1] |= bad
        drop[1:] |= bad
        keep[idx[drop]] = False


def read_log(path: Path) -> ParsedLog:
    """Parse one CSV log; malformed rows are dropped and counted (one warning per file)."""
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from None
    rows: list[list[float]] = []
    lines: list[int] = []
    dropped: dict[str, int] = {}
    bad_lines: list[int] = []
    raw = text.split("\n")  # not splitlines(): a stray control byte in a field must not make a line
    if raw and raw[-1] == "":
        raw.pop()  # the newline that ends the last row
    for number, line in enumerate(raw, start=1):
        values, reason = parse_row(line.rstrip("\r"))
        if values is None:
            dropped[reason] = dropped.get(reason, 0) + 1
            bad_lines.append(number)
            continue
        rows.append(values)
        lines.append(number)
    values_arr = np.asarray(rows, float).reshape(-1, N_COLUMNS)
    lines_arr = np.asarray(lines, np.int64)
    keep = increasing_time(values_arr[:, 0])
    if not keep.all():
        dropped["time not strictly increasing"] = int((~keep).sum())
        bad_lines.extend(lines_arr[~keep].tolist())
    parsed = ParsedLog(path=path, values=values_arr[keep], lines=lines_arr[keep], total_rows=len(raw),
                       dropped=dropped, first_bad_line=min(bad_lines) if bad_lines else None)
    why = ", ".join(f"{k}: {v}" for k, v in dropped.items())
    if len(parsed.values) == 0:
        detail = f"{parsed.total_rows} rows, all malformed ({why}; first bad line {parsed.first_bad_line})" \
            if parsed.total_rows else "the file is empty"
        raise DataError(f"{path}: no valid rows: {detail}")
    if parsed.rows_dropped:
        log.warning("%s: dropped %d of %d rows (%s); first bad line %d", path, parsed.rows_dropped,
                    parsed.total_rows, why, parsed.first_bad_line)
    return parsed


def trajectory_ids(t: np.ndarray, max_gap_s: float) -> np.ndarray:
    """A new trajectory at every time step longer than `max_gap_s`: ids 0, 1, ... per row."""
    ids = np.zeros(len(t), np.int64)
    ids[1:] = np.cumsum(np.diff(t) > max_gap_s)
    return ids


def to_table(parsed: ParsedLog, gains: np.ndarray, max_gap_s: float, payload_kg: float | None) -> pa.Table:
    """The dataset columns of one parsed log (tau = motor current x drive gain, t zero-based)."""
    v = parsed.values
    t = v[:, 0] - v[0, 0]
    cols: dict[str, np.ndarray] = {"t": t}
    for name, block in (("q", v[:, Q_COLS]), ("dq", v[:, DQ_COLS]), ("tau", v[:, CURRENT_COLS] * gains)):
        for i in range(N_JOINTS):
            cols[f"{name}{i + 1}"] = np.ascontiguousarray(block[:, i])
    cols["traj"] = trajectory_ids(t, max_gap_s)
    if payload_kg is not None:
        cols["payload_kg"] = np.full(len(t), payload_kg)
        for name in PAYLOAD_COM:
            cols[name] = np.full(len(t), np.nan)  # the centre of mass is not published
    return pa.table(cols)


# ------------------------------------------------------------------------------------------ command
def drive_gains(spec: RobotSpec) -> np.ndarray:
    if spec.torque_source != "current" or spec.torque_constants is None:
        raise ConfigError(f"{spec.folder / 'robot.yaml'}: drive.torque_source must be 'current' with "
                          "drive.torque_constants_nm_per_a: the logs record motor currents")
    if spec.joints != N_JOINTS:
        raise ConfigError(f"{spec.folder / 'robot.yaml'}: joints is {spec.joints}, the logs have {N_JOINTS}")
    return np.asarray(spec.torque_constants, float)


def import_ur10e(
    out_dir: Path,
    train: Sequence[str | Path] | None = None,
    test: Sequence[str | Path] | None = None,
    loaded: Sequence[str | Path] | None = None,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    payload_kg: float = LOADED_PAYLOAD_KG,
    add_test: Sequence[str | Path] | None = None,
) -> dict[str, Any]:
    """Import UR10e CSV logs into `<out>` (one Parquet file per log, `dataset.yaml`, `import.json`).

    Without any of train/test/loaded the public logs under `shared_data_root()` are imported:
    train = the unloaded harmonic runs, test = the joint-wise runs, loaded = the loaded harmonic runs
    (`payload_kg`, default the published 2.805 kg).  Given paths (CSV files or folders) replace all
    three defaults, except `test` alone, which replaces only the test split's.  `add_test` (CSV files or
    folders) joins the test split either way: the collision recordings next to the joint-wise runs, the
    harmonic runs still the training.

    CLI: main.py import ur10e [--train PATH...] [--test PATH...] [--loaded PATH...] [--add-test PATH...]
         --out DIR [--max-gap-s 0.05] [--payload-kg 2.805] [--json]
    """
    if not max_gap_s > 0:
        raise ConfigError(f"--max-gap-s {max_gap_s}: must be > 0 s")
    if not (payload_kg >= 0 and math.isfinite(payload_kg)):
        raise ConfigError(f"--payload-kg {payload_kg}: must be a finite mass >= 0 kg")
    given = {"train": train, "test": test, "loaded": loaded}
    if test and not train and not loaded:
        # Only the test split chosen: the training keeps its defaults (an empty training split is never meant).
        root = shared_data_root()
        if not root.is_dir():
            raise ConfigError(f"--test alone keeps the default training runs, which are not at {root}: "
                              "give them with --train")
        sources = {**default_sources(root), "test": expand_paths(test, "--test")}
        origin = f"{root} (training), given paths (test)"
    elif any(given.values()):
        sources = {k: expand_paths(v or [], f"--{k}") for k, v in given.items()}
        origin = "given paths"
    else:
        root = shared_data_root()
        if not root.is_dir():
            raise ConfigError(f"the public UR10e logs are not at {root}: give the CSV files with --train/--test")
        sources = default_sources(root)
        origin = str(root)
    if add_test:
        sources["test"] = sources["test"] + expand_paths(add_test, "--add-test")
    if not sources["train"] and not sources["test"]:
        raise ConfigError("import ur10e: no CSV files for --train or --test")
    seen: dict[Path, str] = {}
    for split in SPLITS:
        stems: set[str] = set()
        for p in sources[split]:
            key = p.resolve()
            if key in seen:
                raise ConfigError(f"--{split} {p}: already imported as --{seen[key]} (a log belongs to one split)")
            seen[key] = split
            if p.stem in stems:
                raise ConfigError(f"--{split} {p}: another log of this split has the same name '{p.stem}'")
            stems.add(p.stem)

    gains = drive_gains(load_robot_spec(ROBOT))
    out_dir = Path(out_dir)
    files: dict[str, list[dict[str, Any]]] = {k: [] for k in SPLITS}
    steps: list[np.ndarray] = []
    for split in SPLITS:
        mass = payload_kg if split == "loaded" else None
        for src in sources[split]:
            parsed = read_log(src)
            table = to_table(parsed, gains, max_gap_s, mass)
            dest = out_dir / split / f"{src.stem}.parquet"
            dest.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, dest)
            t = parsed.values[:, 0]
            dt = np.diff(t)
            traj = table.column("traj").to_numpy()
            within = dt[np.diff(traj) == 0]
            steps.append(within)
            row = {
                "source": str(src), "file": f"{split}/{dest.name}", "rows_kept": len(t),
                "t0_log_s": float(t[0]),  # the first kept sample's time stamp (the dataset's t starts at 0)
                "rows_dropped": parsed.rows_dropped, "dropped_by_reason": parsed.dropped,
                "first_bad_line": parsed.first_bad_line, "trajectories": int(traj[-1]) + 1,
                "duration_s": round(float(t[-1] - t[0]), 3),
                "period_s": round(float(np.median(within)), 6) if within.size else None,
                "payload_kg": mass, "payload_com_m": None,  # COM of the loaded runs: not published
            }
            files[split].append(row)
            log.info("%s -> %s: %d rows kept, %d dropped, %d trajectories, %.1f s", src, dest,
                     row["rows_kept"], row["rows_dropped"], row["trajectories"], row["duration_s"])
    all_steps = np.concatenate(steps) if steps else np.array([])
    period = round(float(np.median(all_steps)), 6) if all_steps.size else None
    manifest = {
        "description": _description(origin, sources, payload_kg),
        "robot": ROBOT, "joints": N_JOINTS, "period_s": period, "max_gap_s": max_gap_s,
        "train": [r["file"] for r in files["train"]],
        "test": [r["file"] for r in files["test"]],
        "loaded": [r["file"] for r in files["loaded"]],
    }
    (out_dir / "dataset.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False, width=110))
    summary: dict[str, Any] = {
        "out_dir": str(out_dir), "manifest": str(out_dir / "dataset.yaml"), "robot": ROBOT, "source": origin,
        "period_s": period, "max_gap_s": max_gap_s,
        "files": sum(len(v) for v in files.values()),
        "rows_kept": sum(r["rows_kept"] for v in files.values() for r in v),
        "rows_dropped": sum(r["rows_dropped"] for v in files.values() for r in v),
        "trajectories": {k: sum(r["trajectories"] for r in v) for k, v in files.items()},
        "per_file": {r["file"]: {k: r[k] for k in ("rows_kept", "rows_dropped", "first_bad_line", "trajectories",
                                                   "duration_s", "payload_kg")}
                     for v in files.values() for r in v},
    }
    doc = {**{k: v for k, v in summary.items() if k != "per_file"}, "gains_nm_per_a": gains.tolist(),
           "splits": files}
    (out_dir / "import.json").write_text(json.dumps(doc, indent=2, default=json_default))
    return summary


def _description(origin: str, sources: dict[str, list[Path]], payload_kg: float) -> str:
    counts = ", ".join(f"{k}: {len(v)} logs" for k, v in sources.items())
    what = ("train the unloaded harmonic runs, test the joint-wise runs, loaded the loaded harmonic runs"
            if origin != "given paths" else "files as given")
    return (f"Universal Robots UR10e joint-current logs, public data of shamilmamedov/dynamic_calibration "
            f"({origin}; {counts}): {what}; loaded logs carry a {payload_kg} kg payload (centre of mass not "
            f"published); tau = motor current x the drive gains of config/robots/ur10e/robot.yaml "
            f"(main.py import ur10e)")
