"""The DNN and LSTM learners (fit, artefact, single-sample serving) and `main.py tune`, on a small synthetic dataset."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import main
from cell.config import load_config
from cell.data.dataset import Trajectory, write_trajectory
from cell.data.samples import Samples, stack
from cell.model.dynamics.artefact import load_model, save_model
from cell.model.dynamics.fastpredict import FastPredictor
from cell.model.dynamics.features import FeatureSpec
from cell.model.dynamics.learned import LearnedModel
from cell.model.dynamics.nets import NetLearner, NetParams
from cell.model.dynamics.physics import P1Model
from cell.model.dynamics.rigid_body import nominal_p2
from cell.model.robot import RobotModel
from cell.model.specs import robot_by_name
from drivers.errors import ConfigError, DataError
from tasks.lab.evaluate import evaluate
from tasks.lab.train import TrainOptions, fit_model
from tasks.lab.tune import chunk_segments, split_validation, tune
from tasks.lab.tune_space import load_space

DT = 0.008
TINY = NetParams(hidden=12, layers=2, epochs=12, patience=12, batch_size=128, learning_rate=1e-2)
# One feature group (joints 1-3 together, the paper's first group): one network to compile and train.
J123 = FeatureSpec(window=1, grouping="paper", joints=3, angle_sums=True)


def synthetic(robot: RobotModel, seed: int, samples: int = 500) -> Trajectory:
    """A smooth multi-sine motion; torque = the nominal rigid body + viscous and Coulomb friction + noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(samples) * DT
    w = rng.uniform(0.8, 2.5, robot.n)
    a = rng.uniform(0.2, 0.6, robot.n)
    ph = rng.uniform(0, 2 * np.pi, robot.n)
    q = a * np.sin(w * t[:, None] + ph)
    dq = a * w * np.cos(w * t[:, None] + ph)
    ddq = -a * w**2 * np.sin(w * t[:, None] + ph)
    tau = P1Model(robot).predict(q, dq, ddq) + 3.0 * dq + 2.0 * np.tanh(dq / 0.02)
    tau += rng.normal(0, 0.05, tau.shape)
    return Trajectory("syn", t, q, tau, dq, segment=np.arange(samples) // 100)


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, RobotModel, Path]:
    cfg = load_config()
    robot = robot_by_name(cfg)
    d = tmp_path_factory.mktemp("learners") / "data"
    for i in range(8):
        write_trajectory(d / f"train{i}.parquet", synthetic(robot, i))
    for i in range(2):
        write_trajectory(d / f"test{i}.parquet", synthetic(robot, 100 + i))
    (d / "dataset.yaml").write_text(yaml.safe_dump({
        "train": [f"train{i}.parquet" for i in range(8)], "test": ["test0.parquet", "test1.parquet"],
        "joints": robot.n, "robot": robot.model.name, "period_s": DT}))
    return cfg, robot, d / "dataset.yaml"


def samples_of(robot: RobotModel, seeds: range) -> Samples:
    return stack([synthetic(robot, s) for s in seeds])


def test_dnn_data_model_learns_and_round_trips_through_the_artefact(lab, tmp_path):
    _, robot, _ = lab
    s, test = samples_of(robot, range(8)), samples_of(robot, range(100, 102))
    opts = TrainOptions(learner="dnn", net={"D": TINY}, features={"D": J123})
    model = fit_model("D", robot, s, opts)
    assert isinstance(model, LearnedModel) and isinstance(model.forest, NetLearner) and model.learner == "dnn"
    pred = model.predict(test.q, test.dq, test.ddq, test.starts)
    # it has learned the torque: well below the spread of the torque itself on unseen motions
    rmse = np.sqrt(np.mean((pred[:, :3] - test.tau[:, :3]) ** 2, axis=0))
    assert np.all(rmse < test.tau[:, :3].std(axis=0)) and np.mean(rmse / test.tau[:, :3].std(axis=0)) < 0.7
    assert np.isnan(pred[:, 3:]).all()  # joints outside the features: D has nothing for them
    save_model(model, tmp_path / "d")
    assert (tmp_path / "d" / "nets.npz").exists() and not list((tmp_path / "d").glob("booster_*"))
    back = load_model(tmp_path / "d", robot)
    assert isinstance(back, LearnedModel) and back.learner == "dnn" and back.meta.extra["learner"] == "dnn"
    np.testing.assert_array_equal(back.predict(test.q, test.dq, test.ddq, test.starts), pred)


