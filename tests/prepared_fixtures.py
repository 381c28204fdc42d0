"""Artefacts that take a minute to build, built once per test run and shared by the tests that need them.

`prepared_peg`, `prepared_wipe`: the tool's virtual-sensor artefacts (dataset, causal H1, calibration) exactly
as `main.py run` builds them on a fresh clone when they are missing (`app.sensing.run_prepare` with the default
config on the simulated cell), made once in the run's shared folder and copied into the test's own working
directory (`artifacts/`): a test that writes there changes its own copy, never the shared one.

Shared across pytest-xdist workers: the run's shared folder is the parent of each worker's base temporary
folder (the base folder itself without xdist), and the first process to need an artefact builds it under a
file lock while the others wait for it (`built_once`).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

_RUN_DIR: list[Path] = []  # the run's shared folder, set by the session fixture below


@pytest.fixture(scope="session", autouse=True)
def _shared_run_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The folder all of this run's test processes share (one per run, below pytest's base temporary folder)."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared"
    root.mkdir(exist_ok=True)
    _RUN_DIR[:] = [root]
    yield root
    _RUN_DIR.clear()


def run_dir() -> Path:
    """The run's shared folder (a fresh temporary one when called outside a pytest run)."""
    if not _RUN_DIR:
        _RUN_DIR.append(Path(tempfile.mkdtemp(prefix="tmcell-tests-")))
    return _RUN_DIR[0]


def built_once(name: str, build: Callable[[Path], None]) -> Path:
    """`<run dir>/<name>`, made by `build(folder)` the first time any process of this run asks for it.

    The build runs under an exclusive lock on `<name>.lock` and is marked complete (`<name>.done`) when it
    returns: a process waiting on the lock finds either no mark (and builds afresh) or the whole artefact,
    never half of one; a failed build leaves no mark, and the next asker tries again."""
    root = run_dir()
    folder, mark = root / name, root / f"{name}.done"
    with open(root / f"{name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not mark.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            mark.touch()
    return folder


def _prepare_in(tool: str) -> Callable[[Path], None]:
    def build(folder: Path) -> None:
        # What a run on a fresh clone does when the tool's artefacts are missing (app.sensing
        # .ensure_virtual_artefacts): the default config's paths, relative to the working directory.
        from app.sensing import PREPARE_SAMPLES, run_prepare
        from cell.config import load_config

        with contextlib.chdir(folder):
            run_prepare(load_config(), tool, "sim", None, PREPARE_SAMPLES, force=False)

    return build


def _copy_prepared(tool: str) -> Path:
    """The tool's prepared artefacts, copied into the working directory's artifacts/ (the test's own)."""
    store = built_once(f"prepared-{tool}", _prepare_in(tool))
    dst = Path.cwd() / "artifacts"
    shutil.copytree(store / "artifacts", dst, dirs_exist_ok=True)
    return dst


@pytest.fixture
def prepared_peg(_isolated_runs: None) -> Path:
    """The peg tool's prepared artefacts in the test's working directory (built once per run)."""
    return _copy_prepared("peg")


@pytest.fixture
def prepared_wipe(_isolated_runs: None) -> Path:
    """The wiping tool's prepared artefacts in the test's working directory (built once per run)."""
    return _copy_prepared("wipe")
