"""Physical consistency of link inertial parameters: the pseudo-inertia test and the log-Cholesky parametrisation.

A body's 10 inertial parameters (Pinocchio order: m, m c, and the rotational inertia about the body
frame's origin) are physically realisable exactly when its 4x4 pseudo-inertia matrix
J = [[Sigma, h], [h^T, m]] (Sigma = tr(I)/2 * 1 - I, h = m c) is positive definite (Wensing, Kim and
Slotine 2017).  Writing J = U U^T with U upper triangular and a positive diagonal (Rucker and Wensing
2022, log-Cholesky) maps any 10 real numbers to a realisable body, so an unconstrained solver that
works in these coordinates can only return physical parameters.
"""

from __future__ import annotations

import numpy as np


def pseudo_inertia(p: np.ndarray) -> np.ndarray:
    """4x4 pseudo-inertia of one body's 10 dynamic parameters (Pinocchio order)."""
    m, hx, hy, hz, ixx, ixy, iyy, ixz, iyz, izz = p
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    sigma = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    J = np.empty((4, 4))
    J[:3, :3] = sigma
    J[:3, 3] = J[3, :3] = (hx, hy, hz)
    J[3, 3] = m
    return J


def from_pseudo_inertia(J: np.ndarray) -> np.ndarray:
    sigma = J[:3, :3]
    inertia = np.trace(sigma) * np.eye(3) - sigma
    return np.array([J[3, 3], J[0, 3], J[1, 3], J[2, 3], inertia[0, 0], inertia[0, 1], inertia[1, 1],
                     inertia[0, 2], inertia[1, 2], inertia[2, 2]])


def is_consistent(p: np.ndarray, tol: float = 0.0) -> bool:
    """Positive mass and a positive-definite pseudo-inertia (smallest eigenvalue above `tol`)."""
    return bool(p[0] > 0 and np.linalg.eigvalsh(pseudo_inertia(p)).min() > tol)


LOG_LIMIT = 30.0  # |log| coordinates are clipped here: a solver's trial step must not overflow exp


def _upper(theta: np.ndarray) -> np.ndarray:
    alpha, d1, d2, d3, s12, s23, s13, t1, t2, t3 = theta
    alpha, d1, d2, d3 = np.clip((alpha, d1, d2, d3), -LOG_LIMIT, LOG_LIMIT)
    return np.exp(alpha) * np.array([[np.exp(d1), s12, s13, t1], [0.0, np.exp(d2), s23, t2],
                                     [0.0, 0.0, np.exp(d3), t3], [0.0, 0.0, 0.0, 1.0]])


def params_from_theta(theta: np.ndarray) -> np.ndarray:
    """10 dynamic parameters of the body whose log-Cholesky coordinates are `theta` (always realisable)."""
    U = _upper(theta)
    return from_pseudo_inertia(U @ U.T)


def theta_from_params(p: np.ndarray, floor: float = 1e-9) -> np.ndarray:
    """Log-Cholesky coordinates of a body; one that is not realisable is first moved onto the nearest
    positive-definite pseudo-inertia (eigenvalues floored at `floor`)."""
    J = pseudo_inertia(np.asarray(p, float))
    w, V = np.linalg.eigh(J)
    if w.min() <= floor:
        J = (V * np.maximum(w, floor)) @ V.T
    # J = U U^T with U upper triangular: the Cholesky factor of the index-reversed matrix, reversed.
    P = np.eye(4)[::-1]
    L = np.linalg.cholesky(P @ J @ P)
    U = P @ L @ P
    alpha = np.log(U[3, 3])
    U = U / U[3, 3]
    return np.array([alpha, np.log(U[0, 0]), np.log(U[1, 1]), np.log(U[2, 2]), U[0, 1], U[1, 2], U[0, 2],
                     U[0, 3], U[1, 3], U[2, 3]])
