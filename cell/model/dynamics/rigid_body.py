"""The rigid body with joint losses in P2's form (parameters, serving, identification settings), and what every
physics model shares: the robot's metadata, batched RNEA, the softened friction sign."""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from cell.model.dynamics.base import ModelMeta
from cell.model.dynamics.friction import extra_columns, term_names, validate_terms
from cell.model.robot import RobotModel
from drivers.configio import join, require


def urdf_sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def robot_meta(robot: RobotModel, kind: str, **kw: Any) -> ModelMeta:
    """Metadata naming the robot a model belongs to (what loading checks)."""
    tool = {"mass": robot.tool.mass, "com": None if robot.tool.com is None else list(map(float, robot.tool.com))}
    extra = dict(kw.pop("extra", {}))
    extra.setdefault("tool", tool)
    return ModelMeta(kind=kind, robot=robot.model.name, urdf_sha256=urdf_sha256(robot.urdf), joints=robot.n,
                     extra=extra, **kw)


def smooth_sign(v: np.ndarray, eps: float) -> np.ndarray:
    """sign(v), softened below `eps` [rad/s] so a joint at rest carries no arbitrary friction sign."""
    return np.tanh(np.asarray(v) / eps) if eps > 0 else np.sign(v)


def rnea_batch(model: pin.Model, data: pin.Data, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
    out = np.empty((q.shape[0], model.nv))
    for k in range(q.shape[0]):
        out[k] = pin.rnea(model, data, q[k], dq[k], ddq[k])
    return out


def nominal_parameters(model: pin.Model) -> np.ndarray:
    """pi of the model (inertias incl. the nominal tool) and zero losses."""
    n = model.nv
    inertial = np.concatenate([model.inertias[j].toDynamicParameters() for j in range(1, n + 1)])
    return np.concatenate([inertial, np.zeros(3 * n)])


@dataclass
class IdentificationConfig:
    """Least squares on the base regressor, weighted per joint, pulled toward the nominal parameters."""

    # Prior on the inertial parameters (MAP estimate): each may deviate from its nominal value by about
    # this fraction of its size (floors 0.3 kg, 0.03 kg m, 0.01 kg m^2).  Poorly excited directions
    # then stay near the datasheet instead of wandering off; well excited ones follow the data.
    prior_relative_std: float = 0.5
    # Losses: wide priors around zero (rotor inertia in kg m^2, viscous in N m s/rad, Coulomb in N m):
    # free where the data speaks, bounded where it does not (a joint that hardly accelerates).
    rotor_inertia_prior_std: float = 2.0
    loss_prior_std: float = 30.0
    sign_eps: float = 0.005  # rad/s, softening of sign(q') in the Coulomb term
    max_samples: int = 60000  # the regressor of more samples than this is built from an even subset
    # A joint slower than this [rad/s] is left out of its own torque equation: in the sticking regime
    # the friction torque is anything up to the breakaway level, which no loss model describes.
    min_speed: float = 0.0
    chunk: int = 4000
    nonneg_losses: bool = True  # B_m, C_m, f_c >= 0 where identifiable on their own
    seed: int = 0
    # "map": the linear MAP estimate on the base parameters (a full pi nearest the nominal one is then
    # reconstructed; its physical consistency is reported, not enforced).  "log_cholesky": every link's
    # parameters in log-Cholesky coordinates (cell/model/dynamics/consistency.py), so each identified link is
    # a realisable body (positive mass, positive-definite inertia), solved by nonlinear least squares.
    consistency: str = "map"
    # Loss terms beyond B_m q'' + C_m q' + f_c sign(q') (cell/model/dynamics/friction.py EXTRA_TERMS);
    # they need consistency "log_cholesky".
    loss_terms: tuple[str, ...] = ()

    def validate(self, where: str) -> None:
        require(self.prior_relative_std > 0, join(where, "prior_relative_std"), "must be > 0")
        require(self.loss_prior_std > 0, join(where, "loss_prior_std"), "must be > 0")
        require(self.rotor_inertia_prior_std > 0, join(where, "rotor_inertia_prior_std"), "must be > 0")
        require(self.sign_eps >= 0, join(where, "sign_eps"), "must be >= 0")
        require(self.max_samples >= 100, join(where, "max_samples"), "must be >= 100")
        require(self.consistency in ("map", "log_cholesky"), join(where, "consistency"),
                f"must be map or log_cholesky, got {self.consistency!r}")
        validate_terms(list(self.loss_terms), join(where, "loss_terms"))
        require(not self.loss_terms or self.consistency == "log_cholesky", join(where, "loss_terms"),
                "need consistency: log_cholesky")


@dataclass
class P2Params:
    """Identified parameters: a full pi reproducing the base parameters (for RNEA), and the losses."""

    inertial: np.ndarray  # (n, 10) per body, Pinocchio order, about the joint frame
    B_m: np.ndarray
    C_m: np.ndarray
    f_c: np.ndarray
    sign_eps: float
    beta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    beta_names: list[str] = field(default_factory=list)
    report: dict[str, Any] = field(default_factory=dict)
    extra_terms: list[str] = field(default_factory=list)  # cell/model/dynamics/friction.py terms
    extra: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (n, columns of extra_terms)

    def to_dict(self) -> dict[str, Any]:
        return {
            "inertial": self.inertial.tolist(), "B_m": self.B_m.tolist(), "C_m": self.C_m.tolist(),
            "f_c": self.f_c.tolist(), "sign_eps": self.sign_eps, "beta": self.beta.tolist(),
            "beta_names": self.beta_names, "report": self.report, "extra_terms": self.extra_terms,
            "extra": self.extra.tolist(),
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> P2Params:
        terms = list(d.get("extra_terms", []))
        validate_terms(terms, "p2.extra_terms")
        n = len(d["B_m"])
        extra = np.asarray(d.get("extra", []), float).reshape(n, len(term_names(terms)))
        return P2Params(
            inertial=np.asarray(d["inertial"], float), B_m=np.asarray(d["B_m"], float),
            C_m=np.asarray(d["C_m"], float), f_c=np.asarray(d["f_c"], float), sign_eps=float(d["sign_eps"]),
            beta=np.asarray(d.get("beta", []), float), beta_names=list(d.get("beta_names", [])),
            report=dict(d.get("report", {})), extra_terms=terms, extra=extra,
        )


class P2Model:
    """Model P2: identified rigid body + B_m q'' + C_m q' + f_c sign(q').

    `rigid` and `losses` are the two halves the hybrids H2 and H3 keep.
    """

    def __init__(self, robot: RobotModel, params: P2Params, meta: ModelMeta | None = None) -> None:
        self.robot = robot
        self.params = params
        self.model = robot.model.copy()
        for j in range(1, self.model.njoints):
            self.model.inertias[j] = pin.Inertia.FromDynamicParameters(params.inertial[j - 1])
        self.data = self.model.createData()
        self.meta = meta or robot_meta(robot, "P2")

    def rigid(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return rnea_batch(self.model, self.data, np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq))

    def losses(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, rigid: np.ndarray | None = None) -> np.ndarray:
        """The joint losses; a `load` term reads the rigid-body torque (`rigid`, computed when not given)."""
        p = self.params
        s = smooth_sign(dq, p.sign_eps)
        out = p.B_m * ddq + p.C_m * dq + p.f_c * s
        if p.extra_terms:
            if rigid is None and "load" in p.extra_terms:
                one = np.ndim(q) == 1
                rigid = self.rigid_one(q, dq, ddq) if one else self.rigid(q, dq, ddq)
            out = out + np.sum(extra_columns(p.extra_terms, np.asarray(dq), s, rigid) * p.extra, axis=-1)
        return out

    def predict(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, starts: np.ndarray | None = None) -> np.ndarray:
        q, dq, ddq = np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq)
        rigid = self.rigid(q, dq, ddq)
        return rigid + self.losses(q, dq, ddq, rigid)

    def predict_one(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """One sample (n,) without batch overhead (the served path)."""
        rigid = self.rigid_one(q, dq, ddq)
        return rigid + self.losses(q, dq, ddq, rigid)

    def with_payload(self, mass: float, com: np.ndarray | None = None) -> P2Model:
        """The same arm carrying `mass` kg more at `com` (flange frame, m; the flange origin when unknown):
        a point mass added to the last link, no new data needed."""
        if not np.isfinite(mass) or mass < 0:
            raise ValueError(f"payload mass {mass} kg: must be finite and >= 0")
        com = np.zeros(3) if com is None else np.asarray(com, float)
        flange = self.robot.model.frames[self.robot.flange_id]
        point = pin.Inertia(float(mass), flange.placement.act(com), np.zeros((3, 3)))
        inertial = self.params.inertial.copy()
        inertial[flange.parentJoint - 1] += point.toDynamicParameters()
        payload = {"mass": float(mass), "com": com.tolist()}
        params = dataclasses.replace(self.params, inertial=inertial, report={**self.params.report, "payload": payload})
        return P2Model(self.robot, params, self.meta)

    def rigid_one(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return np.array(pin.rnea(self.model, self.data, q, dq, ddq))


def nominal_p2(robot: RobotModel, sign_eps: float = 0.005) -> P2Model:
    """The nominal rigid body (P1's, URDF + nominal tool) in P2's form with zero losses: the physics
    part of H2 as the paper's Table 2 has it (the same M, C, G column as P1)."""
    n = robot.n
    inertial = np.array([robot.model.inertias[j].toDynamicParameters() for j in range(1, n + 1)])
    z = np.zeros(n)
    return P2Model(robot, P2Params(inertial=inertial, B_m=z, C_m=z.copy(), f_c=z.copy(), sign_eps=sign_eps,
                                   report={"nominal": True}), robot_meta(robot, "P1"))


def mass_matrix_positive(robot: RobotModel, inertial: np.ndarray, B_m: np.ndarray, q: np.ndarray,
                         checks: int = 50) -> bool:
    """M(q) + diag(B_m) of the arm with these link parameters positive definite on up to `checks` of the states q."""
    model = robot.model.copy()
    for j in range(1, model.njoints):
        model.inertias[j] = pin.Inertia.FromDynamicParameters(inertial[j - 1])
    data = model.createData()
    for k in np.linspace(0, len(q) - 1, min(checks, len(q))).astype(np.int64):
        M = pin.crba(model, data, q[k])
        M = np.triu(M) + np.triu(M, 1).T + np.diag(B_m)
        if np.linalg.eigvalsh(M).min() <= 0:
            return False
    return True
