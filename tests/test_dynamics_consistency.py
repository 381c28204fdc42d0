"""Physically consistent P2: log-Cholesky link parameters, extra loss terms, payloads on the flange.

The identification tests run on synthetic data of the UR10e model: a 'true' arm (the nominal links
with masses and centres of mass changed by up to 15 %, each still a realisable body) with known joint
losses, sampled on random sinusoids around a posture, plus 0.05 N·m of torque noise.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from cell.model.dynamics.consistency import is_consistent, params_from_theta, pseudo_inertia, theta_from_params
from cell.model.dynamics.friction import EXTRA_TERMS, term_names
from cell.model.dynamics.physics import P1Model, identify_p2
from cell.model.dynamics.rigid_body import IdentificationConfig, P2Model, P2Params
from cell.model.specs import load_robot_spec, robot_model
from drivers.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
URDFS = [ROOT / "config/robots/ur10e/ur10e.urdf", ROOT / "config/robots/tm5-700/tm5-700.urdf"]
TERMS = ("offset", "viscous_asym", "stribeck", "load")
NOISE = 0.05  # N·m
EPS = 0.005  # rad/s, the sign softening of both the true losses and the identification (its default)
Q0 = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])  # a UR10e posture: elbow bent, wrist down
PAYLOAD_KG = 2.8

# The true arm's losses per joint: rotor inertia, viscous, Coulomb, a constant offset (asymmetric
# Coulomb friction) and gear friction proportional to the transmitted rigid-body torque.
TRUE_BM = np.array([0.8, 0.8, 0.4, 0.1, 0.1, 0.1])
TRUE_CM = np.array([6.0, 6.0, 4.0, 1.5, 1.5, 1.0])
TRUE_FC = np.array([8.0, 7.0, 5.0, 2.0, 2.0, 1.5])
TRUE_OFFSET = np.array([1.0, -1.5, 0.8, 0.3, -0.2, 0.1])
TRUE_LOAD = np.array([0.03, 0.04, 0.05, 0.03, 0.03, 0.03])


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """OpenBLAS on one thread while the block runs.  The consistent identification makes a few hundred
    small SVDs; on a 2-core machine busy with another job, OpenBLAS's threads make each one ~70x slower
    (a 6 s fit takes minutes).  Not a correctness matter: only the test's run time."""
    setters = []
    for path in {line.split()[-1] for line in Path("/proc/self/maps").read_text().splitlines() if "openblas" in line}:
        lib = ctypes.CDLL(path)
        for setter, getter in (("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                               ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads")):
            if hasattr(lib, setter) and hasattr(lib, getter):
                setters.append((getattr(lib, setter), int(getattr(lib, getter)())))
    for set_threads, _ in setters:
        set_threads(1)
    try:
        yield
    finally:
        for set_threads, before in setters:
            set_threads(before)


# ------------------------------------------------------------------------------------------ log-Cholesky
@pytest.mark.parametrize("urdf", URDFS, ids=lambda p: p.stem)
def test_log_cholesky_round_trip_of_every_urdf_link(urdf):
    model = pin.buildModelFromUrdf(str(urdf))
    assert model.njoints == 7
    for j in range(1, model.njoints):
        p = model.inertias[j].toDynamicParameters()
        assert is_consistent(p), (urdf.name, j)
        theta = theta_from_params(p)
        assert theta.shape == (10,) and np.all(np.isfinite(theta))
        np.testing.assert_allclose(params_from_theta(theta), p, rtol=1e-9, atol=1e-12, err_msg=f"{urdf.name} link {j}")


def test_any_theta_is_a_realisable_body():
    rng = np.random.default_rng(0)
    for _ in range(500):
        theta = rng.normal(0.0, 1.5, 10)
        p = params_from_theta(theta)
        assert is_consistent(p), theta
        # A realisable body: positive mass, and about its COM a positive-definite inertia that obeys
        # the triangle inequalities (each principal moment below the sum of the other two).
        I_com = pin.Inertia.FromDynamicParameters(p).inertia
        w = np.linalg.eigvalsh(I_com)
        assert p[0] > 0 and w.min() > 0
        assert w[2] <= w[0] + w[1] + 1e-9 * w.sum()
        # And the coordinates of that body map back onto it.
        np.testing.assert_allclose(params_from_theta(theta_from_params(p)), p, rtol=1e-7, atol=1e-9)


