"""Motion datasets (Parquet + YAML manifest): the manifest, and trajectories read with strict validation.

Format (documented in docs/dataset.md):

* one or more Parquet files (or folders of Parquet parts, such as a run's `log/`) with columns
  `t, q1..qn, tau1..taun` and optionally `dq1..dqn`, `traj` (trajectory id) and the payload columns
  `payload_kg`, `payload_com_x..z`; extra columns are ignored, so the control loop's step logs are valid
  datasets as they are;
* a YAML manifest naming which files are for training, for testing and (optionally) carry a payload.

Derivatives: cell/sensing/derivatives.py; trajectories stacked for fitting: cell/data/samples.py.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from cell.sensing.derivatives import FilterConfig
from drivers.configio import join, load_dataclass, read_yaml, require
from drivers.errors import DataError

Split = Literal["train", "test", "loaded"]
GAP_FACTOR = 1.5  # a time step longer than this x the median step starts a new trajectory (no max_gap_s)
PAYLOAD_COM = ("payload_com_x", "payload_com_y", "payload_com_z")  # m, flange frame


@dataclass
class DatasetManifest:
    """dataset.yaml: file lists are relative to the manifest's folder unless absolute."""

    train: list[str] = field(default_factory=list)
    test: list[str] = field(default_factory=list)
    loaded: list[str] = field(default_factory=list)  # files recorded with a payload (payload-transfer check)
    joints: int | None = None  # checked against the URDF when given
    robot: str = ""  # robot name from the URDF; a loader asked for another robot refuses the dataset
    period_s: float | None = None  # nominal (median) sample period, informational
    # Gap rule: a time step longer than this starts a new trajectory; unset: longer than 1.5 x the median step.
    max_gap_s: float | None = None
    description: str = ""
    filter: FilterConfig = field(default_factory=FilterConfig)

    def validate(self, where: str) -> None:
        require(bool(self.train) or bool(self.test), join(where, "train"), "or test must list at least one file")
        if self.joints is not None:
            require(self.joints >= 1, join(where, "joints"), "must be >= 1")
        if self.max_gap_s is not None:
            require(self.max_gap_s > 0, join(where, "max_gap_s"), f"must be > 0 s, got {self.max_gap_s}")


def load_manifest(path: Path) -> DatasetManifest:
    return load_dataclass(DatasetManifest, read_yaml(Path(path)), f"{path}:")


# Paths a manifest may name: data files and folders, never a system tree (a manifest pointing at
# /proc made a recursive listing run for minutes) and never more parts than a dataset has.
SYSTEM_TREES = (Path("/proc"), Path("/sys"), Path("/dev"))
MAX_PARTS = 10_000


def manifest_files(path: Path, split: Split) -> list[Path]:
    man = load_manifest(path)
    base = Path(path).parent
    out = []
    for p in map(Path, getattr(man, split)):
        full = p if p.is_absolute() else base / p
        resolved = full.resolve()
        if any(resolved == t or t in resolved.parents for t in SYSTEM_TREES):
            raise DataError(f"{path}: {split} entry '{p}' is inside {resolved.anchor}{resolved.parts[1]}: "
                            "not a dataset file")
        if resolved.exists() and not (resolved.is_file() or resolved.is_dir()):
            raise DataError(f"{path}: {split} entry '{p}' is not a regular file or folder")
        out.append(full)
    return out


def parquet_parts(path: Path) -> list[Path]:
    """A dataset entry's Parquet files: the file itself, or a folder's parts (at most MAX_PARTS)."""
    path = Path(path)
    if not path.is_dir():
        return [path]
    parts = []
    for part in path.rglob("*.parquet"):
        if part.name.startswith("."):
            continue
        parts.append(part)
        if len(parts) > MAX_PARTS:
            raise DataError(f"{path}: more than {MAX_PARTS} Parquet parts: not a dataset folder")
    return sorted(parts)


# ----------------------------------------------------------------------------------------- data
@dataclass
class Trajectory:
    """One continuous recording: consecutive samples `t` apart, joint arrays (N, n)."""

    name: str  # "<file>" or "<file>#<traj id>"
    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    dq: np.ndarray | None = None
    segment: np.ndarray | None = None  # optional per-row segment (move) id, for subsampling
    payload: tuple[float, np.ndarray | None] | None = None  # (kg, COM (3,) in the flange frame or unknown)

    @property
    def n(self) -> int:
        return int(self.q.shape[1])

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def slice(self, a: int, b: int, name: str | None = None) -> Trajectory:
        return Trajectory(
            name=name or self.name, t=self.t[a:b], q=self.q[a:b], tau=self.tau[a:b],
            dq=None if self.dq is None else self.dq[a:b],
            segment=None if self.segment is None else self.segment[a:b], payload=self.payload,
        )


def _joint_count(columns: Sequence[str], prefix: str) -> int:
    n = 0
    while f"{prefix}{n + 1}" in columns:
        n += 1
    return n


