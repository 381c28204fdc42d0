"""Hybrids' trust and uncertainty (cell/model/dynamics/uncertainty.py): the coverage grid, the sticking regime,
residual levels by speed; H1 blending toward P2 where unsure (batch, artefact, served path) and the
Kalman observer taking the model's uncertainty as its measurement noise."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cell.data.samples import Samples
from cell.model.dynamics.artefact import load_model, save_model
from cell.model.dynamics.fastpredict import FastPredictor
from cell.model.dynamics.learned import LearnedModel, XGBParams
from cell.model.dynamics.uncertainty import SPEED_EDGES, Coverage, CoverageConfig
from cell.sensing.observer import KalmanObserver
from drivers.interfaces import ArmState
from tasks.lab.train import TrainOptions, fit_model
from tests.test_dynamics_learned import fit_h1, motion

# One thread: on a 2-core machine busy with another job, XGBoost's two threads spin against it (30 s vs 0.2 s).
SMALL = XGBParams(n_estimators=60, max_depth=5, learning_rate=0.2, nthread=1, early_stopping_rounds=10)
COVERAGE = CoverageConfig(min_count=10, stick_speed=0.005)
DT = 0.008


# ------------------------------------------------------------------------------------------ Coverage alone
def grid(min_count: float = 10.0, stick_speed: float = 0.0, n: int = 3) -> Coverage:
    """A 2x2x2 grid on learned joint 1 (index 1) of a 3-joint arm, unit cells from the origin:
    cell (0,0,0) holds 20 samples, cell (1,0,0) 5, the rest none."""
    counts = np.zeros((1, 2, 2, 2), np.int32)
    counts[0, 0, 0, 0] = 20
    counts[0, 1, 0, 0] = 5
    S = len(SPEED_EDGES) - 1
    sigma_h = np.tile(np.linspace(0.5, 1.1, S), (n, 1))
    sigma_p = 4.0 * sigma_h
    return Coverage(np.array([1]), np.zeros((1, 3)), np.ones((1, 3)), counts, min_count, stick_speed,
                    sigma_h, sigma_p, np.array([3.0, 6.0, 9.0]), True)


def states(*rows: tuple[float, float, float], n: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, dq, ddq) arrays with joint 1 at the given (q, dq, ddq) and the others at 7 (off any grid)."""
    q, dq, ddq = (np.full((len(rows), n), 7.0) for _ in range(3))
    for k, (a, b, c) in enumerate(rows):
        q[k, 1], dq[k, 1], ddq[k, 1] = a, b, c
    return q, dq, ddq


