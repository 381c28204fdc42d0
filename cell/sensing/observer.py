"""External-torque observers: what the joints feel from outside, tau_ext = tau_measured - tau_free.

Sign convention (the cell's): tau_ext = J^T W, with W the wrench the tool exerts on the environment,
so a tool pressing on a table gives the joint torques a static J^T W on top of the free-motion torque.

Two observers on the same hybrid model (H1 = identified P2 + learned residual):

* `KalmanObserver` (the paper's): tau_ext = tau - tau_free(q, dq, ddq) from the model with the
  causal derivative pipeline the model was trained with, then a random-walk Kalman filter with one
  independent state per joint (the matrices are diagonal, so the joints never mix: `DiagonalKalman`);
* `MomentumObserver` (De Luca's generalised momentum observer): needs no joint acceleration for its
  rigid-body part; M, C and g come from Pinocchio on the identified P2 parameters (the rotor inertia
  B_m joins M), and the learned residual enters as a known torque.

Both re-bias in free space (arm at rest, no contact): the mean raw estimate over the last
`rebias_window` samples becomes the zero.

The virtual sensor's observers and the collision detector's run on the same model at the same sample every
control period: the model is evaluated once per sample for all of them (`cell/sensing/model_step.py`).
"""

from __future__ import annotations

import collections
from typing import Protocol

import numpy as np

from cell.model.dynamics.learned import LearnedModel
from cell.sensing.derivatives import FilterConfig
from cell.sensing.model_step import ModelStep
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


class DiagonalKalman:
    """filterpy's `KalmanFilter` for F = H = I and diagonal Q, R and P: one random-walk state per joint.

    The same predict and Joseph-form update, joint by joint and in filterpy's order of operations, so the
    same numbers: its n x n products and inverse of a diagonal matrix only ever multiply by zeros.  They
    cost a tenth of a millisecond every control period.  `x`, `P`, `Q`, `R`, `F` and `H` read and set as
    filterpy's do ((n, 1) and (n, n)); `p`, `q` and `r` are the diagonals."""

    def __init__(self, process_var: np.ndarray, measurement_var: np.ndarray) -> None:
        self.q = np.array(process_var, float).reshape(-1)
        self.r = np.array(measurement_var, float).reshape(-1)
        self.n = len(self.q)
        self.p = self.r.copy()
        self._x = np.zeros(self.n)

    @property
    def x(self) -> np.ndarray:
        return self._x.reshape(-1, 1)

    @x.setter
    def x(self, value: np.ndarray) -> None:
        self._x = np.array(value, float).reshape(-1)

    @property
    def estimate(self) -> np.ndarray:
        """The state as a vector (n,): a view, not to be modified."""
        return self._x

    @property
    def P(self) -> np.ndarray:
        return np.diag(self.p)

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self.p = np.diag(np.asarray(value, float)).copy()

    @property
    def Q(self) -> np.ndarray:
        return np.diag(self.q)

    @property
    def R(self) -> np.ndarray:
        return np.diag(self.r)

    @R.setter
    def R(self, value: np.ndarray) -> None:
        self.r = np.diag(np.asarray(value, float)).copy()

    @property
    def F(self) -> np.ndarray:
        return np.eye(self.n)

    H = F

    def predict(self) -> None:
        self.p = self.p + self.q  # P = F P F' + Q

    def update(self, z: np.ndarray) -> None:
        y = np.asarray(z, float).reshape(-1) - self._x
        k = self.p * (1.0 / (self.p + self.r))  # K = P H' inv(H P H' + R)
        self._x = self._x + k * y
        i_kh = 1.0 - k
        self.p = i_kh * self.p * i_kh + k * self.r * k  # Joseph form: (I - KH) P (I - KH)' + K R K'