def _column(table: pa.Table, name: str, file: Path, allow_nan: bool = False) -> np.ndarray:
    try:
        arr = table.column(name).to_numpy(zero_copy_only=False)
    except KeyError:
        raise DataError(f"{file}: missing column '{name}'") from None
    try:
        values = np.asarray(arr, dtype=float)
    except (TypeError, ValueError):
        raise DataError(f"{file}: column '{name}' is not numeric") from None
    bad = np.isinf(values) if allow_nan else ~np.isfinite(values)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{file}: column '{name}' has {int(bad.sum())} NaN/inf rows (first at row {first}); "
            "drop or repair those rows"
        )
    limit = _magnitude_limit(name)
    if limit is not None:
        big = np.abs(values) > limit
        if big.any():
            first = int(np.flatnonzero(big)[0])
            raise DataError(f"{file}: column '{name}' has {int(big.sum())} rows beyond +-{limit:g} (first at row "
                            f"{first}: {values[first]:.6g}): not a physical value")
    return values


# Largest plausible magnitudes per column family (SI): a value beyond is corrupt data, which would
# otherwise overflow the derivative filters and the models.
MAGNITUDE_LIMITS = {"t": 1e11, "q": 100.0, "dq": 100.0, "tau": 1e5}
MIN_TIME_STEP_S = 1e-5  # no arm reports faster than 100 kHz; smaller steps are corrupt time stamps


def _magnitude_limit(name: str) -> float | None:
    prefix = name.rstrip("0123456789")
    return MAGNITUDE_LIMITS.get(prefix)


def read_table(path: Path) -> pa.Table:
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.is_dir():
        parquet_parts(path)  # bounded: refuses a tree of more parts than a dataset has
    try:
        return pq.read_table(path)
    except (pa.ArrowException, OSError, ValueError) as exc:  # a damaged file fails in many ways
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise DataError(f"{path}: not a readable Parquet file or folder ({first})") from None


