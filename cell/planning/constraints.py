"""The torque and speed constraints toppra plans under: the part of a torque model it can take, and bounds graded
per grid point."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import toppra.constraint as ta_con
from toppra.constraint.linear_constraint import canlinear_colloc_to_interpolate

from cell.model.dynamics.rigid_body import P2Model

DISCRETIZATIONS = {"interpolation": ta_con.DiscretizationType.Interpolation,
                   "collocation": ta_con.DiscretizationType.Collocation}
InvDyn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (n,) x3 -> (n,), second order in the path speed


@dataclass
class ToppraTerms:
    """The part of a torque model toppra can take as its constraint: `inv_dyn` must be quadratic in the
    path speed (rigid body, rotor inertia), `coulomb` the per-joint f_c of `f_c sign(q')`."""

    inv_dyn: InvDyn
    coulomb: np.ndarray | None = None


def toppra_terms(model: object) -> ToppraTerms | None:
    """The identified physics of a model-lab model (P2, or the physics part of H1-H3), or None (P1, D).

    Rotor inertia matters most: at the accelerations a time-optimal plan reaches, `B_m q''` is as large
    as the rigid body's torque, and leaving it to the iteration would make the path look infeasible.
    """
    p2 = model if isinstance(model, P2Model) else getattr(model, "physics", None)
    if not isinstance(p2, P2Model):
        return None
    B_m = np.asarray(p2.params.B_m, float)

    def inv_dyn(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return p2.rigid_one(q, dq, ddq) + B_m * ddq

    return ToppraTerms(inv_dyn, np.asarray(p2.params.f_c, float))


class GradedTorqueConstraint(ta_con.JointTorqueConstraint):
    """toppra's joint torque constraint with the bound scaled by `factor` (per grid point, or per grid point
    and joint): the torque
    coefficients a, b, c of each grid point are divided by its factor, which keeps F and g the same at every
    grid point (so toppra's solvers take it as they take the plain constraint)."""

    def __init__(self, inv_dyn: InvDyn, tau_lim: np.ndarray, coulomb: np.ndarray, factor: np.ndarray,
                 discretization: str, offset: np.ndarray | None = None) -> None:
        super().__init__(inv_dyn, tau_lim, coulomb, discretization_scheme=DISCRETIZATIONS["collocation"])
        self.factor = np.asarray(factor, float)
        self.interpolate = discretization == "interpolation"
        self.offset = offset  # (grid points, n): torque beyond inv_dyn there, added to c

    def compute_constraint_params(self, path: object, gridpoints: np.ndarray) -> tuple[object, ...]:
        a, b, c, F, g, _, _ = super().compute_constraint_params(path, gridpoints)
        if self.offset is not None:
            c = c + self.offset
        f = self.factor if self.factor.ndim == 2 else self.factor[:, None]
        a, b, c = a / f, b / f, c / f
        if self.interpolate:
            return tuple(canlinear_colloc_to_interpolate(a, b, c, F, g, None, None, gridpoints, identical=True))
        return a, b, c, F, g, None, None


class SpeedCapConstraint(ta_con.LinearConstraint):
    """An upper bound on the path speed per grid point (toppra's `xbound` on sd^2): whatever cap the caller
    computed, here the joint speeds and the TCP speed held over each grid point's neighbourhood."""

    def __init__(self, cap: np.ndarray) -> None:
        super().__init__()
        self.cap = np.asarray(cap, float)

    def compute_constraint_params(self, path: object, gridpoints: np.ndarray) -> tuple[object, ...]:
        xbound = np.column_stack([np.zeros(len(gridpoints)), self.cap**2])
        return None, None, None, None, None, None, xbound
