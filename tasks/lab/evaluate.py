"""The model lab's evaluation: the six models and their variants fitted and scored on held-out trajectories."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cell.config import CellConfig, resolve
from cell.data.dataset import Trajectory, load_manifest, load_split, manifest_files
from cell.data.samples import stack, subsample_segments
from cell.model.dynamics.artefact import save_model
from cell.model.dynamics.rigid_body import P2Model
from cell.model.specs import CELL_ROBOT, robot_by_name
from drivers.configio import dumps_strict, read_yaml
from drivers.errors import ConfigError
from tasks.lab.checks import (
    leave_one_file_out,
    payload_transfer,
    regime_errors,
    trajectory_errors,
    uncertainty_report,
)
from tasks.lab.report import evaluation_table, plot_evaluation
from tasks.lab.train import (
    DEFAULT_XGB,
    PAPER_FEATURES,
    TrainOptions,
    default_net,
    fit_model,
    identify_in_regime,
    lab_settings,
    load_samples,
)

log = logging.getLogger(__name__)

DEFAULT_CURVE = (24_000, 64_000, 128_000, 256_000, 500_000)


def statistics(rmse: np.ndarray, nmse: np.ndarray) -> dict[str, Any]:
    """The paper's statistics over trajectories (mean, std, max, min of the per-trajectory RMSE)."""
    def per_joint(a: np.ndarray, fn: Callable[..., Any]) -> list[float | None]:
        return [None if np.isnan(a[:, j]).all() else round(float(fn(a[:, j])), 4) for j in range(a.shape[1])]

    j123 = rmse[:, :3].reshape(-1)
    return {
        "rmse_mean": per_joint(rmse, np.mean), "rmse_std": per_joint(rmse, np.std),
        "rmse_max": per_joint(rmse, np.max), "rmse_min": per_joint(rmse, np.min),
        "nmse_mean": per_joint(nmse, np.mean),
        "j123": {"mean": float(np.mean(j123)), "std": float(np.std(j123)), "max": float(np.max(j123)),
                 "min": float(np.min(j123))},
    }


def noise_floor(cfg: CellConfig) -> list[float] | None:
    """The simulated plant's torque-sensing noise (std per joint): no model can beat it on RMSE."""
    try:
        prof = read_yaml(resolve(cfg.plant))
        return [float(v) for v in prof["torque_sensing"]["noise_std"]]
    except (ConfigError, KeyError, TypeError, ValueError):
        return None


