"""No silent wrong state: an interrupted calibration stores nothing, `import --test` keeps the training defaults,
`bench model` holds out trajectories of a dataset without a test split, `plan` says "not calibrated" rather than
inventing a kinematic figure, `status` labels its wrench, `emulate cell` outlives a closed stdin on its port,
and long jobs off a terminal log their progress in ~10 % steps."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml

from bench.planning_calibration import bisect_fraction, load_or_calibrate
from cell.data.dataset import load_split
from tasks.lab import import_ur10e as imp
from tests.test_import_ur10e import csv_lines, log_rows, write_csv

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------ the planning calibration
def calibration_with_run(run):
    """A calibration whose 'plan' at fraction f is a stand-in trajectory carrying f."""
    from types import SimpleNamespace

    ref = [("a", np.zeros(6)), ("b", np.ones(6))]

    def plan_at(f):
        return lambda w: SimpleNamespace(fraction=f, duration=1.0 / f)

    return lambda: {"fraction": bisect_fraction(plan_at, ref, run, 0.9, 6, 0.05, 1.0, "kinematic")[0]}


def test_an_interrupted_calibration_stores_nothing(tmp_path):
    calls = []

    def run(traj):  # over the limit above a fraction of 0.3; Ctrl+C during the fourth reference run
        calls.append(traj)
        over = traj.fraction > 0.3
        return {"outcome": "interrupted" if len(calls) == 4 else "done", "peak_ratio": [1.0 if over else 0.5]}

    path = tmp_path / "planning" / "kinematic.json"
    with pytest.raises(KeyboardInterrupt):
        load_or_calibrate(path, {"arm": "x"}, calibration_with_run(run))
    assert len(calls) == 4
    assert not path.exists() and not list(tmp_path.rglob("*.json*"))


def test_a_completed_calibration_is_stored_and_reused(tmp_path):
    def run(traj):
        return {"outcome": "done", "peak_ratio": [1.0 if traj.fraction > 0.3 else 0.5]}

    path = tmp_path / "kinematic.json"
    made = load_or_calibrate(path, {"arm": "x"}, calibration_with_run(run))
    assert made["loaded"] is False and 0.2 < made["fraction"] <= 0.3
    assert [p.name for p in tmp_path.iterdir()] == ["kinematic.json"]  # no temporary file left beside it
    again = load_or_calibrate(path, {"arm": "x"}, lambda: pytest.fail("calibrated again"))
    assert again["loaded"] is True and again["fraction"] == made["fraction"]


# ------------------------------------------------------------------------------------ import ur10e --test
def test_import_with_only_test_keeps_the_default_training(tmp_path, monkeypatch):
    root = tmp_path / "ur10e"
    write_csv(root / "identification" / "ur-harm.csv", csv_lines(log_rows(200, seed=1)))
    write_csv(root / "identification" / "ur-harm50secLoad.csv", csv_lines(log_rows(120, seed=3)))
    write_csv(root / "jointwise" / "ur-joint_1.csv", csv_lines(log_rows(150, seed=2)))
    mine = write_csv(tmp_path / "mine" / "ur-collision.csv", csv_lines(log_rows(150, seed=4)))
    monkeypatch.setattr(imp, "shared_data_root", lambda: root)
    summary = imp.import_ur10e(tmp_path / "out", test=[mine])
    assert summary["trajectories"]["train"] >= 1 and summary["trajectories"]["loaded"] >= 1, summary
    manifest = yaml.safe_load((tmp_path / "out" / "dataset.yaml").read_text())
    assert [Path(f).stem for f in manifest["test"]] == ["ur-collision"]


# ---------------------------------------------------------------------------- bench model's held-out split
def test_bench_model_holds_out_trajectories_when_the_dataset_has_no_test_split(tmp_path):
    from app.commands_bench import held_out_dataset

    data = tmp_path / "data"
    data.mkdir()
    n, trajs = 40, 6
    cols = {"t": np.tile(np.arange(n) * 0.008, trajs)}
    for name in ("q", "dq", "tau"):
        for j in range(1, 7):
            cols[f"{name}{j}"] = np.sin(np.arange(n * trajs) * 0.01 * j)
    cols["traj"] = np.repeat(np.arange(trajs), n)
    pq.write_table(pa.table(cols), data / "train.parquet")
    (data / "dataset.yaml").write_text("robot: tm5-700\njoints: 6\nperiod_s: 0.008\ntrain:\n- train.parquet\n"
                                       "test: []\n")
    derived, held = held_out_dataset(data / "dataset.yaml", tmp_path / "tmp")
    assert held == 1 and derived != data / "dataset.yaml"
    test = load_split(derived, "test", 6, "tm5-700")
    train = load_split(derived, "train", 6, "tm5-700")
    assert len(test) == 1 and len(train) == trajs - 1
    (data / "dataset.yaml").write_text(
        (data / "dataset.yaml").read_text().replace("test: []", "test:\n- train.parquet"))
    assert held_out_dataset(data / "dataset.yaml", tmp_path / "tmp2") == (data / "dataset.yaml", 0)


# ------------------------------------------------------------------------------ plan against kinematic
def test_plan_says_not_calibrated_without_a_kinematic_calibration(tmp_path):
    from app.commands_plan import add_kinematic_comparison, kinematic_baseline
    from app.planning_model import PLANS
    from cell.config import load_config
    from cell.model.specs import cell_robot
    from tasks.setup.plan import load_plan_file

    cfg = load_config(None)
    robot = cell_robot(cfg)
    pcfg = load_plan_file(PLANS).planner
    baseline = kinematic_baseline(cfg, robot, None, pcfg, None, "sim", None, tmp_path)
    assert baseline[0] is None and baseline[1].startswith("not calibrated")
    (tmp_path / "kinematic.json").write_text(json.dumps({"key": {"arm": "another"}, "acceleration_limits": [1] * 6}))
    assert kinematic_baseline(cfg, robot, None, pcfg, None, "sim", None, tmp_path)[1].startswith(
        "not calibrated for this arm")
    out: dict[str, Any] = {"paths": {"p": {"improvement_vs_uniform_pct": 44.0, "optimized_s": 1.0}},
                            "mean_improvement_vs_uniform_pct": 44.0}
    add_kinematic_comparison(out, baseline, {}, cfg, robot, None)
    assert out["mean_improvement_vs_kinematic_pct"] == "not calibrated"
    assert out["paths"]["p"]["improvement_vs_kinematic_pct"] == "not calibrated"
    assert out["paths"]["p"]["improvement_vs_uniform_pct"] == 44.0 == out["mean_improvement_vs_uniform_pct"]


# ---------------------------------------------------------------------------------------------- status
class _FakeArm:
    class lifecycle:  # noqa: N801 - stands in for the enum member
        value = "armed"

    def read_state(self):
        from types import SimpleNamespace

        return SimpleNamespace(t=1.5, q=np.zeros(6), dq=np.zeros(6), tau=np.arange(6.0),
                               status=SimpleNamespace(estop=False, project_running=True))


class _FakeForce:
    def read(self, state):
        from types import SimpleNamespace

        return SimpleNamespace(vector=np.array([1.0, 2.0, 60.0, 0.1, 0.2, 0.3]))


class _FakeRobot:
    def tcp_pose(self, q):
        from types import SimpleNamespace

        return SimpleNamespace(translation=np.array([0.4, 0.1, 0.2]))


def test_status_labels_the_wrench_and_watch_refreshes_until_ctrl_c(monkeypatch, capsys):
    from types import SimpleNamespace

    import app.commands_cell as cc
    from main import main

    cell = SimpleNamespace(kind="sim", arm=_FakeArm(), force=_FakeForce())
    holder = SimpleNamespace(open=lambda: cell, close=lambda: None)
    monkeypatch.setattr(cc, "open_cell", lambda *a: holder)
    monkeypatch.setattr(cc, "robot_for", lambda *a: _FakeRobot())
    sleeps = []

    def sleep(s):
        sleeps.append(s)
        if len(sleeps) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr("time.sleep", sleep)
    assert main(["-q", "status", "--watch", "--interval", "0.2"]) == 130
    out = capsys.readouterr().out
    assert out.count("wrench at the F/T sensor face, sensor frame, untared: Fx 1.000 N") == 2
    assert "Fz 60.000 N" in out and "Mx 0.100 N m" in out and "joint torques [N m]" in out
    assert sleeps == [0.2, 0.2]
    assert main(["-q", "status", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["wrench_tared"] is False and "sensor frame" in doc["wrench_frame"] and len(doc["wrench"]) == 6


# ----------------------------------------------------------------------------------------------- progress
def test_bars_off_a_terminal_log_about_every_ten_percent(caplog):
    from tqdm import tqdm

    from app.progress import quiet_bars_off_terminal

    quiet_bars_off_terminal()  # pytest captures stderr: not a terminal
    with caplog.at_level(logging.INFO, logger="tmcell"):
        for _ in tqdm(range(200), desc="job", unit="step", mininterval=0):
            pass
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("job:")]
    assert 9 <= len(lines) <= 11, lines
    assert lines[-1].startswith("job: 200/200 step (100 %)") and "ETA" in lines[0]


# ----------------------------------------------------------------------------------------- emulate cell
@pytest.mark.slow
def test_emulate_cell_serves_on_its_port_with_stdin_closed_until_sigint(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # Its log goes to a file: a pipe nobody reads fills up on a busy machine and the child blocks writing to it.
    log_path = tmp_path / "emulate.log"
    with open(log_path, "w") as log_file:
        proc = subprocess.Popen([sys.executable, str(ROOT / "main.py"), "-q", "emulate", "cell", "--port", str(port)],
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log_file, text=True,
                                cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONFAULTHANDLER": "1"},
                                # The runner may ignore SIGINT (a background job does), and the child would inherit
                                # that; an operator's shell would not, so restore the default before exec.
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert proc.stdout is not None
        endpoint = json.loads(proc.stdout.readline())
        assert endpoint["port"] == port
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(timeout=1.5)  # stdin closed from the start: still serving
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)  # faulthandler writes every thread's stack to the log
            proc.wait(timeout=10)
            pytest.fail(f"emulate cell still running 20 s after SIGINT:\n{log_path.read_text()[-4000:]}")
        assert code == 0, log_path.read_text()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
