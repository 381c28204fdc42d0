"""`main.py detect`: the collision detector over a dataset's test trajectories, at the logs' own sample times.

The robot's hybrid model (H1, causal derivatives: what the detector serves) is fitted on the dataset's
training split, or loaded.  Each test trajectory then streams through a fresh `CollisionDetector` sample by
sample, the momentum observer integrating over each step's own time (a log's steps are irregular), and
its residual is zeroed once after a settling window at the start (the bench zeroes a resting arm the same
way).  Detections are latched as the control loop's guard latches them, one per excursion over the
thresholds, and an excursion also ends after RELEASE_S under them.  For a trajectory that holds one pose
throughout, the pushes it contains (`find_pushes`) are matched to the detections: the real-arm check of
docs/collision.md.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell.collision.config import DetectorSettings
from cell.collision.detector import CollisionDetector
from cell.collision.guard import ContactGuard
from cell.config import CellConfig
from cell.data.dataset import Trajectory, load_manifest, load_split
from cell.model.dynamics.artefact import save_model
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from cell.model.specs import load_robot_spec, robot_by_name
from cell.sensing.virtual_sensor import load_observer_model
from drivers.errors import ConfigError, DataError
from drivers.interfaces import ArmState
from tasks.lab.train import TrainOptions, fit_model, lab_settings, load_samples

log = logging.getLogger(__name__)

# A push, as the UR10e collision recordings' README describes one: a joint-1-3 torque away from its
# resting value by more than this, for at least this long.
PUSH_THRESHOLD_NM = 15.0
PUSH_MIN_S = 0.1
# Departures closer than this are one push (a hand's grip shifting, the release's rebound).
PUSH_MERGE_S = 0.3
HOLD_SPEED = 0.03  # rad/s: a trajectory whose joints all stay below this holds one pose (a push test)
DETECT_WITHIN_S = 0.3  # a push counts as detected when a detection follows its onset within this
# A detection is one excursion: the next needs the residuals back under half their thresholds (the guard's
# hysteresis), or under the thresholds for this long.  After a push a held joint's friction sticks at another
# torque within its band, so its residual may not return under half while the arm stays untouched.
RELEASE_S = 0.5


# ------------------------------------------------------------------------------------------ pushes
@dataclass
class Push:
    """One push on a held arm: when the torque left its resting value and came back, and by how much."""

    onset_s: float  # from the trajectory's first sample
    end_s: float
    joint: int  # 1-based: the joint that departed most
    peak_nm: float  # largest departure from the resting value


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of every run of True in `mask`."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1, strict=True))


def find_pushes(t: np.ndarray, tau: np.ndarray, joints: Sequence[int] = (0, 1, 2),
                threshold_nm: float = PUSH_THRESHOLD_NM, min_s: float = PUSH_MIN_S, merge_s: float = PUSH_MERGE_S,
                rest_nm: np.ndarray | None = None) -> list[Push]:
    """The pushes in a held pose's torques (t (N,) s, tau (N, n) N·m; `joints` 0-based).

    A joint departs while |tau_j - rest_j| > `threshold_nm`; rest_j is the joint's median over the
    recording unless given (an arm holding a pose rests most of the time).  Departures of any of the
    joints closer than `merge_s` are one push; it counts when the torque stayed away for at least `min_s`
    (to the first sample back).  Times are from the first sample."""
    t = np.asarray(t, float)
    tau = np.asarray(tau, float)
    if t.ndim != 1 or tau.ndim != 2 or len(t) != len(tau):
        raise ValueError(f"find_pushes: t {t.shape} and tau {tau.shape} do not match")
    if len(t) == 0:
        return []
    js = list(joints)
    rest = np.median(tau[:, js], axis=0) if rest_nm is None else np.asarray(rest_nm, float)[js]
    away = np.abs(tau[:, js] - rest)
    runs = _runs(np.any(away > threshold_nm, axis=1))
    merged: list[list[int]] = []
    for a, b in runs:
        if merged and t[a] - t[merged[-1][1]] < merge_s:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    pushes = []
    for a, b in merged:
        back = t[b + 1] if b + 1 < len(t) else t[b]
        if back - t[a] < min_s:
            continue
        seg = away[a:b + 1]
        j = int(np.argmax(seg.max(axis=0)))
        pushes.append(Push(onset_s=float(t[a] - t[0]), end_s=float(back - t[0]), joint=js[j] + 1,
                           peak_nm=float(seg[:, j].max())))
    return pushes


# ------------------------------------------------------------------------------------------ detection
@dataclass
class DetectorRun:
    """One trajectory through the detector: per-sample ratios and the latched detections."""

    t_s: np.ndarray  # from the first sample
    ratio: np.ndarray  # (N, n) |r_j| / thr_j (NaN while settling)
    detections: list[dict[str, Any]] = field(default_factory=list)
    max_free_ratio: float = 0.0
    settle_s: float = 0.0


# A trajectory's source log name, its detector run and the pushes found in it: what the plot draws.
PlotRun = tuple[str, DetectorRun, list[dict[str, Any]]]


def settle_time(settings: DetectorSettings) -> float:
    """The residual settles within three of the observer's time constants, then the zeroing window averages."""
    return 3.0 / settings.observer_gain + settings.rebias_window_s


