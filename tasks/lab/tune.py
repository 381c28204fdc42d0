"""`main.py tune`: the paper's coordinate-wise grid search (Algorithm 1) or Optuna's Bayesian search over a learner."""

from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cell.config import CellConfig
from cell.data.samples import Samples, subsample_segments
from cell.model.dynamics.artefact import load_model, save_model
from cell.model.dynamics.learned import LEARNERS, LearnedModel
from cell.model.dynamics.rigid_body import P2Model
from cell.model.specs import CELL_ROBOT, robot_by_name
from drivers.configio import dumps_strict
from drivers.errors import CellError, ConfigError
from tasks.lab.train import (
    DEFAULT_XGB,
    TrainOptions,
    default_net,
    fit_model,
    identify_in_regime,
    lab_settings,
    load_samples,
)
from tasks.lab.tune_space import Param, default_space, load_space

log = logging.getLogger(__name__)

TUNABLE = ("D", "H1", "H2", "H3")
VALIDATION_SHARE = 0.2
# Sub-sampling draws whole segments; an excitation run is one segment of minutes, so a small sample would be
# one stretch of one run.  Segments are cut into pieces of at most this many rows (2 s at 8 ms) first.
CHUNK_SAMPLES = 250


class WorkerLost(CellError):
    """A worker process died: the trials it finished are in the study, re-running the command resumes."""
  # of the training family's trajectories (or moves) held out to score a configuration


@dataclasses.dataclass
class Job:
    """What every worker needs to rebuild the objective (picklable: paths and plain settings)."""

    cfg: CellConfig
    dataset: Path
    out: Path
    kind: str
    learner: str
    samples: int
    seed: int
    nthread: int
    robot: str
    max_epochs: int | None = None


def chunk_segments(segment: np.ndarray, length: int) -> np.ndarray:
    """Segment ids with every run of equal ids cut into pieces of at most `length` rows (ids 0..k-1)."""
    change = np.r_[True, segment[1:] != segment[:-1]]
    rows = np.arange(len(segment))
    first = np.maximum.accumulate(np.where(change, rows, 0))
    key = (np.cumsum(change) - 1) * (len(segment) + 1) + (rows - first) // length
    return np.unique(key, return_inverse=True)[1].astype(np.int64)


