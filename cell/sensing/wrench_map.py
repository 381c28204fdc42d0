"""From external joint torques to a tool wrench: the Jacobian route and the paper's learned route.

Both report the wrench the tool exerts on the environment, in the F/T sensor's frame at its face
(`wrench_point` in the flange frame), so the virtual and the physical sensor read the same numbers.

* `JacobianMap`: W = (J^T)^+ tau_ext with J the 6xn LOCAL Jacobian of the wrench point, damped
  near singularities (the damping grows as the smallest singular value drops below a threshold, so
  the gain along a vanishing direction stays bounded) and flagged when ill-conditioned;
* `ContactMap`: the same equations solved with a prior on where a tool is touched: a force at the
  tool's contact point (its TCP) plus a small free moment (Gaussian prior, `free_moment_nm`), weighted
  by the observer's per-joint residual variance.  A tool touched at its tip (a peg) then reads
  moments consistent with that force's lever, not the joints' uncorrelated model errors;
* `LearnedMap` (paper eq. for the 3-axis sensor): Fz = f(q1..q6, tau_ext1..3),
  Mx = f(q1..q6, tau_ext5), My = f(q1..q6, tau_ext4), one XGBoost model each, trained against the F/T
  sensor; served through the compiled trees of `FlatForest` (tens of microseconds).  The three axes
  it does not model (Fx, Fy, Mz) come from the Jacobian route.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
import xgboost as xgb

from cell.model.dynamics.fastpredict import FlatForest
from cell.model.robot import RobotModel

AXES = ("fx", "fy", "fz", "mx", "my", "mz")
# The paper's learned axes: wrench index -> the tau_ext joints (0-based) each one sees besides q1..q6.
LEARNED_INPUTS: dict[str, tuple[int, tuple[int, ...]]] = {
    "fz": (2, (0, 1, 2)),
    "mx": (3, (4,)),
    "my": (4, (3,)),
}


@dataclass
class Mapped:
    wrench: np.ndarray  # (6,) force [N] then moment [N·m]
    ill_conditioned: bool
    sigma_min: float


class PoseJacobian:
    """The LOCAL Jacobian of one wrench point and its SVD, kept for the last pose.

    Every map on the same robot and point shares one (`pose_jacobian`): the virtual sensor's and the collision
    detector's map the same pose every control period, and the SVD is the larger part of a map's work.  Callers
    must not modify the returned arrays."""

    def __init__(self, robot: RobotModel, point: np.ndarray) -> None:
        self.robot = robot
        self.model = robot.model.copy()
        flange = self.model.frames[robot.flange_id]
        frame = pin.Frame("wrench_point", flange.parentJoint, robot.flange_id,
                          flange.placement * pin.SE3(np.eye(3), np.asarray(point, float)), pin.FrameType.OP_FRAME)
        self.fid = self.model.addFrame(frame)
        self.data = self.model.createData()
        self._key = b""
        self._J = np.zeros((6, robot.n))
        self._svd: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, float)
        key = q.tobytes()
        if key != self._key:
            self._J = np.asarray(pin.computeFrameJacobian(self.model, self.data, q, self.fid,
                                                          pin.ReferenceFrame.LOCAL))
            self._key, self._svd = key, None
        return self._J

    def svd(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(U, s, Vt) of J(q): J = U diag(s) Vt, s descending."""
        J = self.jacobian(q)
        if self._svd is None:
            U, s, Vt = np.linalg.svd(J, full_matrices=False)
            self._svd = (U, s, Vt)
        return self._svd


# Held by the maps that use them: a point's cache goes with the last map on its robot and point.
_POSES: weakref.WeakValueDictionary[tuple[int, bytes], PoseJacobian] = weakref.WeakValueDictionary()


def pose_jacobian(robot: RobotModel, point: np.ndarray) -> PoseJacobian:
    """The `PoseJacobian` every map on `robot` at `point` (flange frame, m) shares."""
    point = np.asarray(point, float)
    key = (id(robot), point.tobytes())
    shared = _POSES.get(key)
    if shared is None or shared.robot is not robot:  # (an id is reused once its robot is gone)
        shared = _POSES[key] = PoseJacobian(robot, point)
    return shared


