"""Fuzzing the CLI end to end (main.main(argv)): nested, huge and truncated YAML configs, model files and
datasets give exit code 2 and one error line, never a traceback."""

from __future__ import annotations

import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cell.config import DEFAULT_CONFIG
from main import main

SHIPPED_TEXT = DEFAULT_CONFIG.read_text()
CLI = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def refused(argv: list[str], capsys) -> str:
    """Run the CLI; it must exit 2 with one error line and no traceback.  Returns that line."""
    code = main(["-q", *argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and code == 2 and len(lines) == 1, (code, err)
    return lines[0]


def deep(kind: str, depth: int) -> str:
    if kind == "list":
        return "[" * depth + "]" * depth
    if kind == "map":
        return "{a: " * depth + "1" + "}" * depth
    return "".join("  " * i + "- \n" for i in range(depth)).rstrip() + " x"  # block sequences


# ------------------------------------------------------------------------------------------- configs
@pytest.mark.parametrize("kind", ["list", "map", "block"])
@pytest.mark.parametrize("depth", [40, 400, 5000])
def test_a_deeply_nested_config(tmp_path, capsys, kind, depth):
    path = tmp_path / "cell.yaml"
    path.write_text(SHIPPED_TEXT + f"\nextra: {deep(kind, depth)}\n" if kind != "block"
                    else SHIPPED_TEXT + "\nextra:\n" + deep(kind, depth) + "\n")
    line = refused(["run", "wipe", "--force-source", "sensor", "--config", str(path)], capsys)
    assert str(path) in line


@pytest.mark.parametrize("text", [
    "a: " + "x" * (2 << 20) + "\n",  # larger than any config
    "robot:\n" + "".join(f"  k{i}: {i}\n" for i in range(60_000)),  # a huge mapping within the size cap
    "\x00\x01\x02\xff" * 100,
])
def test_a_huge_or_binary_config(tmp_path, capsys, text):
    path = tmp_path / "cell.yaml"
    path.write_bytes(text.encode("utf-8", "surrogateescape") if "\xff" not in text else text.encode("latin-1"))
    assert str(path) in refused(["run", "wipe", "--force-source", "sensor", "--config", str(path)], capsys)


@CLI
@given(cut=st.integers(1, len(SHIPPED_TEXT) - 1))
def test_a_truncated_config_loads_or_is_refused_in_one_line(tmp_path, capsys, cut):
    path = tmp_path / "cell.yaml"
    path.write_text(SHIPPED_TEXT[:cut])
    # status on a config that loads would open a cell; the parser alone decides here
    from cell.config import load_config
    from drivers.errors import ConfigError

    try:
        load_config(path)
    except ConfigError:
        assert str(path) in refused(["status", "--config", str(path)], capsys)


# ------------------------------------------------------------------------------------------- datasets
def dataset(tmp_path: Path) -> Path:
    import numpy as np

    rng = np.random.default_rng(0)
    cols = {"t": np.arange(200) * 0.008, "traj": np.zeros(200, int), "segment": np.zeros(200, int)}
    for prefix in ("q", "dq", "tau"):
        for i in range(1, 7):
            cols[f"{prefix}{i}"] = rng.normal(0, 0.3, 200)
    folder = tmp_path / "data"
    folder.mkdir()
    pq.write_table(pa.table(cols), folder / "train.parquet")
    pq.write_table(pa.table(cols), folder / "test.parquet")
    (folder / "dataset.yaml").write_text(yaml.safe_dump({"train": ["train.parquet"], "test": ["test.parquet"],
                                                         "joints": 6}))
    return folder / "dataset.yaml"


@pytest.mark.parametrize("damage", ["truncated_parquet", "truncated_manifest", "nested_manifest", "huge_manifest"])
@pytest.mark.parametrize("command", ["train", "evaluate", "bench"])
def test_a_damaged_dataset(tmp_path, capsys, damage, command):
    manifest = dataset(tmp_path)
    if damage == "truncated_parquet":
        part = manifest.parent / "train.parquet"
        part.write_bytes(part.read_bytes()[:300])
    elif damage == "truncated_manifest":
        manifest.write_text(manifest.read_text()[:9])
    elif damage == "nested_manifest":
        manifest.write_text("train: " + deep("list", 500) + "\n")
    else:
        manifest.write_text("train: [" + ", ".join(["train.parquet"] * 200_000) + "]\n")
    argv = {"train": ["train", "--data", str(manifest), "--model", "P1", "--out", str(tmp_path / "m")],
            "evaluate": ["evaluate", "--data", str(manifest), "--out", str(tmp_path / "e"), "--no-curve"],
            "bench": ["bench", "model", "--data", str(manifest)]}[command]
    refused(argv, capsys)


# ------------------------------------------------------------------------------------------- model files
@pytest.fixture(scope="module")
def saved_model(tmp_path_factory) -> Path:
    from tests.test_hardening_cli import make_model

    return make_model(tmp_path_factory.mktemp("model") / "m")


@pytest.mark.parametrize("damage", ["truncated_json", "truncated_booster", "nested_json", "empty_booster"])
@pytest.mark.parametrize("command", [["plan", "--cell", "sim", "--model"], ["calibrate", "--cell", "sim", "--model"],
                                     ["bench", "model", "--data", "DATA", "--model"]])
def test_a_damaged_model(tmp_path, capsys, saved_model, damage, command):
    model = tmp_path / "m"
    shutil.copytree(saved_model, model)
    doc, booster = model / "model.json", model / "booster_j4.ubj"
    if damage == "truncated_json":
        doc.write_text(doc.read_text()[:1000])
    elif damage == "nested_json":
        doc.write_text("[" * 100_000 + "]" * 100_000)
    elif damage == "truncated_booster":
        booster.write_bytes(booster.read_bytes()[:100])
    else:
        booster.write_bytes(b"")
    argv = [dataset(tmp_path).as_posix() if a == "DATA" else a for a in command]
    line = refused([*argv, str(model)], capsys)
    assert str(model) in line
