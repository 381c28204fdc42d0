"""Physics models: P1 (nominal rigid body, RNEA) and the identification of P2 (base parameters by QR, MAP estimate
with B_m, C_m, f_c losses; P2's form is in rigid_body.py)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.optimize import lsq_linear

from cell.model.dynamics.consistency import is_consistent
from cell.model.dynamics.consistent_id import identify_consistent
from cell.model.dynamics.rigid_body import (
    IdentificationConfig,
    P2Model,
    P2Params,
    mass_matrix_positive,
    nominal_parameters,
    rnea_batch,
    robot_meta,
    smooth_sign,
)
from cell.model.robot import RobotModel

log = logging.getLogger(__name__)

INERTIAL_NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")  # Pinocchio's order


class P1Model:
    """Model P1: M(q)q'' + C(q,q')q' + G(q) from the nominal URDF and nominal tool (no losses)."""

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.model = robot.model
        self.data = robot.model.createData()
        self.meta = robot_meta(robot, "P1")

    def predict(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, starts: np.ndarray | None = None) -> np.ndarray:
        return rnea_batch(self.model, self.data, np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq))


# ----------------------------------------------------------------------------------------- regressor
def full_regressor(model: pin.Model, data: pin.Data, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                   sign_eps: float) -> np.ndarray:
    """Stacked (N*n, 13n) regressor: 10 inertial parameters per body, then B_m, C_m, f_c per joint."""
    n = model.nv
    N = q.shape[0]
    out = np.zeros((N, n, 13 * n))
    s = smooth_sign(dq, sign_eps)
    diag = np.arange(n)
    for k in range(N):
        out[k, :, :10 * n] = pin.computeJointTorqueRegressor(model, data, q[k], dq[k], ddq[k])
    out[:, diag, 10 * n + diag] = ddq
    out[:, diag, 11 * n + diag] = dq
    out[:, diag, 12 * n + diag] = s
    return out.reshape(N * n, 13 * n)


def parameter_names(n: int) -> list[str]:
    names = [f"{p}_{j + 1}" for j in range(n) for p in INERTIAL_NAMES]
    names += [f"B_m{j + 1}" for j in range(n)] + [f"C_m{j + 1}" for j in range(n)] + [f"f_c{j + 1}" for j in range(n)]
    return names


@dataclass
class BaseParameters:
    """Identifiable combinations: beta = pi[base] + K @ pi[dependent] (Gram-Schmidt QR in column order,
    so inertial parameters are kept ahead of losses: a loss that only ever appears lumped with an
    inertia, like joint 1's rotor inertia with link 1's Izz, joins that inertia's base parameter)."""

    base: np.ndarray  # column indices of the full parameter vector kept as base columns
    dependent: np.ndarray
    K: np.ndarray  # (len(base), len(dependent))

    def beta(self, pi: np.ndarray) -> np.ndarray:
        return pi[self.base] + self.K @ pi[self.dependent]

    def E(self, p: int) -> np.ndarray:
        """(r, p) map pi -> beta."""
        E = np.zeros((len(self.base), p))
        E[:, self.base] = np.eye(len(self.base))
        E[:, self.dependent] = self.K
        return E


def base_parameters(model: pin.Model, samples: int = 300, seed: int = 0, tol: float = 1e-8,
                    sign_eps: float = 0.005) -> BaseParameters:
    """Structural base parameters from random states (independent of any dataset)."""
    rng = np.random.default_rng(seed)
    n = model.nv
    lo = np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -np.pi)
    hi = np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, np.pi)
    q = rng.uniform(lo, hi, (samples, n))
    dq = rng.uniform(-2, 2, (samples, n))
    ddq = rng.uniform(-5, 5, (samples, n))
    Y = full_regressor(model, model.createData(), q, dq, ddq, sign_eps)
    scale = np.linalg.norm(Y, axis=0)
    kept: list[int] = []
    basis = np.zeros((Y.shape[0], 0))
    for c in range(Y.shape[1]):
        if scale[c] < tol:
            continue
        col = Y[:, c] / scale[c]
        res = col - basis @ (basis.T @ col)
        res = res - basis @ (basis.T @ res)  # re-orthogonalise (classical Gram-Schmidt twice)
        r = float(np.linalg.norm(res))
        if r > 1e-6:
            kept.append(c)
            basis = np.column_stack([basis, res / r])
    base = np.asarray(kept, np.int64)
    dependent = np.setdiff1d(np.arange(Y.shape[1]), base)
    K, *_ = np.linalg.lstsq(Y[:, base], Y[:, dependent], rcond=None)
    err = np.abs(Y[:, base] @ K - Y[:, dependent]).max() if dependent.size else 0.0
    if err > 1e-6 * max(1.0, float(np.abs(Y).max())):
        log.warning("base-parameter reduction is inexact (max error %.2e)", err)
    return BaseParameters(base=base, dependent=dependent, K=K)


