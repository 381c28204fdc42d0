"""Learned models: XGBoost forests or DNN/LSTM nets (D) and the hybrids H1, H2, H3 fitted on physics residuals."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import xgboost as xgb

from cell.data.samples import Samples, holdout_segments
from cell.model.dynamics.base import ModelMeta
from cell.model.dynamics.features import FeatureSpec, Group, group_matrices, groups
from cell.model.dynamics.nets import NetLearner, NetParams
from cell.model.dynamics.rigid_body import P2Model, robot_meta
from cell.model.dynamics.uncertainty import Coverage, CoverageConfig
from cell.model.robot import RobotModel
from drivers.configio import join, require

log = logging.getLogger(__name__)

LearnedKind = Literal["D", "H1", "H2", "H3"]
LEARNERS = ("xgboost", "dnn", "lstm")
# What physics each composition keeps (paper Table 2): the learned part is fitted on the rest.
PHYSICS_PART: dict[str, str] = {"D": "none", "H1": "full", "H2": "rigid", "H3": "losses"}


@dataclass
class XGBParams:
    """XGBoost settings (the paper tunes the same ten; these defaults are a sound untuned start)."""

    n_estimators: int = 400
    max_depth: int = 6
    learning_rate: float = 0.08
    min_child_weight: float = 5.0
    subsample: float = 0.8
    colsample_bytree: float = 0.8
    reg_lambda: float = 1.0
    reg_alpha: float = 0.0
    gamma: float = 0.0
    max_bin: int = 128
    early_stopping_rounds: int = 40
    validation_fraction: float = 0.2  # whole segments held out for early stopping (0: none)
    nthread: int = 2
    seed: int = 0

    def validate(self, where: str) -> None:
        require(self.n_estimators >= 1, join(where, "n_estimators"), "must be >= 1")
        require(1 <= self.max_depth <= 12, join(where, "max_depth"), "must lie in 1..12")
        require(0 < self.learning_rate <= 1, join(where, "learning_rate"), "must lie in (0, 1]")
        require(0 <= self.validation_fraction < 0.9, join(where, "validation_fraction"), "must lie in [0, 0.9)")
        require(self.nthread >= 1, join(where, "nthread"), "must be >= 1")

    def booster_params(self) -> dict[str, Any]:
        return {
            "objective": "reg:squarederror", "tree_method": "hist", "max_depth": self.max_depth,
            "eta": self.learning_rate, "min_child_weight": self.min_child_weight, "subsample": self.subsample,
            "colsample_bytree": self.colsample_bytree, "lambda": self.reg_lambda, "alpha": self.reg_alpha,
            "gamma": self.gamma, "max_bin": self.max_bin, "nthread": self.nthread, "seed": self.seed,
        }

    def to_dict(self) -> dict[str, Any]:
        return dict(vars(self))


class Forest:
    """One booster per learned output joint, each on its group's (windowed) features."""

    def __init__(self, spec: FeatureSpec, n: int, boosters: dict[int, xgb.Booster] | None = None) -> None:
        self.spec = spec
        self.n = n
        self.groups: list[Group] = groups(spec, n)
        self.boosters: dict[int, xgb.Booster] = boosters or {}
        self.fit_seconds = 0.0

    @property
    def outputs(self) -> list[int]:
        return [j for g in self.groups for j in g.outputs]

    def fit(self, s: Samples, target: np.ndarray, params: XGBParams, physics: np.ndarray | None = None,
            report: Callable[[int, float], None] | None = None) -> Forest:
        """target: (N, n) torque (or residual) per joint; only the learned joints are used.
        physics: (N, n) torque the 'load' inputs are made of (see `physics_part`).
        `report(k, RMSE on the held-out segments)` after the k-th joint's booster (for pruning a search)."""
        train_rows, val_rows = holdout_segments(s, params.validation_fraction, params.seed)
        t0 = time.perf_counter()
        for _, g, X in group_matrices(self.spec, self.groups, s.q, s.dq, s.ddq, s.starts, physics):
            Xtr = X[train_rows] if val_rows is not None else X
            for j in g.outputs:
                y = target[:, j].astype(np.float32)
                ytr = y[train_rows] if val_rows is not None else y
                dtrain = xgb.QuantileDMatrix(Xtr, label=ytr, max_bin=params.max_bin, nthread=params.nthread)
                evals = []
                kw: dict[str, Any] = {}
                if val_rows is not None:
                    dval = xgb.QuantileDMatrix(X[val_rows], label=y[val_rows], ref=dtrain, max_bin=params.max_bin,
                                               nthread=params.nthread)
                    evals = [(dval, "val")]
                    kw["early_stopping_rounds"] = params.early_stopping_rounds
                bst = xgb.train(params.booster_params(), dtrain, params.n_estimators, evals=evals,
                                verbose_eval=False, **kw)
                if val_rows is not None and bst.best_iteration is not None:
                    bst = bst[: bst.best_iteration + 1]  # keep the trees up to the best validation score
                self.boosters[j] = bst
                if report is not None and val_rows is not None:
                    err = bst.inplace_predict(X[val_rows]) - y[val_rows]
                    report(len(self.boosters) - 1, float(np.sqrt(np.mean(err**2))))
                log.debug("joint %d: %d trees", j + 1, bst.num_boosted_rounds())
            del X
        self.fit_seconds = time.perf_counter() - t0
        return self

    def predict(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, starts: np.ndarray | None,
                physics: np.ndarray | None = None) -> np.ndarray:
        """(N, n) with NaN on joints that are not learned."""
        out = np.full((np.atleast_2d(q).shape[0], self.n), np.nan)
        for _, g, X in group_matrices(self.spec, self.groups, q, dq, ddq, starts, physics):
            for j in g.outputs:
                out[:, j] = self.boosters[j].inplace_predict(X)
        return out

    def trees(self) -> int:
        return sum(b.num_boosted_rounds() for b in self.boosters.values())


