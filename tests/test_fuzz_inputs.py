"""Fuzzing the cell's inputs (hypothesis): every input gives a result or a one-line error, never a
traceback and never a hang.  Covered: the YAML config loader, the dataset loader (files, manifests and
their bounds), and the CLI's numeric arguments.  The wire codecs have their own property tests
(tests/test_wacoh_codec.py, tests/test_tm5_codecs.py)."""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cell.config import DEFAULT_CONFIG, load_config
from cell.data import dataset
from cell.data.dataset import load_split, load_trajectories
from drivers.errors import CellError, ConfigError, DataError
from main import main

# No per-example deadline: time on a shared machine says little; a runaway input is caught by _within_calls.
FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
SHIPPED = yaml.safe_load(DEFAULT_CONFIG.read_text())
SECTIONS = sorted(SHIPPED)
T = TypeVar("T")


def _one_line(exc: BaseException) -> None:
    assert "\n" not in str(exc) and str(exc)


# "Never a hang" counted in work, not time: loading the shipped config makes about 80k Python and C calls;
# an input that sends the loader into a runaway loop ends at this many, whatever the machine's load.
LOAD_CALL_BUDGET = 1_000_000


class _Runaway(BaseException):
    """Raised from the profiler; a BaseException so no `except Exception` in the code under test hides it."""


def _within_calls(fn: Callable[[], T], budget: int) -> T:
    """fn(), failing the test once it has made more than `budget` function calls."""
    calls = 0

    def count(frame: Any, event: str, arg: Any) -> None:
        nonlocal calls
        if event in ("call", "c_call"):
            calls += 1
            if calls > budget:
                raise _Runaway(f"more than {budget} calls: a runaway loop")

    sys.setprofile(count)
    try:
        return fn()
    finally:
        sys.setprofile(None)


# ------------------------------------------------------------------------------------------- config
scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), st.text(max_size=12),
                    st.floats(allow_nan=True, allow_infinity=True))
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8),
                                                                                           inner, max_size=4),
                      max_leaves=12)


@FAST
@given(section=st.sampled_from(SECTIONS), key=st.text(min_size=1, max_size=20), value=values)
def test_any_mutation_of_the_shipped_config_loads_or_is_one_line(tmp_path, section, key, value):
    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    if isinstance(data[section], dict):
        data[section][key] = value
    else:
        data[section] = value
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    try:
        _within_calls(lambda: load_config(path), LOAD_CALL_BUDGET)
    except ConfigError as exc:
        _one_line(exc)


@FAST
@given(text=st.binary(max_size=400))
def test_arbitrary_bytes_as_a_config_file_are_refused_in_one_line(tmp_path, text):
    path = tmp_path / "cell.yaml"
    path.write_bytes(text)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    _one_line(exc.value)


# ------------------------------------------------------------------------------------------- datasets
def _table(rows: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    cols = {"t": np.arange(rows) * 0.008}
    for prefix in ("q", "dq", "tau"):
        for i in range(1, 7):
            cols[f"{prefix}{i}"] = rng.normal(0, 1, rows)
    return cols


@FAST
@given(column=st.sampled_from(["t", "q2", "dq5", "tau1"]), row=st.integers(0, 39),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e300, -1e300, 1e-12])))
def test_one_corrupt_value_loads_or_names_file_column_and_row(tmp_path, column, row, value):
    cols = _table(40, 0)
    cols[column] = cols[column].copy()
    cols[column][row] = value
    path = tmp_path / "d.parquet"
    pq.write_table(pa.table(cols), path)
    try:
        trajs = load_trajectories(path, 6)
    except DataError as exc:
        _one_line(exc)
        assert str(path) in str(exc) and (f"'{column}'" in str(exc))
        return
    for tr in trajs:  # what loads is physical
        assert np.all(np.isfinite(tr.q)) and np.abs(tr.q).max() <= 100 and np.all(np.diff(tr.t) >= 1e-5)


@FAST
@given(flips=st.lists(st.tuples(st.integers(0, 10**9), st.integers(0, 7)), min_size=1, max_size=6))
def test_bit_flipped_parquet_files_load_or_are_one_line_errors(tmp_path, flips):
    path = tmp_path / "d.parquet"
    pq.write_table(pa.table(_table(60, 1)), path)
    raw = bytearray(path.read_bytes())
    for pos, bit in flips:
        raw[pos % len(raw)] ^= 1 << bit
    path.write_bytes(bytes(raw))
    try:
        trajs = load_trajectories(path, 6)
    except DataError as exc:
        _one_line(exc)
        return
    for tr in trajs:
        assert np.all(np.isfinite(tr.tau)) and np.abs(tr.tau).max() <= 1e5