def run_detector(model: LearnedModel, robot: RobotModel, traj: Trajectory, settings: DetectorSettings) -> DetectorRun:
    """Stream one trajectory through a fresh detector at its own sample times."""
    if len(traj) < 3:
        raise DataError(f"{traj.name}: {len(traj)} samples; the detector needs at least 3")
    t = np.asarray(traj.t, float)
    dt = float(np.median(np.diff(t)))
    dq = traj.dq if traj.dq is not None else np.gradient(traj.q, t, axis=0)
    detector = CollisionDetector(model, robot, dt, settings, np.zeros(3), exact_steps=True)
    settle = settle_time(settings)
    ratio = np.full((len(t), robot.n), np.nan)
    run = DetectorRun(t_s=t - t[0], ratio=ratio, settle_s=settle)
    zeroed = latched = False
    under_since: float | None = None
    for k in range(len(t)):
        state = ArmState(t=float(t[k]), q=traj.q[k], dq=dq[k], tau=traj.tau[k], seq=k)
        rel = float(t[k] - t[0])
        detector.update(state)
        if not zeroed:
            if rel >= settle:
                detector.rebias()
                zeroed = True
            continue
        ratio[k] = r = detector.ratios()
        over = detector.check_free(r)
        worst_ratio = detector.ratio(r)
        run.max_free_ratio = max(run.max_free_ratio, worst_ratio)
        under_since = (under_since if under_since is not None else rel) if worst_ratio <= 1.0 else None
        if over.size == 0:
            if worst_ratio < ContactGuard.RELEASE or (under_since is not None and rel - under_since >= RELEASE_S):
                latched = False
            continue
        if latched:
            continue
        latched = True
        j = int(over[np.argmax(r[over])])
        run.detections.append({"t_s": round(rel, 4), "joint": j + 1, "joints": [int(i) + 1 for i in over],
                               "ratio": round(worst_ratio if detector.together else float(r[j]), 3),
                               "together": detector.together, "residual_nm": round(float(detector.residual[j]), 2),
                               "threshold_nm": round(float(detector.threshold[j]), 2)})
    if not zeroed:
        log.warning("%s: %.3f s long, shorter than the detector's settling (%.3f s): not checked",
                    traj.name, t[-1] - t[0], settle)
    return run


def match_pushes(pushes: list[Push], detections: list[dict[str, Any]],
                 within_s: float = DETECT_WITHIN_S) -> list[dict[str, Any]]:
    """Each push with its first detection from `within_s` before its onset to its end (delay, or None:
    missed).  A detection may precede the onset: the residual can cross a joint's threshold before the
    torque is 15 N·m from rest."""
    out = []
    for p in pushes:
        hits = [d["t_s"] for d in detections if p.onset_s - within_s <= d["t_s"] <= p.end_s]
        first = min(hits) if hits else None
        delay = None if first is None else round(first - p.onset_s, 4) + 0.0  # no "-0.0"
        out.append({"onset_s": round(p.onset_s, 4), "end_s": round(p.end_s, 4), "joint": p.joint,
                    "peak_nm": round(p.peak_nm, 1), "detected_s": first, "delay_s": delay,
                    "in_time": delay is not None and abs(delay) <= within_s})
    return out


# ------------------------------------------------------------------------------------------ command
def detector_settings(cfg: CellConfig, robot: str) -> tuple[DetectorSettings, str]:
    """The robot's own detector settings (`collision` in its robot.yaml), else the cell config's."""
    spec = load_robot_spec(robot)
    own = getattr(spec, "collision", None)
    if own is not None:
        return own, str(spec.folder / "robot.yaml")
    return cfg.collision.detector, "cell config collision.detector"


def _sources(dataset: Path) -> dict[str, dict[str, Any]]:
    """Per dataset file (resolved path): its source log and first time stamp, from `import.json` if present."""
    doc_path = dataset.parent / "import.json"
    if not doc_path.is_file():
        return {}
    try:
        doc = json.loads(doc_path.read_text())
        rows = [r for split in doc.get("splits", {}).values() for r in split]
        return {str((dataset.parent / r["file"]).resolve()): r for r in rows}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DataError(f"{doc_path}: unreadable import record: {exc}") from None