def split_validation(s: Samples, share: float, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Rows to fit on and rows to score on: whole trajectories held out when there are at least five,
    else whole moves (segments); neighbouring rows are near copies, so a row-wise split would not hold out."""
    rng = np.random.default_rng(seed + 7919)  # another draw than the learners' own early-stopping holdout
    slices = s.trajectory_slices()
    if len(slices) >= 5:
        held = rng.choice(len(slices), max(1, int(round(share * len(slices)))), replace=False)
        val = np.zeros(len(s), bool)
        for h in held:
            val[slices[h]] = True
        unit = "trajectories"
    else:
        ids = np.unique(s.segment)
        if len(ids) < 5:
            raise ConfigError("tune: the training split has fewer than 5 trajectories and moves: nothing to hold out")
        val = np.isin(s.segment, rng.choice(ids, max(1, int(round(share * len(ids)))), replace=False))
        unit = "moves"
    return np.flatnonzero(~val), np.flatnonzero(val), unit


class Objective:
    """Validation RMSE (joints 1-3, N·m) of the model fitted with a configuration: fitted on the training
    family's kept rows, scored on its held-out trajectories; the test split is never read."""

    def __init__(self, job: Job) -> None:
        self.job = job
        self.robot = robot_by_name(job.cfg, job.robot)
        self.opts = TrainOptions(learner=job.learner, nthread=job.nthread, seed=job.seed, max_epochs=job.max_epochs,
                                 **lab_settings(job.robot))
        # Split the whole training split by trajectory first, then cut each side to its share of `samples`
        # (whole moves): the held-out trajectories are never seen, not even in part, by the fit.
        s, self.sha = load_samples(job.dataset, "train", self.robot, "zero_phase", None, job.seed)
        s.segment = chunk_segments(s.segment, CHUNK_SAMPLES)
        tr, va, self.unit = split_validation(s, VALIDATION_SHARE, job.seed)
        n_val = max(1, int(round(job.samples * VALIDATION_SHARE)))
        self.fit_rows = subsample_segments(s.take_rows(tr), job.samples - n_val, job.seed)
        self.val_rows = subsample_segments(s.take_rows(va), n_val, job.seed)
        self.all = stack_samples([self.fit_rows, self.val_rows])
        p2_dir = job.out / "p2"
        self.p2: P2Model | None = None
        if job.kind != "D" and (p2_dir / "model.json").exists():
            loaded = load_model(p2_dir, self.robot)
            assert isinstance(loaded, P2Model)
            self.p2 = loaded

    def options(self, config: dict[str, Any]) -> TrainOptions:
        k = self.job.kind
        if self.job.learner == "xgboost":
            xgb = {**self.opts.xgb, k: dataclasses.replace(DEFAULT_XGB[k], **config)}
            return dataclasses.replace(self.opts, xgb=xgb)
        return dataclasses.replace(self.opts, net={k: dataclasses.replace(default_net(k, self.job.learner), **config)})

    def __call__(self, config: dict[str, Any], report: Any = None) -> float:
        model = fit_model(self.job.kind, self.robot, self.fit_rows, self.options(config), self.sha, p2=self.p2,
                          report=report)
        v = self.val_rows
        err = model.predict(v.q, v.dq, v.ddq, v.starts)[:, :3] - v.tau[:, :3]
        return float(np.mean(np.sqrt(np.nanmean(err**2, axis=0))))


def stack_samples(parts: list[Samples]) -> Samples:
    """Row-wise concatenation; each part's trajectories stay separate (the best settings' refit uses both)."""
    offs = np.cumsum([0] + [len(p) for p in parts[:-1]])
    seg = np.cumsum([0] + [int(p.segment.max()) + 1 for p in parts[:-1]])
    return Samples(q=np.concatenate([p.q for p in parts]), dq=np.concatenate([p.dq for p in parts]),
                   ddq=np.concatenate([p.ddq for p in parts]), tau=np.concatenate([p.tau for p in parts]),
                   starts=np.concatenate([p.starts + o for p, o in zip(parts, offs, strict=True)]),
                   names=parts[0].names, mode=parts[0].mode,
                   segment=np.concatenate([p.segment + g for p, g in zip(parts, seg, strict=True)]))


def defaults(kind: str, learner: str, space: list[Param]) -> dict[str, Any]:
    base = DEFAULT_XGB[kind] if learner == "xgboost" else default_net(kind, learner)
    return {p.name: getattr(base, p.name) for p in space}


def _key(config: dict[str, Any]) -> str:
    """A configuration's identity: 50 and 50.0 are the same setting (a study hands back its choices' types)."""
    norm = {k: float(v) if isinstance(v, int | float) and not isinstance(v, bool) else v for k, v in config.items()}
    return json.dumps(norm, sort_keys=True)


# ------------------------------------------------------------------- storage (shared by every worker)
def storage_for(out: Path, url: str | None) -> Any:
    """Optuna storage: a journal file in `out` by default (safe for processes on one machine); a database
    URL (postgresql://, mysql://, sqlite:///) for workers on several machines; a path: a journal file there."""
    import optuna
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    if url and "://" in url:
        return optuna.storages.RDBStorage(url, heartbeat_interval=60, grace_period=120)
    path = Path(url) if url else out / "study.journal"
    path.parent.mkdir(parents=True, exist_ok=True)
    return JournalStorage(JournalFileBackend(str(path)))


def _study(job: Job, method: str, storage_url: str | None, sampler: Any = None, pruner: Any = None) -> Any:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna.create_study(study_name=f"{job.kind}-{job.learner}-{method}",
                               storage=storage_for(job.out, storage_url), direction="minimize",
                               load_if_exists=True, sampler=sampler, pruner=pruner)


def _finished(study: Any) -> list[Any]:
    import optuna

    return [t for t in study.get_trials(deepcopy=False)
            if t.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)]


