"""Residual levels binned by the arm's fastest joint (Coverage.sigma_arm): a slow joint's error while another
joint is fast, kept through the artefact's dict, absent (None) in models saved without it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cell.model.dynamics.uncertainty import SPEED_EDGES, Coverage


def coupled(seed: int = 3, n: int = 3, rows: int = 12000, stick_speed: float = 0.0) -> Coverage:
    """Joint 0 always slow (0.02-0.05 rad/s); joint 1 slow on half the rows, fast (0.5-0.9 rad/s) on the
    other half; joint 2 still.  Joint 0's residual is 0.1 N m while joint 1 is slow and 2.0 N m while it is
    fast (a velocity product), the physics part's three times that."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, (rows, n))
    ddq = rng.uniform(-1, 1, (rows, n))
    dq = np.zeros((rows, n))
    dq[:, 0] = rng.uniform(0.02, 0.05, rows) * rng.choice([-1.0, 1.0], rows)
    fast = np.arange(rows) % 2 == 1
    dq[:, 1] = np.where(fast, rng.uniform(0.5, 0.9, rows), rng.uniform(0.02, 0.05, rows))
    level = np.full((rows, n), 0.1)
    level[:, 0] = np.where(fast, 2.0, 0.1)
    sign = rng.choice([-1.0, 1.0], (rows, n))
    return Coverage.fit([0, 1], q, dq, ddq, level * sign, 3 * level * sign, np.full(n, 0.5), bins=4,
                        min_count=10, stick_speed=stick_speed)


def test_a_slow_joint_of_a_fast_arm_gets_the_level_of_the_fast_arm():
    cov = coupled()
    assert cov.sigma_hybrid_arm is not None and cov.sigma_physics_arm is not None
    assert cov.sigma_hybrid_arm.shape == cov.sigma_hybrid.shape == (3, len(SPEED_EDGES) - 1)
    slow_arm = np.array([[0.03, 0.03, 0.0]])
    fast_arm = np.array([[0.03, 0.7, 0.0]])
    w = np.ones((1, 3))
    own = cov.sigma(fast_arm, w)
    arm = cov.sigma_arm(fast_arm, w)
    assert arm is not None
    # By its own speed, joint 0 mixes both halves of its rows: the RMS of 0.1 and 2.0.
    assert own[0, 0] == pytest.approx(np.sqrt((0.1**2 + 2.0**2) / 2), rel=0.05)
    # By the arm's fastest joint, the fast arm's rows alone: 2.0, well above the own-speed level.
    assert arm[0, 0] == pytest.approx(2.0, rel=1e-6)
    assert arm[0, 0] > 1.3 * own[0, 0]
    # With the whole arm slow, the arm's level is the slow rows' one.
    slow = cov.sigma_arm(slow_arm, w)
    assert slow is not None and slow[0, 0] == pytest.approx(0.1, rel=1e-6)
    # The trust blends toward the physics part's level as for the own-speed levels.
    arm_p = cov.sigma_arm(fast_arm, np.zeros((1, 3)))
    assert arm_p is not None and arm_p[0, 0] == pytest.approx(6.0, rel=1e-6)
    half = cov.sigma_arm(fast_arm, np.full((1, 3), 0.5))
    assert half is not None and half[0, 0] == pytest.approx(np.sqrt(0.5 * 2.0**2 + 0.5 * 6.0**2), rel=1e-6)


def test_the_arm_levels_keep_each_joints_own_sticking_floor():
    # A joint at rest in a moving arm still sticks: its floor comes from its own speed, not the arm's.
    cov = coupled(stick_speed=0.01)
    dq = np.array([[0.0, 0.7, 0.7]])
    arm = cov.sigma_arm(dq, np.ones((1, 3)))
    assert arm is not None
    floor = cov.static_band / np.sqrt(3.0)
    assert arm[0, 0] == pytest.approx(max(floor[0], 2.0))
    moving = cov.sigma_arm(np.array([[0.5, 0.7, 0.7]]), np.ones((1, 3)))
    assert moving is not None and moving[0, 2] == pytest.approx(0.1, rel=1e-6)  # no floor above the stick speed
    assert arm[0, 2] == pytest.approx(moving[0, 2])


