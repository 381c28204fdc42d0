"""Learned and hybrid models: features, XGBoost fits, artefacts (and refusing another robot's), the fast path."""

from __future__ import annotations

import shutil
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
import xgboost as xgb

from cell.data.samples import Samples
from cell.model.dynamics.artefact import load_model, save_model
from cell.model.dynamics.base import TorqueModel
from cell.model.dynamics.fastpredict import FastPredictor, FlatForest
from cell.model.dynamics.features import (
    FeatureSpec,
    WindowBuffer,
    derived,
    derived_layout,
    group_matrix,
    groups,
    history_index,
    state_matrix,
)
from cell.model.dynamics.learned import LearnedModel, XGBParams, fit_learned
from cell.model.dynamics.physics import identify_p2
from drivers.errors import DataError

SMALL = XGBParams(n_estimators=60, max_depth=5, learning_rate=0.2, nthread=2, early_stopping_rounds=10)


def motion(samples: int, seed: int, trajs: int = 4, scale: float = 1.0) -> Samples:
    """Sum-of-sines motion (amplitudes x `scale`) cut into `trajs` trajectories of 10 segments each."""
    rng = np.random.default_rng(seed)
    t = np.arange(samples) * 0.008
    q = np.zeros((samples, 6))
    dq = np.zeros_like(q)
    ddq = np.zeros_like(q)
    for k in range(1, 4):
        w = rng.uniform(0.3, 1.0, 6) * k
        a = scale * rng.uniform(0.1, 0.5, 6) / k
        ph = rng.uniform(0, 6, 6)
        q += a * np.sin(w * t[:, None] + ph)
        dq += a * w * np.cos(w * t[:, None] + ph)
        ddq -= a * w**2 * np.sin(w * t[:, None] + ph)
    per = samples // trajs
    starts = np.arange(trajs) * per
    segment = np.arange(samples) // max(1, per // 10)
    return Samples(q=q, dq=dq, ddq=ddq, tau=np.zeros_like(q), starts=starts, names=[], segment=segment)


def plant_like_torque(robot, s: Samples) -> np.ndarray:
    """Rigid body of a modified model + textbook losses + what P2 cannot express (ripple, Stribeck)."""
    model = robot.model.copy()
    for j in range(1, model.njoints):
        inertia = model.inertias[j]
        model.inertias[j] = pin.Inertia(inertia.mass * 1.1, inertia.lever + 0.02, inertia.inertia)
    data = model.createData()
    rb = np.array([pin.rnea(model, data, s.q[k], s.dq[k], s.ddq[k]) for k in range(len(s))])
    sign = np.tanh(s.dq / 0.005)
    ripple = 1.5 * np.sin(4 * s.q + 0.3) * sign
    stribeck = 3.0 * np.exp(-((s.dq / 0.1) ** 2)) * sign
    return rb + 4.0 * s.dq + 5.0 * sign + ripple + stribeck


def fit_h1(robot, params: XGBParams, coverage=None) -> tuple[Samples, Any, Any]:
    """4000 samples of plant-like torque, the P2 identified on them and an H1 with windowed own-joint inputs."""
    s = motion(4000, 0)
    s.tau = plant_like_torque(robot, s) + np.random.default_rng(1).normal(0, 0.3, s.q.shape)
    p2 = identify_p2(robot, s.q, s.dq, s.ddq, s.tau)
    spec = FeatureSpec(window=3, grouping="own", physics_inputs=True, friction_harmonics=3)
    return s, p2, fit_learned("H1", robot, s, spec, params, p2=p2, coverage=coverage)


@pytest.fixture(scope="module")
def fitted(robot_module):
    s, p2, h1 = fit_h1(robot_module, SMALL)
    d = fit_learned("D", robot_module, s, FeatureSpec(window=1, grouping="per_joint", joints=6), SMALL)
    return s, p2, h1, d


# ------------------------------------------------------------------------------------------ features
def test_paper_grouping_matches_table_1():
    gs = groups(FeatureSpec(window=1, grouping="paper", joints=5, physics_inputs=False), 6)
    assert [g.outputs for g in gs] == [(0, 1, 2), (3,), (4,)]
    assert gs[0].names(6) == ["q1[-0]", "q2[-0]", "q3[-0]", "dq1[-0]", "dq2[-0]", "dq3[-0]",
                              "ddq1[-0]", "ddq2[-0]", "ddq3[-0]"]
    assert gs[1].names(6) == [f"q{i}[-0]" for i in range(1, 7)] + ["dq4[-0]", "ddq4[-0]"]
    assert groups(FeatureSpec(window=10, physics_inputs=False), 6)[0].width == 90