class JacobianMap:
    """Damped (J^T)^+ at the wrench point; `sigma_min` below `singular_sigma` is flagged."""

    kind = "jacobian"

    def __init__(self, robot: RobotModel, point: np.ndarray, singular_sigma: float = 0.03,
                 max_damping: float = 0.05) -> None:
        self.pose = pose_jacobian(robot, point)
        self.sigma0 = float(singular_sigma)
        self.lam_max = float(max_damping)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """The wrench point's LOCAL Jacobian (6 x n) at `q` (shared: not to be modified)."""
        return self.pose.jacobian(q)

    def map(self, q: np.ndarray, tau_ext: np.ndarray) -> Mapped:
        # J^T = V S U^T, so the damped pseudo-inverse of J^T is U diag(s / (s^2 + lam^2)) V^T.
        U, s, Vt = self.pose.svd(q)
        smin = float(s[-1])
        lam2 = 0.0
        if smin < self.sigma0:  # Nakamura-Hanafusa: damping fades in as the arm nears the singularity
            lam2 = (1.0 - (smin / self.sigma0) ** 2) * self.lam_max**2
        gain = s / (s * s + lam2)
        w = U @ (gain * (Vt @ np.asarray(tau_ext, float)))
        return Mapped(wrench=w, ill_conditioned=smin < self.sigma0, sigma_min=smin)


