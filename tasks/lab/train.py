"""The model lab's training: P1/P2/D/H1-H3 fitted on a dataset's samples, their default features and settings."""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from cell.config import CellConfig
from cell.data.dataset import files_sha256, load_manifest, load_split, manifest_files
from cell.data.outputs import check_out_dir
from cell.data.samples import Samples, stack, subsample_segments
from cell.model.dynamics.artefact import save_model
from cell.model.dynamics.features import FeatureSpec
from cell.model.dynamics.learned import LEARNERS, LearnedModel, XGBParams, fit_learned, regime_rows
from cell.model.dynamics.nets import NetParams
from cell.model.dynamics.physics import P1Model, identify_p2
from cell.model.dynamics.rigid_body import IdentificationConfig, P2Model, nominal_p2
from cell.model.dynamics.uncertainty import CoverageConfig
from cell.model.robot import RobotModel
from cell.model.specs import CELL_ROBOT, load_robot_spec, robot_by_name
from cell.sensing.derivatives import DerivativeMode
from drivers.errors import ConfigError

MODEL_KINDS = ("P1", "P2", "D", "H1", "H2", "H3")


# Default inputs per learned model.  The hybrids H1/H2 learn what is left after (part of) the physics:
# mostly joint friction, so each joint sees its own state plus the structure of gear friction (load
# and direction, position harmonics).  H3 and D must also learn the rigid body, which couples all
# joints: they see every angle (D also the link orientations, parameter-free functions of the angles).
# The paper's own design (joints 1-3 grouped, 10-sample window, raw inputs) is `PAPER_FEATURES`,
# evaluated alongside as H1_paper and D_paper.
DEFAULT_FEATURES: dict[str, FeatureSpec] = {
    "D": FeatureSpec(window=1, grouping="full", friction_harmonics=6, angle_sums=True),
    "H1": FeatureSpec(window=1, grouping="own", physics_inputs=True, friction_harmonics=6),
    "H2": FeatureSpec(window=1, grouping="own", physics_inputs=True, friction_harmonics=6),
    "H3": FeatureSpec(window=1, grouping="per_joint", physics_inputs=True, friction_harmonics=6, angle_sums=True),
}
PAPER_FEATURES = FeatureSpec(window=10, grouping="paper")
# A residual is small and smooth: shallow trees with many samples per leaf transfer best to motions
# unlike the training ones; at most 300 trees per joint at a higher rate keeps single-sample serving
# cheap (1.5 % above 600 trees at 0.08 in a sweep on the default plant).  D carries the whole torque
# and needs deeper trees.
RESIDUAL_XGB = XGBParams(max_depth=3, min_child_weight=50, n_estimators=300, learning_rate=0.15,
                         early_stopping_rounds=40)
LARGE_D_SAMPLES = 100_000  # D fitted on at least this many samples keeps every sample for training (fit_model)
DEFAULT_XGB: dict[str, XGBParams] = {"D": XGBParams(), "H1": RESIDUAL_XGB, "H2": RESIDUAL_XGB, "H3": XGBParams()}
# The networks' inputs: the paper's grouping (joints 1-3 together, then one net per joint), instant for
# the DNN and the paper's 10-sample window for the LSTM.  D sees the link orientations (parameter-free);
# a hybrid also sees its physics load and direction (the friction structure the residual is made of).
NET_FEATURES: dict[str, FeatureSpec] = {
    "D": FeatureSpec(window=1, grouping="paper", angle_sums=True),
    "H1": FeatureSpec(window=1, grouping="paper", physics_inputs=True, friction_harmonics=1),
    "H2": FeatureSpec(window=1, grouping="paper", physics_inputs=True, friction_harmonics=1),
    "H3": FeatureSpec(window=1, grouping="paper", physics_inputs=True, friction_harmonics=1, angle_sums=True),
}
LSTM_WINDOW = 10  # the paper's: 80 ms of history at 8 ms
# Untuned starting points (`main.py tune` searches around them): a residual needs a smaller net than D.
DEFAULT_NET: dict[str, NetParams] = {
    "D": NetParams(hidden=128, layers=3, epochs=60, patience=10),
    "H1": NetParams(hidden=32, layers=2, epochs=30, patience=6),
    "H2": NetParams(hidden=32, layers=2, epochs=30, patience=6),
    "H3": NetParams(hidden=64, layers=3, epochs=40, patience=8),
}
# An LSTM step costs its window times a dense layer's work (and four gates): narrower cells, fewer epochs.
DEFAULT_LSTM: dict[str, NetParams] = {
    "D": NetParams(learner="lstm", hidden=48, layers=2, epochs=30, patience=6),
    "H1": NetParams(learner="lstm", hidden=24, layers=2, epochs=25, patience=5),
    "H2": NetParams(learner="lstm", hidden=24, layers=2, epochs=25, patience=5),
    "H3": NetParams(learner="lstm", hidden=32, layers=2, epochs=30, patience=6),
}


