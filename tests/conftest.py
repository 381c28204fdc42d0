"""Shared fixtures (the default config, the nominal robot model) and the `slow` mark, applied by what a test runs."""

from __future__ import annotations

import importlib
import inspect
import io
import os
import re
import textwrap
import tokenize
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from cell.config import CellConfig, load_config, resolve
from cell.control.priority import raised_priority
from cell.model.robot import RobotModel, load_robot

ROOT = Path(__file__).resolve().parents[1]

# The numeric libraries' threads in the test processes and the commands they start.  Two cores shared with
# other jobs, and test.sh runs two test processes: a thread that spins while its partner is descheduled
# turns a millisecond call into a scheduler slice (on a busy machine an SVD of the excitation search took
# 3 ms on one OpenBLAS thread, 520 ms on two; an XGBoost round on two threads 6 ms sleeping, 120 ms
# spinning).  One BLAS thread per process (threadpoolctl for this one, numpy being loaded; the environment
# for its children), and OpenMP threads that sleep while they wait (XGBoost keeps its thread count and
# so its results).  Either can be set otherwise in the environment.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
threadpool_limits(limits=int(os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")

# The drivers' fixtures (emulator, connected device), shared by each driver's test modules; the artefacts
# built once per run and shared by the tests (and the xdist workers) that need them.
pytest_plugins = ["tests.tm5_fixtures", "tests.wacoh_fixtures", "tests.prepared_fixtures", "tests.collision_fixtures"]

# What drives a simulated cell: its factories (the sim cell, the emulated cell in a child process, the app's
# openers), named in code rather than in a string, and the CLI commands that open one (in-process
# `main([...])` or `main.py` in a subprocess).
SIM_CELL_FACTORY = re.compile(r"\b(?:make_sim_cell|EmulatedCell|open_cell|calibration_cells)\b")
SIM_CELL_COMMAND = re.compile(
    r"""\bmain\(\s*\[\s*(?:["']-q["']\s*,\s*)?["'](?:run|bench|plan|prepare|calibrate|collect|status|doctor)["']"""
    r"""|main\.py["']\)?\s*,\s*(?:["']-q["']\s*,\s*)?["'](?:run|bench|plan|prepare|calibrate|collect|status|doctor)["']"""
)
REFUSED = re.compile(r"==\s*2\b|\bSystemExit\b")  # the test expects the command's exit 2: refused before it runs
HELPER_DEPTH = 3  # how far calls into the test module's own helpers are followed


def _source(obj: Any) -> str:
    try:
        return textwrap.dedent(inspect.getsource(obj))
    except (OSError, TypeError):
        return ""


def _code_only(source: str) -> str:
    """The source without its comments and string literals (a test may write code that names a factory)."""
    dropped = {tokenize.COMMENT, tokenize.STRING}
    fstring_parts = ("FSTRING_START", "FSTRING_MIDDLE", "FSTRING_END")  # Python >= 3.12
    dropped |= {getattr(tokenize, n) for n in fstring_parts if hasattr(tokenize, n)}
    try:
        tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    except (tokenize.TokenError, SyntaxError):
        return source
    return " ".join(t.string for t in tokens if t.type not in dropped)


def _names_an_entry(source: str) -> bool:
    """A factory named in code, or a cell command not expected to be refused (exit 2) before a cell opens;
    a refused command that opens a cell after all fails the runtime guard below."""
    if SIM_CELL_FACTORY.search(_code_only(source)):
        return True
    return bool(SIM_CELL_COMMAND.search(source)) and not REFUSED.search(source)


def _helpers(fn: types.FunctionType, depth: int, seen: set[int]) -> Iterator[types.FunctionType]:
    """The functions of fn's own module that fn names (and those they name, to `depth`)."""
    if depth <= 0:
        return
    names: set[str] = set()
    codes = [fn.__code__]
    while codes:  # names used by nested functions and lambdas count too
        code = codes.pop()
        names.update(code.co_names)
        codes.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
    for name in names:
        obj = fn.__globals__.get(name)
        if isinstance(obj, types.FunctionType) and obj.__module__ == fn.__module__ and id(obj) not in seen:
            seen.add(id(obj))
            yield obj
            yield from _helpers(obj, depth - 1, seen)


def drives_a_sim_cell(item: pytest.Item) -> bool:
    """Whether the test's source, its fixtures' or its module helpers' name a sim cell's factory or command."""
    fn = getattr(item, "function", None)
    if not isinstance(fn, types.FunctionType):
        return False
    funcs = [fn, *_helpers(fn, HELPER_DEPTH, {id(fn)})]
    info = getattr(item, "_fixtureinfo", None)
    for defs in (info.name2fixturedefs.values() if info is not None else ()):
        for fixdef in defs:
            func = fixdef.func
            # The suite's own fixtures, not this module's guard (which names the factories it refuses).
            if isinstance(func, types.FunctionType) and func.__module__.startswith("tests.") and \
                    func.__module__ != __name__:
                funcs.append(func)
    return any(_names_an_entry(_source(f)) for f in funcs)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Marks `slow` every test that drives a simulated cell, so `-m "not slow"` leaves it out."""
    for item in items:
        if item.get_closest_marker("slow") is None and drives_a_sim_cell(item):
            item.add_marker(pytest.mark.slow)


def _refuse(what: str, nodeid: str) -> Callable[..., Any]:
    def refuse(*args: Any, **kwargs: Any) -> Any:
        pytest.fail(f"{nodeid} opens {what} but is not marked slow: mark it @pytest.mark.slow, or name the "
                    f"entry point in its source so tests/conftest.py marks it", pytrace=False)
    return refuse


@pytest.fixture(autouse=True)
def _sim_cells_only_in_slow_tests(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test not marked slow fails at the moment it opens a simulated or emulated cell."""
    if request.node.get_closest_marker("slow") is not None:
        return
    for module, attr, name, what in (("sim.cell", "SimCell", "open", "a simulated cell"),
                                     ("sim.emulated", "EmulatedCell", "__init__", "the emulated cell")):
        try:
            cls = getattr(importlib.import_module(module), attr)
        except ImportError:  # a module that does not import cannot open its cell either
            continue
        monkeypatch.setattr(cls, name, _refuse(what, request.node.nodeid))


# The fixtures that serve a test's drivers from a thread of its own process (the TM5 Modbus and WACOH
# emulators) or from a child process (the emulated cell): the replies are due within milliseconds (a 30 ms
# Modbus timeout, a 1 kHz stream, the cell's 8 ms period), and the drivers' threads read them.
DEVICE_FIXTURES = frozenset({"emulator", "make_emulator", "emulated"})


@pytest.fixture(autouse=True)
def _devices_at_raised_priority(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test with such a device runs (and starts its threads and children) at raised priority, as the emulated
    cell's loops do (cell/control/priority.py: nice -10 where permitted): beside another test process and
    other jobs on two cores, its devices then answer and its drivers read in time however busy the machine
    is."""
    if not DEVICE_FIXTURES & set(request.fixturenames):
        yield
        return
    with raised_priority(rt_priority=None):
        yield


@pytest.fixture(autouse=True)
def _isolated_runs(tmp_path, monkeypatch):
    """Every test writes its runs/ below its own temporary folder."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture
def cfg() -> CellConfig:
    return load_config()


@pytest.fixture
def robot(cfg: CellConfig) -> RobotModel:
    return load_robot(resolve(cfg.robot.urdf), cfg.robot.tcp_wipe, cfg.robot.tool_mass, cfg.robot.tool_com)


@pytest.fixture(scope="module")
def robot_module() -> RobotModel:
    """The cell's robot, once per module (for module-scoped fixtures that fit models on it)."""
    from cell.model.specs import cell_robot

    return cell_robot(load_config())


@pytest.fixture
def home(cfg: CellConfig) -> np.ndarray:
    return np.asarray(cfg.robot.home, float)