# ------------------------------------------------------------------------- worker processes
_OBJECTIVE: Objective | None = None


def _init_worker(job: Job) -> None:
    global _OBJECTIVE
    os.environ.setdefault("OMP_NUM_THREADS", str(job.nthread))
    _OBJECTIVE = Objective(job)


def _evaluate(config: dict[str, Any]) -> tuple[dict[str, Any], float, float]:
    assert _OBJECTIVE is not None
    t0 = time.perf_counter()
    return config, _OBJECTIVE(config), time.perf_counter() - t0


def _suggest(trial: Any, space: list[Param]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for p in space:
        if p.kind == "categorical":
            out[p.name] = trial.suggest_categorical(p.name, list(p.grid))
        elif p.kind == "int":
            out[p.name] = trial.suggest_int(p.name, int(p.low or 0), int(p.high or 0), log=p.log)
        else:
            out[p.name] = trial.suggest_float(p.name, float(p.low or 0), float(p.high or 0), log=p.log)
    return out


def _bayes_worker(job: Job, space: list[Param], trials: int, storage_url: str | None, sampler_name: str,
                  index: int) -> None:
    """One worker of the Bayesian search: takes trials from the shared study until it holds `trials`."""
    import optuna
    from optuna.study import MaxTrialsCallback
    from optuna.trial import TrialState

    _init_worker(job)
    assert _OBJECTIVE is not None
    obj = _OBJECTIVE
    sampler: Any = (optuna.samplers.GPSampler(seed=job.seed + index) if sampler_name == "gp"
                    else optuna.samplers.TPESampler(seed=job.seed + index, n_startup_trials=8))
    pruner = optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=2)
    study = _study(job, "bayes", storage_url, sampler, pruner)
    if len(_finished(study)) >= trials:
        return

    def objective(trial: Any) -> float:
        config = _suggest(trial, space)

        def report(step: int, value: float) -> None:
            trial.report(value, step)
            if trial.should_prune():
                raise optuna.TrialPruned()

        return obj(config, report)

    study.optimize(objective, callbacks=[MaxTrialsCallback(trials, states=(TrialState.COMPLETE, TrialState.PRUNED))],
                   gc_after_trial=True)


def _watch(study: Any, procs: list[Any], total: int) -> None:
    """Progress bar over the shared study while the worker processes run."""
    with tqdm(total=total, desc="tune", unit="trial") as bar:
        while any(p.is_alive() for p in procs):
            time.sleep(1.0)
            bar.n = min(total, len(_finished(study)))
            bar.refresh()
        bar.n = min(total, len(_finished(study)))
        bar.refresh()
    bad = [p.exitcode for p in procs if p.exitcode not in (0, None)]
    if bad:
        log.warning("tune: %d worker(s) ended with exit code(s) %s: re-run the command to resume", len(bad), bad)


def run_bayes(job: Job, space: list[Param], trials: int, workers: int, storage_url: str | None,
              sampler: str) -> dict[str, Any]:
    study = _study(job, "bayes", storage_url)
    ctx = mp.get_context("spawn")  # a fresh interpreter per worker: no forked JAX or XGBoost thread pools
    procs = [ctx.Process(target=_bayes_worker, args=(job, space, trials, storage_url, sampler, i), daemon=False)
             for i in range(workers)]
    for p in procs:
        p.start()
    try:
        _watch(study, procs, trials)
    finally:
        for p in procs:
            p.join()
    done = [t for t in _finished(study) if t.value is not None and t.state.name == "COMPLETE"]
    if not done:
        raise ConfigError("tune: no trial completed (see the workers' errors above)")
    history = [{"number": t.number, "value": t.value, "state": t.state.name, "params": t.params,
                "seconds": (t.datetime_complete - t.datetime_start).total_seconds()
                if t.datetime_complete and t.datetime_start else None} for t in _finished(study)]
    best = min(done, key=lambda t: t.value)
    return {"best_params": dict(best.params), "best_rmse": float(best.value), "history": history,
            "pruned": sum(1 for t in _finished(study) if t.state.name == "PRUNED")}


