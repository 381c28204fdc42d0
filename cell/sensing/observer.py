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

The virtual sensor's observer and the collision detector's run on the same model at the same sample every
control period: what depends on the sample alone (rigid body, losses, trust, M, C, g) is computed once for
both (`SampleCache`).  What depends on an observer's own estimate (the learned part's load input) is not.
"""

from __future__ import annotations

import collections
import hashlib
import json
import weakref
from collections.abc import Callable
from typing import Protocol

import numpy as np
import pinocchio as pin

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


class SampleCache:
    """The hybrid model's sample-only parts at the last (q, q', q''), for every observer on that model.

    The virtual sensor's observer and the collision detector's each ran the rigid body, the losses, the
    trust weights and (momentum observers) M, C and g at the same sample, every period.  Keyed on the
    exact inputs, a consumer at another sample recomputes: each gets what it would have computed alone.
    Callers must not modify the returned arrays."""

    def __init__(self, model: LearnedModel) -> None:
        assert model.physics is not None
        self.p2 = model.physics
        self.trust = model.coverage
        self.pm = self.p2.model
        self.pd = self.pm.createData()
        self.B = np.diag(self.p2.params.B_m)
        # (the sample's key, what was computed there), replaced as one: a reader never pairs one
        # sample's key with another's results.
        self._current: tuple[tuple[bytes, ...], dict[str, object]] = ((), {})

    def _get(self, name: str, key: tuple[bytes, ...], make: Callable[[], object]) -> object:
        current = self._current
        if current[0] != key:
            current = (key, {})
            self._current = current
        memo = current[1]
        if name not in memo:
            memo[name] = make()
        return memo[name]

    def rigid(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        key = (q.tobytes(), dq.tobytes(), ddq.tobytes())
        return self._get("rigid", key, lambda: self.p2.rigid_one(q, dq, ddq))  # type: ignore[return-value]

    def losses(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        key = (q.tobytes(), dq.tobytes(), ddq.tobytes())
        return self._get("losses", key, lambda: self.p2.losses(q, dq, ddq))  # type: ignore[return-value]

    def losses_at_rest_acceleration(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """The losses without their B_m q'' part (the momentum observer puts the rotor inertia into M)."""
        key = (q.tobytes(), dq.tobytes(), ddq.tobytes())
        return self._get("losses0", key,  # type: ignore[return-value]
                         lambda: self.p2.losses(q, dq, np.zeros_like(ddq)))

    def weight(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        assert self.trust is not None
        trust = self.trust
        key = (q.tobytes(), dq.tobytes(), ddq.tobytes())
        return self._get("weight", key, lambda: trust.weight_one(q, dq, ddq))  # type: ignore[return-value]

    def mass_coriolis_gravity(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """M(q) + B_m, C(q, q') and g(q) of the identified rigid body (Pinocchio)."""
        key = (q.tobytes(), dq.tobytes(), ddq.tobytes())

        def make() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            pm, pd = self.pm, self.pd
            M = pin.crba(pm, pd, q)
            M = np.triu(M) + np.triu(M, 1).T + self.B
            C = np.array(pin.computeCoriolisMatrix(pm, pd, q, dq))
            g = np.array(pin.computeGeneralizedGravity(pm, pd, q))
            return M, C, g
        return self._get("mcg", key, make)  # type: ignore[return-value]


# Held by the observers that use them: a cache goes with the last observer on its model.
_CACHES: weakref.WeakValueDictionary[str, SampleCache] = weakref.WeakValueDictionary()


def _model_digest(model: LearnedModel) -> str:
    """What the sample-only parts depend on: the robot, the identified physics and the trust model."""
    assert model.physics is not None
    h = hashlib.sha256(model.meta.urdf_sha256.encode())
    h.update(json.dumps(model.physics.params.to_dict(), sort_keys=True, default=str).encode())
    trust = model.coverage
    if trust is not None:
        for name, value in sorted(vars(trust).items()):
            h.update(name.encode())
            h.update(np.asarray(value).tobytes() if isinstance(value, np.ndarray) else repr(value).encode())
    return h.hexdigest()


def sample_cache(model: LearnedModel) -> SampleCache:
    """The cache every observer on this model (or an identical copy of it: the guard and the virtual sensor
    load their own) shares."""
    key = _model_digest(model)
    cache = _CACHES.get(key)
    if cache is None:
        cache = _CACHES[key] = SampleCache(model)
    return cache


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
        self.shared = sample_cache(model)

    def parts_contact(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                      external: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rigid-body torque, learned torque) for one sample; the hybrid's torque is their sum plus
        the losses when the model's physics part is `full`."""
        assert self.p2 is not None
        x = self._x
        x[:self._nw] = self.window.push(q, dq, ddq)
        rigid = self.shared.rigid(q, dq, ddq)
        if self._has_extra:
            x[self._nw:] = self._derived(q, dq, rigid + external)
        learned = np.zeros_like(rigid)
        learned[self.outputs] = self.forest.predict(x)
        trust = self.model.coverage
        if trust is not None and (trust.gates or self.want_variance):
            w = self.shared.weight(q, dq, ddq) if trust.gates else np.ones(self.n)
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
            tau += self.shared.losses(q, dq, ddq)
        return tau

    def step_contact(self, q: np.ndarray, dq: np.ndarray | None, external: np.ndarray) -> np.ndarray:
        v, a = self.derivs.step(q, dq)
        return self.predict_contact(np.asarray(q, float), v, a, external)


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
        self.kf = DiagonalKalman(self.Q, self.R)
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
                bound = self.gate * np.sqrt(kf.p + R)
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
                 filter_cfg: FilterConfig | None = None, trapezoid: bool = False, exact_steps: bool = False) -> None:
        self.trapezoid = trapezoid  # integrate the torques by the trapezoidal rule (rectangle: False)
        # A log's own clock (the controller's time stamps) is the true step, however irregular: integrate
        # over it unclipped.  Off, a step is clipped to [0.25, 4] periods (a host's read times jitter).
        self.exact_steps = exact_steps
        if model.physics is None:
            raise ValueError("the momentum observer needs a model with a physics part (H1)")
        self.fast = ContactPredictor(model, dt, filter_cfg)
        self.p2 = model.physics
        self.n = n = model.forest.n
        self.dt = dt
        self.K = np.broadcast_to(np.asarray(gain, float), (n,)).copy()
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
        shared = self.fast.shared
        if self.fast.part != "full":  # the learned part covers the losses too
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
                h = float(state.t - self._t) if self.exact_steps else \
                    float(np.clip(state.t - self._t, 0.25 * self.dt, 4.0 * self.dt))
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
