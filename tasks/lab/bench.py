"""Serving figures of the model lab (`main.py bench model`): the hybrid model's single-sample path, its fit
and batch speed, and one virtual-sensor step per observer and wrench mapping."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, cast

import numpy as np

from cell.config import CellConfig
from cell.data.samples import Samples
from cell.model.dynamics.artefact import load_model
from cell.model.dynamics.fastpredict import FastPredictor
from cell.model.dynamics.learned import Forest, LearnedModel, physics_part
from cell.model.dynamics.nets import NetLearner, NetParams
from cell.model.robot import RobotModel
from cell.model.specs import CELL_ROBOT, robot_by_name
from cell.sensing.derivatives import DerivativeMode
from cell.sensing.observer import make_observer
from cell.sensing.virtual_sensor import VirtualForceSource, contact_map
from cell.sensing.wrench_map import JacobianMap, LearnedMap, fit_learned_axes
from drivers.errors import ConfigError
from drivers.interfaces import ArmState
from tasks.lab.train import TrainOptions, fit_model, lab_settings, load_samples


def bench_model(
    cfg: CellConfig,
    dataset: Path,
    model_path: Path | None = None,
    train_samples: int = 24_000,
    fit_samples: int = 500_000,
    calls: int = 5000,
    nthread: int = 2,
    seed: int = 0,
    robot: str = CELL_ROBOT,
) -> dict[str, Any]:
    """Serving figures of the hybrid model (H1, joints 1-5, physics plus residual):

    * `hybrid_predict_p99_us`: one sample through `FastPredictor.predict_one` (compiled trees);
    * `stock_predict_p50_us`: the same sample path with XGBoost's own `inplace_predict` per booster;
      `speedup` = stock p50 / hybrid p50 (both measured here, same features, same physics);
    * `max_abs_diff_nm`: the two paths against each other and against the batch model;
    * `fit_s`: fitting the model's XGBoost part on `fit_samples` samples with `nthread` threads;
    * `batch_samples_per_s`: `LearnedModel.predict` (physics + features + trees) over the test split.

    The model is `model_path` (an artefact) or, without it, an H1 trained on `train_samples` of the
    dataset's training split with causal derivatives (what the controller would be given).

    CLI: main.py bench model --data artifacts/data/default/dataset.yaml [--model artifacts/models/h1]
         [--calls 5000] [--fit-samples 500000] [--train-samples 24000] [--nthread 2] [--seed 0]
         [--robot tm5-700] [--json]
    """
    settings = lab_settings(robot)
    robot_model = robot_by_name(cfg, robot)
    dataset = Path(dataset)
    opts = TrainOptions(nthread=nthread, seed=seed, derivatives="causal", **settings)
    if model_path is not None:
        loaded = load_model(Path(model_path), robot_model)
        if not isinstance(loaded, LearnedModel):
            raise ConfigError(f"--model {model_path}: a {loaded.meta.kind} model has no learned part to serve")
        model = loaded
        mode = cast(DerivativeMode, str(model.meta.features.get("derivatives", "zero_phase")))
    else:
        s, sha = load_samples(dataset, "train", robot_model, "causal", train_samples, seed)
        fitted = fit_model("H1", robot_model, s, opts, sha)
        assert isinstance(fitted, LearnedModel)
        model = fitted
        mode = "causal"
    tests, _ = load_samples(dataset, "test", robot_model, mode)
    # --- single sample: the compiled path and the stock path on the same stream of samples
    fast = FastPredictor(model, cfg.loop.period_s)
    stock = FastPredictor(model, cfg.loop.period_s, stock=True)
    n_calls = min(calls, len(tests))
    rows = np.arange(n_calls)
    batch = model.predict(tests.q[rows], tests.dq[rows], tests.ddq[rows], np.array([0]))
    out_fast = np.empty((n_calls, robot_model.n))
    out_stock = np.empty((n_calls, robot_model.n))

    # The served sample includes its uncertainty when the model has one (cell/model/dynamics/uncertainty.py).
    with_sigma = model.coverage is not None

    def stream(pred: FastPredictor, out: np.ndarray) -> np.ndarray:
        """One pass over the stream, one timed call per control period's sample [us]."""
        pred.reset()
        times = np.empty(n_calls)
        for k in range(n_calls):
            q, dq, ddq = tests.q[k], tests.dq[k], tests.ddq[k]
            ns0 = time.perf_counter_ns()
            out[k] = pred.predict_one(q, dq, ddq)
            if with_sigma:
                pred.last_sigma()
            times[k] = (time.perf_counter_ns() - ns0) / 1e3
        return times

    # Fast, stock, fast again: each path in a loop of its own (as the controller would run it, not
    # sharing caches with the other), and the fast path's figures from both of its passes.
    t_fast = stream(fast, out_fast)
    t_stock = stream(stock, out_stock)
    t_fast = np.concatenate([t_fast, stream(fast, out_fast)])
    warm = slice(min(50, n_calls // 10), None)  # the first calls of a pass pay for caches and allocation
    outs = model.forest.outputs
    diff_stock = float(np.max(np.abs(out_fast[:, outs] - out_stock[:, outs])))
    diff_batch = float(np.max(np.abs(out_fast[:, outs] - batch[:, outs])))
    # --- batch throughput over the test split
    t0 = time.perf_counter()
    model.predict(tests.q, tests.dq, tests.ddq, tests.starts)
    batch_rate = len(tests) / (time.perf_counter() - t0)
    # --- fitting the XGBoost part on fit_samples samples
    big, _ = load_samples(dataset, "train", robot_model, mode, fit_samples, seed)
    t0 = time.perf_counter()
    physics, load = physics_part(model.kind, model.physics, big.q, big.dq, big.ddq)
    t_phys = time.perf_counter() - t0
    forest: Forest | NetLearner
    if isinstance(model.params, NetParams):  # a DNN/LSTM part: the same networks refitted (JAX, CPU)
        forest = NetLearner(model.forest.spec, robot_model.n)
        forest.fit(big, big.tau - physics, dataclasses.replace(model.params, nthread=nthread), load)
    else:
        forest = Forest(model.forest.spec, robot_model.n)
        forest.fit(big, big.tau - physics, dataclasses.replace(model.params, nthread=nthread), load)
    t_fast = np.concatenate([t_fast[:n_calls][warm], t_fast[n_calls:][warm]])
    t_stock = t_stock[warm]
    p50, p99 = float(np.percentile(t_fast, 50)), float(np.percentile(t_fast, 99))
    s50 = float(np.percentile(t_stock, 50))
    return {
        "model": model.meta.kind, "learner": model.learner, "features": model.meta.features,
        "trees": model.forest.trees(),
        "compiled_depth": fast.forest.depth, "joints": [int(j) + 1 for j in outs],
        "hybrid_predict_p50_us": round(p50, 2), "hybrid_predict_p99_us": round(p99, 2),
        "hybrid_predict_max_us": round(float(np.max(t_fast)), 2),
        "stock_predict_p50_us": round(s50, 2),
        "stock_predict_p99_us": round(float(np.percentile(t_stock, 99)), 2),
        "speedup": round(s50 / p50, 2), "calls": n_calls, "includes_uncertainty": with_sigma,
        "max_abs_diff_vs_stock_nm": diff_stock, "max_abs_diff_vs_batch_nm": diff_batch,
        "fit_s": round(forest.fit_seconds, 2), "fit_samples": len(big), "fit_physics_s": round(t_phys, 2),
        "fit_trees": forest.trees(), "nthread": nthread,
        "batch_samples_per_s": round(batch_rate, 0), "batch_samples": len(tests),
        **bench_virtual_sensor(cfg, robot_model, model, tests, min(calls, 3000)),
    }


def bench_virtual_sensor(cfg: CellConfig, robot: RobotModel, model: LearnedModel, stream: Samples,
                         calls: int = 3000) -> dict[str, Any]:
    """One control step of the virtual sensor (observer + wrench mapping, `VirtualForceSource.read`)
    over a recorded stream, per route; `virtual_sensor_step_p99_us` is the configured route's.

    The learned map here is fitted on the stream itself (the Jacobian's wrench as the target) with the
    calibration's tree settings: the timing depends on the trees' number and depth, not their values."""

    vs = cfg.virtual_sensor
    dt = cfg.loop.period_s
    n = min(calls, len(stream))
    states = [ArmState(t=k * dt, q=stream.q[k], dq=stream.dq[k], tau=stream.tau[k]) for k in range(n)]
    R = np.array([0.8, 1.0, 0.6, 0.2, 0.2, 0.25]) ** 2  # typical calibrated residual variances [N·m]^2
    jac = JacobianMap(robot, np.asarray(vs.wrench_point, float), vs.singular_sigma, vs.max_damping)
    obs = make_observer("kalman", model, dt, R, np.asarray(vs.process_noise_nm), vs.momentum_gain, vs.rebias_window_s,
                            vs.innovation_gate)
    taus = np.array([obs.update(s) for s in states])
    wrench = np.array([jac.map(s.q, t).wrench for s, t in zip(states, taus, strict=True)])
    boosters = fit_learned_axes(stream.q[:n], taus, wrench)
    maps: dict[str, JacobianMap | LearnedMap] = {"jacobian": jac, "learned": LearnedMap(boosters, jac, robot.n),
                                                 "contact": contact_map(vs, robot, R)}
    warm = min(50, n // 10)
    out: dict[str, Any] = {}
    for kind in ("kalman", "momentum"):
        for mapping, wmap in maps.items():
            o = make_observer(kind, model, dt, R, np.asarray(vs.process_noise_nm), vs.momentum_gain, vs.rebias_window_s,
                            vs.innovation_gate)
            src = VirtualForceSource(o, wmap)
            times = np.empty(n)
            for k, st in enumerate(states):
                ns0 = time.perf_counter_ns()
                src.read(st)
                times[k] = (time.perf_counter_ns() - ns0) / 1e3
            t = times[warm:]
            out[f"{kind}+{mapping}"] = {"p50_us": round(float(np.percentile(t, 50)), 1),
                                        "p99_us": round(float(np.percentile(t, 99)), 1)}
    chosen = f"{vs.observer}+{vs.mapping}"
    return {"virtual_sensor_route": chosen, "virtual_sensor_step_p50_us": out[chosen]["p50_us"],
            "virtual_sensor_step_p99_us": out[chosen]["p99_us"], "virtual_sensor_routes": out}
