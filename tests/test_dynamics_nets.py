"""The networks' two forwards agree: numpy (what serves the virtual sensor) and JAX (what training fits)."""

from __future__ import annotations

import numpy as np
import pytest

from cell.model.dynamics.nets import NetParams, _init, forward_jax, forward_np

jnp = pytest.importorskip("jax.numpy")
jax = pytest.importorskip("jax")

WINDOW, WIDTH, EXTRA, OUTPUTS = 4, 3, 2, 2


def _random_weights(params: NetParams, seed: int) -> dict[str, np.ndarray]:
    """The training's initial shapes with every entry drawn at random (biases too), so no term is zero."""
    rng = np.random.default_rng(seed)
    shapes = _init(params, WINDOW * WIDTH + EXTRA, OUTPUTS, WINDOW, WIDTH, seed)
    return {k: rng.normal(0.0, 0.5, v.shape).astype(np.float32) for k, v in shapes.items()}


@pytest.mark.parametrize("learner,activation", [("lstm", "tanh"), ("lstm", "relu"), ("dnn", "tanh")])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numpy_forward_matches_the_jax_forward(learner, activation, seed):
    params = NetParams(learner=learner, hidden=5, layers=2, activation=activation, dropout=0.3,
                       recurrent_dropout=0.3)
    weights = _random_weights(params, seed)
    x = np.random.default_rng(100 + seed).normal(0.0, 1.0, (32, WINDOW * WIDTH + EXTRA)).astype(np.float32)
    served = forward_np(weights, x, params, WINDOW, WIDTH)
    trained = np.asarray(forward_jax({k: jnp.asarray(v) for k, v in weights.items()}, jnp.asarray(x), params,
                                     WINDOW, WIDTH, jax.random.PRNGKey(seed), False))
    assert served.shape == (32, OUTPUTS) and np.ptp(served) > 0.1  # a non-trivial output to compare
    np.testing.assert_allclose(served, trained, rtol=0, atol=1e-6)


def test_the_comparison_sees_a_wrong_step_order():
    """Guard on the test itself: the newest-first window run the wrong way round does not pass."""
    params = NetParams(learner="lstm", hidden=5, layers=2)
    weights = _random_weights(params, 3)
    x = np.random.default_rng(7).normal(0.0, 1.0, (32, WINDOW * WIDTH + EXTRA)).astype(np.float32)
    seq = x[:, :WINDOW * WIDTH].reshape(32, WINDOW, WIDTH)[:, ::-1].reshape(32, -1)
    flipped = np.concatenate([seq, x[:, WINDOW * WIDTH:]], axis=1)
    trained = np.asarray(forward_jax({k: jnp.asarray(v) for k, v in weights.items()}, jnp.asarray(x), params,
                                     WINDOW, WIDTH, jax.random.PRNGKey(0), False))
    assert np.max(np.abs(forward_np(weights, flipped, params, WINDOW, WIDTH) - trained)) > 1e-3