def default_net(kind: str, learner: str) -> NetParams:
    """The untuned settings of a DNN or LSTM part of `kind`."""
    table = DEFAULT_LSTM if learner == "lstm" else DEFAULT_NET
    return table.get(kind, NetParams())


@dataclasses.dataclass
class TrainOptions:
    """What `train` and `evaluate` fit: features and XGBoost settings per model, derivative filter."""

    features: dict[str, FeatureSpec] = dataclasses.field(default_factory=lambda: dict(DEFAULT_FEATURES))
    xgb: dict[str, XGBParams] = dataclasses.field(default_factory=lambda: dict(DEFAULT_XGB))
    derivatives: DerivativeMode = "zero_phase"
    identification: IdentificationConfig = dataclasses.field(default_factory=IdentificationConfig)
    coverage: CoverageConfig = dataclasses.field(default_factory=CoverageConfig)
    nthread: int = 2
    seed: int = 0
    max_trees: int | None = None  # cap on boosting rounds (quick runs)
    # H2's rigid body: "nominal" is the paper's Table 2 (the same M, C, G as P1, the learned part
    # covers losses, inertial errors and the rest); "identified" takes P2's identified rigid body.
    h2_rigid: str = "nominal"
    learner: str = "xgboost"  # the learned part of D and the hybrids: xgboost, dnn or lstm
    net: dict[str, NetParams] = dataclasses.field(default_factory=dict)  # per kind, else DEFAULT_NET
    max_epochs: int | None = None  # cap on the networks' epochs (quick runs)

    def spec(self, kind: str) -> FeatureSpec:
        if self.learner != "xgboost" and kind not in self.features_set:
            spec = NET_FEATURES.get(kind, PAPER_FEATURES)
            if self.learner == "lstm":
                spec = dataclasses.replace(spec, window=LSTM_WINDOW)
        else:
            spec = self.features.get(kind, DEFAULT_FEATURES.get(kind, PAPER_FEATURES))
        spec.validate(f"features[{kind}]")
        return spec

    @property
    def features_set(self) -> set[str]:
        """Kinds whose features were set explicitly (a network then uses them too, not NET_FEATURES)."""
        return {k for k, v in self.features.items() if DEFAULT_FEATURES.get(k) != v}

    def params(self, kind: str) -> XGBParams | NetParams:
        if self.learner not in LEARNERS:
            raise ConfigError(f"--learner {self.learner}: unknown (one of {', '.join(LEARNERS)})")
        if self.learner != "xgboost":
            n = self.net.get(kind, default_net(kind, self.learner))
            epochs = n.epochs if self.max_epochs is None else min(n.epochs, self.max_epochs)
            return dataclasses.replace(n, learner=self.learner, nthread=self.nthread, seed=self.seed, epochs=epochs)
        return self.xgb_params(kind)

    def xgb_params(self, kind: str) -> XGBParams:
        p = self.xgb.get(kind, DEFAULT_XGB.get(kind, XGBParams()))
        rounds = p.n_estimators if self.max_trees is None else min(p.n_estimators, self.max_trees)
        return dataclasses.replace(p, nthread=self.nthread, seed=self.seed, n_estimators=rounds)

    def override(self, kinds: Sequence[str] | None = None, **changes: Any) -> TrainOptions:
        """The same options with some feature settings (FeatureSpec fields) replaced for the learned
        models `kinds` (all by default); None values are ignored."""
        changes = {k: v for k, v in changes.items() if v is not None}
        grouping = changes.get("grouping")
        if grouping is not None and grouping not in ("paper", "per_joint", "full", "own"):
            raise ConfigError(f"--grouping {grouping}: unknown (paper, per_joint, full, own)")
        feats = {k: dataclasses.replace(v, **changes) if kinds is None or k in kinds else v
                 for k, v in self.features.items()}
        return dataclasses.replace(self, features=feats)


def lab_settings(robot: str = CELL_ROBOT) -> dict[str, Any]:
    """How the lab models a robot (TrainOptions fields): its robot.yaml `identification` and `learning`."""
    spec = load_robot_spec(robot)
    return {"identification": spec.identification, "coverage": spec.learning}


def fit_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """The robot.yaml settings a model is fitted with (`lab_settings`: `identification`, `learning`) as its meta
    keeps them (JSON's types): `prepare` trains again a model fitted with others."""
    return json.loads(json.dumps({"identification": dataclasses.asdict(settings["identification"]),
                                  "learning": dataclasses.asdict(settings["coverage"])}))


def load_samples(dataset: Path, split: Literal["train", "test"], robot: RobotModel, mode: DerivativeMode = "zero_phase",
                 samples: int | None = None, seed: int = 0) -> tuple[Samples, str]:
    """A split's trajectories stacked with derivatives (the manifest's filter), optionally cut to
    `samples` rows of whole segments; and the content hash of its files.  A dataset of another robot
    than `robot` (the manifest's `robot` against the URDF's robot name) is refused."""
    man = load_manifest(dataset)
    trajs = load_split(dataset, split, robot.n, robot.model.name)
    s = stack(trajs, mode, man.filter)
    if samples is not None:
        s = subsample_segments(s, samples, seed)
    return s, files_sha256(manifest_files(dataset, split))