def _origin(traj: Trajectory, sources: dict[str, dict[str, Any]]) -> tuple[str, float]:
    """(source file, first sample's time in the log's own clock) of a test trajectory."""
    file = traj.name.split("#")[0]
    row = sources.get(str(Path(file).resolve()))
    if row is None:
        return file, float(traj.t[0])
    return str(row.get("source", file)), float(row.get("t0_log_s", 0.0)) + float(traj.t[0])


def fit_or_load(cfg: CellConfig, dataset: Path, robot_name: str, robot: RobotModel, model_dir: Path | None,
                samples: int | None, nthread: int, seed: int) -> tuple[LearnedModel, str]:
    """The hybrid model: loaded from `model_dir` when it holds one, else fitted (and saved there if given)."""
    if model_dir is not None and (model_dir / "model.json").is_file():
        return load_observer_model(model_dir, robot), f"loaded {model_dir}"
    opts = TrainOptions(derivatives="causal", nthread=nthread, seed=seed, **lab_settings(robot_name))
    s, sha = load_samples(dataset, "train", robot, "causal", samples, seed)
    model = fit_model("H1", robot, s, opts, sha)
    assert isinstance(model, LearnedModel)
    how = f"H1 fitted on {len(s)} training samples"
    if model_dir is not None:
        save_model(model, model_dir)
        how += f", saved to {model_dir}"
    return model, how


def detect(cfg: CellConfig, dataset: Path, robot_name: str, model_dir: Path | None = None, samples: int | None = None,
           nthread: int = 2, seed: int = 0) -> tuple[dict[str, Any], list[PlotRun]]:
    """The detector over every test trajectory of `dataset`: a summary, and per trajectory its source log's name,
    the detector's run and the pushes found in it (what `detect_plot.plot_detections` draws).

    CLI: main.py detect --robot NAME --data DATASET.yaml [--model DIR] [--samples N] [--plot PNG] [--json]
    """
    dataset = Path(dataset)
    if not dataset.is_file():
        raise ConfigError(f"--data {dataset}: no such dataset manifest")
    man = load_manifest(dataset)
    if not man.test:
        raise DataError(f"{dataset}: lists no test trajectories to run the detector over")
    robot = robot_by_name(cfg, robot_name)
    settings, settings_from = detector_settings(cfg, robot_name)
    if len(settings.floor_nm) != robot.n:
        raise ConfigError(f"{settings_from}: floor_nm needs {robot.n} values (one per joint), "
                          f"got {len(settings.floor_nm)}")
    trajs = load_split(dataset, "test", robot.n, robot.model.name)
    model, how = fit_or_load(cfg, dataset, robot_name, robot, model_dir, samples, nthread, seed)
    sources = _sources(dataset)
    rows: list[dict[str, Any]] = []
    runs: list[PlotRun] = []
    for traj in trajs:
        source, t0 = _origin(traj, sources)
        run = run_detector(model, robot, traj, settings)
        steps = np.diff(traj.t)
        row: dict[str, Any] = {
            # the source log's name; a log split at gaps adds the dataset's trajectory suffix (#id/piece)
            "name": Path(source).name + traj.name[len(traj.name.split("#")[0]):],
            "source": source, "t0_log_s": round(t0, 4), "duration_s": round(float(traj.t[-1] - traj.t[0]), 3),
            "samples": len(traj), "step_s": [round(float(steps.min()), 4), round(float(np.median(steps)), 4),
                                             round(float(steps.max()), 4)],
            "detections": run.detections, "max_free_ratio": round(run.max_free_ratio, 3),
        }
        pushes: list[dict[str, Any]] = []
        dq = traj.dq if traj.dq is not None else np.gradient(traj.q, traj.t, axis=0)
        if float(np.max(np.abs(dq))) < HOLD_SPEED:
            pushes = match_pushes(find_pushes(traj.t, traj.tau), run.detections)
            row["pushes"] = pushes
        rows.append(row)
        runs.append((Path(source).stem, run, pushes))
        log.info("%s: %d detections, max ratio %.2f%s", source, len(run.detections), run.max_free_ratio,
                 f", pushes {sum(p['in_time'] for p in pushes)}/{len(pushes)} in time" if pushes else "")
    held = [p for r in rows for p in r.get("pushes", [])]
    free = [r for r in rows if "pushes" not in r]
    out: dict[str, Any] = {
        "robot": robot_name, "dataset": str(dataset), "model": how, "settings_from": settings_from,
        "settings": dataclasses.asdict(settings),
        "pushes": len(held), "pushes_detected_in_time": sum(p["in_time"] for p in held),
        "push_delays_s": [p["delay_s"] for p in held],
        "detections_in_motion": sum(len(r["detections"]) for r in free),
        "max_free_ratio_in_motion": max((r["max_free_ratio"] for r in free), default=None),
        "trajectories": rows,
    }
    return out, runs