def test_lstm_hybrid_serves_one_sample_as_the_batch_and_reads_its_window(lab, tmp_path):
    _, robot, _ = lab
    s = samples_of(robot, range(4))
    spec = FeatureSpec(window=10, grouping="paper", joints=3, physics_inputs=True)
    opts = TrainOptions(learner="lstm", features={"H1": spec},
                        net={"H1": dataclasses.replace(TINY, epochs=3, dropout=0.1, recurrent_dropout=0.1)})
    model = fit_model("H1", robot, s, opts, p2=nominal_p2(robot))  # the nominal physics: no identification here
    assert isinstance(model, LearnedModel) and model.forest.spec.window == 10  # the paper's window
    save_model(model, tmp_path / "h1")
    back = load_model(tmp_path / "h1", robot)
    assert isinstance(back, LearnedModel)
    t = samples_of(robot, range(200, 201))
    rows = slice(0, 60)
    batch = back.predict(t.q[rows], t.dq[rows], t.ddq[rows], np.array([0]))
    fast = FastPredictor(back, DT)
    one = np.array([fast.predict_one(t.q[k], t.dq[k], t.ddq[k]) for k in range(60)])
    np.testing.assert_allclose(one, batch, atol=1e-3)
    # an LSTM cell: four gates of 12 units
    assert isinstance(back.forest, NetLearner) and back.forest.nets[0].weights["Wh"].shape == (12, 48)
    # The residual sees the 10 newest samples: a change 9 samples back moves it, 10 back does not.
    learned = back.forest
    q, dq, ddq = t.q[:30].copy(), t.dq[:30].copy(), t.ddq[:30].copy()
    base = learned.predict(q, dq, ddq, np.array([0]), back.physics_torque(q, dq, ddq))[29]
    for lag, moves in ((9, True), (10, False)):
        dq2 = dq.copy()
        dq2[29 - lag] += 0.5
        out = learned.predict(q, dq2, ddq, np.array([0]), back.physics_torque(q, dq2, ddq))[29]
        assert (np.nanmax(np.abs(out - base)) > 1e-6) == moves


def test_a_tampered_network_file_is_refused(lab, tmp_path):
    _, robot, _ = lab
    model = fit_model("D", robot, samples_of(robot, range(2)),
                      TrainOptions(learner="dnn", net={"D": dataclasses.replace(TINY, epochs=1)}, features={"D": J123}))
    path = save_model(model, tmp_path / "d")
    z = dict(np.load(path / "nets.npz"))
    z["g0/x_mean"] = z["g0/x_mean"][:-1]
    np.savez(path / "nets.npz", **z)
    with pytest.raises(DataError, match="inputs"):
        load_model(path, robot)
    (path / "nets.npz").unlink()
    with pytest.raises(DataError, match="missing"):
        load_model(path, robot)


def test_validation_holds_out_whole_trajectories_of_the_training_family(lab):
    _, robot, _ = lab
    s = samples_of(robot, range(10))
    tr, va, unit = split_validation(s, 0.2, 0)
    assert unit == "trajectories" and len(va) == 1000 and len(set(tr) & set(va)) == 0
    held = {int(np.searchsorted(s.starts, r, side="right")) - 1 for r in va}
    assert len(held) == 2  # two whole trajectories, not scattered rows
    # a long excitation segment is cut into pieces before sub-sampling draws whole segments
    seg = chunk_segments(np.r_[np.zeros(600, np.int64), np.ones(100, np.int64), np.zeros(10, np.int64)], 250)
    assert list(np.bincount(seg)) == [250, 250, 100, 100, 10]


