"""Run recordings: runs/<timestamp>-<task>/ with a chunked Parquet step log, resolved config, summary, plot.

The step log is a folder of Parquet parts (`log/part-00000.parquet`, ...), each written whole and
renamed into place, so a run killed at any moment leaves every completed chunk readable
(`pyarrow.parquet.read_table(run/"log")` reads them as one table).  As each part is closed its sha256
and row count go into `log/_manifest.json` (readers of the folder skip `_` files), which `verify_log`
checks: a part damaged on disk is refused, never read as values.
"""

from __future__ import annotations

import collections
import datetime as _dt
import hashlib
import json
import logging
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from cell.data.atomic import save_atomic, write_atomic
from drivers.configio import dumps_strict
from drivers.errors import ConfigError, DataError, RecordingError

log = logging.getLogger(__name__)

MANIFEST = "_manifest.json"  # in log/; the `_` keeps it out of pyarrow's reads of the folder
MANIFEST_FORMAT = "tmcell-step-log"
_NAN = float("nan")


def new_run_dir(root: Path, task: str) -> Path:
    """A new folder `root`/<timestamp>-<task>[-k] (its step log's `log/` is the Recorder's)."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(root) / f"{stamp}-{task}"
    try:
        base.parent.mkdir(parents=True, exist_ok=True)
        # Created, not checked then created: two runs starting in the same second each get their own.
        for k in range(1, 10_000):
            path = base if k == 1 else base.with_name(f"{base.name}-{k}")
            try:
                path.mkdir()
                return path
            except FileExistsError:
                continue
    except OSError as exc:
        raise ConfigError(f"{root}: cannot create a run folder there: {exc.strerror or exc} "
                          "(recording.directory in the config, or --no-record)") from None
    raise ConfigError(f"{root}: 10000 run folders named {base.name}* already exist")


class Recorder:
    """Buffers step rows (flat dicts of scalars/strings) column by column; a worker thread writes them as Parquet
    parts, so the control loop never waits on the disk.

    The first row names the columns and their kinds; a later row's missing column is recorded as null (NaN in a
    column of numbers), an extra one ignored.  The columns whose first value is a float are kept in one numpy
    block per part, which the writer hands to Arrow without converting (the conversion of Python lists took the
    interpreter lock from the control loop for most of a millisecond per part); the others in lists.
    A part that cannot be written fails the recording: `append`, `flush` and `close` raise its RecordingError
    from then on (in the caller's thread, at the latest one period after the failed write), and no later part
    is written (a log with a hole in it would read as a jump in time)."""

    def __init__(self, run_dir: Path, chunk_rows: int = 250) -> None:
        # The parts are built and written beside the control periods.  pyarrow's default pool (jemalloc) hands the
        # memory back to the OS in the background afterwards, and the next few dozen periods ran slower (5 % on
        # average against 2.5 % with the system allocator, peg runs alternated): the process keeps malloc's.
        pa.set_memory_pool(pa.system_memory_pool())
        self.run_dir = Path(run_dir)
        self.log_dir = self.run_dir / "log"
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.chunk_rows = chunk_rows
        self._names: list[str] | None = None  # every column, in the first row's order
        self._numbers: list[str] = []  # the columns of floats, rows of `_block`
        self._columns: dict[str, list[Any]] = {}  # the others
        self._block = np.empty((0, chunk_rows))
        self._rows = 0  # rows in `_block` and `_columns` not yet handed over
        self._parts = 0
        self._checksums: dict[str, dict[str, Any]] = {}  # part file -> sha256 and rows, as in the manifest
        self.rows_written = 0
        self.closed = False
        self._failure: RecordingError | None = None
        # One worker, so the parts are written in order.  A part takes a few milliseconds (half a period, more on a
        # slow or busy disk); written in the loop's thread it delayed the next period.  The worker is started here,
        # before any control loop, so that the loop's raised priority covers it too (cell/control/priority.py):
        # it holds the interpreter lock while it converts a part's columns.
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="step-log")
        self._writer.submit(lambda: None).result()
        self._pending: collections.deque[Future[None]] = collections.deque()

    def append(self, row: dict[str, Any]) -> None:
        if self.closed:
            raise RuntimeError("recording is closed")
        if self._failure is not None:
            raise self._failure
        if self._names is None:
            self._names = list(row)
            self._numbers = [c for c, v in row.items() if isinstance(v, float)]
            self._columns = {c: [] for c, v in row.items() if not isinstance(v, float)}
            self._block = np.empty((len(self._numbers), self.chunk_rows))
        try:
            self._block[:, self._rows] = [row.get(c, _NAN) for c in self._numbers]
        except (TypeError, ValueError):
            bad = next((c for c in self._numbers if not isinstance(row.get(c), (float, int, type(None)))), "?")
            wait(self._pending)  # the parts before this row are whole: they are written first
            self._failure = RecordingError(f"{self.log_dir / _part_name(self._parts)}: cannot write the step log: "
                                           f"column {bad!r} holds a {type(row.get(bad)).__name__} among numbers")
            raise self._failure from None
        for name, values in self._columns.items():
            values.append(row.get(name))
        self._rows += 1
        if self._rows >= self.chunk_rows:
            self._hand_over()

    def flush(self) -> None:
        """Hand the buffered rows to the writer and wait until every part so far is on disk (RecordingError if one
        could not be written)."""
        if self._rows:
            self._hand_over()
        while self._pending:
            self._pending.popleft().result()
        if self._failure is not None:
            raise self._failure

    def _hand_over(self) -> None:
        assert self._names is not None
        rows, self._rows = self._rows, 0
        block, self._block = self._block, np.empty_like(self._block)
        others, self._columns = self._columns, {c: [] for c in self._columns}
        numbers = {c: block[j, :rows] for j, c in enumerate(self._numbers)}
        columns = {c: numbers[c] if c in numbers else others[c] for c in self._names}
        part = self.log_dir / _part_name(self._parts)
        self._parts += 1
        # Futures of written parts are dropped as they complete: a failure is kept in `_failure`.
        while self._pending and self._pending[0].done():
            self._pending.popleft()
        self._pending.append(self._writer.submit(self._write_part, part, columns, rows))

    def _write_part(self, final: Path, columns: dict[str, Any], rows: int) -> None:
        """The worker's job: one part, its checksum and the manifest."""
        if self._failure is not None:
            raise self._failure
        try:
            table = pa.table(columns)
            # Not synced to disk: a killed run still leaves every part whole.
            save_atomic(final, lambda tmp: pq.write_table(table, tmp), durable=False)
            self._checksums[final.name] = {"sha256": _sha256(final), "rows": rows}
            self._write_manifest()
        except OSError as exc:
            self._failure = RecordingError(f"{final}: cannot write the step log: {exc.strerror or exc}")
            raise self._failure from None
        except pa.ArrowException as exc:  # a column whose rows hold values of different kinds
            self._failure = RecordingError(f"{final}: cannot write the step log: {type(exc).__name__}: {exc}")
            raise self._failure from None
        except RecordingError as exc:
            self._failure = exc
            raise
        self.rows_written += rows

    def _write_manifest(self) -> None:
        """The parts' checksums, replaced whole (a reader sees the previous manifest or this one)."""
        path = self.log_dir / MANIFEST
        doc = {"format": MANIFEST_FORMAT, "format_version": 1, "parts": self._checksums}
        try:
            write_atomic(path, json.dumps(doc, indent=1) + "\n", durable=False)
        except OSError as exc:
            raise RecordingError(f"{path}: cannot write the step log's manifest: {exc.strerror or exc}") from None

    def close(self) -> None:
        """Write what is buffered and wait for the writer (RecordingError if a part could not be written)."""
        if self.closed:
            return
        try:
            self.flush()
        finally:
            self.closed = True
            self._writer.shutdown(wait=True)

    def write_config(self, config: dict[str, Any]) -> None:
        _write(self.run_dir / "config.yaml", yaml.safe_dump(config, sort_keys=False))

    def write_summary(self, summary: dict[str, Any]) -> Path:
        path = self.run_dir / "summary.json"
        _write(path, dumps_strict(summary, indent=2) + "\n")
        return path


def _part_name(index: int) -> str:
    return f"part-{index:05d}.parquet"


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot write: {exc.strerror or exc}") from None


def read_log(run_dir: Path) -> pa.Table:
    """The whole step log of a run (every completed chunk)."""
    return pq.read_table(Path(run_dir) / "log")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def verify_log(run_dir: Path) -> bool:
    """Check every part of a run's step log against its manifest: each listed part present with its sha256,
    no part unlisted.  One-line DataError otherwise; False (nothing to check) for a recording made before
    the manifest existed."""
    log_dir = Path(run_dir) / "log"
    path = log_dir / MANIFEST
    if not path.exists():
        return False
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise DataError(f"{path}: unreadable step-log manifest ({type(exc).__name__})") from None
    parts = doc.get("parts") if isinstance(doc, dict) and doc.get("format") == MANIFEST_FORMAT else None
    if not isinstance(parts, dict) or not all(isinstance(v, dict) for v in parts.values()):
        raise DataError(f"{path}: not a step-log manifest (format {MANIFEST_FORMAT!r} with its parts)")
    on_disk = {p.name for p in log_dir.glob("*.parquet") if not p.name.startswith((".", "_"))}
    unlisted = sorted(on_disk - set(parts))
    if unlisted:
        raise DataError(f"{log_dir / unlisted[0]}: a step-log part the manifest does not list (added afterwards?)")
    for name, entry in sorted(parts.items()):
        part = log_dir / name
        if name not in on_disk:
            raise DataError(f"{part}: listed in the step log's manifest but missing")
        try:
            actual = _sha256(part)
        except OSError as exc:
            raise DataError(f"{part}: cannot read: {exc.strerror or exc}") from None
        if actual != entry.get("sha256"):
            raise DataError(f"{part}: checksum mismatch (sha256 {actual[:12]}..., the manifest's "
                            f"{str(entry.get('sha256'))[:12]}...): the file is damaged")
    return True