def test_weight_is_the_cell_count_over_min_count():
    cov = grid()
    q, dq, ddq = states((0.5, 0.5, 0.5), (1.5, 0.5, 0.5), (0.5, 1.5, 0.5), (-0.5, 0.5, 0.5), (2.5, 0.5, 0.5),
                        (0.5, 0.5, 9.0))
    w = cov.weight(q, dq, ddq)
    # dense cell (20 >= 10), thin cell (5 of 10), empty cell, below / above / far outside the grid
    np.testing.assert_allclose(w[:, 1], [1.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    # Joints that are not learned have nothing to weigh.
    np.testing.assert_array_equal(w[:, [0, 2]], 1.0)
    # Without a min_count the grid is not used.
    np.testing.assert_array_equal(grid(min_count=0.0).weight(q, dq, ddq), 1.0)
    # A cell with more samples than min_count is trusted no more than fully.
    np.testing.assert_allclose(grid(min_count=4.0).weight(q, dq, ddq)[:2, 1], [1.0, 1.0])


def test_weight_fades_out_in_the_sticking_regime():
    cov = grid(min_count=0.0, stick_speed=0.01)
    speeds = np.array([0.0, 0.0025, -0.005, 0.01, 0.02, -0.3])
    q, dq, ddq = states(*[(0.5, v, 0.5) for v in speeds])
    w = cov.weight(q, dq, ddq)[:, 1]
    np.testing.assert_allclose(w, np.minimum(1.0, np.abs(speeds) / 0.01))
    assert w[0] == 0.0 and np.all(w[3:] == 1.0)
    # Both together multiply: a thin cell at half the stick speed.
    both = grid(min_count=10.0, stick_speed=0.01)
    q, dq, ddq = states((1.5, 0.005, 0.5))
    np.testing.assert_allclose(both.weight(q, dq, ddq)[0, 1], 0.25)


def test_weight_one_equals_weight_row_by_row():
    cov = grid(stick_speed=0.01)
    rng = np.random.default_rng(0)
    q, dq, ddq = rng.uniform(-0.5, 2.5, (3, 300, 3))
    dq[::7] *= 0.004  # some rows in the sticking regime
    batch = cov.weight(q, dq, ddq)
    assert {0.0, 1.0} <= set(np.round(batch[:, 1], 6)) and np.any((batch[:, 1] > 0) & (batch[:, 1] < 1))
    for k in range(len(q)):
        np.testing.assert_array_equal(cov.weight_one(q[k], dq[k], ddq[k]), batch[k])


def test_sigma_blends_the_levels_and_covers_the_static_band():
    cov = grid(stick_speed=0.01)
    n = 3
    speeds = np.array([0.0, 0.005, 0.05, 0.5, 2.0])
    dq = np.repeat(speeds[:, None], n, axis=1)
    b = np.searchsorted(SPEED_EDGES, speeds, side="right") - 1
    sh, sp = cov.sigma_hybrid[:, b].T, cov.sigma_physics[:, b].T  # (rows, n)
    moving = speeds >= 0.01
    # Where the residual is trusted the hybrid's level, where it is not the physics part's.
    np.testing.assert_allclose(cov.sigma(dq, np.ones_like(dq))[moving], sh[moving])
    np.testing.assert_allclose(cov.sigma(dq, np.zeros_like(dq))[moving], sp[moving])
    np.testing.assert_allclose(cov.sigma(dq, np.full_like(dq, 0.5))[moving],
                               np.sqrt(0.5 * sh[moving] ** 2 + 0.5 * sp[moving] ** 2))
    # Sticking: at least the static band's spread f_c / sqrt(3), whatever the trust.
    for w in (0.0, 1.0):
        s = cov.sigma(dq, np.full_like(dq, w))
        assert np.all(s[~moving] >= cov.static_band / np.sqrt(3.0) - 1e-12)
        np.testing.assert_allclose(s[~moving], np.maximum(cov.static_band / np.sqrt(3.0),
                                                          (sh if w else sp)[~moving]))
    # Without a stick speed there is no sticking floor.
    plain = grid(stick_speed=0.0)
    np.testing.assert_allclose(plain.sigma(dq, np.ones_like(dq)), sh)


def test_fit_counts_levels_and_grid():
    rng = np.random.default_rng(1)
    N, n = 20000, 2
    q = rng.uniform(-1, 1, (N, n))
    dq = rng.uniform(-0.5, 0.5, (N, n))
    ddq = rng.uniform(-2, 2, (N, n))
    # Residuals whose level depends on the speed: 0.1 below 0.1 rad/s, 1.0 above (hybrid); x3 (physics).
    level = np.where(np.abs(dq) < 0.1, 0.1, 1.0)
    sign = rng.choice([-1.0, 1.0], (N, n))
    cov = Coverage.fit([0, 1], q, dq, ddq, level * sign, 3 * level * sign, np.array([2.0, 4.0]), bins=4,
                       min_count=50, stick_speed=0.0)
    assert cov.counts.shape == (2, 4, 4, 4)
    # Every sample between the 0.5 and 99.5 percentiles on all three axes is counted once.
    assert 0.95 * N < cov.counts[0].sum() <= N
    # Uniform data: ~300 samples a cell, all dense; outside the data's box nothing.
    w = cov.weight(np.zeros((1, n)), np.full((1, n), 0.2), np.zeros((1, n)))
    np.testing.assert_array_equal(w, 1.0)
    np.testing.assert_array_equal(cov.weight(np.full((1, n), 1.5), np.full((1, n), 0.2), np.zeros((1, n))), 0.0)
    # The levels: RMS of each speed bin's residual.
    s_slow = cov.sigma(np.full((1, n), 0.05), np.ones((1, n)))
    s_fast = cov.sigma(np.full((1, n), 0.2), np.ones((1, n)))
    np.testing.assert_allclose(s_slow, 0.1, rtol=1e-9)
    np.testing.assert_allclose(s_fast, 1.0, rtol=1e-9)
    np.testing.assert_allclose(cov.sigma(np.full((1, n), 0.2), np.zeros((1, n))), 3.0, rtol=1e-9)
    # A speed bin with (almost) no rows takes the joint's overall level.
    overall = np.sqrt(np.mean(level**2, axis=0))
    np.testing.assert_allclose(cov.sigma(np.full((1, n), 5.0), np.ones((1, n)))[0], overall, rtol=1e-9)


def test_coverage_dict_round_trip_and_inconsistent_shapes():
    cov = grid(stick_speed=0.01)
    back = Coverage.from_dict(json.loads(json.dumps(cov.to_dict())))
    for f in dataclasses.fields(Coverage):
        np.testing.assert_array_equal(getattr(back, f.name), getattr(cov, f.name), err_msg=f.name)
    rng = np.random.default_rng(2)
    q, dq, ddq = rng.uniform(-0.5, 2.5, (3, 100, 3))
    np.testing.assert_array_equal(back.weight(q, dq, ddq), cov.weight(q, dq, ddq))
    np.testing.assert_array_equal(back.sigma(dq, back.weight(q, dq, ddq)), cov.sigma(dq, cov.weight(q, dq, ddq)))
    d = cov.to_dict()
    bad = {
        "counts of another joint count": {**d, "counts": np.zeros((2, 2, 2, 2)).tolist()},
        "counts not a 3-d grid per joint": {**d, "counts": np.zeros((1, 4)).tolist()},
        "levels of other speed bins": {**d, "sigma_hybrid": np.zeros((3, 4)).tolist()},
        "grid corner of another size": {**d, "lo": [0.0, 0.0]},
    }
    for why, doc in bad.items():
        with pytest.raises(ValueError):
            Coverage.from_dict(doc)
            pytest.fail(why)


# ------------------------------------------------------------------------------------------ fitted hybrids
@pytest.fixture(scope="module")
def fitted(robot_module):
    return fit_h1(robot_module, SMALL, COVERAGE)


def without_coverage(model: LearnedModel) -> LearnedModel:
    return dataclasses.replace(model, coverage=None)


def probe(robot_module) -> Samples:
    """Motion twice as wide as the training one: part inside the training coverage, part outside."""
    return motion(1500, 31, trajs=1, scale=2.0)


def test_h1_falls_back_to_p2_outside_its_coverage(robot_module, fitted):
    s, p2, h1 = fitted
    cov = h1.coverage
    assert cov is not None and cov.blend and cov.min_count == 10 and cov.stick_speed == 0.005
    outs = h1.forest.outputs
    assert list(outs) == list(range(6))  # every joint learned by default
    # Far outside the training data (every joint 2.5 rad away): trust 0, exactly P2.
    far = motion(300, 5, trajs=1)
    q = far.q + 2.5
    w = h1.trust(q, far.dq, far.ddq)
    np.testing.assert_array_equal(w[:, outs], 0.0)
    physics = p2.predict(q, far.dq, far.ddq)
    np.testing.assert_array_equal(h1.predict(q, far.dq, far.ddq, far.starts)[:, outs], physics[:, outs])
    # The unblended model does learn something there: the fallback is what makes them equal.
    assert np.abs(without_coverage(h1).predict(q, far.dq, far.ddq, far.starts) - physics).max() > 0.1
    # On the training motion (inside the coverage, moving) the learned part is kept in full.
    pred = h1.predict(s.q, s.dq, s.ddq, s.starts)
    full = without_coverage(h1).predict(s.q, s.dq, s.ddq, s.starts)
    w = h1.trust(s.q, s.dq, s.ddq)
    trusted = w == 1.0
    assert trusted.mean() > 0.8
    np.testing.assert_array_equal(pred[trusted], full[trusted])
    assert np.abs(pred - p2.predict(s.q, s.dq, s.ddq))[trusted].mean() > 0.3
    # And H1 still beats P2 on its own training motion (the blend keeps what it learned).
    assert np.sqrt(np.mean((pred - s.tau) ** 2)) < 0.8 * np.sqrt(np.mean((p2.predict(s.q, s.dq, s.ddq) - s.tau) ** 2))


def test_h1_blends_by_its_trust(robot_module, fitted):
    s, p2, h1 = fitted
    t = probe(robot_module)
    w = h1.trust(t.q, t.dq, t.ddq)
    assert np.any(w == 0) and np.any(w == 1) and np.any((w > 0) & (w < 1))
    phys = p2.predict(t.q, t.dq, t.ddq)
    full = without_coverage(h1).predict(t.q, t.dq, t.ddq, t.starts)
    np.testing.assert_allclose(h1.predict(t.q, t.dq, t.ddq, t.starts), phys + w * (full - phys), atol=1e-9)
    # Resting joints (|q'| < stick_speed) are not trusted, even in a dense cell.
    rest = np.abs(t.dq) < COVERAGE.stick_speed
    assert rest.any()
    np.testing.assert_array_less(w[rest], np.abs(t.dq[rest]) / COVERAGE.stick_speed + 1e-12)


def test_predict_with_uncertainty(robot_module, fitted):
    s, p2, h1 = fitted
    t = probe(robot_module)
    tau, sigma, w = h1.predict_with_uncertainty(t.q, t.dq, t.ddq, t.starts)
    np.testing.assert_array_equal(tau, h1.predict(t.q, t.dq, t.ddq, t.starts))
    np.testing.assert_array_equal(w, h1.trust(t.q, t.dq, t.ddq))
    assert sigma.shape == tau.shape and np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    np.testing.assert_array_equal(sigma, h1.coverage.sigma(t.dq, w))
    # Where H1 is unsure it is as uncertain as P2; P2 misses the ripple and Stribeck friction H1 learned.
    moving = np.abs(t.dq) > 0.05
    assert np.median(sigma[(w == 0) & moving]) > 1.5 * np.median(sigma[(w == 1) & moving])
    # Sticking joints: at least f_c / sqrt(3).
    rest = np.abs(t.dq) < COVERAGE.stick_speed
    band = np.broadcast_to(np.abs(p2.params.f_c) / np.sqrt(3.0), sigma.shape)
    assert np.all(sigma[rest] >= band[rest] - 1e-12) and np.all(band[rest] > 1.0)
    # Without a coverage model (an older artefact) the uncertainty is unknown.
    _, none, ones = without_coverage(h1).predict_with_uncertainty(t.q[:5], t.dq[:5], t.ddq[:5])
    assert np.isnan(none).all() and np.all(ones == 1)


def test_artefact_keeps_the_coverage(robot_module, fitted, tmp_path):
    s, p2, h1 = fitted
    save_model(h1, tmp_path / "h1")
    assert "coverage" in json.loads((tmp_path / "h1" / "model.json").read_text())
    back = load_model(tmp_path / "h1", robot_module)
    assert isinstance(back, LearnedModel) and back.coverage is not None and back.coverage.blend
    t = probe(robot_module)
    a = h1.predict_with_uncertainty(t.q, t.dq, t.ddq, t.starts)
    b = back.predict_with_uncertainty(t.q, t.dq, t.ddq, t.starts)
    for x, y, what in zip(a, b, ("torque", "sigma", "trust"), strict=True):
        np.testing.assert_array_equal(y, x, err_msg=what)


def test_fast_predictor_blends_like_the_batch(robot_module, fitted):
    s, p2, h1 = fitted
    t = probe(robot_module)
    w = h1.trust(t.q, t.dq, t.ddq)
    assert np.any(w == 0) and np.any((w > 0) & (w < 1))
    fast = FastPredictor(h1, DT)
    stream = np.array([fast.predict_one(t.q[k], t.dq[k], t.ddq[k]) for k in range(len(t))])
    batch = h1.predict(t.q, t.dq, t.ddq, np.array([0]))
    np.testing.assert_allclose(stream, batch, rtol=1e-5, atol=1e-4)
    # Not trivially: the unblended model differs by more than that where the trust is below 1.
    full = without_coverage(h1).predict(t.q, t.dq, t.ddq, np.array([0]))
    assert np.abs(full - batch)[w < 1].max() > 0.1


@pytest.fixture(scope="module")
def others(robot_module, fitted):
    s, p2, _ = fitted
    opts = TrainOptions(coverage=COVERAGE, max_trees=40, nthread=1)
    return {kind: fit_model(kind, robot_module, s, opts, p2=p2) for kind in ("H2", "H3")}


@pytest.mark.parametrize("kind", ["H2", "H3"])
def test_h2_h3_report_but_do_not_blend(robot_module, fitted, others, kind):
    model = others[kind]
    assert isinstance(model, LearnedModel) and model.kind == kind
    assert model.coverage is not None and not model.coverage.blend
    t = probe(robot_module)
    tau, sigma, w = model.predict_with_uncertainty(t.q, t.dq, t.ddq, t.starts)
    assert np.any(w[:, model.forest.outputs] < 1)  # a blend would have changed something
    np.testing.assert_array_equal(tau, without_coverage(model).predict(t.q, t.dq, t.ddq, t.starts))
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    fast = FastPredictor(model, DT)
    stream = np.array([fast.predict_one(t.q[k], t.dq[k], t.ddq[k]) for k in range(300)])
    np.testing.assert_allclose(stream, tau[:300], rtol=1e-5, atol=1e-4)


# ------------------------------------------------------------------------------------------ observer
def rest_state(robot_module, fitted) -> ArmState:
    s, p2, _ = fitted
    q = s.q[len(s) // 2]
    return ArmState(t=0.0, q=q, dq=np.zeros(6), tau=p2.predict_one(q, np.zeros(6), np.zeros(6)))


def test_kalman_measurement_noise_from_the_model(robot_module, fitted):
    s, p2, h1 = fitted
    state = rest_state(robot_module, fitted)
    calibrated = np.full(6, 0.04)
    obs = KalmanObserver(h1, DT, calibrated, np.full(6, 1e-4), model_noise=True)
    for k in range(3):
        obs.update(dataclasses.replace(state, t=k * DT))
    r_diag = np.diag(obs.kf.R)
    _, sigma, _ = h1.predict_with_uncertainty(state.q[None], np.zeros((1, 6)), np.zeros((1, 6)))
    np.testing.assert_allclose(r_diag, np.maximum(calibrated, sigma[0] ** 2))
    band_var = p2.params.f_c**2 / 3.0
    outs = h1.forest.outputs
    assert np.all(r_diag[outs] >= band_var[outs] - 1e-9) and np.all(band_var[outs] > calibrated[outs])
    assert np.all(r_diag >= calibrated)
    # A calibrated variance above the model's is kept.
    loud = np.full(6, 1e3)
    obs = KalmanObserver(h1, DT, loud, np.full(6, 1e-4), model_noise=True)
    obs.update(state)
    np.testing.assert_array_equal(np.diag(obs.kf.R), loud)


def test_kalman_measurement_noise_calibrated_by_default(robot_module, fitted):
    s, p2, h1 = fitted
    state = rest_state(robot_module, fitted)
    calibrated = np.linspace(0.02, 0.07, 6)
    for obs in (KalmanObserver(h1, DT, calibrated, np.full(6, 1e-4)),
                KalmanObserver(h1, DT, calibrated, np.full(6, 1e-4), model_noise=False),
                KalmanObserver(without_coverage(h1), DT, calibrated, np.full(6, 1e-4), model_noise=True)):
        for k in range(3):
            obs.update(dataclasses.replace(state, t=k * DT))
        np.testing.assert_array_equal(obs.kf.R, np.diag(calibrated))


# ------------------------------------------------------------------------------------------ shared model step
def _states(robot_module, fitted, n: int = 60, push_nm: float = 4.0) -> list[ArmState]:
    """Samples of the training motion with a push on joint 2 from the middle on (the load input matters)."""
    s, p2, _ = fitted
    out = []
    for k in range(n):
        tau = p2.predict_one(s.q[k], s.dq[k], s.ddq[k]).copy()
        if k >= n // 2:
            tau[1] += push_nm
        out.append(ArmState(t=k * DT, q=s.q[k], dq=s.dq[k], tau=tau))
    return out


def test_observers_on_one_step_evaluate_the_model_once_per_sample(robot_module, fitted):
    from cell.sensing.model_step import ModelStep
    from cell.sensing.observer import MomentumObserver

    _, _, h1 = fitted
    states = _states(robot_module, fitted)
    step = ModelStep(h1, DT)
    lead = KalmanObserver(h1, DT, np.full(6, 0.04), np.full(6, 1e-3), step=step)
    follower = MomentumObserver(h1, DT, 50.0, step=step)
    own_load = MomentumObserver(h1, DT, 50.0, step=step, own_load=True)
    alone = KalmanObserver(h1, DT, np.full(6, 0.04), np.full(6, 1e-3))
    follower_alone = MomentumObserver(h1, DT, 50.0)
    differs = 0.0
    for state in states:
        np.testing.assert_array_equal(lead.update(state), alone.update(state))  # the lead computes as alone
        shared, own = follower.update(state), follower_alone.update(state)
        # The follower's load input is the lead's estimate, not its own: close, not equal.
        np.testing.assert_allclose(shared, own, atol=0.5)
        differs = max(differs, float(np.max(np.abs(shared - own))))
        # A follower with its own load input computes what it did alone, on the shared derivatives and window.
        np.testing.assert_array_equal(own_load.update(state), own)
    assert differs > 0  # the push loads the gears: the load input matters
    assert step.evaluations == len(states)
    assert lead.step is follower.step is step and step.lead is lead
    # The lead not updated on a sample: the follower evaluates it itself.
    extra = dataclasses.replace(states[-1], t=len(states) * DT)
    follower.update(extra)
    assert step.evaluations == len(states) + 1
    # A follower's reset leaves the lead's stream alone; the lead's restarts it.
    follower.reset()
    assert step.fast.derivs._v_prev is not None
    lead.reset()
    assert step.fast.derivs._v_prev is None


def test_a_follower_reads_the_lead_sample_for_the_same_state_only(robot_module, fitted):
    from cell.sensing.model_step import ModelStep
    from cell.sensing.observer import MomentumObserver

    _, _, h1 = fitted
    a, b = _states(robot_module, fitted, n=2)
    step = ModelStep(h1, DT)
    lead = MomentumObserver(h1, DT, 50.0, step=step)
    follower = MomentumObserver(h1, DT, 50.0, step=step)
    lead.update(a)
    follower.update(a)
    assert step.evaluations == 1
    # An equal state in another object is another sample (a repeated read is the lead's to judge).
    follower.update(dataclasses.replace(b))
    lead.update(b)
    assert step.evaluations == 3
