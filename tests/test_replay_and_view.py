"""Replay of a recorded run and its Rerun recording: the virtual sensor's figures reproduced, the .rrd read back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.config import CONFIG_DIR
from cell.data.recorder import read_log
from main import main
from tests.vsfixtures import artefacts


@pytest.fixture(scope="module")
def vs():
    return artefacts()


@pytest.fixture(scope="module")
def wipe_run(vs, tmp_path_factory):
    """One wipe with the small model's virtual sensor in the loop, recorded: (run folder, its summary)."""
    import os

    cfg = vs["cfg"]
    here = tmp_path_factory.mktemp("wipe-run")
    raw = yaml.safe_load((CONFIG_DIR / "cell.yaml").read_text())
    raw["robot"]["urdf"] = str(CONFIG_DIR / raw["robot"]["urdf"])
    raw["plant"] = str(CONFIG_DIR / raw["plant"])
    raw["recording"]["directory"] = str(here / "runs")
    raw["virtual_sensor"].update(model_dir=cfg.virtual_sensor.model_dir,
                                 calibration_dir=cfg.virtual_sensor.calibration_dir)
    path = here / "cell.yaml"
    path.write_text(yaml.safe_dump(raw))
    old = os.getcwd()
    os.chdir(here)
    try:
        code = main(["-q", "run", "wipe", "--config", str(path)])
    finally:
        os.chdir(old)
    assert code == 0
    run = next((here / "runs").iterdir())
    return run, json.loads((run / "summary.json").read_text())


def last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.mark.slow
def test_replay_reproduces_the_runs_virtual_vs_sensor_figures(wipe_run, capsys):
    run, summary = wipe_run
    assert summary["virtual_vs_sensor_samples"] > 500
    assert main(["-q", "replay", str(run), "--json"]) == 0
    out = last_json(capsys)
    keys = [k for k in summary if k.startswith("virtual_vs_sensor_")]
    assert len(keys) == 6
    for k in keys:
        assert out[k] == pytest.approx(summary[k], abs=1e-6), k
    assert out["max_abs_difference"] <= 1e-6
    # Another observer on the same recording: scored on the same samples, with its own (different) errors.
    other = "kalman" if summary["virtual_sensor"].startswith("momentum") else "momentum"
    assert main(["-q", "replay", str(run), "--observer", other, "--json"]) == 0
    alt = last_json(capsys)
    assert alt["virtual_sensor"].startswith(other)
    assert alt["virtual_vs_sensor_samples"] == summary["virtual_vs_sensor_samples"]
    assert alt["virtual_vs_sensor_fz_mae_n"] != pytest.approx(summary["virtual_vs_sensor_fz_mae_n"], abs=1e-6)


@pytest.mark.slow
def test_every_run_keeps_a_rerun_recording_that_reads_back(wipe_run):
    from rerun.chunk import RrdReader

    run, summary = wipe_run
    rrd = run / "recording.rrd"
    assert summary["rerun"].endswith("recording.rrd") and rrd.exists()
    table = read_log(run)
    store = RrdReader(rrd).stream().collect()
    series: dict[str, list[float]] = {}
    frames: dict[str, int] = {}
    texts: list[str] = []
    for chunk in store.stream():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith("Scalars:scalars"):
                values = batch.column(name).to_pylist()
                series.setdefault(chunk.entity_path, []).extend(v[0] for v in values)
            elif name.endswith("TextLog:text"):
                texts.extend(str(v[0]) for v in batch.column(name).to_pylist())
        frames[chunk.entity_path] = frames.get(chunk.entity_path, 0) + chunk.num_rows
    # The wrench time series hold what the step log holds, virtual and measured, row for row.
    fz = np.asarray(table.column("fz").to_numpy(zero_copy_only=False), float)
    sensor_fz = np.asarray(table.column("sensor_fz").to_numpy(zero_copy_only=False), float)
    np.testing.assert_allclose(series["/wrench/virtual/fz"], fz)
    np.testing.assert_allclose(series["/wrench/sensor/fz"], sensor_fz)
    assert len(series["/wrench/setpoint/fz"]) == table.num_rows
    # The scene: the arm, its TCP path and the force arrows, one frame every few periods.
    for entity in ("/arm/links", "/arm/geometry/boxes", "/arm/geometry/cylinders", "/arm/tcp_path",
                   "/wrench/virtual/arrow", "/wrench/sensor/arrow"):
        assert frames.get(entity, 0) >= table.num_rows // 5, entity
    # The task's states as they changed, and the outcome.
    assert {"approach", "wipe", "retract"} <= set(texts)
    assert "outcome: done" in texts


def test_replay_refuses_a_folder_that_is_no_run(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nowhere")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["replay", str(tmp_path / "empty")]) == 2
    assert "not a recorded run" in capsys.readouterr().err


def test_write_rrd_of_a_tiny_log(tmp_path, robot):
    """The .rrd writer on a hand-made two-row log with the F/T sensor in the loop: no virtual entities."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    from cell.view.rerun_view import write_rrd

    rows = {"t": [0.0, 0.008], "state": ["approach", "press"], "fz_setpoint": [0.0, 60.0]}
    for i in range(robot.n):
        rows[f"q{i + 1}"] = [0.1 * i, 0.1 * i]
    for k, a in enumerate(("fx", "fy", "fz", "mx", "my", "mz")):
        rows[a] = [float(k), float(k) + 1.0]
    path = write_rrd(tmp_path, pa.table(rows), robot, {"force_source": "sensor", "outcome": "failed",
                                                       "reason": "test"})
    entities = {c.entity_path for c in RrdReader(path).stream().collect().stream()}
    assert {"/wrench/sensor/fz", "/arm/links", "/arm/geometry/boxes", "/task/state", "/events"} <= entities
    assert not any(e.startswith("/wrench/virtual") for e in entities)
    assert Path(path).name == "recording.rrd"


def test_view_is_one_bench_trial_only(capsys):
    assert main(["bench", "peg-in-hole", "--trials", "3", "--view"]) == 2
    assert "--only K" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:  # --view is an option of bench peg-in-hole alone
        main(["bench", "sim", "--view"])
    assert refused.value.code == 2 and "unrecognized arguments: --view" in capsys.readouterr().err