def test_arm_levels_survive_the_dict_round_trip():
    cov = coupled()
    back = Coverage.from_dict(json.loads(json.dumps(cov.to_dict())))
    assert cov.sigma_hybrid_arm is not None and cov.sigma_physics_arm is not None
    np.testing.assert_array_equal(back.sigma_hybrid_arm, cov.sigma_hybrid_arm)
    np.testing.assert_array_equal(back.sigma_physics_arm, cov.sigma_physics_arm)
    rng = np.random.default_rng(4)
    dq = rng.uniform(-1.0, 1.0, (50, 3))
    w = rng.uniform(0.0, 1.0, (50, 3))
    np.testing.assert_array_equal(back.sigma_arm(dq, w), cov.sigma_arm(dq, w))
    np.testing.assert_array_equal(back.sigma(dq, w), cov.sigma(dq, w))


def test_a_model_saved_without_arm_levels_loads_without_them():
    d = coupled().to_dict()
    old = {k: v for k, v in d.items() if k not in ("sigma_hybrid_arm", "sigma_physics_arm")}
    back = Coverage.from_dict(old)
    assert back.sigma_hybrid_arm is None and back.sigma_physics_arm is None
    assert back.sigma_arm(np.array([[0.03, 0.7, 0.0]]), np.ones((1, 3))) is None
    assert "sigma_hybrid_arm" not in back.to_dict() and "sigma_physics_arm" not in back.to_dict()
    # Its own-speed levels are read as before.
    np.testing.assert_array_equal(back.sigma_hybrid, np.asarray(d["sigma_hybrid"]))
    # One table without the other is no pair: none is used.
    half = Coverage.from_dict({**old, "sigma_hybrid_arm": d["sigma_hybrid_arm"]})
    assert half.sigma_arm(np.array([[0.03, 0.7, 0.0]]), np.ones((1, 3))) is None


@pytest.mark.parametrize("key", ["sigma_hybrid_arm", "sigma_physics_arm"])
@pytest.mark.parametrize("shape", [(3, 4), (2, len(SPEED_EDGES) - 1), (len(SPEED_EDGES) - 1,)])
def test_arm_tables_of_another_shape_are_refused(key, shape):
    d = coupled().to_dict()
    with pytest.raises(ValueError, match="inconsistent shapes"):
        Coverage.from_dict({**d, key: np.zeros(shape).tolist()})


def test_the_arm_level_of_one_sample_and_of_many_is_the_fastest_joints_bin_blended():
    # One sample (the detector's per-period call) and many give, per sample, the arm tables' column of the bin
    # the fastest joint falls in, blended by the trust and floored where a joint sticks (its own speed).
    from cell.model.dynamics.uncertainty import SPEED_EDGES

    rng = np.random.default_rng(3)
    n, stick = 3, 0.02
    band = np.array([1.0, 2.0, 3.0])
    hyb, phys = rng.uniform(0.1, 2.0, (n, 7)), rng.uniform(0.1, 2.0, (n, 7))
    cov = Coverage(np.arange(n), np.zeros((n, 3)), np.ones((n, 3)), np.zeros((n, 2, 2, 2), np.int32), 0.0, stick,
                   rng.uniform(0.1, 2.0, (n, 7)), rng.uniform(0.1, 2.0, (n, 7)), band, True, hyb, phys)

    def expected(dq: np.ndarray, w: np.ndarray) -> np.ndarray:
        b = min(max(int(np.searchsorted(SPEED_EDGES, np.abs(dq).max(), side="right")) - 1, 0), 6)
        s = np.sqrt(w * hyb[:, b] ** 2 + (1.0 - w) * phys[:, b] ** 2)
        return np.where(np.abs(dq) < stick, np.maximum(s, band / np.sqrt(3.0)), s)

    dqs = rng.choice([0.0, 0.005, 0.05, 0.2, 0.6, 2.0], (50, n)) * rng.choice([-1.0, 1.0], (50, n))
    ws = rng.uniform(0, 1, (50, n))
    many = cov.sigma_arm(dqs, ws)
    assert many is not None and many.shape == (50, n)
    for dq, w, row in zip(dqs, ws, many, strict=True):
        one = cov.sigma_arm(dq, w)
        assert one is not None and one.shape == (n,)
        np.testing.assert_allclose(one, expected(dq, w), rtol=1e-12)
        np.testing.assert_allclose(row, expected(dq, w), rtol=1e-12)
    cov.sigma_hybrid_arm = None
    assert cov.sigma_arm(np.zeros(n), np.ones(n)) is None