def evaluate(
    cfg: CellConfig,
    dataset: Path,
    out_dir: Path,
    train_samples: int = 24_000,
    large_samples: int = 500_000,
    curve: Sequence[int] | None = DEFAULT_CURVE,
    nthread: int = 2,
    seed: int = 0,
    save_models: bool = True,
    paper_variants: bool = True,
    max_trees: int | None = None,
    robot: str = CELL_ROBOT,
    lofo: bool = False,
    learners: Sequence[str] | None = None,
    tuned: Sequence[Path] | None = None,
    max_epochs: int | None = None,
) -> dict[str, Any]:
    """Fit P1, P2, D, H1, H2, H3 on `train_samples` of the training split (whole moves; the hybrids'
    P2 identified on the same samples), D also on `large_samples` (D_large), and as variants H2 on
    P2's identified rigid body (H2_identified; H2 itself keeps P1's nominal one, as the paper's
    Table 2) and the paper's own feature design (H1_paper, D_paper); score them all on the test split
    (a different motion family):
    per model and joint the mean, std, max, min of the per-trajectory RMSE and the nMSE; learning
    curves of D and H1 against the training-set size.  Writes `<out>/evaluation.json`,
    `<out>/table.md`, `<out>/evaluation.png` and the fitted models under `<out>/models/`.

    CLI: main.py evaluate --data artifacts/data/default/dataset.yaml --out artifacts/eval/default
         [--train-samples 24000] [--large-samples 500000] [--curve 24000,64000,128000,256000,500000]
         [--no-curve] [--max-trees N] [--nthread 2] [--seed 0] [--plant config/plants/alt.yaml] [--json]
         [--learners dnn,lstm] [--tuned artifacts/tune/h1 ...] [--max-epochs N]
    (`--plant` only names the profile whose torque-noise floor the report compares against.)
    `learners` adds D, H1, H2, H3 with those learned parts (rows D_dnn, H1_lstm, ...: the paper's Table 3),
    fitted on the same samples; `tuned` adds each `tune` folder's best settings, refitted here on the
    same samples (row <model>_<learner>_tuned).
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    robot_name = robot
    robot_model = robot_by_name(cfg, robot_name)
    opts = TrainOptions(nthread=nthread, seed=seed, max_trees=max_trees, **lab_settings(robot_name))
    dataset = Path(dataset)
    everything, sha = load_samples(dataset, "train", robot_model)
    man = load_manifest(dataset)
    tests = [stack([t], "zero_phase", man.filter)
             for t in load_split(dataset, "test", robot_model.n, robot_model.model.name)]
    small = subsample_segments(everything, train_samples, seed)
    large = subsample_segments(everything, large_samples, seed)
    log.info("evaluate: %d training samples available, %d test trajectories (%d samples)",
             len(everything), len(tests), sum(len(t) for t in tests))
    out_dir.mkdir(parents=True, exist_ok=True)  # only once the data is known good: a refusal leaves nothing

    models: dict[str, Any] = {}
    fit_s: dict[str, float] = {}
    sizes: dict[str, int] = {}
    steps = ["P1", "P2", "D", "H1", "H2", "H3", "D_large"]
    if paper_variants:
        steps += ["H2_identified", "H1_paper", "D_paper"]
    variants = {f"{k}_{L}": dataclasses.replace(opts, learner=L, max_epochs=max_epochs)
                for L in (learners or []) if L != "xgboost" for k in ("D", "H1", "H2", "H3")}
    variants.update(tuned_options(opts, tuned or [], max_epochs))
    steps += list(variants)
    p2_small: P2Model | None = None
    for name in tqdm(steps, desc="fit models", unit="model"):
        t0 = time.perf_counter()
        kind = name.split("_")[0]
        data = large if name == "D_large" else small
        spec = PAPER_FEATURES if name.endswith("_paper") else None
        o = dataclasses.replace(opts, h2_rigid="identified") if name == "H2_identified" else variants.get(name, opts)
        model = fit_model(kind, robot_model, data, o, sha, p2=p2_small if data is small else None, spec=spec)
        if name == "P2":
            assert isinstance(model, P2Model)
            p2_small = model
        models[name] = model
        fit_s[name] = time.perf_counter() - t0
        sizes[name] = 0 if name == "P1" else len(data)
    results: dict[str, Any] = {}
    for name, model in models.items():
        rmse, nmse = trajectory_errors(model, tests)
        results[name] = statistics(rmse, nmse)
        results[name].update(training_samples=sizes[name], fit_s=round(fit_s[name], 2),
                             features=model.meta.features)
    if save_models:
        for name, model in models.items():
            save_model(model, out_dir / "models" / name)

    curve_out: dict[str, list[dict[str, float]]] = {"D": [], "H1": []}
    for size in tqdm([int(c) for c in (curve or []) if int(c) <= len(everything)], desc="learning curve", unit="size"):
        sub = subsample_segments(everything, size, seed)
        p2 = identify_in_regime(robot_model, sub, opts, sha)
        for kind in ("D", "H1"):
            m = fit_model(kind, robot_model, sub, opts, sha, p2=p2)
            rmse, _ = trajectory_errors(m, tests)
            curve_out[kind].append({"samples": len(sub), "rmse_j123": round(float(np.mean(rmse[:, :3])), 4)})

    mean = {k: v["j123"]["mean"] for k, v in results.items()}
    six = ["P1", "P2", "D", "H1", "H2", "H3"]
    # Only the simulated plant's torque noise is known; a real arm's recordings report none.
    floor = noise_floor(cfg) if robot_name == CELL_ROBOT else None
    floor_j123 = float(np.mean(floor[:3])) if floor else None
    summary: dict[str, Any] = {
        "dataset": str(dataset), "plant": cfg.plant, "test_trajectories": len(tests),
        "test_samples": int(sum(len(t) for t in tests)), "train_samples": len(small),
        "large_samples": len(large),
        "mean_rmse_j123": {k: round(v, 4) for k, v in mean.items()},
        "p2_over_p1": round(mean["P2"] / mean["P1"], 4),
        "h1_over_p2": round(mean["H1"] / mean["P2"], 4),
        "d_large_over_p2": round(mean["D_large"] / mean["P2"], 4),
        "h1_is_best": all(mean["H1"] <= mean[k] for k in six),
        "h1_is_best_of_all": all(mean["H1"] <= mean[k] for k in mean),
        "best_model": min(mean, key=lambda k: mean[k]),
        "noise_floor_per_joint_nm": floor,
        "noise_floor_j123_nm": floor_j123,
        # RMSE over the noise floor: 1.0 would be a perfect model (only the sensor noise left).
        "over_noise_floor": {k: round(v / floor_j123, 3) for k, v in mean.items()} if floor_j123 else None,
        "learning_curve": curve_out,
        "models": results,
        "identified_p2": p2_small.params.report if p2_small is not None else None,
    }
    summary["regimes"] = regime_errors({k: models[k] for k in six}, tests)
    summary["uncertainty"] = {k: uncertainty_report(models[k], tests) for k in ("H1", "H2", "H3")}
    if man.loaded:
        loaded = load_split(dataset, "loaded", robot_model.n, robot_model.model.name)
        summary["payload_transfer"] = payload_transfer(
            {k: models[k] for k in ("P2", "H1", "H2", "H3")}, loaded, man.filter)
    if lofo:
        def fit_fold(trajs: list[Trajectory]) -> dict[str, Any]:
            s_all = stack(trajs, "zero_phase", man.filter)
            sub = subsample_segments(s_all, train_samples, seed)
            p2 = identify_in_regime(robot_model, sub, opts, sha)
            return {"P1": models["P1"], "P2": p2, "H1": fit_model("H1", robot_model, sub, opts, sha, p2=p2)}

        summary["leave_one_file_out"] = leave_one_file_out(manifest_files(dataset, "train"), fit_fold, robot_model.n,
                                                           man.filter, man.max_gap_s)
    summary["wall_s"] = round(time.perf_counter() - t_start, 1)
    (out_dir / "evaluation.json").write_text(dumps_strict(summary, indent=2))
    (out_dir / "table.md").write_text(evaluation_table(summary))
    try:
        summary["plot"] = str(plot_evaluation(summary, out_dir / "evaluation.png"))
    except Exception as exc:  # a plot must never lose the figures
        log.error("could not draw the evaluation plot: %s", exc)
    return summary


def tuned_options(opts: TrainOptions, dirs: Sequence[Path], max_epochs: int | None) -> dict[str, TrainOptions]:
    """Row name -> options holding a `tune` folder's best settings (its model/search.json)."""

    out: dict[str, TrainOptions] = {}
    for d in dirs:
        f = Path(d) / "model" / "search.json"
        if not f.exists():
            raise ConfigError(f"--tuned {d}: no model/search.json (not a `main.py tune` output folder)")
        try:
            doc = json.loads(f.read_text())
            kind, learner, best = doc["model"], doc["learner"], dict(doc["best_params"])
            if learner == "xgboost":
                o = dataclasses.replace(opts, xgb={**opts.xgb, kind: dataclasses.replace(DEFAULT_XGB[kind], **best)})
            else:
                o = dataclasses.replace(opts, learner=learner, max_epochs=max_epochs,
                                        net={kind: dataclasses.replace(default_net(kind, learner), **best)})
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{f}: not a tune search record ({exc})") from None
        out[f"{kind}_{learner}_tuned"] = o
    return out
