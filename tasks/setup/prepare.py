"""`prepare`: everything a tool needs for sensorless tasks: collect with it mounted, train the causal H1, calibrate.

Each step is skipped when its artefact is present and matches (unless `force`).  On top of the `samples`
of the mixed family the dataset gets `PREPARE_SLOW_SHARE` x `samples` of slow, small-amplitude
excitation: careful task motion (the peg's slides and rotations, 0.005-0.05 rad/s) runs in the
friction's low-speed regime, which the fast families only cross at their turning points.  Given the
tool's working posture (the CLI gives its task's start, lifted clear of the work surface), it also
gets `PREPARE_SWEEP_SHARE` x `samples` of slow constant-speed sweeps around it
(`cell.data.excitation.sweep.sweep_excitation`): the task's postures at the task's steady speeds.  Given
the settings `plan` times its moves with, it gets `PREPARE_FAST_SHARE` x `samples` of such moves: the
speeds the collision thresholds must know.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cell.config import CellConfig
from cell.data.dataset import files_sha256, load_manifest, manifest_files
from cell.model.dynamics.artefact import load_model
from cell.model.dynamics.base import TorqueModel
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from cell.planning.config import PlannerConfig
from cell.sensing.artefacts import calibration_matches
from cell.sensing.virtual_sensor import PERIOD_TOLERANCE
from drivers.errors import DataError
from tasks.lab.collect import collect
from tasks.lab.train import fit_settings, lab_settings, train
from tasks.setup.calibrate import LoadApplier, calibrate

log = logging.getLogger(__name__)

PREPARE_SLOW_SHARE = 0.25
PREPARE_SWEEP_SHARE = 0.4  # of `samples`: slow sweeps around the tool's working posture (when given)
PREPARE_FAST_SHARE = 0.25  # of `samples`: moves timed as `plan` times them (when its settings are given)


def prepare(
    cfg: CellConfig,
    tool: str,
    robot: RobotModel,
    collect_opener: Callable[[], Any],
    calibrate_opener: Callable[[], Any],
    applier_fn: Callable[[Any], LoadApplier],
    samples: int = 40_000,
    force: bool = False,
    seed: int = 0,
    cell_info: dict[str, Any] | None = None,
    working_posture: np.ndarray | None = None,
    fast_planner: PlannerConfig | None = None,
) -> dict[str, Any]:
    """Collect (with `tool` mounted) -> train the causal H1 -> calibrate, into the default artefact paths.

    `working_posture`: the joints where the tool's task starts; the collection then adds slow sweeps
    around it (`PREPARE_SWEEP_SHARE` x `samples`).  `fast_planner`: the settings `plan` times its moves
    with; the collection then adds such moves (`PREPARE_FAST_SHARE` x `samples`).

    CLI: main.py prepare [--tool wipe|peg] [--cell sim] [--samples 40000] [--force] [--fast-moves] [--json]
    """

    t0 = time.perf_counter()
    vs = cfg.virtual_sensor
    data_dir, model_dir, cal_dir = vs.path("data", tool), vs.path("model", tool), vs.path("calibration", tool)
    manifest = data_dir / "dataset.yaml"
    steps: dict[str, Any] = {}
    stale = False
    for part, wanted, what in (("sweep", working_posture is not None, "the slow sweeps around the working posture"),
                               ("fast", fast_planner is not None, "moves at the cell's working speeds")):
        if manifest.exists() and wanted and not stale and not _has_part(data_dir, part):
            log.warning("prepare %s: %s was collected without %s: collecting it again", tool, data_dir, what)
            stale = True
    period = dataset_period(manifest) if manifest.exists() else None
    if period is not None and abs(period - cfg.loop.period_s) > PERIOD_TOLERANCE * cfg.loop.period_s:
        log.warning("prepare %s: %s was sampled every %.1f ms, this cell runs every %.1f ms: collecting it again",
                    tool, data_dir, period * 1e3, cfg.loop.period_s * 1e3)
        stale = True
    if force or stale or not manifest.exists():
        log.info("prepare %s: collecting %d samples with the %s tool into %s", tool, samples, tool, data_dir)
        sweeps = PREPARE_SWEEP_SHARE if working_posture is not None else 0.0
        fast = PREPARE_FAST_SHARE if fast_planner is not None else 0.0
        res = collect(cfg, collect_opener, data_dir, samples=samples, test_trajectories=0, seed=seed,
                      slow_share=PREPARE_SLOW_SHARE, sweep_share=sweeps, sweep_centre=working_posture,
                      fast_share=fast, fast_planner=fast_planner)
        steps["collect"] = {"done": True, "train_samples": res["train_samples"], "wall_s": round(res["wall_s"], 1)}
    else:
        steps["collect"] = {"done": False, "reason": f"{manifest} exists"}
    data_sha = files_sha256(manifest_files(manifest, "train"))
    model_ok = False
    if (model_dir / "model.json").exists() and not force and not steps["collect"]["done"]:
        try:
            m = load_model(model_dir, robot)
            model_ok = (isinstance(m, LearnedModel) and m.meta.kind == "H1" and m.meta.training_data_sha256 == data_sha
                        and m.meta.features.get("derivatives") == "causal")
            if model_ok and not fitted_with_current_settings(m):
                log.warning("prepare %s: %s was fitted with other robot.yaml `identification` or `learning` settings: "
                            "training it again", tool, model_dir)
                model_ok = False
        except DataError:
            model_ok = False
    if model_ok:
        steps["train"] = {"done": False, "reason": f"{model_dir} is a causal H1 on {manifest}"}
    else:
        log.info("prepare %s: training the causal H1 into %s", tool, model_dir)
        t1 = time.perf_counter()
        # One XGBoost thread: on a shared two-core machine two threads spin-wait for each other and
        # a seconds-long fit takes a minute.
        res = train(cfg, manifest, model_dir, kind="H1", derivatives="causal", nthread=1, seed=seed)
        steps["train"] = {"done": True, "samples": res["samples"], "wall_s": round(time.perf_counter() - t1, 1)}
    why = "forced" if force else calibration_matches(cfg, robot, tool, model_dir, cal_dir)
    if steps["train"]["done"] or why:
        log.info("prepare %s: calibrating into %s (%s)", tool, cal_dir, why or "new model")
        rep = calibrate(cfg, tool, robot, calibrate_opener, applier_fn, model_dir, cal_dir, cell_info)
        steps["calibrate"] = {"done": True, **{k: rep[k] for k in ("fz_mae_n", "mx_mae_nm", "my_mae_nm", "route",
                                                                   "wall_s")}}
    else:
        steps["calibrate"] = {"done": False, "reason": f"{cal_dir} matches the robot, the tool and the model"}
    return {"tool": tool, "data": str(data_dir), "model": str(model_dir), "calibration": str(cal_dir),
            "steps": steps, "wall_s": round(time.perf_counter() - t0, 1)}


def fitted_with_current_settings(model: TorqueModel) -> bool:
    """Whether a model was fitted with the robot's current `identification` and `learning` settings (robot.yaml), as
    `train` records them in its meta; a model without that record is taken as fitted with others."""
    return model.meta.extra.get("fit_settings") == fit_settings(lab_settings())


def dataset_period(manifest: Path) -> float | None:
    """The sample period a dataset's manifest states (None when it states none or cannot be read)."""
    try:
        return load_manifest(manifest).period_s
    except DataError:
        return None


def _has_part(data_dir: Path, part: str) -> bool:
    """Whether the dataset's collection included a training part (`sweep`, `fast`: its collect.json says so)."""
    try:
        info = json.loads((data_dir / "collect.json").read_text())["plans"]["train"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return isinstance(info, dict) and part in info
