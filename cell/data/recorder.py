"""Run recordings: runs/<timestamp>-<task>/ with a chunked Parquet step log, resolved config, summary, plot.

The step log is a folder of Parquet parts (`log/part-00000.parquet`, ...), each written whole and
renamed into place, so a run killed at any moment leaves every completed chunk readable
(`pyarrow.parquet.read_table(run/"log")` reads them as one table).
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from drivers.configio import dumps_strict
from drivers.errors import ConfigError, RecordingError

log = logging.getLogger(__name__)


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
    """Buffers step rows (flat dicts of scalars/strings) and flushes them as Parquet parts."""

    def __init__(self, run_dir: Path, chunk_rows: int = 250) -> None:
        self.run_dir = Path(run_dir)
        self.log_dir = self.run_dir / "log"
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.chunk_rows = chunk_rows
        self._rows: list[dict[str, Any]] = []
        self._parts = 0
        self._columns: list[str] | None = None
        self.rows_written = 0
        self.closed = False

    def append(self, row: dict[str, Any]) -> None:
        if self.closed:
            raise RuntimeError("recording is closed")
        if self._columns is None:
            self._columns = list(row)
        elif self.closed:
            return
        self._rows.append(row)
        if len(self._rows) >= self.chunk_rows:
            self.flush()

    def flush(self) -> None:
        if not self._rows:
            return
        assert self._columns is not None
        cols = {c: [r.get(c) for r in self._rows] for c in self._columns}
        table = pa.table(cols)
        final = self.log_dir / f"part-{self._parts:05d}.parquet"
        tmp = final.with_name(f".{final.name}.tmp")  # dot-files are skipped by readers of the folder
        try:
            pq.write_table(table, tmp)
            os.replace(tmp, final)
        except OSError as exc:
            raise RecordingError(f"{final}: cannot write the step log: {exc.strerror or exc}") from None
        self._parts += 1
        self.rows_written += len(self._rows)
        self._rows = []

    def close(self) -> None:
        if self.closed:
            return
        try:
            self.flush()
        finally:
            self.closed = True

    def write_config(self, config: dict[str, Any]) -> None:
        _write(self.run_dir / "config.yaml", yaml.safe_dump(config, sort_keys=False))

    def write_summary(self, summary: dict[str, Any]) -> Path:
        path = self.run_dir / "summary.json"
        _write(path, dumps_strict(summary, indent=2) + "\n")
        return path


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot write: {exc.strerror or exc}") from None


def read_log(run_dir: Path) -> pa.Table:
    """The whole step log of a run (every completed chunk)."""
    return pq.read_table(Path(run_dir) / "log")
