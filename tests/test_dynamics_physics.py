"""P1 and P2: base parameters by QR, and identification that recovers a known model with modified parameters."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from cell.model.dynamics.artefact import load_model, save_model
from cell.model.dynamics.base import TorqueModel
from cell.model.dynamics.physics import P1Model, base_parameters, full_regressor, identify_p2
from cell.model.dynamics.rigid_body import IdentificationConfig, P2Model, nominal_parameters

TRUE_BM = np.array([0.6, 0.6, 0.3, 0.06, 0.06, 0.06])
TRUE_CM = np.array([5.0, 5.0, 3.5, 1.0, 1.0, 0.8])
TRUE_FC = np.array([5.5, 5.5, 4.0, 1.5, 1.5, 1.2])
EPS = 0.005


def excitation(n: int, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A sum of sines per joint (analytic derivatives)."""
    rng = np.random.default_rng(seed)
    t = np.arange(samples) * 0.008
    q = np.zeros((samples, n))
    dq = np.zeros_like(q)
    ddq = np.zeros_like(q)
    for k in range(1, 6):
        w = rng.uniform(0.3, 1.2, n) * k
        a = rng.uniform(0.05, 0.4, n) / np.sqrt(k)
        ph = rng.uniform(0, 2 * np.pi, n)
        q += a * np.sin(w * t[:, None] + ph)
        dq += a * w * np.cos(w * t[:, None] + ph)
        ddq += -a * w**2 * np.sin(w * t[:, None] + ph)
    return q, dq, ddq


@pytest.fixture(scope="module")
def true_model(robot_module):
    """The nominal model with every link's mass, COM and inertia changed: the 'real' arm."""
    model = robot_module.model.copy()
    rng = np.random.default_rng(5)
    for j in range(1, model.njoints):
        inertia = model.inertias[j]
        model.inertias[j] = pin.Inertia(inertia.mass * rng.uniform(0.85, 1.15),
                                        inertia.lever + rng.uniform(-0.04, 0.04, 3),
                                        inertia.inertia * rng.uniform(0.7, 1.3))
    return model


def true_torque(model: pin.Model, q, dq, ddq) -> np.ndarray:
    data = model.createData()
    rb = np.array([pin.rnea(model, data, q[k], dq[k], ddq[k]) for k in range(len(q))])
    return rb + TRUE_BM * ddq + TRUE_CM * dq + TRUE_FC * np.tanh(dq / EPS)


def test_base_regressor_reproduces_the_full_regressor(robot_module):
    model = robot_module.model
    bp = base_parameters(model)
    rng = np.random.default_rng(0)
    q, dq, ddq = rng.normal(size=(3, 20, 6))
    Y = full_regressor(model, model.createData(), q, dq, ddq, EPS)
    pi = nominal_parameters(model) + rng.normal(size=Y.shape[1])
    np.testing.assert_allclose(Y[:, bp.base] @ bp.beta(pi), Y @ pi, atol=1e-8)
    assert 40 <= len(bp.base) < Y.shape[1]


def test_p1_is_the_nominal_rnea(robot_module):
    q, dq, ddq = excitation(6, 50, 1)
    p1 = P1Model(robot_module)
    assert isinstance(p1, TorqueModel)
    expected = [robot_module.rnea(q[k], dq[k], ddq[k]) for k in range(50)]
    np.testing.assert_allclose(p1.predict(q, dq, ddq), expected)


def test_p2_identification_recovers_a_known_model(robot_module, true_model):
    q, dq, ddq = excitation(6, 6000, 2)
    tau_true = true_torque(true_model, q, dq, ddq)
    rng = np.random.default_rng(3)
    tau = tau_true + rng.normal(0, 0.3, tau_true.shape)
    p2 = identify_p2(robot_module, q, dq, ddq, tau, IdentificationConfig(sign_eps=EPS))
    # On fresh motion, P2 predicts the true torque to well below the noise, P1 does not come close.
    q2, dq2, ddq2 = excitation(6, 2000, 9)
    truth = true_torque(true_model, q2, dq2, ddq2)
    p2_err = np.sqrt(np.mean((p2.predict(q2, dq2, ddq2) - truth) ** 2, axis=0))
    p1_err = np.sqrt(np.mean((P1Model(robot_module).predict(q2, dq2, ddq2) - truth) ** 2, axis=0))
    assert np.all(p2_err < 0.15), p2_err
    assert np.all(p1_err[:3] > 3.0), p1_err
    # Viscous and Coulomb friction are identifiable on their own: recovered within a few percent.
    np.testing.assert_allclose(p2.params.C_m, TRUE_CM, rtol=0.05)
    np.testing.assert_allclose(p2.params.f_c, TRUE_FC, rtol=0.05)
    assert p2.params.report["mass_matrix_positive"]
    assert np.all(p2.params.f_c >= 0) and np.all(p2.params.C_m >= 0)


def test_p2_keeps_parameters_near_nominal_without_excitation(robot_module, true_model):
    """Barely moving data near the upright pose: the prior keeps the unobservable masses at the datasheet."""
    q, dq, ddq = excitation(6, 1500, 4)
    q, dq, ddq = q * 0.05, dq * 0.05, ddq * 0.05
    tau = true_torque(true_model, q, dq, ddq) + np.random.default_rng(1).normal(0, 0.3, q.shape)
    p2 = identify_p2(robot_module, q, dq, ddq, tau, IdentificationConfig(sign_eps=EPS))
    masses = p2.params.inertial[:, 0]
    nominal = np.array([robot_module.model.inertias[j].mass for j in range(1, 7)])
    np.testing.assert_allclose(masses, nominal, rtol=0.35)
    assert p2.params.report["mass_matrix_positive"]


def test_p2_never_identifies_friction_that_pushes(robot_module):
    q, dq, ddq = excitation(6, 1500, 4)
    data = robot_module.model.createData()
    tau = np.array([pin.rnea(robot_module.model, data, q[k], dq[k], ddq[k]) for k in range(len(q))])
    tau -= 2.0 * np.tanh(dq / EPS) + 1.0 * dq  # 'friction' that helps motion: unphysical
    p2 = identify_p2(robot_module, q, dq, ddq, tau, IdentificationConfig(sign_eps=EPS))
    assert np.all(p2.params.f_c >= 0) and np.all(p2.params.C_m >= 0)
    bounded = [f"B_m{j + 1}" for j in range(6) if f"B_m{j + 1}" not in p2.params.report["lumped_losses"]]
    assert all(p2.params.B_m[int(b[3:]) - 1] >= 0 for b in bounded)
    assert np.max(p2.params.f_c) < 0.1 and np.max(p2.params.C_m) < 0.1


def test_p2_artefact_round_trip(robot_module, true_model, tmp_path):
    q, dq, ddq = excitation(6, 1500, 6)
    tau = true_torque(true_model, q, dq, ddq)
    p2 = identify_p2(robot_module, q, dq, ddq, tau)
    save_model(p2, tmp_path / "p2")
    back = load_model(tmp_path / "p2", robot_module)
    assert isinstance(back, P2Model) and back.meta.kind == "P2"
    np.testing.assert_allclose(back.predict(q[:50], dq[:50], ddq[:50]), p2.predict(q[:50], dq[:50], ddq[:50]))
    np.testing.assert_allclose(back.predict_one(q[7], dq[7], ddq[7]), p2.predict(q[7:8], dq[7:8], ddq[7:8])[0])