def body(mass: float, com: np.ndarray, I_com: np.ndarray) -> np.ndarray:
    """10 dynamic parameters (Pinocchio order) of a body whose rotational inertia `I_com` is given about
    its COM (parallel-axis theorem by hand: pin.Inertia refuses an unphysical one)."""
    c = np.asarray(com, float)
    I = np.asarray(I_com, float) + mass * (c @ c * np.eye(3) - np.outer(c, c))
    return np.r_[mass, mass * c, I[0, 0], I[0, 1], I[1, 1], I[0, 2], I[1, 2], I[2, 2]]


def test_unrealisable_bodies_are_not_consistent():
    com = np.array([0.05, -0.02, 0.1])
    good = body(2.0, com, np.diag([0.02, 0.03, 0.04]))
    assert is_consistent(good)
    np.testing.assert_allclose(good, pin.Inertia(2.0, com, np.diag([0.02, 0.03, 0.04])).toDynamicParameters())
    bad = {
        "negative principal inertia": body(2.0, com, np.diag([-0.01, 0.03, 0.04])),
        "triangle inequality (Ixx > Iyy + Izz)": body(2.0, com, np.diag([0.08, 0.03, 0.04])),
        "negative mass": -1.0 * good,
    }
    for why, p in bad.items():
        assert not is_consistent(p), why
        assert np.linalg.eigvalsh(pseudo_inertia(p)).min() < 0, why
        # theta_from_params moves it onto the realisable set: what comes back is a consistent body.
        fixed = params_from_theta(theta_from_params(p))
        assert is_consistent(fixed), why
    # Exactly on the triangle inequality's boundary (a flat body: pseudo-inertia singular up to rounding)
    # is not realisable with any margin.
    flat = body(2.0, com, np.diag([0.07, 0.03, 0.04]))
    assert not is_consistent(flat, tol=1e-9)
    assert is_consistent(good, tol=1e-9)


# ------------------------------------------------------------------------------------------ config
def test_loss_terms_need_log_cholesky_and_known_names():
    IdentificationConfig(consistency="log_cholesky", loss_terms=TERMS).validate("robot.identification")
    IdentificationConfig().validate("robot.identification")
    with pytest.raises(ConfigError, match="loss_terms"):
        IdentificationConfig(loss_terms=("load",)).validate("robot.identification")
    with pytest.raises(ConfigError, match="loss_terms.*'coulomb_squared'"):
        IdentificationConfig(consistency="log_cholesky", loss_terms=("offset", "coulomb_squared")).validate("x")
    with pytest.raises(ConfigError, match="consistency"):
        IdentificationConfig(consistency="cholesky").validate("x")
    assert set(TERMS) == set(EXTRA_TERMS)


# ------------------------------------------------------------------------------------------ identification
@pytest.fixture(scope="module")
def ur10e():
    return robot_model(load_robot_spec("ur10e"))


@pytest.fixture(scope="module")
def true_arm(ur10e) -> pin.Model:
    """The nominal UR10e with every link's mass and COM changed by up to 15 % (inertia about the COM kept)."""
    model = ur10e.model.copy()
    rng = np.random.default_rng(1)
    for j in range(1, model.njoints):
        inertia = model.inertias[j]
        model.inertias[j] = pin.Inertia(inertia.mass * rng.uniform(0.85, 1.15),
                                        inertia.lever * rng.uniform(0.85, 1.15, 3), inertia.inertia)
        assert is_consistent(model.inertias[j].toDynamicParameters())
    return model


def loaded(model: pin.Model, robot, mass: float, com=(0.0, 0.0, 0.0)) -> pin.Model:
    """`model` carrying a point mass at `com` (flange frame): the point's inertia moved from the flange
    frame into the flange's joint frame and added to that joint's body."""
    out = model.copy()
    flange = out.frames[robot.flange_id]
    point = pin.Inertia(mass, np.asarray(com, float), np.zeros((3, 3)))
    out.inertias[flange.parentJoint] = out.inertias[flange.parentJoint] + flange.placement.act(point)
    return out