def identify_in_regime(robot: RobotModel, s: Samples, opts: TrainOptions, data_sha: str = "") -> P2Model:
    """P2 identified on the moves within the regime the learned residual is fitted in (robot.yaml `learning`,
    `regime_rows`): the hybrid is the one these moves alone give, and the moves beyond set only its levels there
    (identified on them too, the physics part shifts the slow regime the tasks run in: docs/collision.md)."""
    rows = regime_rows(s, opts.coverage.fit_max_speed, opts.coverage.fit_max_accel)
    sub = s if rows is None else s.take_rows(rows)
    return identify_p2(robot, sub.q, sub.dq, sub.ddq, sub.tau, opts.identification, data_sha)


def fit_model(kind: str, robot: RobotModel, s: Samples, opts: TrainOptions, data_sha: str = "",
              p2: P2Model | None = None, spec: FeatureSpec | None = None,
              report: Callable[[int, float], None] | None = None) -> P1Model | P2Model | LearnedModel:
    """One model of the six on prepared samples (a hybrid identifies its P2 on the same samples)."""
    if kind == "P1":
        return P1Model(robot)
    if kind not in MODEL_KINDS:
        raise ConfigError(f"--model {kind}: unknown (one of {', '.join(MODEL_KINDS)})")
    if kind == "H2" and opts.h2_rigid == "nominal":
        p2 = nominal_p2(robot)
    elif p2 is None and kind != "D":
        p2 = identify_in_regime(robot, s, opts, data_sha)
    if kind == "P2":
        assert p2 is not None
        return p2
    params = opts.params(kind)
    if kind == "D" and len(s) >= LARGE_D_SAMPLES and isinstance(params, XGBParams):
        # With hundreds of thousands of samples the tree budget, not over-fitting, bounds D, and an
        # early-stopping holdout only withholds a fifth of the data (default plant, 500k: J1-3 RMSE
        # 1.82 N m with the holdout, 1.64 without).
        params = dataclasses.replace(params, validation_fraction=0.0)
    return fit_learned(kind, robot, s, spec or opts.spec(kind), params, p2=p2, training_data_sha256=data_sha,
                       coverage=opts.coverage, report=report)


def train(
    cfg: CellConfig,
    dataset: Path,
    out: Path,
    kind: str = "H1",
    samples: int | None = None,
    window: int | None = None,
    grouping: str | None = None,
    derivatives: str = "zero_phase",
    nthread: int = 2,
    seed: int = 0,
    robot: str = CELL_ROBOT,
    learner: str = "xgboost",
) -> dict[str, Any]:
    """Fit one model on the training split of a dataset and save it as an artefact folder.

    A model served in the control loop is trained with `derivatives="causal"`: its features then
    come from the same causal pipeline (`cell.sensing.derivatives.CausalDerivatives`) the controller runs.

    CLI: main.py train --data artifacts/data/default/dataset.yaml --model H1 --out artifacts/models/h1
         [--samples 24000] [--window 1] [--grouping own|paper|per_joint|full]
         [--derivatives zero_phase|causal] [--learner xgboost|dnn|lstm] [--nthread 2] [--seed 0]
         [--robot tm5-700] [--json]
    """
    if derivatives not in ("zero_phase", "causal"):
        raise ConfigError(f"--derivatives {derivatives}: unknown (zero_phase or causal)")
    check_out_dir(Path(out))  # before the fit: a model that cannot be saved is minutes lost
    settings = lab_settings(robot)
    robot_model = robot_by_name(cfg, robot)
    opts = TrainOptions(derivatives=cast(DerivativeMode, derivatives), nthread=nthread, seed=seed, learner=learner,
                        **settings)
    if learner != "xgboost" and (window is not None or grouping is not None):
        # the override applies to the features a network uses, not to the trees' defaults
        opts.features = {**opts.features, kind: opts.spec(kind)}
    opts = opts.override(kinds=[kind] if learner != "xgboost" else None, window=window, grouping=grouping)
    t0 = time.perf_counter()
    s, sha = load_samples(Path(dataset), "train", robot_model, opts.derivatives, samples, seed)
    model = fit_model(kind, robot_model, s, opts, sha)
    model.meta.extra["fit_settings"] = fit_settings(settings)
    fit_s = time.perf_counter() - t0
    pred = model.predict(s.q, s.dq, s.ddq, s.starts)
    rmse = np.sqrt(np.nanmean((pred - s.tau) ** 2, axis=0))
    path = save_model(model, Path(out))
    return {"model": kind, "learner": learner, "out": str(path), "samples": len(s), "fit_s": round(fit_s, 2),
            "derivatives": derivatives, "train_rmse_per_joint_nm": np.round(rmse, 4).tolist(),
            "meta": dataclasses.asdict(model.meta)}