def space(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "space.yaml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, message", [
    ("max_depht: {type: int, low: 1, high: 4, grid: [2]}", "not a xgboost hyperparameter"),
    ("max_depth: {type: int, low: 4, high: 2, grid: [3]}", "must be below high"),
    ("max_depth: {type: int, low: 1, high: 4, grid: [2, 9]}", "outside"),
    ("learning_rate: {type: float, low: 0, high: 1, log: true, grid: [0.1]}", "log range"),
    ("max_depth: {type: integer, low: 1, high: 4, grid: [2]}", "type 'integer'"),
    ("max_depth: {type: int, low: 1, high: 4}", "grid must be"),
    ("nthread: {type: int, low: 1, high: 4, grid: [2]}", "not a xgboost hyperparameter"),
])
def test_a_bad_search_space_is_one_clear_error(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        load_space(space(tmp_path, text), "xgboost")


def test_cli_tune_refuses_a_bad_space_with_one_line_and_exit_2(lab, tmp_path, capsys):
    _, _, data = lab
    bad = space(tmp_path, "max_depth: {type: int, low: 1, high: 4, grid: [7]}")
    code = main.main(["tune", "--data", str(data), "--model", "H1", "--method", "grid", "--trials", "3",
                      "--space", str(bad), "--out", str(tmp_path / "t")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "space.yaml: max_depth" in err[0]
    assert not (tmp_path / "t").exists()


def test_grid_search_is_algorithm_1_and_resumes_from_its_storage(lab, tmp_path):
    cfg, _, data = lab
    sp = space(tmp_path, "max_depth: {type: int, low: 1, high: 6, grid: [1, 2, 3]}\n"
                         "n_estimators: {type: int, low: 5, high: 100, grid: [10, 40]}\n")
    out = tmp_path / "grid"
    r = tune(cfg, data, out, kind="D", method="grid", trials=50, space_path=sp, samples=1500)
    # Algorithm 1 stops when a full cycle changes nothing, well before the budget of this 2-D grid.
    assert r["converged"] and r["cycles"] >= 2 and r["trials"] < 50
    assert r["best_rmse"] <= r["default_rmse"]
    history = json.loads((out / "history.json").read_text())
    assert min(h["value"] for h in history) == pytest.approx(r["best_rmse"], abs=1e-4)
    model = load_model(out / "model", lab[1])
    assert isinstance(model, LearnedModel) and model.meta.extra["search"]["best_params"] == r["best_params"]
    assert (out / "history.png").stat().st_size > 1000 and (out / "model" / "search.json").exists()
    # Re-running finds every configuration in the study: no new trial, the same answer.
    again = tune(cfg, data, out, kind="D", method="grid", trials=50, space_path=sp, samples=1500)
    assert again["trials"] == r["trials"] and again["best_params"] == r["best_params"]
    assert again["search_s"] < r["search_s"]
    # evaluate takes the search's best settings, refitted on its own samples, as a row of its table
    ev = evaluate(cfg, data, tmp_path / "eval", train_samples=1500, large_samples=1500, curve=None, save_models=False,
                  paper_variants=False, max_trees=20, tuned=[out])
    assert "D_xgboost_tuned" in ev["mean_rmse_j123"]
    assert "D_xgboost_tuned" in (tmp_path / "eval" / "table.md").read_text()
    assert ev["models"]["D_xgboost_tuned"]["features"]["grouping"] == "full"  # D's own features, the tuned trees


def test_bayes_search_with_two_worker_processes_shares_one_study(lab, tmp_path):
    cfg, _, data = lab
    sp = space(tmp_path, "max_depth: {type: int, low: 1, high: 4, grid: [2]}\n"
                         "n_estimators: {type: int, low: 5, high: 60, grid: [10]}\n")
    out = tmp_path / "bayes"
    r = tune(cfg, data, out, kind="D", method="bayes", trials=4, workers=2, space_path=sp, samples=1500)
    assert r["trials"] >= 4 and r["best_rmse"] <= r["default_rmse"]
    assert (out / "study.journal").exists()
    # resuming with a larger budget adds only the missing trials
    r2 = tune(cfg, data, out, kind="D", method="bayes", trials=5, workers=1, space_path=sp, samples=1500)
    assert 5 <= r2["trials"] <= 6


def test_tune_refuses_physics_models_and_unknown_learners(lab, tmp_path):
    cfg, _, data = lab
    with pytest.raises(ConfigError, match="only a learned model"):
        tune(cfg, data, tmp_path / "x", kind="P2")
    with pytest.raises(ConfigError, match="--learner svm"):
        tune(cfg, data, tmp_path / "x", learner="svm")