@pytest.mark.parametrize("entry", ["/proc/self", "../../../../../../proc/self/status", "/dev/null", "/sys"])
def test_a_manifest_cannot_point_into_system_trees(tmp_path, monkeypatch, entry):
    manifest = tmp_path / "dataset.yaml"
    manifest.write_text(yaml.safe_dump({"train": [entry], "joints": 6}))
    # Refused from the path alone: never walked (a recursive glob of /proc or /sys would not end) nor read.
    touched: list[str] = []

    def refuse(name: str) -> Callable[..., Any]:
        def spy(*args: Any, **kwargs: Any) -> Any:
            touched.append(name)
            raise AssertionError(f"{name} called on a system tree")
        return spy

    monkeypatch.setattr(Path, "rglob", refuse("Path.rglob"))
    monkeypatch.setattr(Path, "iterdir", refuse("Path.iterdir"))
    monkeypatch.setattr(dataset, "load_trajectories", refuse("load_trajectories"))
    with pytest.raises(DataError) as exc:
        load_split(manifest, "train", 6)
    _one_line(exc.value)
    assert touched == []


def test_a_booster_name_outside_the_artefact_is_refused(tmp_path, robot):
    import json

    from cell.model.dynamics.artefact import load_model, save_model
    from cell.model.dynamics.features import FeatureSpec
    from cell.model.dynamics.learned import XGBParams, fit_learned
    from cell.model.dynamics.rigid_body import nominal_p2
    from tests.test_dynamics_learned import motion

    s = motion(600, 0)
    s.tau = nominal_p2(robot).predict(s.q, s.dq, s.ddq)
    model = fit_learned("H1", robot, s, FeatureSpec(window=1, grouping="own"), XGBParams(n_estimators=3),
                        p2=nominal_p2(robot))
    save_model(model, tmp_path / "m")
    doc = json.loads((tmp_path / "m" / "model.json").read_text())
    doc["boosters"]["1"] = "../../etc/passwd"
    (tmp_path / "m" / "model.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match="is not a booster file of this artefact"):
        load_model(tmp_path / "m", robot)


# ------------------------------------------------------------------------------------------- CLI
NUMERIC_OPTIONS = [
    (["run", "wipe", "--no-record", "--seed"], "seed"),
    (["bench", "peg-in-hole", "--trials"], "trials"),
    (["bench", "peg-in-hole", "--max-offset-mm"], "offset"),
    (["bench", "peg-in-hole", "--peg-diameter-mm"], "diameter"),
    (["collect", "--out", "o", "--samples"], "samples"),
    (["evaluate", "--data", "d.yaml", "--out", "o", "--curve"], "curve"),
    (["bench", "drivers", "--n"], "n"),
]


@settings(max_examples=80, deadline=3000)
@given(option=st.sampled_from(NUMERIC_OPTIONS),
       text=st.one_of(st.text(max_size=8), st.sampled_from(["nan", "inf", "-inf", "-1", "0", "1e400", "1,,2", " "])))
def test_cli_numbers_are_validated_when_parsed(option, text):
    """The parser alone accepts or refuses (argparse: exit 2, one error line); nothing runs."""
    import contextlib
    import io

    from main import build_parser

    argv, dest = option
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            args = build_parser().parse_args([*argv, text])
    except SystemExit as exc:
        assert exc.code == 2
        lines = err.getvalue().strip().splitlines()
        assert lines and "error:" in lines[-1] and "Traceback" not in err.getvalue()
        return
    value = vars(args)[{"offset": "max_offset_mm", "diameter": "peg_diameter_mm"}.get(dest, dest)]
    for v in value if isinstance(value, list) else [value]:
        assert isinstance(v, int | float) and math.isfinite(v) and v >= 0


def test_cell_errors_are_all_one_line_in_the_cli(tmp_path, capsys):
    bad = tmp_path / "cell.yaml"
    bad.write_text("robot: [1, 2\n")
    code = main(["run", "wipe", "--config", str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("error:")
    assert issubclass(ConfigError, CellError)


def test_the_shipped_config_is_a_fixed_point_of_the_loader(tmp_path):
    cfg = load_config()
    assert cfg.safety.max_tool_force_n == SHIPPED["safety"]["max_tool_force_n"]
    assert Path(cfg.source) == DEFAULT_CONFIG
