"""External-torque observers: what the joints feel from outside, tau_ext = tau_measured - tau_free.

Sign convention (the cell's): tau_ext = J^T W, with W the wrench the tool exerts on the environment,
so a tool pressing on a table gives the joint torques a static J^T W on top of the free-motion torque.

Two observers on the same hybrid model (H1 = identified P2 + learned residual):

* `KalmanObserver` (the paper's): tau_ext = tau - tau_free(q, dq, ddq) from the model with the
  causal derivative pipeline the model was trained with, then a random-walk Kalman filter with one
  independent state per joint (filterpy; the matrices are diagonal, so the joints never mix);
* `MomentumObserver` (De Luca's generalised momentum observer): needs no joint acceleration for its
  rigid-body part; M, C and g come from Pinocchio on the identified P2 parameters (the rotor inertia
  B_m joins M), and the learned residual enters as a known torque.

Both re-bias in free space (arm at rest, no contact): the mean raw estimate over the last
`rebias_window` samples becomes the zero.
"""

from __future__ import annotations

import collections
from typing import Protocol

import numpy as np
import pinocchio as pin
from filterpy.kalman import KalmanFilter

from cell.model.dynamics.fastpredict import FastPredictor
from cell.model.dynamics.learned import LearnedModel
from cell.sensing.derivatives import FilterConfig
from drivers.interfaces import ArmState


class TorqueObserver(Protocol):
    kind: str

    def update(self, state: ArmState) -> np.ndarray:
        """One control period: the external joint torque estimate (n,) [N·m]."""

    def rebias(self) -> None:
        """Zero the estimate at the current state (arm at rest, no contact)."""

    def reset(self) -> None:
        """Forget all history (a new stream)."""


class _Bias:
    """The free-space zero: a ring of the recent raw estimates and the offset taken from them."""

    def __init__(self, n: int, window: int) -> None:
        self.ring: collections.deque[np.ndarray] = collections.deque(maxlen=max(1, window))
        self.offset = np.zeros(n)

    def push(self, raw: np.ndarray) -> None:
        self.ring.append(raw)

    def rebias(self) -> np.ndarray:
        """Set the offset to the recent mean; returns the change (to shift filter states by)."""
        if not self.ring:
            return np.zeros_like(self.offset)
        new = np.mean(np.asarray(self.ring), axis=0)
        change = new - self.offset
        self.offset = new
        return change

    def reset(self) -> None:
        self.ring.clear()
        self.offset[:] = 0.0


class ContactPredictor(FastPredictor):
    """The hybrid model's free-motion torque while in contact.

    The learned friction of H1 grows with the torque its gears transmit (its `physics_inputs`
    feature), which the model lab can only see as the rigid-body torque: in free motion that is
    all they transmit.  In contact the motors also carry the external torque, and so does the
    friction, so the load input here is rigid + the last external-torque estimate (causal: the
    previous period's).  With `external` = 0 this is exactly `FastPredictor.predict_one`.
    """

    def __init__(self, model: LearnedModel, dt: float, filter_cfg: FilterConfig | None = None) -> None:
        super().__init__(model, dt, filter_cfg)
        if self.part not in ("full", "rigid") or self.p2 is None:
            raise ValueError(f"the observers need a hybrid model with the rigid body (H1, H2), got {model.kind}")
        # The model's own uncertainty at the last sample [N·m]^2, kept when `want_variance` (NaN otherwise,
        # and without a coverage model).
        self.want_variance = False
        self.variance = np.full(self.n, np.nan)

    def parts_contact(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                      external: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rigid-body torque, learned torque) for one sample; the hybrid's torque is their sum plus
        the losses when the model's physics part is `full`."""
        assert self.p2 is not None
        x = self._x
        x[:self._nw] = self.window.push(q, dq, ddq)
        rigid = self.p2.rigid_one(q, dq, ddq)
        if self._has_extra:
            x[self._nw:] = self._derived(q, dq, rigid + external)
        learned = np.zeros_like(rigid)
        learned[self.outputs] = self.forest.predict(x)
        trust = self.model.coverage
        if trust is not None and (trust.gates or self.want_variance):
            w = trust.weight_one(q, dq, ddq) if trust.gates else np.ones(self.n)
            if self.coverage is not None:  # a blending model (H1) whose trust can fall: the learned part by it
                learned *= w
            if self.want_variance:
                self.variance = trust.sigma(dq[None, :], w[None, :])[0] ** 2
        return rigid, learned

    def predict_contact(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, external: np.ndarray) -> np.ndarray:
        assert self.p2 is not None
        rigid, learned = self.parts_contact(q, dq, ddq, external)
        tau = rigid + learned
        if self.part == "full":
            tau += self.p2.losses(q, dq, ddq)
        return tau

    def step_contact(self, q: np.ndarray, dq: np.ndarray | None, external: np.ndarray) -> np.ndarray:
        v, a = self.derivs.step(q, dq)
        return self.predict_contact(np.asarray(q, float), v, a, external)


