"""Physically consistent P2 identification: link parameters in log-Cholesky coordinates, losses with extra terms."""

from __future__ import annotations

import logging

import numpy as np
import pinocchio as pin
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from cell.model.dynamics.consistency import is_consistent, params_from_theta, theta_from_params
from cell.model.dynamics.friction import extra_columns, term_names
from cell.model.dynamics.rigid_body import (
    IdentificationConfig,
    P2Model,
    P2Params,
    mass_matrix_positive,
    nominal_parameters,
    robot_meta,
)
from cell.model.robot import RobotModel

log = logging.getLogger(__name__)

BASIC_LOSSES = ("B_m", "C_m", "f_c")  # rotor inertia, viscous, Coulomb: the first three loss columns
# A weak prior on each link's log-Cholesky scale coordinates (alpha, d1..d3) about the nominal link's:
# without it a direction the data does not see can drift to the realisable set's boundary (a
# flat, degenerate body); with it each body stays strictly realisable.  e^2: a factor of ~7 in size.
LOG_PRIOR_STD = 2.0
LOG_COORDS = np.array([0, 1, 2, 3])


def _regressors(model: pin.Model, data: pin.Data, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                sign_eps: float, terms: tuple[str, ...], pi_inertial: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, n, 10n) inertial regressor and (N, n, T) per-joint loss columns; a `load` term reads the
    rigid-body torque of `pi_inertial`."""
    N, n = q.shape
    Y = np.empty((N, n, 10 * n))
    for k in range(N):
        Y[k] = pin.computeJointTorqueRegressor(model, data, q[k], dq[k], ddq[k])
    s = np.tanh(dq / sign_eps) if sign_eps > 0 else np.sign(dq)
    rigid = Y @ pi_inertial if "load" in terms else None
    F = np.concatenate([np.stack([ddq, dq, s], axis=-1), extra_columns(terms, dq, s, rigid)], axis=-1)
    return Y, F


def _normal_equations(Y: np.ndarray, F: np.ndarray, tau: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H = A^T W^2 A and g = A^T W^2 tau for A = [Y | block-diagonal F] (loss columns joint by joint)."""
    N, n, p = Y.shape
    T = F.shape[-1]
    A = np.zeros((N, n, p + n * T))
    A[:, :, :p] = Y
    for j in range(n):
        A[:, j, p + j * T:p + (j + 1) * T] = F[:, j]
    Aw = (A * w[None, :, None]).reshape(N * n, -1)
    bw = (tau * w[None, :]).reshape(-1)
    return Aw.T @ Aw, Aw.T @ bw