def run_grid(job: Job, space: list[Param], trials: int, workers: int, storage_url: str | None) -> dict[str, Any]:
    """Algorithm 1: from the default configuration, a 1-D grid search on each hyperparameter in turn with
    the others held at their best, cycling until a full cycle changes nothing (or `trials` are spent).
    Every evaluated configuration is a trial of the shared study: a re-run takes them from there."""
    import optuna

    study = _study(job, "grid", storage_url)
    start = defaults(job.kind, job.learner, space)
    dists: dict[str, Any] = {
        p.name: optuna.distributions.CategoricalDistribution(sorted({*p.grid, start[p.name]}, key=str)) for p in space}
    cache: dict[str, float] = {_key(t.params): float(t.value) for t in _finished(study) if t.value is not None}
    history: list[dict[str, Any]] = [{"number": t.number, "value": t.value, "state": t.state.name, "params": t.params}
                                     for t in _finished(study)]
    budget = {"left": trials - len(cache)}
    ctx = mp.get_context("spawn")
    pool = ProcessPoolExecutor(workers, ctx, initializer=_init_worker, initargs=(job,)) if workers > 1 else None
    if pool is None:
        _init_worker(job)
    bar = tqdm(total=trials, initial=min(trials, len(cache)), desc="tune (grid)", unit="trial")

    def evaluate_all(configs: list[dict[str, Any]]) -> list[float]:
        todo = [c for c in configs if _key(c) not in cache][: max(0, budget["left"])]
        results = pool.map(_evaluate, todo) if pool is not None else map(_evaluate, todo)
        for config, value, secs in results:
            cache[_key(config)] = value
            study.add_trial(optuna.trial.create_trial(params=config, distributions=dists, value=value))
            history.append({"number": len(history), "value": value, "state": "COMPLETE", "params": config,
                            "seconds": secs})
            budget["left"] -= 1
            bar.update(1)
        return [cache.get(_key(c), np.inf) for c in configs]

    try:
        current = dict(start)
        changed, truncated, cycles = True, False, 0
        best = default = evaluate_all([current])[0]
        while budget["left"] > 0:
            changed = False
            for p in space:
                cands = [{**current, p.name: v} for v in p.grid]
                scores = evaluate_all(cands)
                truncated |= not np.all(np.isfinite(scores))  # the budget ran out inside this cycle
                k = int(np.argmin(scores))
                if scores[k] < best and cands[k][p.name] != current[p.name]:
                    current, best, changed = cands[k], scores[k], True
            cycles += 1
            if not changed:
                break
    except BrokenProcessPool:
        raise WorkerLost(f"tune: a grid worker died; {len(cache)} scored configurations are in the study, "
                         "re-run the same command to resume") from None
    finally:
        bar.close()
        if pool is not None:
            pool.shutdown()
    if not np.isfinite(best):
        raise ConfigError(f"tune: --trials {trials} leaves no trial for the default configuration")
    return {"best_params": current, "best_rmse": float(best), "default_rmse": float(default), "history": history,
            "cycles": cycles,
            "converged": not changed and not truncated}