def _payload_columns(table: pa.Table, path: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(payload_kg (N,), COM (N, 3) with NaN where unknown) when the file has them, else None."""
    cols = table.column_names
    present = [c for c in PAYLOAD_COM if c in cols]
    if "payload_kg" not in cols:
        if present:
            raise DataError(f"{path}: column '{present[0]}' without column 'payload_kg' (the payload's mass in kg)")
        return None, None
    kg = _column(table, "payload_kg", path)
    if np.any(kg < 0):
        raise DataError(f"{path}: column 'payload_kg' is negative at row {int(np.flatnonzero(kg < 0)[0])}")
    if not present:
        return kg, None
    if len(present) < 3:
        missing = next(c for c in PAYLOAD_COM if c not in cols)
        raise DataError(f"{path}: missing column '{missing}' (give all of payload_com_x..z or none)")
    return kg, np.column_stack([_column(table, c, path, allow_nan=True) for c in PAYLOAD_COM])


def _payload(kg: np.ndarray | None, com: np.ndarray | None, a: int, b: int, path: Path,
             tid: int) -> tuple[float, np.ndarray | None] | None:
    """One trajectory's payload (rows a..b-1): constant within it; an all-NaN COM is unknown (None)."""
    if kg is None:
        return None
    if np.any(kg[a:b] != kg[a]):
        raise DataError(f"{path}: column 'payload_kg' changes within trajectory {tid} (rows {a}..{b - 1}); "
                        "a payload is constant per trajectory")
    if com is None or np.isnan(com[a:b]).all():
        return float(kg[a]), None
    rows = com[a:b]
    if np.isnan(rows).any() or np.any(rows != rows[0]):
        raise DataError(f"{path}: columns 'payload_com_x..z' change within trajectory {tid} (rows {a}..{b - 1}); "
                        "a payload is constant per trajectory (all NaN when its COM is unknown)")
    return float(kg[a]), rows[0].copy()


def load_trajectories(path: Path, n_joints: int | None = None, max_gap_s: float | None = None) -> list[Trajectory]:
    """Read and validate one dataset file; split it into trajectories by `traj` and by time gaps
    (a step longer than `max_gap_s`, or without it longer than GAP_FACTOR x the trajectory's median step).

    Raises DataError naming the file and the column for: missing columns, NaN/inf values,
    non-increasing time, a joint count different from `n_joints` (the URDF's), and a payload that
    changes within a trajectory.
    """
    path = Path(path)
    table = read_table(path)
    cols = table.column_names
    if "t" not in cols:
        raise DataError(f"{path}: missing column 't' (time in s)")
    nq = _joint_count(cols, "q")
    if nq == 0:
        raise DataError(f"{path}: missing column 'q1' (joint positions q1..qn in rad)")
    if n_joints is not None and nq != n_joints:
        col = f"q{n_joints}" if nq < n_joints else f"q{n_joints + 1}"
        what = "missing column" if nq < n_joints else "unexpected column"
        raise DataError(
            f"{path}: {what} '{col}': the file has {nq} joints (q1..q{nq}) but the URDF has {n_joints}"
        )
    n = nq
    for prefix in ("tau",):
        for i in range(1, n + 1):
            if f"{prefix}{i}" not in cols:
                raise DataError(f"{path}: missing column '{prefix}{i}' (measured joint torque in N·m)")
    ndq = _joint_count(cols, "dq")
    if 0 < ndq < n:
        raise DataError(f"{path}: missing column 'dq{ndq + 1}' (give all of dq1..dq{n} or none)")
    if table.num_rows < 2:
        raise DataError(f"{path}: column 't' has {table.num_rows} rows; a trajectory needs at least 2")
    t = _column(table, "t", path)
    q = np.column_stack([_column(table, f"q{i}", path) for i in range(1, n + 1)])
    tau = np.column_stack([_column(table, f"tau{i}", path) for i in range(1, n + 1)])
    dq = np.column_stack([_column(table, f"dq{i}", path) for i in range(1, n + 1)]) if ndq else None
    traj_id = _column(table, "traj", path).astype(np.int64) if "traj" in cols else np.zeros(len(t), np.int64)
    segment = _column(table, "segment", path).astype(np.int64) if "segment" in cols else None
    payload_kg, payload_com = _payload_columns(table, path)

    out: list[Trajectory] = []
    # Rows of one trajectory id are contiguous in a well-formed file; time increases within each.
    change = np.flatnonzero(np.diff(traj_id) != 0) + 1
    bounds = np.concatenate([[0], change, [len(t)]])
    seen: set[int] = set()
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        tid = int(traj_id[a])
        if tid in seen:
            raise DataError(f"{path}: column 'traj' value {tid} is not contiguous (rows {a}..{b - 1} repeat it)")
        seen.add(tid)
        dt = np.diff(t[a:b])
        if np.any(dt <= 0):
            k = int(np.flatnonzero(dt <= 0)[0]) + a + 1
            raise DataError(
                f"{path}: column 't' is not strictly increasing at row {k} (t={t[k]:.6g} s after {t[k - 1]:.6g} s)"
            )
        if np.any(dt < MIN_TIME_STEP_S):
            k = int(np.flatnonzero(dt < MIN_TIME_STEP_S)[0]) + a + 1
            raise DataError(f"{path}: column 't' steps by {dt[k - a - 1]:.3g} s at row {k}: below "
                            f"{MIN_TIME_STEP_S:g} s, not a sample period")
        # A gap (a dropped chunk, concatenated runs) breaks the trajectory: derivatives must not span it.
        if max_gap_s is not None:
            gaps = np.flatnonzero(dt > max_gap_s) + 1
        else:
            step = float(np.median(dt)) if dt.size else 0.0
            gaps = np.flatnonzero(dt > GAP_FACTOR * step) + 1 if step > 0 else np.array([], int)
        pieces = np.concatenate([[0], gaps, [b - a]]) + a
        for k, (c, d) in enumerate(zip(pieces[:-1], pieces[1:], strict=True)):
            if d - c < 2:
                continue
            name = str(path) if len(bounds) == 2 else f"{path}#{tid}"
            if len(pieces) > 2:
                name += f"/{k}"
            out.append(Trajectory(
                name=name, t=t[c:d], q=q[c:d], tau=tau[c:d], dq=None if dq is None else dq[c:d],
                segment=None if segment is None else segment[c:d],
                payload=_payload(payload_kg, payload_com, c, d, path, tid),
            ))
    return out


def load_split(manifest: Path, split: Split, n_joints: int | None = None,
               robot: str | None = None) -> list[Trajectory]:
    """A manifest's split as trajectories; refused when the manifest names another `robot` than asked for."""
    man = load_manifest(manifest)
    if robot and man.robot and man.robot != robot:
        raise DataError(f"{manifest}: the dataset is of robot '{man.robot}' but --robot is '{robot}'")
    if n_joints is not None and man.joints is not None and man.joints != n_joints:
        raise DataError(f"{manifest}: joints is {man.joints} but the URDF has {n_joints} joints")
    files = manifest_files(manifest, split)
    if not files:
        raise DataError(f"{manifest}: lists no {split} files")
    out: list[Trajectory] = []
    for f in files:
        out.extend(load_trajectories(f, n_joints, man.max_gap_s))
    return out


def files_sha256(paths: Iterable[Path]) -> str:
    """Content hash of dataset files (folders: every Parquet part inside, in name order)."""
    h = hashlib.sha256()
    for p in sorted(Path(x) for x in paths):
        for part in parquet_parts(p):
            h.update(part.name.encode())
            h.update(part.read_bytes())
    return h.hexdigest()


def write_trajectory(path: Path, traj: Trajectory, traj_id: int | None = None) -> None:
    """Write one trajectory in the dataset format (used by tests and by `collect`)."""
    cols: dict[str, np.ndarray] = {"t": traj.t}
    for prefix, arr in (("q", traj.q), ("dq", traj.dq), ("tau", traj.tau)):
        if arr is None:
            continue
        for i in range(arr.shape[1]):
            cols[f"{prefix}{i + 1}"] = arr[:, i]
    if traj_id is not None:
        cols["traj"] = np.full(len(traj.t), traj_id, np.int64)
    if traj.segment is not None:
        cols["segment"] = traj.segment
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(cols), path)