class KalmanObserver:
    """The paper's observer: model residual tau - tau_free, Kalman-filtered per joint.

    measurement_var: (n,) R, the variance of the model's residual in free motion [N·m]^2;
    process_var: (n,) Q, the random-walk variance per period [N·m]^2 (how fast a contact may change);
    model_noise: R raised each period to the model's own variance there (`ContactPredictor.variance`),
      when the model has one.
    """

    kind = "kalman"
    GATE_RUN = 3

    def __init__(self, model: LearnedModel, dt: float, measurement_var: np.ndarray, process_var: np.ndarray,
                 rebias_samples: int = 25, filter_cfg: FilterConfig | None = None, gate: float = 3.0,
                 model_noise: bool = False) -> None:
        self.fast = ContactPredictor(model, dt, filter_cfg)
        self.model_noise = model_noise and model.coverage is not None
        self.fast.want_variance = self.model_noise
        self.gate = gate
        self.n = n = model.forest.n
        self.R = np.asarray(measurement_var, float).reshape(n)
        self.Q = np.asarray(process_var, float).reshape(n)
        kf = KalmanFilter(dim_x=n, dim_z=n)
        kf.F = np.eye(n)
        kf.H = np.eye(n)
        kf.Q = np.diag(self.Q)
        kf.R = np.diag(self.R)
        self.kf = kf
        self.bias = _Bias(n, rebias_samples)
        self.raw = np.zeros(n)  # last unfiltered estimate (after the bias), for diagnostics
        self.reset()

    def reset(self) -> None:
        self.fast.reset()
        self.bias.reset()
        self.kf.x = np.zeros((self.n, 1))
        self.kf.P = np.diag(self.R)  # start as uncertain as one measurement
        self._started = False
        self._estimate = np.zeros(self.n)  # the last external torque estimate (the gears carry it too)
        self._run = np.zeros(self.n)  # signed count of consecutive same-signed gated innovations

    def update(self, state: ArmState) -> np.ndarray:
        tau_free = self.fast.step_contact(state.q, state.dq, self._estimate)
        raw = np.asarray(state.tau, float) - tau_free
        self.bias.push(raw)
        z = raw - self.bias.offset
        self.raw = z
        kf = self.kf
        R = self.R
        if self.model_noise:
            R = np.maximum(self.R, self.fast.variance)
            kf.R = np.diag(R)
        if not self._started:  # the first sample is the best initial state there is
            kf.x = z.reshape(-1, 1).copy()
            self._started = True
        else:
            kf.predict()
            if self.gate > 0:
                # Innovation gate (a Huber-type robust filter): a joint breaking away from stiction
                # swings the residual by +-10 N·m for a few periods, alternating in sign; clipped to
                # `gate` standard deviations it moves the estimate by little.  A real contact pushes
                # one way: after GATE_RUN same-signed excursions in a row it passes unclipped.
                x = kf.x.reshape(-1)
                bound = self.gate * np.sqrt(np.diag(kf.P) + R)
                y = z - x
                outside = np.abs(y) > bound
                sign = np.sign(y)
                same = outside & (sign == np.sign(self._run))
                self._run = np.where(same, self._run + sign, np.where(outside, sign, 0.0))
                clip = outside & (np.abs(self._run) <= self.GATE_RUN)
                z = np.where(clip, x + np.clip(y, -bound, bound), z)
            kf.update(z.reshape(-1, 1))
        out = np.asarray(kf.x, float).reshape(-1).copy()
        self._estimate = out
        return out

    def rebias(self) -> None:
        change = self.bias.rebias()
        self.kf.x = self.kf.x - change.reshape(-1, 1)


