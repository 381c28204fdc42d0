"""Where a command will write, checked before its work: a folder it can create and write in, a file it can replace."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from drivers.errors import ConfigError


def _probe(folder: Path, what: str) -> None:
    """Create and remove a file in `folder`: the one test of writability that holds for every filesystem
    (permission bits say nothing about read-only mounts, ACLs or root)."""
    try:
        fd, name = tempfile.mkstemp(dir=folder, prefix=".write-check-")
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        raise ConfigError(f"{what} {folder}: cannot write there: {exc.strerror or exc}") from None


def _nearest_existing(path: Path) -> Path:
    for parent in (path, *path.parents):
        if parent.exists():
            return parent
    return Path(".")


def check_out_dir(path: Path, what: str = "--out") -> Path:
    """`path` is, or can become, a folder this process writes in; nothing is created.  One-line ConfigError
    otherwise (a file in the way, a read-only or missing parent)."""
    path = Path(path)
    existing = _nearest_existing(path)
    if not existing.is_dir():
        where = "" if existing == path else f" ({existing} is a file)"
        raise ConfigError(f"{what} {path}: not a folder{where}")
    _probe(existing, what)
    return path


def check_out_file(path: Path, what: str = "--out") -> Path:
    """`path` is a file this process can write (replace) whose folder exists or can be made; nothing is created."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {path}: a folder, not a file")
    check_out_dir(path.parent, what)
    return path