@dataclass
class LearnedModel:
    """D, H1, H2 or H3: an optional physics part (from an identified P2) plus a forest on the rest.

    Joints outside the forest's outputs get the physics part alone (NaN for D).
    """

    kind: str
    forest: Forest | NetLearner  # the learned part: XGBoost trees or DNN/LSTM nets (same interface)
    physics: P2Model | None
    meta: ModelMeta
    params: XGBParams | NetParams = field(default_factory=XGBParams)
    coverage: Coverage | None = None  # trust and uncertainty of the learned residual (hybrids only)

    @property
    def learner(self) -> str:
        return self.forest.learner if isinstance(self.forest, NetLearner) else "xgboost"

    @property
    def part(self) -> str:
        return PHYSICS_PART[self.kind]

    def physics_torque(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return physics_part(self.kind, self.physics, q, dq, ddq)[0]

    def predict(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, starts: np.ndarray | None = None) -> np.ndarray:
        q, dq, ddq = np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq)
        if self.kind == "D":
            return self.forest.predict(q, dq, ddq, starts)
        base, load = physics_part(self.kind, self.physics, q, dq, ddq)
        learned = self.forest.predict(q, dq, ddq, starts, load)
        outs = self.forest.outputs
        if self.coverage is not None and self.coverage.blend:
            learned[:, outs] *= self.trust(q, dq, ddq)[:, outs]
        base[:, outs] += learned[:, outs]
        return base

    def trust(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """(N, n) trust in the learned residual: 1 without a coverage model, else `Coverage.weight` (what
        the prediction is blended by when `coverage.blend`, what the uncertainty is made of always)."""
        if self.coverage is None or self.kind == "D":
            return np.ones(np.atleast_2d(q).shape)
        return self.coverage.weight(q, dq, ddq)

    def predict_with_uncertainty(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray,
                                 starts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(torque, one-sigma uncertainty, trust) per sample and joint; the uncertainty is NaN without a
        coverage model (a model saved before it existed, or D)."""
        tau = self.predict(q, dq, ddq, starts)
        w = self.trust(q, dq, ddq)
        if self.coverage is None or self.kind == "D":
            return tau, np.full(tau.shape, np.nan), w
        return tau, self.coverage.sigma(np.atleast_2d(dq), w), w


def physics_part(kind: str, p2: P2Model | None, q: np.ndarray, dq: np.ndarray,
                 ddq: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(the model's physics torque, the torque its 'load' input is made of).

    The load is the rigid-body torque for H1 and H2 (what the gears transmit, which is what friction
    grows with), the loss torque for H3 (the only physics it keeps), none for D.
    """
    part = PHYSICS_PART[kind]
    q, dq, ddq = np.atleast_2d(q), np.atleast_2d(dq), np.atleast_2d(ddq)
    if part == "none":
        return np.zeros_like(q, dtype=float), None
    if p2 is None:
        raise ValueError(f"model {kind} needs an identified P2 for its physics part")
    if part == "losses":
        losses = p2.losses(q, dq, ddq)
        return losses, losses
    rigid = p2.rigid(q, dq, ddq)
    if part == "rigid":
        return rigid.copy(), rigid
    return rigid + p2.losses(q, dq, ddq), rigid


def regime_rows(s: Samples, max_speed: float, max_accel: float) -> np.ndarray | None:
    """The rows a hybrid's learned residual is fitted on: those of the segments (moves) whose arm's fastest joint
    stays within `max_speed` [rad/s] and `max_accel` [rad/s^2] throughout (0: no limit); None when that is
    every row.  Whole segments, because the derivative filter lags a hard start: its first rows read slow while
    the torque already carries the acceleration.

    Fast, hard-braking moves leave residuals ten times those of the slow motion the tasks run in (inertia and
    coupling errors the physics part still carries), and trees fitted on both lose the slow regime: they learn
    the fast rows' load-dependent error and apply it to slow rows under the same gravity load.  So the hybrid is
    fitted where the tasks run (`tasks.lab.train.identify_in_regime` identifies its physics part on the same
    moves), and beyond, the fast moves give the thresholds the model's error, measured on them."""
    inside = np.ones(len(s), bool)
    if max_speed > 0:
        inside &= np.abs(s.dq).max(axis=1) <= max_speed
    if max_accel > 0:
        inside &= np.abs(s.ddq).max(axis=1) <= max_accel
    if inside.all():
        return None
    keep = ~np.isin(s.segment, np.unique(s.segment[~inside]))
    return np.flatnonzero(keep)


def fit_learned(
    kind: str,
    robot: RobotModel,
    samples: Samples,
    spec: FeatureSpec | None = None,
    params: XGBParams | NetParams | None = None,
    p2: P2Model | None = None,
    training_data_sha256: str = "",
    coverage: CoverageConfig | None = None,
    report: Callable[[int, float], None] | None = None,
) -> LearnedModel:
    """Fit D (torque) or a hybrid (the residual left by its physics part) on `samples`, a hybrid's forest on the
    moves within `coverage`'s regime (`regime_rows`); a hybrid also gets its coverage and residual levels
    (cell/model/dynamics/uncertainty.py), measured on the segments the forest held out for early stopping (all
    samples when it held none) and, by the arm's fastest joint, on the moves beyond the regime past its speed."""
    if kind not in PHYSICS_PART:
        raise ValueError(f"unknown learned model {kind!r} (D, H1, H2, H3)")
    spec = spec or FeatureSpec()
    if kind == "D" and spec.physics_inputs:
        spec = dataclasses.replace(spec, physics_inputs=False)  # D has no physics part to feed
    params = params or XGBParams()
    cc = coverage or CoverageConfig()
    cc.validate("coverage")
    physics, load = physics_part(kind, p2, samples.q, samples.dq, samples.ddq)
    target = samples.tau - physics
    # (D has no physics part to take the moves beyond the regime: it learns the whole torque on every move.)
    fit_rows = regime_rows(samples, cc.fit_max_speed, cc.fit_max_accel) if kind != "D" else None
    fit = samples if fit_rows is None else samples.take_rows(fit_rows)
    fit_target = target if fit_rows is None else target[fit_rows]
    fit_load = load if fit_rows is None or load is None else load[fit_rows]
    forest: Forest | NetLearner
    if isinstance(params, NetParams):
        forest = NetLearner(spec, robot.n, params).fit(fit, fit_target, params, fit_load, report)
        extra: dict[str, Any] = {"learner": params.learner, "net": params.to_dict(), "weights": forest.weights()}
    else:
        forest = Forest(spec, robot.n).fit(fit, fit_target, params, fit_load, report)
        extra = {"xgboost": params.to_dict(), "trees": forest.trees()}
    if fit_rows is not None:
        extra["fit_rows"] = len(fit_rows)
    meta = robot_meta(
        robot, kind, features={**spec.to_dict(), "derivatives": samples.mode, "sample_period_s": samples.period_s},
        training_data_sha256=training_data_sha256, training_samples=len(samples),
        extra={**extra, "fit_seconds": forest.fit_seconds, "physics": PHYSICS_PART[kind]},
    )
    log.info("%s (%s) on %d samples in %.1f s", kind, extra.get("learner", "xgboost"), len(samples),
             forest.fit_seconds)
    cov = None
    if kind != "D" and p2 is not None:
        learned = forest.predict(samples.q, samples.dq, samples.ddq, samples.starts, load)
        outs = forest.outputs
        resid_h = target.copy()
        resid_h[:, outs] -= learned[:, outs]
        _, val_rows = holdout_segments(fit, params.validation_fraction, params.seed)
        own_rows = None
        if fit_rows is not None:
            # Levels from rows the forest never saw: its held-out segments, and for the levels by the arm's
            # fastest joint also the rows of the other segments beyond the regime's speed (its cruise; a hard
            # start's rows at lower speeds are the commanded-acceleration term's, as in a model fitted on all).
            own_rows = fit_rows if val_rows is None else fit_rows[val_rows]
            beyond = np.setdiff1d(np.arange(len(samples)), fit_rows)
            if cc.fit_max_speed > 0:
                beyond = beyond[np.abs(samples.dq[beyond]).max(axis=1) > cc.fit_max_speed]
            val_rows = np.union1d(own_rows, beyond)
        cov = Coverage.fit(outs, samples.q, samples.dq, samples.ddq, resid_h, target, np.abs(p2.params.f_c),
                           cc.bins, cc.min_count, cc.stick_speed, val_rows, blend=kind == "H1", own_level_rows=own_rows)
        meta.extra["coverage"] = {"min_count": cc.min_count, "stick_speed": cc.stick_speed, "bins": cc.bins}
        if fit_rows is not None:
            meta.extra["coverage"].update(fit_max_speed=cc.fit_max_speed, fit_max_accel=cc.fit_max_accel)
    return LearnedModel(kind=kind, forest=forest, physics=p2 if kind != "D" else None, meta=meta, params=params,
                        coverage=cov)