def test_derived_friction_and_angle_inputs():
    spec = FeatureSpec(window=2, grouping="own", physics_inputs=True, friction_harmonics=2, angle_sums=True)
    gs = groups(spec, 6)
    names = gs[1].names(6)
    assert names[:6] == ["q2[-0]", "dq2[-0]", "ddq2[-0]", "q2[-1]", "dq2[-1]", "ddq2[-1]"]
    assert names[6:12] == ["load2", "dir2", "sin1q2", "cos1q2", "sin2q2", "cos2q2"]
    assert "cos(q2..q4)" in names and len(names) == 12 + 2 * 21
    rng = np.random.default_rng(0)
    q, dq, tau = rng.normal(size=(3, 4, 6))
    E = derived(spec, q, dq, tau)
    cols = dict(zip([nm for nm, _ in derived_layout(spec, 6)], E.T, strict=True))
    s2 = np.tanh(dq[:, 1] / spec.sign_eps)
    np.testing.assert_allclose(cols["load2"], np.abs(tau[:, 1]) * s2)
    np.testing.assert_allclose(cols["cos2q2"], np.cos(2 * q[:, 1]) * s2)
    np.testing.assert_allclose(cols["sin(q2..q4)"], np.sin(q[:, 1:4].sum(axis=1)))


def test_windows_never_reach_into_the_previous_trajectory():
    idx = history_index(8, np.array([0, 5]), 3)
    np.testing.assert_array_equal(idx[5], [5, 5, 5])
    np.testing.assert_array_equal(idx[7], [7, 6, 5])
    np.testing.assert_array_equal(idx[1], [1, 0, 0])


def test_window_buffer_equals_batch_features():
    s = motion(200, 3, trajs=1)
    gs = groups(FeatureSpec(window=10, physics_inputs=False), 6)
    state = state_matrix(s.q, s.dq, s.ddq)
    batch = np.hstack([group_matrix(g, state, np.array([0])) for g in gs])
    buf = WindowBuffer(gs, 6)
    for k in range(200):
        np.testing.assert_array_equal(buf.push(s.q[k], s.dq[k], s.ddq[k]), batch[k])


# ------------------------------------------------------------------------------------------ models
def test_hybrid_learns_what_physics_misses(robot_module, fitted):
    s, p2, h1, d = fitted
    assert isinstance(h1, TorqueModel) and isinstance(h1, LearnedModel)
    test = motion(3000, 11, trajs=2)
    truth = plant_like_torque(robot_module, test)
    err_p2 = np.sqrt(np.mean((p2.predict(test.q, test.dq, test.ddq) - truth)[:, :3] ** 2))
    pred = h1.predict(test.q, test.dq, test.ddq, test.starts)
    err_h1 = np.sqrt(np.mean((pred - truth)[:, :3] ** 2))
    assert err_h1 < 0.8 * err_p2, (err_h1, err_p2)
    assert not np.isnan(pred).any()  # joint 6 falls back to physics
    d_pred = d.predict(test.q, test.dq, test.ddq)
    assert d_pred.shape == (3000, 6) and not np.isnan(d_pred).any()


def test_d_leaves_unlearned_joints_nan(robot_module):
    s = motion(1500, 5)
    s.tau = plant_like_torque(robot_module, s)
    d = fit_learned("D", robot_module, s, FeatureSpec(window=1, joints=5), SMALL)
    out = d.predict(s.q[:10], s.dq[:10], s.ddq[:10])
    assert np.isnan(out[:, 5]).all() and not np.isnan(out[:, :5]).any()


def test_hybrid_needs_physics(robot_module):
    s = motion(500, 5)
    with pytest.raises(ValueError, match="needs an identified P2"):
        fit_learned("H1", robot_module, s, FeatureSpec(window=1), SMALL, p2=None)


# ------------------------------------------------------------------------------------------ fast path
def test_flat_forest_equals_xgboost_including_values_on_thresholds():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(3000, 7)).astype(np.float32)
    X[:, 3] = np.round(X[:, 3], 1)  # repeated values: splits land exactly on data values
    y = np.sin(X[:, 0]) + X[:, 1] * X[:, 3] + (X[:, 2] > 0.3)
    boosters = [xgb.train({"max_depth": d, "eta": 0.3, "nthread": 2, "base_score": b}, xgb.DMatrix(X, label=y + b), 40)
                for d, b in ((3, 0.0), (6, 5.0))]
    forest = FlatForest(boosters, [0, np.arange(7)])
    probe = np.vstack([X[:300], rng.normal(size=(200, 7)).astype(np.float32)])
    # Values exactly at split thresholds go right in XGBoost (x < threshold goes left).
    thresholds = forest.thr[np.isfinite(forest.thr)]
    at = probe[:100].copy()
    at[:, 3] = rng.choice(thresholds, 100)
    probe = np.vstack([probe, at])
    ours = np.array([forest.predict(row) for row in probe])
    theirs = np.column_stack([b.inplace_predict(probe) for b in boosters])
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5)


