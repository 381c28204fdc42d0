"""Atomic file writes: a reader sees the old file or the new one, never part of one, and writers never collide."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

# mkstemp creates its file readable by the owner only; the file that replaces the target gets the
# permissions a plain open() would have given it (read once here: os.umask can only be read by setting it).
_UMASK = os.umask(0o022)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(target: Path, *, durable: bool = True) -> Iterator[Path]:
    """A temporary path beside `target` to write the new file to; on a clean exit it replaces `target`.

    The name is unique (two processes or threads saving the same file never share one), hidden (a leading
    dot: readers of the folder skip it) and ends in `target`'s extension (writers that choose the format by
    it, e.g. XGBoost's `.ubj`, still do).  `durable` fsyncs the file before the rename and the folder after
    it, so a power cut leaves the old file or the new one; a loop that cannot wait on the disk passes False.
    On any failure the temporary file is removed and `target` is left as it was."""
    target = Path(target)
    fd, name = tempfile.mkstemp(dir=target.parent, prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}")
    os.close(fd)
    tmp = Path(name)
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)
        yield tmp
        if durable:
            _fsync(tmp, os.O_RDONLY)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if durable:
        with contextlib.suppress(OSError):  # not every platform or file system syncs a folder
            _fsync(target.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))


def write_atomic(target: Path, data: str | bytes, *, durable: bool = True) -> Path:
    """Write `data` (text as UTF-8) to `target` atomically; returns `target`."""
    raw = data.encode("utf-8") if isinstance(data, str) else data
    with atomic_path(target, durable=durable) as tmp:
        tmp.write_bytes(raw)
    return Path(target)


def save_atomic(target: Path, save: Callable[[Path], object], *, durable: bool = True) -> Path:
    """Let `save(path)` write the file (a library's own writer), then put it in place atomically."""
    with atomic_path(target, durable=durable) as tmp:
        save(tmp)
    return Path(target)


def _fsync(path: Path, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