def sinusoids(samples: int, seed: int, dt: float = 0.008) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three random sinusoids per joint (within +-1 rad of Q0), analytic derivatives."""
    rng = np.random.default_rng(seed)
    t = np.arange(samples)[:, None] * dt
    q = np.tile(Q0, (samples, 1))
    dq = np.zeros_like(q)
    ddq = np.zeros_like(q)
    for _ in range(3):
        w = rng.uniform(0.4, 2.0, 6)
        a = rng.uniform(0.1, 0.33, 6)
        ph = rng.uniform(0, 2 * np.pi, 6)
        q += a * np.sin(w * t + ph)
        dq += a * w * np.cos(w * t + ph)
        ddq -= a * w**2 * np.sin(w * t + ph)
    return q, dq, ddq


def true_torque(model: pin.Model, q, dq, ddq) -> np.ndarray:
    data = model.createData()
    rigid = np.array([pin.rnea(model, data, q[k], dq[k], ddq[k]) for k in range(len(q))])
    s = np.tanh(dq / EPS)
    return rigid + TRUE_BM * ddq + TRUE_CM * dq + TRUE_FC * s + TRUE_OFFSET + TRUE_LOAD * np.abs(rigid) * s


def rmse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


@pytest.fixture(scope="module")
def identified(ur10e, true_arm) -> P2Model:
    q, dq, ddq = sinusoids(3000, 2)
    tau = true_torque(true_arm, q, dq, ddq) + np.random.default_rng(3).normal(0, NOISE, q.shape)
    with single_threaded_blas():
        return identify_p2(ur10e, q, dq, ddq, tau, IdentificationConfig(consistency="log_cholesky", loss_terms=TERMS))


def test_consistent_p2_predicts_held_out_motion_to_the_noise(ur10e, true_arm, identified):
    q, dq, ddq = sinusoids(1500, 7)  # other sinusoids than the training ones
    truth = true_torque(true_arm, q, dq, ddq)
    measured = truth + np.random.default_rng(8).normal(0, NOISE, q.shape)
    err_p2 = rmse(identified.predict(q, dq, ddq), measured)
    err_p1 = rmse(P1Model(ur10e).predict(q, dq, ddq), measured)
    assert np.all(err_p2 < 0.2 * err_p1), (err_p2, err_p1)
    # Against the measurement it is the noise; against the truth well below it.
    assert np.all(err_p2 < 1.5 * NOISE), err_p2
    assert np.all(rmse(identified.predict(q, dq, ddq), truth) < 0.5 * NOISE)
    # The served single-sample path is the same model.
    np.testing.assert_allclose(identified.predict_one(q[5], dq[5], ddq[5]), identified.predict(q[5], dq[5], ddq[5])[0],
                               atol=1e-9)


def test_consistent_p2_links_are_realisable_and_losses_physical(identified):
    par = identified.params
    assert par.report["consistency"] == "log_cholesky"
    assert par.report["physically_consistent"] is True
    assert par.inertial.shape == (6, 10)
    for j in range(6):
        assert is_consistent(par.inertial[j]), j
    assert np.all(par.B_m >= 0) and np.all(par.C_m >= 0) and np.all(par.f_c >= 0)
    # The losses well excited by this data come back near the true ones.
    np.testing.assert_allclose(par.C_m, TRUE_CM, rtol=0.05)
    np.testing.assert_allclose(par.f_c, TRUE_FC, rtol=0.05)
    names = term_names(TERMS)
    assert par.extra_terms == list(TERMS) and par.extra.shape == (6, len(names))
    np.testing.assert_allclose(par.extra[:, names.index("offset")], TRUE_OFFSET, atol=0.1)
    np.testing.assert_allclose(par.extra[:3, names.index("load")], TRUE_LOAD[:3], atol=0.01)


def test_extra_terms_round_trip_through_json(ur10e, identified):
    d = json.loads(json.dumps(identified.params.to_dict()))
    back = P2Params.from_dict(d)
    assert back.extra_terms == list(TERMS)
    np.testing.assert_array_equal(back.extra, identified.params.extra)
    q, dq, ddq = sinusoids(200, 11)
    again = P2Model(ur10e, back)
    np.testing.assert_array_equal(again.predict(q, dq, ddq), identified.predict(q, dq, ddq))
    # The extra terms do matter: without them the prediction changes.
    bare = P2Params.from_dict({**d, "extra_terms": [], "extra": []})
    assert np.abs(P2Model(ur10e, bare).predict(q, dq, ddq) - identified.predict(q, dq, ddq)).max() > 0.5
    # An artefact written before the extra terms existed loads as a P2 without them.
    old = P2Params.from_dict({k: v for k, v in d.items() if k not in ("extra_terms", "extra")})
    np.testing.assert_array_equal(P2Model(ur10e, old).predict(q, dq, ddq), P2Model(ur10e, bare).predict(q, dq, ddq))
    # A file whose coefficients do not match its terms is refused.
    with pytest.raises(ValueError):
        P2Params.from_dict({**d, "extra": np.asarray(d["extra"])[:, :-1].tolist()})


def test_consistent_p2_never_identifies_friction_that_pushes(ur10e):
    """Data whose 'friction' helps the motion (unphysical): the bounded losses stay at zero."""
    q, dq, ddq = sinusoids(1500, 4)
    data = ur10e.model.createData()
    tau = np.array([pin.rnea(ur10e.model, data, q[k], dq[k], ddq[k]) for k in range(len(q))])
    tau -= 2.0 * np.tanh(dq / EPS) + 1.0 * dq
    with single_threaded_blas():
        p2 = identify_p2(ur10e, q, dq, ddq, tau, IdentificationConfig(consistency="log_cholesky"))
    par = p2.params
    assert np.all(par.B_m >= 0) and np.all(par.C_m >= 0) and np.all(par.f_c >= 0)
    assert np.max(par.f_c) < 0.1 and np.max(par.C_m) < 0.1
    assert par.report["physically_consistent"] is True


# ------------------------------------------------------------------------------------------ payload
def test_payload_on_the_flange_without_new_data(ur10e, true_arm, identified):
    """P2 identified without a payload predicts the arm carrying 2.8 kg at the flange once told the mass."""
    heavy = loaded(true_arm, ur10e, PAYLOAD_KG)
    q, dq, ddq = sinusoids(1500, 13)
    tau = true_torque(heavy, q, dq, ddq) + np.random.default_rng(14).normal(0, NOISE, q.shape)
    with_payload = identified.with_payload(PAYLOAD_KG)
    err_bare = rmse(identified.predict(q, dq, ddq), tau)
    err_payload = rmse(with_payload.predict(q, dq, ddq), tau)
    assert np.all(err_payload[1:3] < 0.3 * err_bare[1:3]), (err_payload, err_bare)
    assert np.all(err_bare[1:3] > 5.0), err_bare  # 2.8 kg at ~1.2 m: tens of N·m on the shoulder
    assert np.all(err_payload < 0.2), err_payload
    # The identified model itself is unchanged, and a zero payload changes nothing.
    np.testing.assert_allclose(rmse(identified.predict(q, dq, ddq), tau), err_bare)
    np.testing.assert_allclose(identified.with_payload(0.0).predict(q[:50], dq[:50], ddq[:50]),
                               identified.predict(q[:50], dq[:50], ddq[:50]), atol=1e-9)
    assert with_payload.params.report["payload"]["mass"] == PAYLOAD_KG
    assert is_consistent(with_payload.params.inertial[5])


def test_payload_with_a_com_off_the_flange(ur10e, true_arm, identified):
    """A COM given in the flange frame is placed there (checked against the true arm carrying it there)."""
    com = np.array([0.0, 0.0, 0.1])
    heavy = loaded(true_arm, ur10e, PAYLOAD_KG, com)
    q, dq, ddq = sinusoids(400, 15)
    tau = true_torque(heavy, q, dq, ddq)
    err_at_com = rmse(identified.with_payload(PAYLOAD_KG, com).predict(q, dq, ddq), tau)
    err_at_flange = rmse(identified.with_payload(PAYLOAD_KG).predict(q, dq, ddq), tau)
    assert np.all(err_at_com < 0.2), err_at_com
    assert err_at_flange[4] > 2 * err_at_com[4] + 0.05, (err_at_flange, err_at_com)


@pytest.mark.parametrize("mass", [-1.0, float("nan"), float("inf")])
def test_payload_must_be_a_finite_non_negative_mass(identified, mass):
    with pytest.raises(ValueError, match="payload"):
        identified.with_payload(mass)