def plot_history(history: list[dict[str, Any]], default_rmse: float, path: Path, title: str) -> Path:
    """Validation RMSE of every trial in order, the best so far, and the default configuration's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vals = [(h["number"], h["value"]) for h in history if h.get("value") is not None and h["state"] == "COMPLETE"]
    vals.sort()
    fig, ax = plt.subplots(figsize=(7, 4))
    if vals:
        n, v = zip(*vals, strict=True)
        ax.plot(n, v, "o", ms=4, alpha=0.6, label="trial")
        ax.plot(n, np.minimum.accumulate(v), "-", label="best so far")
    ax.axhline(default_rmse, color="k", ls="--", lw=1, label="default settings")
    ax.set_xlabel("trial")
    ax.set_ylabel("validation RMSE J1-3 [N·m]")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def tune(cfg: CellConfig, dataset: Path, out: Path, kind: str = "H1", learner: str = "xgboost", method: str = "bayes",
         trials: int = 40, workers: int = 1, storage: str | None = None, space_path: Path | None = None,
         samples: int = 24_000, sampler: str = "tpe", nthread: int = 1, seed: int = 0, robot: str = CELL_ROBOT,
         max_epochs: int | None = None) -> dict[str, Any]:
    """Search a learner's hyperparameters for one model; refit the best on all the samples and save it.

    Writes `<out>/model/` (a normal model artefact; `search.json` beside its model.json, the search in
    its metadata), `<out>/history.json`, `<out>/history.png` and the study's storage (`study.journal`).

    CLI: main.py tune --data artifacts/data/default/dataset.yaml --model H1 [--learner xgboost|dnn|lstm]
         --method grid|bayes --trials 40 [--workers 2] [--storage URL] [--space config/tune/xgboost.yaml]
         [--samples 24000] [--sampler tpe|gp] --out artifacts/tune/h1 [--json]
    """
    if kind not in TUNABLE:
        raise ConfigError(f"--model {kind}: only a learned model can be tuned ({', '.join(TUNABLE)})")
    if learner not in LEARNERS:
        raise ConfigError(f"--learner {learner}: unknown (one of {', '.join(LEARNERS)})")
    if method not in ("grid", "bayes"):
        raise ConfigError(f"--method {method}: unknown (grid or bayes)")
    space = load_space(space_path or default_space(learner), learner)
    t0 = time.perf_counter()
    out = Path(out)
    job = Job(cfg, Path(dataset), out, kind, learner, samples, seed, nthread, robot, max_epochs)
    obj = Objective(job)  # loads and checks the data before anything is written
    out.mkdir(parents=True, exist_ok=True)
    if kind not in ("D", "H2") and not (out / "p2" / "model.json").exists():
        # every worker uses this one identified P2 (fitted on the kept rows only)
        f = obj.fit_rows
        obj.p2 = identify_in_regime(obj.robot, f, obj.opts, obj.sha)
        save_model(obj.p2, out / "p2")
    start = defaults(kind, learner, space)
    t_search = time.perf_counter()
    if method == "grid":
        res = run_grid(job, space, trials, workers, storage)
        default_rmse = res["default_rmse"]
    else:
        # today's settings scored on the same split, once per output folder (a resumed run reads it back)
        default_file = out / "default.json"
        if default_file.exists():
            default_rmse = float(json.loads(default_file.read_text())["default_rmse"])
        else:
            default_rmse = obj(start)
            default_file.write_text(json.dumps({"default_rmse": default_rmse, "params": start}))
        res = run_bayes(job, space, trials, workers, storage, sampler)
    search_s = time.perf_counter() - t_search
    best_params = res["best_params"]
    if res["best_rmse"] > default_rmse:  # the search found nothing better: keep today's settings
        best_params, res["best_rmse"] = start, default_rmse
    model = fit_model(kind, obj.robot, obj.all, obj.options(best_params), obj.sha, p2=obj.p2)
    assert isinstance(model, LearnedModel)
    extra: dict[str, Any] = {k: res[k] for k in ("cycles", "converged", "pruned") if k in res}
    search: dict[str, Any] = {"method": method, "learner": learner, "model": kind, "trials": len(res["history"]),
              "best_rmse": round(res["best_rmse"], 4), "default_rmse": round(default_rmse, 4),
              "best_params": best_params, "default_params": start, "validation": obj.unit,
              "validation_samples": len(obj.val_rows), "fit_samples": len(obj.fit_rows), "workers": workers,
              "search_s": round(search_s, 1), **extra}
    model.meta.extra["search"] = search
    model_dir = save_model(model, out / "model")
    (model_dir / "search.json").write_text(dumps_strict({**search, "history": res["history"]}, indent=1))
    (out / "history.json").write_text(dumps_strict(res["history"], indent=1))
    png = plot_history(res["history"], default_rmse, out / "history.png", f"{kind} ({learner}), {method}")
    return {**search, "model_dir": str(model_dir), "plot": str(png), "wall_s": round(time.perf_counter() - t0, 1)}
