"""Cross-checks of the model lab: leave-one-file-out validation, payload transfer (fit unloaded, predict loaded)."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cell.data.dataset import Trajectory, load_trajectories
from cell.data.samples import Samples, stack
from cell.model.dynamics.learned import LearnedModel
from cell.model.dynamics.physics import P1Model
from cell.model.dynamics.rigid_body import P2Model
from cell.sensing.derivatives import FilterConfig

log = logging.getLogger(__name__)


def trajectory_errors(model: Any, tests: Sequence[Samples]) -> tuple[np.ndarray, np.ndarray]:
    """Per test trajectory and joint: RMSE and nMSE (MSE over the variance of the measured torque)."""
    rmse, nmse = [], []
    for t in tests:
        err = model.predict(t.q, t.dq, t.ddq, t.starts) - t.tau
        mse = np.mean(err**2, axis=0)
        rmse.append(np.sqrt(mse))
        nmse.append(mse / np.maximum(np.var(t.tau, axis=0), 1e-12))
    return np.asarray(rmse), np.asarray(nmse)


def j123_rmse(model: Any, tests: Sequence[Samples]) -> float:
    """Mean over trajectories and joints 1-3 of the per-trajectory RMSE [N·m]."""
    return float(np.mean(trajectory_errors(model, tests)[0][:, :3]))


def with_payload(model: P2Model | LearnedModel, mass: float, com: np.ndarray | None) -> P2Model | LearnedModel:
    """The model with a payload on the flange: P2's rigid body gains it, a hybrid keeps its learned part."""
    if isinstance(model, P2Model):
        return model.with_payload(mass, com)
    if model.physics is None:
        return model  # D has no physics to carry a payload
    return dataclasses.replace(model, physics=model.physics.with_payload(mass, com))


def payload_transfer(models: dict[str, Any], loaded: Sequence[Trajectory], filt: FilterConfig) -> dict[str, Any]:
    """Loaded runs predicted by models fitted on unloaded data: J1-3 RMSE with the payload given (its mass,
    and its centre of mass when known, else the flange origin) and without it."""
    groups: dict[tuple[float, tuple[float, ...] | None], list[Samples]] = {}
    for tr in loaded:
        if tr.payload is None:
            continue
        mass, com = tr.payload
        key = (float(mass), None if com is None else tuple(float(c) for c in com))
        groups.setdefault(key, []).append(stack([tr], "zero_phase", filt))
    if not groups:
        return {"trajectories": 0}
    out: dict[str, Any] = {"trajectories": sum(len(v) for v in groups.values()),
                           "payloads_kg": sorted({k[0] for k in groups}), "models": {}}
    for name, model in models.items():
        if isinstance(model, P1Model):
            continue
        errs_with, errs_without, counts = [], [], []
        for (mass, com_xyz), tests in groups.items():
            loaded_model = with_payload(model, mass, None if com_xyz is None else np.asarray(com_xyz))
            errs_with.append(j123_rmse(loaded_model, tests))
            errs_without.append(j123_rmse(model, tests))
            counts.append(len(tests))
        w = np.asarray(counts, float) / sum(counts)
        out["models"][name] = {"rmse_j123_with_payload": round(float(w @ errs_with), 4),
                               "rmse_j123_without_payload": round(float(w @ errs_without), 4)}
    return out


def leave_one_file_out(files: Sequence[Path], fit: Callable[[list[Trajectory]], dict[str, Any]],
                       n_joints: int, filt: FilterConfig, max_gap_s: float | None = None) -> dict[str, Any]:
    """Each training file held out in turn: `fit(trajectories of the others)` returns the models by name
    (P1, P2, H1 at least), scored on the held-out file.  Reports per fold and the mean and worst H1/P2."""
    by_file = {Path(f): load_trajectories(Path(f), n_joints, max_gap_s) for f in files}
    folds = []
    for held in tqdm(list(by_file), desc="leave one file out", unit="fold"):
        train = [tr for f, trs in by_file.items() if f != held for tr in trs]
        tests = [stack([tr], "zero_phase", filt) for tr in by_file[held]]
        models = fit(train)
        scores = {name: round(j123_rmse(m, tests), 4) for name, m in models.items()}
        folds.append({"file": held.name, "rmse_j123": scores,
                      "h1_over_p2": round(scores["H1"] / scores["P2"], 4),
                      "p2_over_p1": round(scores["P2"] / scores["P1"], 4)})
    ratios = np.array([f["h1_over_p2"] for f in folds])
    return {"folds": folds, "h1_over_p2_mean": round(float(ratios.mean()), 4),
            "h1_over_p2_worst": round(float(ratios.max()), 4),
            "p2_over_p1_mean": round(float(np.mean([f["p2_over_p1"] for f in folds])), 4)}




def regime_errors(models: dict[str, Any], tests: Sequence[Samples], moving_speed: float = 0.01) -> dict[str, Any]:
    """Pooled RMSE of joints 1-3 where each joint moves (|q'| >= `moving_speed`) and where it rests:
    at rest a joint's friction holds a torque set by the motion's history, which no model of the
    state predicts, so a test family with long rests (joint-wise runs: one joint moves, five rest)
    weighs that part heavily."""
    dq = np.concatenate([t.dq[:, :3] for t in tests])
    moving = np.abs(dq) >= moving_speed
    out: dict[str, Any] = {"moving_speed": moving_speed, "resting_share_j123": round(float(1 - moving.mean()), 4),
                           "models": {}}
    for name, model in models.items():
        err = np.concatenate([model.predict(t.q, t.dq, t.ddq, t.starts)[:, :3] - t.tau[:, :3] for t in tests])
        out["models"][name] = {
            "moving_rmse_j123": round(float(np.sqrt(np.mean(err[moving] ** 2))), 4) if moving.any() else None,
            "resting_rmse_j123": round(float(np.sqrt(np.mean(err[~moving] ** 2))), 4) if (~moving).any() else None,
        }
    return out


def uncertainty_report(model: LearnedModel, tests: Sequence[Samples]) -> dict[str, Any]:
    """How the model's one-sigma uncertainty and trust behave on held-out trajectories: the mean sigma
    and trust on joints 1-3, and the share of errors within 1 and 2 sigma (0.68 / 0.95 if calibrated)."""
    z, sig, trust = [], [], []
    for t in tests:
        tau, s, w = model.predict_with_uncertainty(t.q, t.dq, t.ddq, t.starts)
        z.append(np.abs(tau[:, :3] - t.tau[:, :3]) / s[:, :3])
        sig.append(s[:, :3])
        trust.append(w[:, :3])
    zz = np.concatenate(z)
    if not np.isfinite(zz).any():
        return {"available": False}
    return {"available": True, "mean_sigma_j123": round(float(np.nanmean(np.concatenate(sig))), 4),
            "mean_trust_j123": round(float(np.mean(np.concatenate(trust))), 4),
            "within_1_sigma": round(float(np.nanmean(zz <= 1)), 4),
            "within_2_sigma": round(float(np.nanmean(zz <= 2)), 4)}