class KalmanObserver:
    """The paper's observer: model residual tau - tau_free, Kalman-filtered per joint.

    measurement_var: (n,) R, the variance of the model's residual in free motion [N·m]^2;
    process_var: (n,) Q, the random-walk variance per period [N·m]^2 (how fast a contact may change);
    model_noise: R raised each period to the model's own variance there (`FreeMotion.variance`), when the
      model has one;
    step: the model evaluation it shares with the cell's other observers (its own when None).
    """

    kind = "kalman"
    GATE_RUN = 3

    def __init__(self, model: LearnedModel, dt: float, measurement_var: np.ndarray, process_var: np.ndarray,
                 rebias_samples: int = 25, filter_cfg: FilterConfig | None = None, gate: float = 3.0,
                 model_noise: bool = False, step: ModelStep | None = None) -> None:
        self.step = step if step is not None else ModelStep(model, dt, filter_cfg)
        self.step.join(self)
        self.model_noise = model_noise and model.coverage is not None
        if self.model_noise:
            self.step.want_variance()
        self.gate = gate
        self.n = n = model.forest.n
        self.R = np.asarray(measurement_var, float).reshape(n)
        self.Q = np.asarray(process_var, float).reshape(n)
        self.kf = DiagonalKalman(self.Q, self.R)
        self.bias = _Bias(n, rebias_samples)
        self.raw = np.zeros(n)  # last unfiltered estimate (after the bias), for diagnostics
        self.reset()

    def reset(self) -> None:
        self.step.reset(self)
        self.bias.reset()
        self.kf.x = np.zeros((self.n, 1))
        self.kf.P = np.diag(self.R)  # start as uncertain as one measurement
        self._started = False
        self._run = np.zeros(self.n)  # signed count of consecutive same-signed gated innovations

    def update(self, state: ArmState) -> np.ndarray:
        sample = self.step.at(state, self)
        tau_free = sample.rigid + sample.learned
        if self.step.part == "full":
            tau_free += self.step.shared.losses(sample.q, sample.v, sample.a)
        raw = np.asarray(state.tau, float) - tau_free
        self.bias.push(raw)
        z = raw - self.bias.offset
        self.raw = z
        kf = self.kf
        R = self.R
        if self.model_noise:
            R = np.maximum(self.R, sample.variance)
            kf.r = R
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
                x = kf.estimate
                bound = self.gate * np.sqrt(kf.p + R)
                y = z - x
                outside = np.abs(y) > bound
                if outside.any():
                    sign = np.sign(y)
                    same = outside & (sign == np.sign(self._run))
                    self._run = np.where(same, self._run + sign, np.where(outside, sign, 0.0))
                    clip = outside & (np.abs(self._run) <= self.GATE_RUN)
                    z = np.where(clip, x + np.minimum(np.maximum(y, -bound), bound), z)
                else:  # every innovation inside the gate (the usual period): the runs end, nothing is clipped
                    self._run = np.zeros(self.n)
            kf.update(z)
        out = kf.estimate.copy()
        self.step.publish(self, out)
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
                 filter_cfg: FilterConfig | None = None, trapezoid: bool = False, exact_steps: bool = False,
                 step: ModelStep | None = None, own_load: bool = False) -> None:
        self.trapezoid = trapezoid  # integrate the torques by the trapezoidal rule (rectangle: False)
        # A log's own clock (the controller's time stamps) is the true step, however irregular: integrate
        # over it unclipped.  Off, a step is clipped to [0.25, 4] periods (a host's read times jitter).
        self.exact_steps = exact_steps
        if model.physics is None:
            raise ValueError("the momentum observer needs a model with a physics part (H1)")
        self.step = step if step is not None else ModelStep(model, dt, filter_cfg)
        self.step.join(self, own_load)  # own_load: its own estimate as the learned part's load input
        self.p2 = model.physics
        self.n = n = model.forest.n
        self.dt = dt
        self.K = np.broadcast_to(np.asarray(gain, float), (n,)).copy()
        self.bias = _Bias(n, rebias_samples)
        self.raw = np.zeros(n)
        self.reset()

    def reset(self) -> None:
        self.step.reset(self)
        self.bias.reset()
        self.r = np.zeros(self.n)
        self.integral = np.zeros(self.n)
        self._beta: np.ndarray | None = None
        self._t: float | None = None
        self.p0: np.ndarray | None = None
        self.inertial = np.zeros(self.n)
        self.acceleration = np.zeros(self.n)
        self.mass = np.zeros((self.n, self.n))  # M(q) + B_m at the last sample

    def update(self, state: ArmState) -> np.ndarray:
        sample = self.step.at(state, self)
        q, v, a = sample.q, sample.v, sample.a
        # The learned residual: the hybrid's torque minus its physics part (both on the same sample).
        residual = sample.learned
        shared = self.step.shared
        if self.step.part != "full":  # the learned part covers the losses too
            residual = residual - shared.losses(q, v, a)
        losses = shared.losses_at_rest_acceleration(q, v, a)  # without B_m q'': the rotor inertia joins M below
        M, C, g = shared.mass_coriolis_gravity(q, v, a)
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
                h = float(state.t - self._t)
                if not self.exact_steps:
                    h = min(max(h, 0.25 * self.dt), 4.0 * self.dt)
            self.integral += (0.5 * (beta + self._beta) + self.r) * h
        else:
            h = float(state.t - self._t) if self.exact_steps and self._t is not None else self.dt
            self.integral += (beta + self.r) * h
        self._beta = beta
        self._t = float(state.t)
        self.r = self.K * (p - self.p0 - self.integral)
        raw = -self.r
        self.bias.push(raw)
        out = raw - self.bias.offset
        self.raw = out
        self.step.publish(self, out)
        return out

    def rebias(self) -> None:
        self.bias.rebias()


def make_observer(kind: str, model: LearnedModel, dt: float, measurement_var: np.ndarray,
                  process_noise_nm: np.ndarray, momentum_gain: float, rebias_window_s: float,
                  gate: float = 3.0, model_noise: bool = False, step: ModelStep | None = None,
                  own_load: bool = False) -> TorqueObserver:
    """The configured observer (`virtual_sensor.observer`; `model_noise`: measurement_noise "model"), on the
    shared model `step` when given (`own_load`: a momentum observer following it with its own load input)."""
    samples = max(1, int(round(rebias_window_s / dt)))
    if kind == "kalman":
        return KalmanObserver(model, dt, measurement_var, np.asarray(process_noise_nm, float) ** 2, samples,
                              gate=gate, model_noise=model_noise, step=step)
    if kind == "momentum":
        return MomentumObserver(model, dt, momentum_gain, samples, step=step, own_load=own_load)
    raise ValueError(f"unknown observer {kind!r} (kalman or momentum)")
