"""Saved models: a folder with `model.json` (metadata, physics, features) and UBJ boosters or `nets.npz`."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import xgboost as xgb

from cell.data.atomic import atomic_path, save_atomic, write_atomic
from cell.model.dynamics.base import ModelMeta
from cell.model.dynamics.features import FeatureSpec
from cell.model.dynamics.learned import PHYSICS_PART, Forest, LearnedModel, XGBParams
from cell.model.dynamics.nets import NetLearner, NetParams, flatten_nets, unflatten_nets
from cell.model.dynamics.physics import P1Model
from cell.model.dynamics.rigid_body import P2Model, P2Params, urdf_sha256
from cell.model.dynamics.uncertainty import Coverage
from cell.model.robot import RobotModel
from drivers.configio import load_dataclass, read_versioned_json
from drivers.errors import DataError

log = logging.getLogger(__name__)

FORMAT = "tmcell-torque-model"
FORMAT_VERSION = 1
NETS_FILE = "nets.npz"
AnyModel = P1Model | P2Model | LearnedModel


def save_model(model: AnyModel, path: Path) -> Path:
    """Write `path/model.json` (+ `path/booster_j<k>.ubj`); the folder is replaced atomically per file."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "meta": dataclasses.asdict(model.meta),
        "xgboost_version": xgb.__version__,
    }
    if isinstance(model, P2Model):
        doc["p2"] = model.params.to_dict()
    elif isinstance(model, LearnedModel):
        if model.physics is not None:
            doc["p2"] = model.physics.params.to_dict()
            doc["p2_meta"] = dataclasses.asdict(model.physics.meta)
        doc["features"] = model.forest.spec.to_dict()
        if isinstance(model.forest, NetLearner):
            doc["learner"] = model.forest.learner
            doc["net"] = model.forest.params.to_dict()
            with atomic_path(path / NETS_FILE) as tmp, tmp.open("wb") as fh:
                np.savez(fh, allow_pickle=False, **flatten_nets(model.forest.nets))
            doc["nets"] = NETS_FILE
        else:
            doc["xgboost"] = model.params.to_dict()
            boosters = {}
            for j, bst in sorted(model.forest.boosters.items()):
                name = f"booster_j{j + 1}.ubj"
                # The temporary file keeps the .ubj extension: it selects the format.
                save_atomic(path / name, bst.save_model)
                boosters[str(j + 1)] = name
            doc["boosters"] = boosters
        if model.coverage is not None:
            doc["coverage"] = model.coverage.to_dict()
    write_atomic(path / "model.json", json.dumps(doc, indent=1))
    return path


def _meta(d: dict[str, Any]) -> ModelMeta:
    fields = {f.name for f in dataclasses.fields(ModelMeta)}
    return ModelMeta(**{k: v for k, v in d.items() if k in fields})


def check_robot(meta: ModelMeta, robot: RobotModel, where: str) -> None:
    """Refuse a model made for another robot: name, URDF content hash and joint count must match."""
    have = (robot.model.name, urdf_sha256(robot.urdf), robot.n)
    want = (meta.robot, meta.urdf_sha256, meta.joints)
    if have != want:
        raise DataError(
            f"{where}: model was made for robot '{meta.robot}' ({meta.joints} joints, URDF sha256 "
            f"{meta.urdf_sha256[:12]}), but this cell's robot is '{have[0]}' ({have[2]} joints, URDF {robot.urdf} "
            f"sha256 {have[1][:12]}); retrain it for this robot"
        )
    tool = meta.extra.get("tool")
    if tool and abs(float(tool.get("mass", 0.0)) - robot.tool.mass) > 1e-9:
        log.warning("%s: trained with a %.3f kg tool, this cell's nominal tool is %.3f kg", where,
                    float(tool["mass"]), robot.tool.mass)


def load_model(path: Path, robot: RobotModel) -> AnyModel:
    """A saved model artefact; any damage to it (truncated, missing or wrongly typed entries) is a one-line
    DataError naming the file, never a traceback."""
    try:
        return _load_model(Path(path), robot)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RecursionError) as exc:
        doc_path = Path(path) / "model.json" if Path(path).is_dir() else Path(path)
        detail = "nested too deeply" if isinstance(exc, RecursionError) else f"{type(exc).__name__}: {exc}"
        raise DataError(f"{doc_path}: damaged model file ({detail})") from None