# ----------------------------------------------------------------------------------------- P2
def identify_p2(
    robot: RobotModel,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    tau: np.ndarray,
    cfg: IdentificationConfig | None = None,
    training_data_sha256: str = "",
) -> P2Model:
    """Identify P2 from measured motion: base parameters by QR, weighted least squares with a
    prior toward the nominal base parameters, and non-negative losses (bounded least squares).
    With `cfg.consistency == "log_cholesky"`: `cell.model.dynamics.consistent_id.identify_consistent`."""
    cfg = cfg or IdentificationConfig()
    cfg.validate("identification")
    if cfg.consistency == "log_cholesky":
        return identify_consistent(robot, q, dq, ddq, tau, cfg, training_data_sha256)
    model = robot.model
    n = model.nv
    N = q.shape[0]
    rows = np.arange(N)
    if cfg.max_samples < N:
        rows = np.linspace(0, N - 1, cfg.max_samples).astype(np.int64)
    bp = base_parameters(model, sign_eps=cfg.sign_eps)
    pi_nom = nominal_parameters(model)
    beta_nom = bp.beta(pi_nom)
    r = len(bp.base)
    data = model.createData()

    def normal_equations(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        AtA = np.zeros((r, r))
        Atb = np.zeros(r)
        btb = 0.0
        for a in range(0, len(rows), cfg.chunk):
            idx = rows[a:a + cfg.chunk]
            Y = full_regressor(model, data, q[idx], dq[idx], ddq[idx], cfg.sign_eps)
            # Y @ pi = Y_b @ pi_b + Y_d @ pi_d and Y_d = Y_b @ K, so Y @ pi = Y_b @ beta.
            A = Y[:, bp.base]
            w = np.tile(weights, len(idx))
            if cfg.min_speed > 0:
                w = w * (np.abs(dq[idx]) >= cfg.min_speed).reshape(-1)
            Aw = A * w[:, None]
            bw = tau[idx].reshape(-1) * w
            AtA += Aw.T @ Aw
            Atb += Aw.T @ bw
            btb += float(bw @ bw)
        return AtA, Atb, btb

    # Prior std of each base parameter from per-parameter scales (see `prior_relative_std`).
    floor = np.tile([0.3, 0.03, 0.03, 0.03, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01], n)
    pi_scale = np.concatenate([np.maximum(np.abs(pi_nom[:10 * n]), floor) * cfg.prior_relative_std,
                               np.full(n, cfg.rotor_inertia_prior_std), np.full(2 * n, cfg.loss_prior_std)])
    E_full = bp.E(len(pi_nom))
    prior_std = np.sqrt((E_full**2) @ pi_scale**2)
    losses_only = bp.base >= 10 * n

    def solve(AtA: np.ndarray, Atb: np.ndarray) -> np.ndarray:
        P = 1.0 / prior_std**2
        H = AtA + np.diag(P)
        g = Atb + P * beta_nom
        scale = np.sqrt(np.diag(H))
        Hs = H / np.outer(scale, scale)
        L = np.linalg.cholesky(Hs + 1e-12 * np.eye(r))
        # min ||L^T z - L^-1 g_s||^2 over z = scale * beta has the same minimiser as H beta = g,
        # and lets the losses be bounded below by zero.
        rhs = np.linalg.solve(L, g / scale)
        lb = np.full(r, -np.inf)
        if cfg.nonneg_losses:
            lb[losses_only] = 0.0
        res = lsq_linear(L.T, rhs, bounds=(lb, np.full(r, np.inf)), method="bvls", lsq_solver="exact")
        return res.x / scale

    # Two-step weighting: an unweighted fit gives each joint's residual level, the second fit divides
    # by it so the wrist joints (small torques) are not drowned by the shoulder.
    w0 = np.ones(n)
    beta0 = solve(*normal_equations(w0)[:2])
    sigma = _residual_std(robot, bp, beta0, q[rows], dq[rows], ddq[rows], tau[rows], cfg.sign_eps)
    w1 = 1.0 / np.maximum(sigma, 1e-3)
    beta = solve(*normal_equations(w1)[:2])

    # A full pi that reproduces beta exactly and stays nearest the nominal one (weighted minimum-norm
    # update), so P2 predicts through Pinocchio's RNEA.  Each inertial parameter may move in proportion
    # to its nominal size (floors 0.3 kg, 0.03 kg m, 0.01 kg m^2); losses move freely, so a lumped base
    # parameter such as joint 1's Izz + rotor inertia keeps the nominal link inertia and puts the
    # rest into B_m.
    Winv = pi_scale**2
    pi = pi_nom + Winv * (E_full.T @ np.linalg.solve((E_full * Winv) @ E_full.T, beta - E_full @ pi_nom))
    # Losses identifiable on their own are base parameters: take them exactly (the update above only
    # adds round-off), so the bounds hold to the last bit.
    pi[bp.base[losses_only]] = beta[losses_only]
    if cfg.nonneg_losses:
        pi[bp.base[losses_only]] = np.maximum(pi[bp.base[losses_only]], 0.0)
    inertial = pi[:10 * n].reshape(n, 10)
    B_m, C_m, f_c = pi[10 * n:11 * n], pi[11 * n:12 * n], pi[12 * n:13 * n]
    names = parameter_names(n)
    lumped = [names[c] for c in bp.dependent if c >= 10 * n]
    sigma_final = _residual_std(robot, bp, beta, q[rows], dq[rows], ddq[rows], tau[rows], cfg.sign_eps)
    report = {
        "samples": int(len(rows)),
        "base_parameters": r,
        "residual_std_per_joint_nm": np.round(sigma_final, 4).tolist(),
        "lumped_losses": lumped,  # not identifiable on their own; folded into an inertial base parameter
        "masses_kg": np.round(inertial[:, 0], 4).tolist(),
        "mass_matrix_positive": mass_matrix_positive(robot, inertial, B_m, q[rows]),
        "consistency": "map",
        "physically_consistent": all(is_consistent(inertial[j]) for j in range(n)),
    }
    if not report["mass_matrix_positive"]:
        log.warning("identified P2 has a mass matrix that is not positive definite on some training states")
    params = P2Params(inertial=inertial, B_m=B_m, C_m=C_m, f_c=f_c, sign_eps=cfg.sign_eps, beta=beta,
                      beta_names=[names[c] for c in bp.base], report=report)
    meta = robot_meta(robot, "P2", training_data_sha256=training_data_sha256, training_samples=int(N),
                      features={"sign_eps": cfg.sign_eps, "prior_relative_std": cfg.prior_relative_std})
    return P2Model(robot, params, meta)


def _residual_std(robot: RobotModel, bp: BaseParameters, beta: np.ndarray, q: np.ndarray, dq: np.ndarray,
                  ddq: np.ndarray, tau: np.ndarray, sign_eps: float, max_rows: int = 5000) -> np.ndarray:
    n = robot.n
    idx = np.linspace(0, len(q) - 1, min(max_rows, len(q))).astype(np.int64)
    Y = full_regressor(robot.model, robot.model.createData(), q[idx], dq[idx], ddq[idx], sign_eps)
    pred = (Y[:, bp.base] @ beta).reshape(len(idx), n)
    return np.asarray(np.std(tau[idx] - pred, axis=0))


