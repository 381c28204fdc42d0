"""`main.py detect`: the collision detector over UR10e-format logs (synthetic fixtures; the real logs when present)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from main import main
from tasks.lab.detect import find_pushes
from tasks.lab.import_ur10e import N_COLUMNS, shared_data_root

UR10E = Path(__file__).resolve().parents[1] / "config" / "robots" / "ur10e"
GAINS = np.array([10.0, 10.6956, 8.4566, 9.0029, 9.48, 10.1232])
POSE = np.array([-0.28, -1.95, -1.67, -1.53, 0.99, 0.39])
PUSH_AT_S, PUSH_S, PUSH_NM = 3.0, 0.6, 40.0  # on joint 2 of the held pose


def _times(n: int, t0: float, rng: np.random.Generator) -> np.ndarray:
    """The logs' clock: 10 ms steps with some 2 ms and 30 ms ones."""
    steps = np.full(n - 1, 0.010)
    steps[rng.choice(n - 1, n // 40, replace=False)] = 0.002
    steps[rng.choice(n - 1, n // 40, replace=False)] = 0.030
    return t0 + np.concatenate([[0.0], np.cumsum(steps)])


def _log(t: np.ndarray, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, extra: np.ndarray,
         rng: np.random.Generator) -> np.ndarray:
    """31 columns as the UR10e logs: the URDF's rigid body with viscous and smooth Coulomb friction."""
    model = pin.buildModelFromUrdf(str(UR10E / "ur10e.urdf"))
    data = model.createData()
    tau = np.array([pin.rnea(model, data, q[k], dq[k], ddq[k]) for k in range(len(t))])
    tau += 3.0 * dq + 4.0 * np.tanh(dq / 0.02) + extra + rng.normal(0, 0.3, tau.shape)
    rows = np.zeros((len(t), N_COLUMNS))
    rows[:, 0], rows[:, 1:7], rows[:, 7:13], rows[:, 13:19] = t, q, dq, tau / GAINS
    return rows


def _harmonic(t: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    amp, f, ph = rng.uniform(0.2, 0.4, 6), rng.uniform(0.1, 0.3, 6), rng.uniform(0, 2 * np.pi, 6)
    s = t - t[0]
    w = 2 * np.pi * f
    q = POSE + amp * np.sin(w * s[:, None] + ph)
    dq = amp * w * np.cos(w * s[:, None] + ph)
    ddq = -amp * w**2 * np.sin(w * s[:, None] + ph)
    return q, dq, ddq


def _write(path: Path, rows: np.ndarray) -> Path:
    path.write_text("".join(",".join(f"{v:.6f}" for v in r) + "\n" for r in rows))
    return path


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ur10e_logs")
    rng = np.random.default_rng(3)
    t = _times(6000, 1200.0, rng)
    q, dq, ddq = _harmonic(t, 1)
    train = _write(d / "harm.csv", _log(t, q, dq, ddq, np.zeros_like(q), rng))
    t = _times(800, 300.5, rng)
    hold = np.tile(POSE, (len(t), 1))
    push = np.zeros_like(hold)
    s = t - t[0]
    # a hand's push: 40 N·m on joint 2, ramped over 0.1 s
    push[:, 1] = PUSH_NM * np.clip((s - PUSH_AT_S) / 0.1, 0, 1) * (s < PUSH_AT_S + PUSH_S)
    held = _write(d / "push_pose.csv", _log(t, hold, np.zeros_like(hold), np.zeros_like(hold), push, rng))
    t = _times(1500, 800.25, rng)
    q, dq, ddq = _harmonic(t, 1)  # the training's motion family, another stretch of it
    free = _write(d / "free.csv", _log(t + 25.0, q, dq, ddq, np.zeros_like(q), rng))
    return {"train": train, "hold": held, "free": free, "dir": d}


@pytest.fixture(scope="module")
def dataset(logs: dict[str, Path]) -> Path:
    out = logs["dir"] / "data"
    assert main(["-q", "import", "ur10e", "--train", str(logs["train"]), "--test", str(logs["free"]),
                 "--add-test", str(logs["hold"]), "--out", str(out)]) == 0
    return out / "dataset.yaml"


def _last_json(capsys: pytest.CaptureFixture[str]) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_find_pushes_takes_long_departures_only_and_merges_a_release_rebound():
    t = np.arange(0, 10, 0.01)
    tau = np.tile([2.0, 60.0, 30.0], (len(t), 1))
    tau[(t >= 2.0) & (t < 2.6), 1] += 30.0  # a push on joint 2 ...
    tau[(t >= 2.7) & (t < 2.8), 1] -= 17.0  # ... and its release's rebound, 0.1 s later
    tau[(t >= 5.0) & (t < 5.05), 0] -= 40.0  # 50 ms: a spike, not a push
    tau[(t >= 7.0) & (t < 7.5), 0] -= 16.0  # joint 1, just over 15 N·m
    tau[(t >= 8.0) & (t < 9.0), 2] += 14.0  # under 15 N·m: not a push
    pushes = find_pushes(t, tau)
    assert [(round(p.onset_s, 2), p.joint) for p in pushes] == [(2.0, 2), (7.0, 1)]
    assert pushes[0].end_s == pytest.approx(2.8) and pushes[0].peak_nm == pytest.approx(30.0)


def test_the_import_takes_the_collision_file_as_a_test_log(dataset: Path, logs: dict[str, Path]):
    doc = json.loads((dataset.parent / "import.json").read_text())
    tests = {Path(r["source"]).name: r for r in doc["splits"]["test"]}
    assert set(tests) == {"free.csv", "push_pose.csv"}
    assert tests["push_pose.csv"]["t0_log_s"] == pytest.approx(300.5)


def test_detect_end_to_end_finds_the_push_near_its_onset_and_nothing_in_free_motion(
        dataset: Path, logs: dict[str, Path], capsys: pytest.CaptureFixture[str]):
    png = logs["dir"] / "detect.png"
    model = logs["dir"] / "h1"
    assert main(["-q", "detect", "--robot", "ur10e", "--data", str(dataset), "--model", str(model),
                 "--plot", str(png), "--json"]) == 0
    out = _last_json(capsys)
    rows = {r["name"]: r for r in out["trajectories"]}
    assert set(rows) == {"free.csv", "push_pose.csv"}
    held, free = rows["push_pose.csv"], rows["free.csv"]
    assert held["t0_log_s"] == pytest.approx(300.5) and free["t0_log_s"] == pytest.approx(825.25)
    assert len(held["detections"]) == 1
    d = held["detections"][0]
    assert set(d) >= {"t_s", "joint", "ratio"} and d["joint"] == 2 and d["ratio"] > 1
    assert PUSH_AT_S - 0.05 <= d["t_s"] <= PUSH_AT_S + 0.3
    assert held["pushes"][0]["in_time"] and out["pushes_detected_in_time"] == out["pushes"] == 1
    assert free["detections"] == [] and 0 < free["max_free_ratio"] < 1
    assert held["max_free_ratio"] > 1
    assert png.is_file() and png.stat().st_size > 10_000
    # the saved model is loaded the second time, with the same result
    assert main(["-q", "detect", "--robot", "ur10e", "--data", str(dataset), "--model", str(model), "--json"]) == 0
    again = _last_json(capsys)
    assert again["model"].startswith("loaded")
    assert again["trajectories"] == out["trajectories"]


def test_bad_inputs_exit_2_with_one_line(tmp_path: Path, dataset: Path, capsys: pytest.CaptureFixture[str]):
    assert main(["-q", "detect", "--robot", "ur10e", "--data", str(tmp_path / "nowhere.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere.yaml" in err[0]
    no_test = tmp_path / "train_only.yaml"
    man = dataset.read_text().split("\ntest:")[0]
    no_test.write_text(man.replace("train/", str(dataset.parent / "train") + "/") + "\n")
    assert main(["-q", "detect", "--robot", "ur10e", "--data", str(no_test)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no test trajectories" in err[0] and "train_only.yaml" in err[0]


@pytest.mark.slow
def test_on_the_real_logs_every_push_is_detected_in_time_and_joint_wise_runs_raise_none(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    root = shared_data_root()
    if not (root / "collision").is_dir():
        pytest.skip(f"the public UR10e logs are not at {root}")
    out_dir = tmp_path / "ur10e"
    assert main(["-q", "import", "ur10e", "--add-test", str(root / "collision"), "--out", str(out_dir)]) == 0
    capsys.readouterr()
    assert main(["-q", "detect", "--robot", "ur10e", "--data", str(out_dir / "dataset.yaml"), "--json"]) == 0
    out = _last_json(capsys)
    assert out["pushes"] >= 4 and out["pushes_detected_in_time"] == out["pushes"]
    assert all(abs(d) <= 0.3 for d in out["push_delays_s"])
    assert out["detections_in_motion"] == 0 and out["max_free_ratio_in_motion"] < 1
    push = next(r for r in out["trajectories"] if r["name"].startswith("ur-20_01_22-push_pose_1"))
    assert push["t0_log_s"] == pytest.approx(200.533)