def test_fast_predictor_equals_the_model_on_a_stream(fitted):
    s, p2, h1, d = fitted
    test = motion(400, 21, trajs=1)
    for model in (h1, d):
        fast = FastPredictor(model, 0.008)
        stream = np.array([fast.predict_one(test.q[k], test.dq[k], test.ddq[k]) for k in range(len(test))])
        batch = model.predict(test.q, test.dq, test.ddq, np.array([0]))
        np.testing.assert_allclose(stream, batch, rtol=1e-5, atol=1e-4)


def test_fast_path_is_faster_than_stock_single_row(fitted, monkeypatch):
    s, p2, h1, d = fitted
    fast = FastPredictor(h1, 0.008)
    stock = FastPredictor(h1, 0.008, stock=True)
    q, dq, ddq = s.q[100], s.dq[100], s.ddq[100]
    np.testing.assert_allclose(fast.predict_one(q, dq, ddq), stock.predict_one(q, dq, ddq), rtol=1e-5, atol=1e-4)

    # Fast because it never enters XGBoost per sample (its one-row set-up is what costs): counted, not
    # timed, so a busy machine cannot flip it.  `bench model` measures the real ratio.
    entered = {"fast": 0, "stock": 0}
    which = "fast"
    for name in ("predict", "inplace_predict"):
        real = getattr(xgb.Booster, name)

        def spy(self, *args, _real=real, **kwargs):
            entered[which] += 1
            return _real(self, *args, **kwargs)

        monkeypatch.setattr(xgb.Booster, name, spy)
    for _ in range(5):
        fast.predict_one(q, dq, ddq)
    which = "stock"
    for _ in range(5):
        stock.predict_one(q, dq, ddq)
    assert entered["fast"] == 0
    assert entered["stock"] >= 5


# ------------------------------------------------------------------------------------------ artefacts
def test_artefact_round_trip_keeps_predictions(robot_module, fitted, tmp_path):
    s, p2, h1, d = fitted
    for model in (h1, d):
        save_model(model, tmp_path / model.kind)
        back = load_model(tmp_path / model.kind, robot_module)
        assert isinstance(back, LearnedModel) and back.kind == model.kind
        assert back.meta.features == model.meta.features
        np.testing.assert_allclose(back.predict(s.q[:300], s.dq[:300], s.ddq[:300], np.array([0])),
                                   model.predict(s.q[:300], s.dq[:300], s.ddq[:300], np.array([0])), rtol=1e-6)


def test_artefact_from_another_robot_is_refused(robot_module, fitted, tmp_path):
    from cell.model.robot import load_robot

    s, p2, h1, d = fitted
    save_model(h1, tmp_path / "h1")
    other_urdf = tmp_path / "other.urdf"
    text = robot_module.urdf.read_text().replace('<mass value="8.567"/>', '<mass value="9.0"/>')
    other_urdf.write_text(text)
    other = load_robot(other_urdf, [0, 0, 0.155], 1.4, [0, 0, 0.11])
    with pytest.raises(DataError, match=r"h1/model\.json: model was made for robot 'tm5-700'.*URDF sha256"):
        load_model(tmp_path / "h1", other)
    # A different joint count: drop the last joint from the URDF.
    six = robot_module.urdf.read_text()
    five = six.replace('<joint name="joint_6" type="revolute">', '<joint name="joint_6" type="fixed">')
    (tmp_path / "five.urdf").write_text(five)
    five_dof = load_robot(tmp_path / "five.urdf", [0, 0, 0.155], 1.4, [0, 0, 0.11])
    with pytest.raises(DataError, match=r"6 joints.*5 joints"):
        load_model(tmp_path / "h1", five_dof)


def test_damaged_artefact_gives_a_clear_error(robot_module, fitted, tmp_path):
    s, p2, h1, d = fitted
    save_model(h1, tmp_path / "h1")
    (tmp_path / "h1" / "booster_j2.ubj").unlink()
    with pytest.raises(DataError, match="booster file .* for joint 2 is missing"):
        load_model(tmp_path / "h1", robot_module)
    shutil.rmtree(tmp_path / "h1")
    with pytest.raises(DataError, match="no model.json"):
        load_model(tmp_path / "h1", robot_module)


def test_served_step_runs_the_same_causal_pipeline_as_training(fitted):
    """`FastPredictor.step(q, dq)` = causal derivatives + model, exactly as features built offline."""
    from cell.sensing.derivatives import CausalDerivatives

    s, p2, h1, d = fitted
    test = motion(300, 31, trajs=1)
    v, a = CausalDerivatives(6, 0.008).run(test.q, test.dq)
    offline = h1.predict(test.q, v, a, np.array([0]))
    fast = FastPredictor(h1, 0.008)
    online = np.array([fast.step(test.q[k], test.dq[k]) for k in range(len(test))])
    np.testing.assert_allclose(online, offline, rtol=1e-5, atol=1e-4)