def identify_consistent(robot: RobotModel, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, tau: np.ndarray,
                        cfg: IdentificationConfig, training_data_sha256: str = "") -> P2Model:
    """See `_identify`; BLAS on one thread: its ~400 small factorisations (~130 x 110) gain nothing from
    threads, and on a busy 2-core machine two threads made one fit 63 s instead of 6 s."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _identify(robot, q, dq, ddq, tau, cfg, training_data_sha256)


def _identify(robot: RobotModel, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, tau: np.ndarray,
              cfg: IdentificationConfig, training_data_sha256: str = "") -> P2Model:
    """MAP estimate of every link's 10 parameters (each a realisable body by construction) and every
    joint's losses: min |W (Y pi + F phi - tau)|^2 + |(pi - pi_nom) / scale|^2 + |phi / loss_prior|^2,
    with pi = pi(theta) in log-Cholesky coordinates and B_m, C_m, f_c >= 0 (`nonneg_losses`).
    W weighs each joint by its residual level (a first, linear fit), as `identify_p2` does."""
    model = robot.model
    n = model.nv
    N = q.shape[0]
    rows = np.arange(N) if cfg.max_samples >= N else np.linspace(0, N - 1, cfg.max_samples).astype(np.int64)
    terms = tuple(cfg.loss_terms)
    pi_nom = nominal_parameters(model)[:10 * n]
    T = 3 + len(term_names(terms))
    floor = np.tile([0.3, 0.03, 0.03, 0.03, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01], n)
    pi_scale = np.maximum(np.abs(pi_nom), floor) * cfg.prior_relative_std
    loss_scale = np.tile(np.r_[cfg.rotor_inertia_prior_std, np.full(T - 1, cfg.loss_prior_std)], n)
    data = model.createData()

    def assemble(pi_in: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        H = np.zeros((10 * n + n * T,) * 2)
        g = np.zeros(10 * n + n * T)
        for a in range(0, len(rows), cfg.chunk):
            idx = rows[a:a + cfg.chunk]
            Y, F = _regressors(model, data, q[idx], dq[idx], ddq[idx], cfg.sign_eps, terms, pi_in)
            h, gg = _normal_equations(Y, F, tau[idx], w)
            H += h
            g += gg
        return H, g

    prior_prec = np.r_[1.0 / pi_scale**2, 1.0 / loss_scale**2]
    x_prior = np.r_[pi_nom, np.zeros(n * T)]

    def linear(H: np.ndarray, g: np.ndarray) -> np.ndarray:
        return np.linalg.solve(H + np.diag(prior_prec), g + prior_prec * x_prior)

    def residual_std(x: np.ndarray, pi_in: np.ndarray) -> np.ndarray:
        idx = rows[np.linspace(0, len(rows) - 1, min(5000, len(rows))).astype(np.int64)]
        Y, F = _regressors(model, data, q[idx], dq[idx], ddq[idx], cfg.sign_eps, terms, pi_in)
        pred = Y @ x[:10 * n] + np.einsum("njt,jt->nj", F, x[10 * n:].reshape(n, T))
        return np.asarray(np.std(tau[idx] - pred, axis=0))

    # A linear fit at unit weights gives each joint's residual level, then the load term's torque.
    H, g = assemble(pi_nom, np.ones(n))
    x = linear(H, g)
    w = 1.0 / np.maximum(residual_std(x, pi_nom), 1e-3)
    pi_load = pi_nom
    lo = np.full(n * T, -np.inf)
    if cfg.nonneg_losses:
        lo.reshape(n, T)[:, :3] = 0.0
    report_steps = []
    theta_nom = np.concatenate([theta_from_params(pi_nom[10 * j:10 * j + 10]) for j in range(n)])
    log_idx = (LOG_COORDS[None, :] + 10 * np.arange(n)[:, None]).reshape(-1)
    for _ in range(2 if "load" in terms else 1):
        H, g = assemble(pi_load, w)
        x = linear(H, g)
        # Start from the linear MAP estimate, each link moved onto the realisable set.
        theta0 = np.concatenate([theta_from_params(x[10 * j:10 * j + 10]) for j in range(n)])
        phi0 = np.clip(x[10 * n:], lo + 1e-9, None)
        scale = np.sqrt(np.diag(H + np.diag(prior_prec)))
        Hs = (H + np.diag(prior_prec)) / np.outer(scale, scale)
        L = np.linalg.cholesky(Hs + 1e-10 * np.eye(len(Hs)))
        rhs = np.linalg.solve(L, (g + prior_prec * x_prior) / scale)

        def fun(z: np.ndarray, L: np.ndarray = L, rhs: np.ndarray = rhs, scale: np.ndarray = scale) -> np.ndarray:
            pi = np.concatenate([params_from_theta(z[10 * j:10 * j + 10]) for j in range(n)])
            xx = np.r_[pi, z[10 * n:]]
            # |L^T (D x) - rhs|^2 is the MAP objective up to a constant; then the log-scale prior.
            return np.r_[L.T @ (xx * scale) - rhs, (z[log_idx] - theta_nom[log_idx]) / LOG_PRIOR_STD]

        z0 = np.r_[theta0, phi0]
        bounds = (np.r_[np.full(10 * n, -np.inf), lo], np.full(len(z0), np.inf))
        sol = least_squares(fun, z0, bounds=bounds, method="trf", x_scale="jac", max_nfev=200)
        pi = np.concatenate([params_from_theta(sol.x[10 * j:10 * j + 10]) for j in range(n)])
        x = np.r_[pi, sol.x[10 * n:]]
        report_steps.append({"nfev": int(sol.nfev), "cost": float(sol.cost), "status": int(sol.status)})
        pi_load = pi
    inertial = x[:10 * n].reshape(n, 10)
    losses = x[10 * n:].reshape(n, T)
    sigma = residual_std(x, pi_load)
    consistent = [is_consistent(inertial[j]) for j in range(n)]
    report = {
        "samples": int(len(rows)), "consistency": "log_cholesky", "loss_terms": list(terms),
        "residual_std_per_joint_nm": np.round(sigma, 4).tolist(),
        "masses_kg": np.round(inertial[:, 0], 4).tolist(),
        "physically_consistent": all(consistent),
        "mass_matrix_positive": mass_matrix_positive(robot, inertial, losses[:, 0], q[rows]),
        "losses": {name: np.round(losses[:, k], 4).tolist()
                   for k, name in enumerate(BASIC_LOSSES + tuple(term_names(terms)))},
        "solver": report_steps,
    }
    params = P2Params(inertial=inertial, B_m=losses[:, 0].copy(), C_m=losses[:, 1].copy(), f_c=losses[:, 2].copy(),
                      sign_eps=cfg.sign_eps, report=report, extra_terms=list(terms), extra=losses[:, 3:].copy())
    meta = robot_meta(robot, "P2", training_data_sha256=training_data_sha256, training_samples=int(N),
                      features={"sign_eps": cfg.sign_eps, "prior_relative_std": cfg.prior_relative_std,
                                "consistency": "log_cholesky", "loss_terms": list(terms)})
    return P2Model(robot, params, meta)
