"""The regime a hybrid's learned residual is fitted in (learned.py `regime_rows`): whole moves beyond it are left
to the physics part, their rows still set the levels by the arm's fastest joint; a dataset within it fits as before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cell.data.samples import Samples
from cell.model.dynamics.features import FeatureSpec
from cell.model.dynamics.learned import LearnedModel, XGBParams, fit_learned, regime_rows
from cell.model.dynamics.physics import identify_p2
from cell.model.dynamics.uncertainty import SPEED_EDGES, CoverageConfig
from tests.test_dynamics_learned import motion, plant_like_torque

SMALL = XGBParams(n_estimators=40, max_depth=3, learning_rate=0.2, nthread=1, early_stopping_rounds=10)
SPEC = FeatureSpec(window=1, grouping="own", physics_inputs=True, friction_harmonics=2)
REGIME = CoverageConfig(fit_max_speed=1.0, fit_max_accel=6.0)


def joined(slow: Samples, fast: Samples) -> Samples:
    """Both motions as one dataset, the fast one's trajectories and segments after the slow one's."""
    n = len(slow)
    return Samples(q=np.vstack([slow.q, fast.q]), dq=np.vstack([slow.dq, fast.dq]),
                   ddq=np.vstack([slow.ddq, fast.ddq]), tau=np.vstack([slow.tau, fast.tau]),
                   starts=np.concatenate([slow.starts, fast.starts + n]), names=[],
                   segment=np.concatenate([slow.segment, fast.segment + slow.segment.max() + 1]))


@pytest.fixture(scope="module")
def data(robot_module):
    slow = motion(3000, 0, scale=0.6)
    fast = motion(3000, 5, scale=3.0)
    for s in (slow, fast):
        s.tau = plant_like_torque(robot_module, s) + np.random.default_rng(1).normal(0, 0.2, s.q.shape)
    # The fast moves carry an error the slow ones do not: 15 % of the torque (an inertia the physics part misses).
    fast.tau = fast.tau * 1.15
    both = joined(slow, fast)
    p2 = identify_p2(robot_module, both.q, both.dq, both.ddq, both.tau)
    return slow, fast, both, p2


def test_whole_segments_beyond_the_regime_are_left_out():
    s = motion(400, 2, trajs=1, scale=0.2)
    assert np.abs(s.dq).max() < 1.0 and np.abs(s.ddq).max() < 6.0
    assert regime_rows(s, 1.0, 6.0) is None  # all within: every row, as before
    s.dq[105, 3] = 1.5  # one row of segment 2 too fast
    s.ddq[250, 0] = -7.0  # one row of segment 6 accelerating too hard
    rows = regime_rows(s, 1.0, 6.0)
    assert rows is not None
    left_out = np.setdiff1d(np.arange(len(s)), rows)
    np.testing.assert_array_equal(np.unique(s.segment[left_out]), [s.segment[105], s.segment[250]])
    np.testing.assert_array_equal(left_out, np.flatnonzero(np.isin(s.segment, [s.segment[105], s.segment[250]])))
    accel_only = regime_rows(s, 0.0, 6.0)  # the speed unlimited: segment 2 is back in
    assert accel_only is not None and len(accel_only) > len(rows)
    assert regime_rows(s, 0.0, 0.0) is None  # no limits


def test_the_residual_is_fitted_on_the_regime_alone(robot_module, data):
    slow, fast, both, p2 = data
    assert np.abs(fast.dq).max() > 1.5 and np.abs(slow.dq).max() < 1.0
    regime = fit_learned("H1", robot_module, both, SPEC, SMALL, p2=p2, coverage=REGIME)
    rows = regime_rows(both, REGIME.fit_max_speed, REGIME.fit_max_accel)
    assert rows is not None and regime.meta.extra["fit_rows"] == len(rows)
    alone = fit_learned("H1", robot_module, both.take_rows(rows), SPEC, SMALL, p2=p2)
    # The same forest as one fitted on those rows alone: the fast moves changed nothing in it.
    np.testing.assert_array_equal(regime.predict(both.q, both.dq, both.ddq, both.starts),
                                  alone.predict(both.q, both.dq, both.ddq, both.starts))
    everything = fit_learned("H1", robot_module, both, SPEC, SMALL, p2=p2)
    assert "fit_rows" not in everything.meta.extra
    # Fitted on every row, the fast moves' error leaks into the slow motion; fitted on the regime, it does not.
    def slow_rms(m) -> float:
        e = slow.tau - m.predict(slow.q, slow.dq, slow.ddq, slow.starts)
        return float(np.sqrt(np.mean(e[:, :3] ** 2)))
    assert slow_rms(regime) < 0.85 * slow_rms(everything)


def test_the_levels_beyond_the_regime_come_from_its_cruise(robot_module, data):
    slow, fast, both, p2 = data
    regime = fit_learned("H1", robot_module, both, SPEC, SMALL, p2=p2, coverage=REGIME)
    rows = regime_rows(both, REGIME.fit_max_speed, REGIME.fit_max_accel)
    assert rows is not None
    alone = fit_learned("H1", robot_module, both.take_rows(rows), SPEC, SMALL, p2=p2)
    cov, ref = regime.coverage, alone.coverage
    assert cov is not None and ref is not None and cov.sigma_hybrid_arm is not None
    assert ref.sigma_hybrid_arm is not None
    # By the joint's own speed: the regime's held-out rows, as a model fitted on them alone.
    np.testing.assert_allclose(cov.sigma_hybrid, ref.sigma_hybrid)
    # By the arm's fastest joint: the same below the regime's speed (0.1-1 rad/s, where these moves' arm is),
    # the fast moves' error above it.
    top = len(SPEED_EDGES) - 2  # the 1+ rad/s bin
    np.testing.assert_allclose(cov.sigma_hybrid_arm[:, top - 2:top], ref.sigma_hybrid_arm[:, top - 2:top])
    cruise = np.abs(both.dq).max(axis=1) > REGIME.fit_max_speed
    e = both.tau - regime.predict(both.q, both.dq, both.ddq, both.starts)
    np.testing.assert_allclose(cov.sigma_hybrid_arm[:3, top], np.sqrt(np.mean(e[cruise, :3] ** 2, axis=0)), rtol=1e-6)
    assert np.all(cov.sigma_hybrid_arm[:3, top] > 2 * cov.sigma_hybrid[:3, top - 2])
    # The grid spans the fast moves too: their speeds are within the trained reach.
    reach = cov.lo[:, 1] + cov.width[:, 1] * cov.bins
    assert reach.max() > 1.5


def test_the_regime_limits_are_checked():
    with pytest.raises(Exception, match="fit_max_speed"):
        dataclasses.replace(REGIME, fit_max_speed=-1.0).validate("learning")


def test_the_hybrid_is_the_one_its_regime_alone_gives(robot_module, data):
    from tasks.lab.train import TrainOptions, fit_model

    slow, fast, both, _ = data
    opts = TrainOptions(derivatives="zero_phase", nthread=1, coverage=REGIME, max_trees=30)
    opts.features = {**opts.features, "H1": SPEC}
    rows = regime_rows(both, REGIME.fit_max_speed, REGIME.fit_max_accel)
    assert rows is not None
    regime = fit_model("H1", robot_module, both, opts)
    alone = fit_model("H1", robot_module, both.take_rows(rows), opts)
    assert isinstance(regime, LearnedModel) and isinstance(alone, LearnedModel)
    # The physics part identified on the regime's moves alone, and so the whole prediction, everywhere.
    np.testing.assert_array_equal(regime.physics_torque(both.q, both.dq, both.ddq),
                                  alone.physics_torque(both.q, both.dq, both.ddq))
    np.testing.assert_array_equal(regime.predict(both.q, both.dq, both.ddq, both.starts),
                                  alone.predict(both.q, both.dq, both.ddq, both.starts))