class MomentumObserver:
    """Generalised momentum observer: r' = K (-tau_ext - r) without joint accelerations in M, C, g.

    With p = (M + B_m) dq and the model M ddq + C dq + g + losses(dq) + residual = tau - tau_ext,
    dp/dt = tau - tau_ext + C^T dq - g - losses - residual, so
    r = K (p - p0 - integral(tau + C^T dq - g - losses - residual + r) dt) follows -tau_ext with the
    bandwidth K [1/s].  The learned residual is a known torque from the hybrid model (its features
    use the causal ddq estimate, as in training); the viscous and Coulomb losses use dq only.
    """

    kind = "momentum"

    def __init__(self, model: LearnedModel, dt: float, gain: float | np.ndarray, rebias_samples: int = 25,
                 filter_cfg: FilterConfig | None = None, trapezoid: bool = False) -> None:
        self.trapezoid = trapezoid  # integrate the torques by the trapezoidal rule (rectangle: False)
        if model.physics is None:
            raise ValueError("the momentum observer needs a model with a physics part (H1)")
        self.fast = ContactPredictor(model, dt, filter_cfg)
        self.p2 = model.physics
        self.pm = self.p2.model
        self.pd = self.pm.createData()
        self.n = n = model.forest.n
        self.dt = dt
        self.K = np.broadcast_to(np.asarray(gain, float), (n,)).copy()
        par = self.p2.params
        self.B = np.diag(par.B_m)
        self._no_acc = np.zeros(n)
        self.bias = _Bias(n, rebias_samples)
        self.raw = np.zeros(n)
        self.reset()

    def reset(self) -> None:
        self.fast.reset()
        self.bias.reset()
        self.r = np.zeros(self.n)
        self.integral = np.zeros(self.n)
        self._beta: np.ndarray | None = None
        self._t: float | None = None
        self.p0: np.ndarray | None = None
        self._estimate = np.zeros(self.n)
        self.inertial = np.zeros(self.n)
        self.acceleration = np.zeros(self.n)
        self.mass = np.zeros((self.n, self.n))  # M(q) + B_m at the last sample

    def update(self, state: ArmState) -> np.ndarray:
        q = np.asarray(state.q, float)
        v, a = self.fast.derivs.step(q, state.dq)
        # The learned residual: the hybrid's torque minus its physics part (both on the same sample).
        _, residual = self.fast.parts_contact(q, v, a, self._estimate)
        if self.fast.part != "full":  # the learned part covers the losses too
            residual = residual - self.p2.losses(q, v, a)
        losses = self.p2.losses(q, v, self._no_acc)  # without B_m q'': the rotor inertia joins M below
        pm, pd = self.pm, self.pd
        M = pin.crba(pm, pd, q)
        M = np.triu(M) + np.triu(M, 1).T + self.B
        C = pin.computeCoriolisMatrix(pm, pd, q, v)
        g = pin.computeGeneralizedGravity(pm, pd, q)
        p = M @ v
        self.acceleration = a
        self.mass = M
        self.inertial = M @ a  # the rigid body's inertial torque at the causal acceleration (for thresholds)
        if self.p0 is None:
            self.p0 = p
        beta = np.asarray(state.tau, float) + C.T @ v - g - losses - residual
        if self.trapezoid and self._beta is not None:
            # The torque changes within a period (the servo's feedforward as a move starts): the
            # end-of-period sample integrated as a constant reads that change as an external torque.
            # Over a wire the samples come at the host's pace, not the controller's: a late or skipped
            # read spans more than a period, and the momentum moved over all of it.
            h = self.dt
            if self._t is not None:
                h = float(np.clip(state.t - self._t, 0.25 * self.dt, 4.0 * self.dt))
            self.integral += (0.5 * (beta + self._beta) + self.r) * h
        else:
            self.integral += (beta + self.r) * self.dt
        self._beta = beta
        self._t = float(state.t)
        self.r = self.K * (p - self.p0 - self.integral)
        raw = -self.r
        self.bias.push(raw)
        out = raw - self.bias.offset
        self.raw = out
        self._estimate = out
        return out

    def rebias(self) -> None:
        self.bias.rebias()


def make_observer(kind: str, model: LearnedModel, dt: float, measurement_var: np.ndarray,
                  process_noise_nm: np.ndarray, momentum_gain: float, rebias_window_s: float,
                  gate: float = 3.0, model_noise: bool = False) -> TorqueObserver:
    """The configured observer (`virtual_sensor.observer`; `model_noise`: measurement_noise "model")."""
    samples = max(1, int(round(rebias_window_s / dt)))
    if kind == "kalman":
        return KalmanObserver(model, dt, measurement_var, np.asarray(process_noise_nm, float) ** 2, samples,
                              gate=gate, model_noise=model_noise)
    if kind == "momentum":
        return MomentumObserver(model, dt, momentum_gain, samples)
    raise ValueError(f"unknown observer {kind!r} (kalman or momentum)")