class ContactMap(JacobianMap):
    """Wrench from tau_ext = J^T w with w = A p, p = (F, m): the force F at the contact point `contact`
    (flange frame) and a free moment m, so the moment at the wrench point is r x F + m.

    Minimises sum_j (J^T A p - tau_ext)_j^2 / var_j + |m|^2 / free_moment_nm^2 (the joints weighted by
    the variance of their model residual).  Six joint torques determine any 6-axis wrench exactly; the
    prior decides how errors in them split between a force and a moment: a moment the contact's lever
    does not explain must be supported by the joints that carry moments best, else it is read as the
    force it would take.  Near a singularity the whole wrench is damped as in `JacobianMap`."""

    kind = "contact"

    def __init__(self, robot: RobotModel, point: np.ndarray, contact: np.ndarray, free_moment_nm: float,
                 joint_var: np.ndarray, singular_sigma: float = 0.03, max_damping: float = 0.05) -> None:
        super().__init__(robot, point, singular_sigma, max_damping)
        if free_moment_nm <= 0:
            raise ValueError(f"free_moment_nm must be > 0, got {free_moment_nm}")
        var = np.asarray(joint_var, float).reshape(-1)
        if var.shape != (robot.n,) or not np.all(np.isfinite(var)) or np.any(var <= 0):
            raise ValueError(f"joint_var must be {robot.n} positive numbers, got {var.tolist()}")
        r = np.asarray(contact, float) - np.asarray(point, float)  # the wrench point's frame is the flange's
        self.A = np.eye(6)
        self.A[3:, :3] = pin.skew(r)
        self.W = np.diag(1.0 / var)
        self.prior = np.diag([0.0, 0.0, 0.0] + [1.0 / free_moment_nm**2] * 3)
        self._wbar = float(np.mean(1.0 / var))
        self._last: tuple[bytes, tuple[np.ndarray, np.ndarray, float]] | None = None

    def _normal_equations(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(B, H, smallest singular value) at q; the last pose's are kept (the touch channel maps a second
        torque at the same pose every period a touch is expected)."""
        key = np.asarray(q, float).tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        J = self.jacobian(q)
        smin = float(self.pose.svd(q)[1][-1])  # (the SVD the detector's map of this pose shares)
        B = J.T @ self.A
        H = B.T @ self.W @ B + self.prior
        if smin < self.sigma0:  # as JacobianMap: damping fades in near the singularity (here on all of p)
            H = H + (1.0 - (smin / self.sigma0) ** 2) * self.lam_max**2 * self._wbar * np.eye(6)
        self._last = (key, (B, H, smin))
        return B, H, smin

    def map(self, q: np.ndarray, tau_ext: np.ndarray) -> Mapped:
        B, H, smin = self._normal_equations(q)
        p = np.linalg.solve(H, B.T @ (self.W @ np.asarray(tau_ext, float)))
        return Mapped(wrench=self.A @ p, ill_conditioned=smin < self.sigma0, sigma_min=smin)


def learned_features(q: np.ndarray, tau_ext: np.ndarray) -> np.ndarray:
    """(N, 12) float32 rows [q1..q6, tau_ext1..tau_ext6]; each booster reads its own columns."""
    return np.hstack([np.atleast_2d(q), np.atleast_2d(tau_ext)]).astype(np.float32)


def _columns(axis: str, n: int) -> np.ndarray:
    _, joints = LEARNED_INPUTS[axis]
    return np.concatenate([np.arange(n), n + np.asarray(joints)]).astype(np.int64)


LEARNED_XGB: dict[str, Any] = {
    "objective": "reg:squarederror", "tree_method": "hist", "max_depth": 4, "eta": 0.1,
    "min_child_weight": 20, "subsample": 0.8, "colsample_bytree": 1.0, "lambda": 1.0, "max_bin": 128,
    "nthread": 1, "seed": 0,  # small fits: one thread (two spin-wait for each other on a busy machine)
}
LEARNED_ROUNDS = 300


def fit_learned_axes(q: np.ndarray, tau_ext: np.ndarray, wrench: np.ndarray, rounds: int = LEARNED_ROUNDS,
                     params: dict[str, Any] | None = None) -> dict[str, xgb.Booster]:
    """One booster per learned axis on calibration rows: q (N, n), tau_ext (N, n), sensor wrench (N, 6)."""
    n = q.shape[1]
    X = learned_features(q, tau_ext)
    out: dict[str, xgb.Booster] = {}
    for axis, (w_idx, _) in LEARNED_INPUTS.items():
        d = xgb.QuantileDMatrix(X[:, _columns(axis, n)], label=wrench[:, w_idx].astype(np.float32),
                                max_bin=LEARNED_XGB["max_bin"], nthread=1)
        out[axis] = xgb.train({**LEARNED_XGB, **(params or {})}, d, rounds)
    return out


class LearnedMap:
    """The paper's learned Fz, Mx, My (compiled trees), the other axes from the Jacobian route."""

    kind = "learned"

    def __init__(self, boosters: dict[str, xgb.Booster], jacobian: JacobianMap, n: int = 6) -> None:
        missing = [a for a in LEARNED_INPUTS if a not in boosters]
        if missing:
            raise ValueError(f"learned map lacks the {missing[0]} model")
        self.boosters = boosters
        self.jacobian = jacobian
        self.n = n
        axes = list(LEARNED_INPUTS)
        self.index = np.array([LEARNED_INPUTS[a][0] for a in axes])
        self.forest = FlatForest([boosters[a] for a in axes], [_columns(a, n) for a in axes])
        self._x = np.empty(2 * n, np.float32)

    def predict(self, q: np.ndarray, tau_ext: np.ndarray) -> np.ndarray:
        """(3,) Fz, Mx, My for one sample."""
        x = self._x
        x[:self.n] = q
        x[self.n:] = tau_ext
        return self.forest.predict(x)

    def map(self, q: np.ndarray, tau_ext: np.ndarray) -> Mapped:
        m = self.jacobian.map(q, tau_ext)
        m.wrench[self.index] = self.predict(q, tau_ext)
        return m

    def predict_batch(self, q: np.ndarray, tau_ext: np.ndarray) -> np.ndarray:
        """(N, 3) with XGBoost itself (offline scoring)."""
        X = learned_features(q, tau_ext)
        return np.column_stack([self.boosters[a].inplace_predict(X[:, _columns(a, self.n)])
                                for a in LEARNED_INPUTS])