def _load_model(path: Path, robot: RobotModel) -> AnyModel:
    doc_path = path / "model.json" if path.is_dir() else path
    doc = read_versioned_json(doc_path, FORMAT, FORMAT_VERSION, "model file",
                              f"{path}: no model.json (not a saved model)")
    meta = _meta(doc["meta"])
    check_robot(meta, robot, str(doc_path))
    if meta.kind == "P1":
        return P1Model(robot)
    if meta.kind == "P2":
        return P2Model(robot, P2Params.from_dict(doc["p2"]), meta)
    if meta.kind not in PHYSICS_PART:
        raise DataError(f"{doc_path}: unknown model kind {meta.kind!r}")
    p2 = None
    if "p2" in doc:
        p2_meta = _meta(doc["p2_meta"]) if "p2_meta" in doc else dataclasses.replace(meta, kind="P2")
        p2 = P2Model(robot, P2Params.from_dict(doc["p2"]), p2_meta)
    spec = load_dataclass(FeatureSpec, doc["features"], f"{doc_path}: features")
    coverage = None
    if "coverage" in doc:
        try:
            coverage = Coverage.from_dict(doc["coverage"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{doc_path}: coverage: {exc}") from None
    if "nets" in doc:
        return LearnedModel(kind=meta.kind, forest=_load_nets(doc, doc_path, spec, robot.n), physics=p2, meta=meta,
                            params=load_dataclass(NetParams, doc.get("net", {}), f"{doc_path}: net"),
                            coverage=coverage)
    params = load_dataclass(XGBParams, doc.get("xgboost", {}), f"{doc_path}: xgboost")
    boosters: dict[int, xgb.Booster] = {}
    for key, name in doc["boosters"].items():
        # Names are the ones save_model writes: a path elsewhere (../, /) is not part of this artefact.
        if not isinstance(name, str) or not re.fullmatch(r"booster_j\d{1,2}\.ubj", name) or not str(key).isdigit():
            raise DataError(f"{doc_path}: booster entry {key!r}: {name!r} is not a booster file of this artefact")
        file = doc_path.parent / name
        if not file.exists():
            raise DataError(f"{doc_path}: booster file {file} for joint {key} is missing")
        bst = xgb.Booster()
        try:
            bst.load_model(str(file))
        except xgb.core.XGBoostError as exc:  # truncated or damaged: XGBoost's message is a multi-line trace
            first = (str(exc).splitlines() or ["unreadable"])[0]
            first = re.sub(r"^\[[^]]*\]\s*\S+:\d+:\s*", "", first)  # XGBoost's time and source line
            raise DataError(f"{file}: not a readable XGBoost booster ({first})") from None
        bst.set_param({"nthread": params.nthread})
        boosters[int(key) - 1] = bst
    forest = Forest(spec, robot.n, boosters)
    missing = [j + 1 for j in forest.outputs if j not in boosters]
    if missing:
        raise DataError(f"{doc_path}: no booster for joint(s) {missing}")
    return LearnedModel(kind=meta.kind, forest=forest, physics=p2, meta=meta, params=params, coverage=coverage)


def _load_nets(doc: dict[str, Any], doc_path: Path, spec: FeatureSpec, n: int) -> NetLearner:
    """The DNN/LSTM part: `nets.npz` beside model.json, one network per feature group, shapes checked."""
    params = load_dataclass(NetParams, doc.get("net", {}), f"{doc_path}: net")
    params.validate(f"{doc_path}: net")
    if doc["nets"] != NETS_FILE:
        raise DataError(f"{doc_path}: nets entry {doc['nets']!r} is not the network file of this artefact")
    file = doc_path.parent / NETS_FILE
    if not file.exists():
        raise DataError(f"{doc_path}: network file {file} is missing")
    learner = NetLearner(spec, n, params)
    try:
        with np.load(file, allow_pickle=False) as z:
            learner.nets = unflatten_nets({k: z[k] for k in z.files}, len(learner.groups))
        for gi, g in enumerate(learner.groups):
            net = learner.nets[gi]
            if net.x_mean.shape != (g.width,) or net.weights["Wout"].shape[1] != len(g.outputs):
                raise ValueError(f"group {gi} has {net.x_mean.shape} inputs and {net.weights['Wout'].shape[1]} "
                                 f"outputs, the features ask for {g.width} and {len(g.outputs)}")
    except (KeyError, ValueError, OSError) as exc:
        raise DataError(f"{file}: {exc}") from None
    return learner
