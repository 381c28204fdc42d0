"""`main.py import ur10e`: UR10e CSV logs (31 columns, no header) as a dataset; payloads; robot checks."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml

from cell.data.dataset import load_split, load_trajectories
from cell.model.specs import load_robot_spec
from drivers.errors import ConfigError, DataError
from main import main
from tasks.lab import import_ur10e as imp
from tasks.lab.evaluate import evaluate

GAINS = np.asarray(load_robot_spec("ur10e").torque_constants)


def log_rows(n: int = 300, t0: float = 1884.221, seed: int = 0, gap_after: int | None = None,
             long_step_after: int | None = None) -> np.ndarray:
    """(n, 31) rows like the public logs: jittered 9-12 ms steps, optionally one 0.2 s gap and one 30 ms step."""
    rng = np.random.default_rng(seed)
    dt = np.where(np.arange(n - 1) % 3 == 0, 0.012, 0.009)
    if gap_after is not None:
        dt[gap_after] = 0.2
    if long_step_after is not None:
        dt[long_step_after] = 0.03
    t = t0 + np.concatenate([[0.0], np.cumsum(dt)])
    s = np.linspace(0, 3, n)[:, None]
    q = 0.5 * np.sin(s + np.arange(6)) - np.array([0, 1.5, 0, 1.5, 0, 0])
    qd = 0.5 * np.cos(s + np.arange(6))
    current = rng.normal(0, 2, (n, 6))
    return np.column_stack([t, q, qd, current, 0.9 * current, current * GAINS])


def csv_lines(rows: np.ndarray) -> list[str]:
    return [",".join(f"{v:.4f}" for v in r) for r in rows]


def write_csv(path: Path, lines: list[str]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def malformed_log(path: Path) -> tuple[Path, np.ndarray]:
    """A log with a 30-column row (line 11), 'abc' (21), 'nan' (31), a repeated time stamp (lines 40-41)
    and a 0.2 s gap after row 150; returns the path and the rows as written (parsed back)."""
    rows = log_rows(300, gap_after=150)
    lines = csv_lines(rows)
    lines[10] = ",".join(lines[10].split(",")[:30])
    f = lines[20].split(",")
    f[5] = "abc"
    lines[20] = ",".join(f)
    f = lines[30].split(",")
    f[8] = "nan"
    lines[30] = ",".join(f)
    f = lines[40].split(",")
    f[0] = lines[39].split(",")[0]
    lines[40] = ",".join(f)
    written = np.array([[float(v) for v in line.split(",")] for line in csv_lines(rows)])
    return write_csv(path, lines), written


@pytest.fixture
def logs(tmp_path) -> dict[str, Path]:
    train, written = malformed_log(tmp_path / "csv" / "train" / "ur-harm.csv")
    write_csv(tmp_path / "csv" / "train" / "ur-harm2.csv", csv_lines(log_rows(200, seed=1, long_step_after=50)))
    test = write_csv(tmp_path / "csv" / "ur-joint_1.csv", csv_lines(log_rows(150, seed=2)))
    loaded = write_csv(tmp_path / "csv" / "ur-harm50secLoad.csv", csv_lines(log_rows(120, seed=3)))
    return {"train_file": train, "train_dir": train.parent, "test": test, "loaded": loaded,
            "written": written}  # type: ignore[dict-item]


def run_import(tmp_path: Path, logs: dict, **kw) -> tuple[Path, dict]:
    out = tmp_path / "data"
    summary = imp.import_ur10e(out, train=[logs["train_dir"]], test=[logs["test"]], loaded=[logs["loaded"]], **kw)
    return out, summary


def test_torque_is_current_times_gain_and_speeds_are_kept(tmp_path, logs):
    out, _ = run_import(tmp_path, logs)
    table = pq.read_table(out / "test" / "ur-joint_1.parquet")
    rows = np.array([[float(v) for v in line.split(",")] for line in logs["test"].read_text().splitlines()])
    assert table.column_names == ["t", *[f"q{i}" for i in range(1, 7)], *[f"dq{i}" for i in range(1, 7)],
                                  *[f"tau{i}" for i in range(1, 7)], "traj"]
    tau = np.column_stack([table.column(f"tau{i}").to_numpy() for i in range(1, 7)])
    np.testing.assert_allclose(tau, rows[:, 13:19] * GAINS, rtol=1e-12)
    dq = np.column_stack([table.column(f"dq{i}").to_numpy() for i in range(1, 7)])
    np.testing.assert_array_equal(dq, rows[:, 7:13])
    t = table.column("t").to_numpy()
    assert t[0] == 0.0 and t[-1] == pytest.approx(rows[-1, 0] - rows[0, 0])


def test_malformed_rows_are_dropped_counted_and_warned_once(tmp_path, logs, caplog):
    with caplog.at_level(logging.WARNING, logger="tasks.lab.import_ur10e"):
        out, summary = run_import(tmp_path, logs)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, warnings  # only the malformed file warns, once
    assert "ur-harm.csv" in warnings[0] and "dropped 5 of 300 rows" in warnings[0]
    assert "first bad line 11" in warnings[0]
    row = summary["per_file"]["train/ur-harm.parquet"]
    assert row["rows_kept"] == 295 and row["rows_dropped"] == 5 and row["first_bad_line"] == 11
    doc = json.loads((out / "import.json").read_text())
    rec = doc["splits"]["train"][0]
    assert rec["dropped_by_reason"] == {"column count": 1, "not a number": 1, "not finite": 1,
                                        "time not strictly increasing": 2}  # both rows of the repeat
    # The kept rows are the written ones, unrepaired (lines 11, 21, 31, 40, 41 gone).
    table = pq.read_table(out / "train" / "ur-harm.parquet")
    kept = np.delete(logs["written"], [10, 20, 30, 39, 40], axis=0)
    np.testing.assert_allclose(table.column("q3").to_numpy(), kept[:, 3])
    np.testing.assert_allclose(table.column("t").to_numpy(), kept[:, 0] - kept[0, 0], atol=1e-9)


def test_time_rule_drops_both_rows_of_an_out_of_order_pair():
    t = np.array([1.0, 1.01, 5000.0, 1.03, 1.04, 1.04, 1.06, 1.07, 0.5, 1.09])  # a spike, a repeat, a dip
    keep = imp.increasing_time(t)
    assert keep.tolist() == [True, True, False, False, False, False, True, False, False, True]
    assert np.all(np.diff(t[keep]) > 0)


def test_a_file_without_valid_rows_is_an_error(tmp_path):
    bad = write_csv(tmp_path / "bad.csv", ["1,2,3", "abc"])
    with pytest.raises(DataError, match=r"bad\.csv: no valid rows"):
        imp.import_ur10e(tmp_path / "out", train=[bad])


def test_gaps_split_trajectories_but_jitter_does_not(tmp_path, logs):
    out, summary = run_import(tmp_path, logs)
    assert summary["per_file"]["train/ur-harm.parquet"]["trajectories"] == 2  # the 0.2 s gap
    assert summary["per_file"]["train/ur-harm2.parquet"]["trajectories"] == 1  # a 30 ms step is not a gap
    trajs = load_split(out / "dataset.yaml", "train", 6, "ur10e")
    assert [len(t) for t in trajs] == [151 - 5, 149, 200]  # rows 0..150 less the 5 dropped, then 151..299
    traj = pq.read_table(out / "train" / "ur-harm.parquet").column("traj").to_numpy()
    assert set(traj.tolist()) == {0, 1}
    # Without the manifest's max_gap_s the 1.5 x median rule would cut at the 30 ms step as well.
    assert len(load_trajectories(out / "train" / "ur-harm2.parquet", 6)) == 2
    assert len(load_trajectories(out / "train" / "ur-harm2.parquet", 6, max_gap_s=0.05)) == 1


def test_payload_columns_and_trajectory_payload(tmp_path, logs):
    out, summary = run_import(tmp_path, logs)
    table = pq.read_table(out / "loaded" / "ur-harm50secLoad.parquet")
    assert np.all(table.column("payload_kg").to_numpy() == 2.805)
    for c in ("payload_com_x", "payload_com_y", "payload_com_z"):
        assert np.isnan(table.column(c).to_numpy()).all()  # the centre of mass is not published
    assert "payload_kg" not in pq.read_table(out / "test" / "ur-joint_1.parquet").column_names
    (loaded,) = load_split(out / "dataset.yaml", "loaded", 6, "ur10e")
    assert loaded.payload == (2.805, None)
    assert loaded.slice(0, 10).payload == (2.805, None)
    assert all(t.payload is None for t in load_split(out / "dataset.yaml", "test", 6))
    assert summary["per_file"]["loaded/ur-harm50secLoad.parquet"]["payload_kg"] == 2.805


def _payload_file(path: Path, kg: np.ndarray, com: np.ndarray | None) -> Path:
    n = len(kg)
    cols = {"t": np.arange(n) * 0.01, **{f"q{i}": np.zeros(n) for i in range(1, 7)},
            **{f"tau{i}": np.zeros(n) for i in range(1, 7)}, "payload_kg": kg}
    if com is not None:
        cols.update({f"payload_com_{a}": com[:, k] for k, a in enumerate("xyz")})
    pq.write_table(pa.table(cols), path)
    return path


def test_payload_must_be_constant_within_a_trajectory(tmp_path):
    com = np.tile([0.0, 0.01, 0.05], (10, 1))
    (tr,) = load_trajectories(_payload_file(tmp_path / "a.parquet", np.full(10, 1.5), com), 6)
    assert tr.payload is not None and tr.payload[0] == 1.5
    np.testing.assert_array_equal(tr.payload[1], [0.0, 0.01, 0.05])
    kg = np.full(10, 1.5)
    kg[5] = 2.0
    with pytest.raises(DataError, match=r"a2\.parquet: column 'payload_kg' changes within trajectory 0"):
        load_trajectories(_payload_file(tmp_path / "a2.parquet", kg, None), 6)
    com[3, 2] = np.nan
    with pytest.raises(DataError, match="payload_com_x..z' change within trajectory"):
        load_trajectories(_payload_file(tmp_path / "a3.parquet", np.full(10, 1.5), com), 6)


def test_manifest_names_the_robot_and_the_loaded_files(tmp_path, logs):
    out, _ = run_import(tmp_path, logs)
    man = yaml.safe_load((out / "dataset.yaml").read_text())
    assert man["robot"] == "ur10e" and man["joints"] == 6 and man["max_gap_s"] == 0.05
    assert man["train"] == ["train/ur-harm.parquet", "train/ur-harm2.parquet"]
    assert man["test"] == ["test/ur-joint_1.parquet"] and man["loaded"] == ["loaded/ur-harm50secLoad.parquet"]
    assert 0.009 <= man["period_s"] <= 0.012


def test_a_dataset_of_another_robot_is_refused(tmp_path, logs, cfg, capsys):
    out, _ = run_import(tmp_path, logs)
    manifest = out / "dataset.yaml"
    with pytest.raises(DataError) as exc:
        load_split(manifest, "train", 6, "tm5-700")
    assert str(exc.value) == f"{manifest}: the dataset is of robot 'ur10e' but --robot is 'tm5-700'"
    with pytest.raises(DataError, match="--robot is 'tm5-700'"):
        evaluate(cfg, manifest, tmp_path / "eval", curve=None)
    code = main(["-q", "train", "--data", str(manifest), "--model", "P1", "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0] == f"error: {manifest}: the dataset is of robot 'ur10e' but --robot is 'tm5-700'"
    code = main(["-q", "train", "--data", str(manifest), "--model", "P1", "--out", str(tmp_path / "m"),
                 "--robot", "ur10e", "--json"])
    assert code == 0, capsys.readouterr().err
    trained = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert trained["meta"]["robot"] == "ur10e"


def _strict_json(line: str) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"bare {name} in JSON")

    return json.loads(line, parse_constant=refuse)


def test_cli_import_end_to_end_with_json(tmp_path, logs, capsys):
    out = tmp_path / "cli"
    code = main(["-q", "import", "ur10e", "--train", str(logs["train_dir"]), "--test", str(logs["test"]),
                 "--loaded", str(logs["loaded"]), "--out", str(out), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = _strict_json(captured.out.strip().splitlines()[-1])
    assert summary["robot"] == "ur10e" and summary["files"] == 4
    assert summary["rows_dropped"] == 5 and summary["trajectories"] == {"train": 3, "test": 1, "loaded": 1}
    assert summary["per_file"]["loaded/ur-harm50secLoad.parquet"]["payload_kg"] == 2.805
    _strict_json((out / "import.json").read_text())
    assert len(load_split(out / "dataset.yaml", "test", 6, "ur10e")) == 1


def test_cli_errors_are_one_line_and_exit_2(tmp_path, logs, capsys, monkeypatch):
    monkeypatch.setattr(imp, "shared_data_root", lambda: tmp_path / "nowhere")
    assert main(["-q", "import", "ur10e", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0] and "--train/--test" in err[0]
    assert main(["-q", "import", "ur10e", "--train", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.csv: no such file or folder" in err[0]
    bad = write_csv(tmp_path / "empty.csv", ["x,y"])
    assert main(["-q", "import", "ur10e", "--train", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "empty.csv: no valid rows" in err[0]
    with pytest.raises(ConfigError, match="one split"):
        imp.import_ur10e(tmp_path / "o", train=[logs["test"]], test=[logs["test"]])


def test_the_public_logs_import_with_few_dropped_rows(tmp_path):
    root = imp.shared_data_root()
    if not root.is_dir():
        pytest.skip(f"../shared/data/ur10e not present: the public UR10e logs are not at {root}")
    summary = imp.import_ur10e(tmp_path / "ur10e")
    defaults = imp.default_sources(root)
    assert summary["files"] == sum(len(v) for v in defaults.values()) > 0
    assert len(defaults["loaded"]) >= 1 and len(defaults["test"]) >= 1
    for name, row in summary["per_file"].items():
        total = row["rows_kept"] + row["rows_dropped"]
        assert row["rows_dropped"] < 0.01 * total, (name, row)
        table = pq.read_table(tmp_path / "ur10e" / name)
        tau = np.column_stack([table.column(f"tau{i}").to_numpy()[:20] for i in range(1, 7)])
        assert np.isfinite(tau).all() and np.abs(tau).max() < 400, name  # the first rows: finite, within efforts
    for split in ("train", "test", "loaded"):
        assert load_split(tmp_path / "ur10e" / "dataset.yaml", split, 6, "ur10e")
