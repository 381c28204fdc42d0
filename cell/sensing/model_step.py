"""The hybrid model's free-motion torque at each control period's sample, evaluated once for every observer.

The virtual sensor's observer, its touch channel and the collision detector's observer all need the same
prediction at the same sample every period: the causal derivatives, the feature window, the rigid body
and one forest evaluation.  A `ModelStep` computes them once per sample; the observers of one cell share
it (`ModelStep.follow`), and an observer made on its own gets a step of its own.  What depends on the
sample alone and is needed by some observers only (losses, trust weights, M, C, g) is kept per model in
`SampleCache`, keyed on the sample.
"""

from __future__ import annotations

import hashlib
import json
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from cell.model.dynamics.fastpredict import FastPredictor, FlatForest
from cell.model.dynamics.learned import LearnedModel
from cell.sensing.derivatives import FilterConfig
from drivers.interfaces import ArmState


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
        # Another load input changes the load columns alone: only the trees that split on them walk again.
        cols = self._derived.load_columns() if self._has_extra else None
        self._load_cols = (slice(self._nw + cols.start, self._nw + cols.stop) if cols is not None else None)
        self._load_trees = (self.forest.subset(np.arange(self._load_cols.start, self._load_cols.stop))
                            if self._load_cols is not None and isinstance(self.forest, FlatForest) else None)
        self._row = np.empty_like(self._x)  # the row `parts_contact` last kept
        self._leaves = np.zeros(0)  # every tree's leaf in that row

    def parts_contact(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, external: np.ndarray,
                      keep_row: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(rigid-body torque, learned torque) for one sample; the hybrid's torque is their sum plus
        the losses when the model's physics part is `full`.  `keep_row`: keep the feature row and every tree's
        leaf, for `learned_again` at another load input."""
        assert self.p2 is not None
        self._x[:self._nw] = self.window.push(q, dq, ddq)
        rigid = self.shared.rigid(q, dq, ddq)
        return rigid, self._learned(q, dq, ddq, rigid, external, keep_row)

    def _learned(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, rigid: np.ndarray, external: np.ndarray,
                 keep_row: bool) -> np.ndarray:
        x = self._x
        if self._has_extra:
            x[self._nw:] = self._derived(q, dq, rigid + external)
        learned = np.zeros(self.n)
        learned[self.outputs] = self.forest.predict(x)
        if keep_row and self._load_trees is not None:
            assert isinstance(self.forest, FlatForest)
            self._row[:] = x
            self._leaves = self.forest.leaves()
        return self._trust(q, dq, ddq, learned)

    def learned_again(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, rigid: np.ndarray,
                      external: np.ndarray) -> np.ndarray:
        """The learned torque of the sample the last `parts_contact(..., keep_row=True)` took, at another load
        input: only the trees that read the load walk again, and the sums are those of a full walk, bit for bit."""
        if self._load_trees is None or self._load_cols is None:
            return self._learned(q, dq, ddq, rigid, external, keep_row=False)
        assert isinstance(self.forest, FlatForest)
        row = self._row.copy()
        row[self._load_cols] = self._derived.load_values(dq, rigid + external)
        learned = np.zeros(self.n)
        learned[self.outputs] = self.forest.predict_changed(row, self._load_trees, self._leaves)
        return self._trust(q, dq, ddq, learned)

    def _trust(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, learned: np.ndarray) -> np.ndarray:
        """The learned part weighed by the trust where the model blends, and the model's variance when wanted."""
        trust = self.model.coverage
        if trust is not None and (trust.gates or self.want_variance):
            w = self.shared.weight(q, dq, ddq) if trust.gates else np.ones(self.n)
            if self.coverage is not None:  # a blending model (H1) whose trust can fall: the learned part by it
                learned *= w
            if self.want_variance:
                self.variance = trust.sigma(dq, w) ** 2
        return learned


@dataclass(frozen=True)
class FreeMotion:
    """The hybrid model at one sample: what every observer sharing the step reads (arrays not to be modified)."""

    q: np.ndarray  # rad
    v: np.ndarray  # rad/s, the causal derivative pipeline's (the measured speed when there is one)
    a: np.ndarray  # rad/s^2, causal
    rigid: np.ndarray  # N·m, the identified rigid body's torque
    learned: np.ndarray  # N·m, the learned part (trust-weighted), with the load input of `ModelStep.load`
    variance: np.ndarray  # [N·m]^2, the model's own uncertainty there (NaN unless some observer wants it)


class ModelStep:
    """One evaluation of the hybrid model per sample, for every observer that shares it.

    The learned part's load input is rigid + an external-torque estimate (the gears carry the contact
    too): the lead observer's latest one (`publish`).  The lead is the first observer made on the step:
    in a cell, the virtual sensor's main observer; the collision detector follows it.  A follower that
    joins with `own_load` (the touch channel: a touch's friction is read from its own fast estimate, not
    the slow one's) shares the sample's derivatives, window and rigid body but gets the learned part at
    its own load: one more forest evaluation.  The lead evaluates the model on every update; a follower
    reads what the lead evaluated on the same state, and evaluates the sample itself only when the lead
    has not (it then advances the shared derivative filters, as the lead would have).  An observer alone
    on its step computes exactly what it did before steps were shared.
    """

    def __init__(self, model: LearnedModel, dt: float, filter_cfg: FilterConfig | None = None) -> None:
        self.model = model
        self.dt = dt
        self.fast = ContactPredictor(model, dt, filter_cfg)
        self.part = self.fast.part
        self.shared = self.fast.shared
        self.n = self.fast.n
        self.lead: object | None = None
        self.load = np.zeros(self.n)
        # Followers with a load input of their own: their latest estimate, and their sample at the last state.
        self._own_load: dict[int, np.ndarray] = {}
        self._own_sample: dict[int, FreeMotion] = {}
        self._state: ArmState | None = None
        self._sample: FreeMotion | None = None
        self.evaluations = 0  # samples evaluated (one per period when shared)

    def join(self, observer: object, own_load: bool = False) -> None:
        """`observer` reads this step; the first to join leads it, a follower with `own_load` keeps its own
        load input."""
        if self.lead is None:
            self.lead = observer
        elif own_load:
            self._own_load[id(observer)] = np.zeros(self.n)

    def want_variance(self) -> None:
        """Some observer weighs the model's own uncertainty: every sample computes it."""
        self.fast.want_variance = True

    def publish(self, observer: object, estimate: np.ndarray) -> None:
        """The observer's latest external-torque estimate: the next sample's load input when it leads."""
        if observer is self.lead:
            self.load = estimate
        elif id(observer) in self._own_load:
            self._own_load[id(observer)] = estimate

    def reset(self, observer: object) -> None:
        """A new stream, when the lead says so (a follower's reset leaves the lead's filters alone)."""
        if observer is self.lead:
            self.fast.reset()
            self.load = np.zeros(self.n)
            self._state = None
            self._sample = None
            self._own_sample = {}
        if id(observer) in self._own_load:
            self._own_load[id(observer)] = np.zeros(self.n)

    def at(self, state: ArmState, observer: object) -> FreeMotion:
        """The model at `state`: evaluated now for the lead, or the lead's evaluation on the same state."""
        if observer is self.lead or state is not self._state or self._sample is None:
            q = np.asarray(state.q, float)
            v, a = self.fast.derivs.step(q, state.dq)
            rigid, learned = self.fast.parts_contact(q, v, a, self.load, keep_row=bool(self._own_load))
            self._sample = FreeMotion(q=q, v=v, a=a, rigid=rigid, learned=learned,
                                      variance=self.fast.variance.copy())
            self._state = state
            self._own_sample = {}
            self.evaluations += 1
        sample = self._sample
        key = id(observer)
        if key not in self._own_load:
            return sample
        own = self._own_sample.get(key)
        if own is None:
            learned = self.fast.learned_again(sample.q, sample.v, sample.a, sample.rigid, self._own_load[key])
            own = self._own_sample[key] = FreeMotion(q=sample.q, v=sample.v, a=sample.a, rigid=sample.rigid,
                                                     learned=learned, variance=sample.variance)
        return own
