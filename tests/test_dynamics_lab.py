"""The lab's command bodies end to end on the simulated cell, with tiny sizes: collect, train, evaluate, bench."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from cell.data.dataset import load_split
from cell.model.dynamics.artefact import load_model
from cell.model.dynamics.learned import LearnedModel
from cell.model.specs import robot_by_name
from tasks.lab.bench import bench_model
from tasks.lab.collect import collect
from tasks.lab.evaluate import evaluate
from tasks.lab.train import train


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from cell.config import load_config
    from sim.cell import make_sim_cell

    cfg = load_config()
    robot = robot_by_name(cfg)
    out = tmp_path_factory.mktemp("lab") / "data"
    ex = out.parent / "ex.yaml"
    ex.write_text(yaml.safe_dump({"max_configs": 4, "speeds": [0.7, 1.0],
                                  "fourier": {"harmonics": 3, "periods": 1, "base_hz": 0.25, "candidates": 3}}))
    summary = collect(cfg, lambda: make_sim_cell(cfg, robot.limits, scene_kind="table"), out, samples=6000,
                      test_trajectories=2, test_repeats=1, test_moves=2, excitation=str(ex))
    return cfg, out, summary


@pytest.mark.slow
def test_collect_writes_a_valid_dataset_through_the_control_loop(tiny_dataset):
    cfg, out, summary = tiny_dataset
    assert summary["runs"]["train"]["outcome"] == "done" and summary["runs"]["test"]["outcome"] == "done"
    assert summary["train_samples"] >= 6000
    man = yaml.safe_load((out / "dataset.yaml").read_text())
    assert man["train"] == ["train.parquet"] and man["test"] == ["test.parquet"] and man["joints"] == 6
    tests = load_split(out / "dataset.yaml", "test", 6)
    assert len(tests) == 2  # one per test trajectory (traj column)
    assert json.loads((out / "collect.json").read_text())["family"] == "mixed"
    # The run folders are ordinary control-loop recordings, themselves valid datasets.
    assert list((out / "runs").glob("*-collect-train/log/part-*.parquet"))


@pytest.mark.slow
def test_train_evaluate_and_bench_on_the_tiny_dataset(tiny_dataset, tmp_path):
    cfg, out, _ = tiny_dataset
    res = train(cfg, out / "dataset.yaml", tmp_path / "h1", kind="H1", derivatives="causal")
    model = load_model(tmp_path / "h1", robot_by_name(cfg))
    assert isinstance(model, LearnedModel) and model.meta.features["derivatives"] == "causal"
    assert res["samples"] >= 6000 and len(res["train_rmse_per_joint_nm"]) == 6
    ev = evaluate(cfg, out / "dataset.yaml", tmp_path / "eval", train_samples=4000, large_samples=6000,
                  curve=[3000, 6000], save_models=False, paper_variants=False, max_trees=40)
    for key in ("p2_over_p1", "h1_over_p2", "h1_is_best", "noise_floor_j123_nm", "over_noise_floor"):
        assert key in ev
    assert set(ev["mean_rmse_j123"]) == {"P1", "P2", "D", "H1", "H2", "H3", "D_large"}
    assert ev["p2_over_p1"] < 0.8  # even a tiny collection identifies most of what P1 misses
    assert len(ev["learning_curve"]["H1"]) == 2
    assert (tmp_path / "eval" / "evaluation.png").exists() and (tmp_path / "eval" / "table.md").exists()
    saved = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    assert saved["mean_rmse_j123"] == ev["mean_rmse_j123"]
    b = bench_model(cfg, out / "dataset.yaml", tmp_path / "h1", fit_samples=3000, calls=300)
    assert b["max_abs_diff_vs_stock_nm"] < 1e-3 and b["max_abs_diff_vs_batch_nm"] < 1e-3
    keys = ("hybrid_predict_p99_us", "stock_predict_p50_us", "speedup", "fit_s", "fit_samples", "batch_samples_per_s")
    for key in keys:
        assert np.isfinite(b[key])
