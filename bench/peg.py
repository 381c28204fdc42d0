"""Peg-in-hole bench: randomised hole offset and tilt on the simulated cell, scored from the plant's truth."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from tqdm import tqdm

from bench.peg_failures import count_kinds, failure_kind
from cell.config import CellConfig, resolve
from cell.control.loop import ControlLoop, Observation, OpenCell
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.data.recorder import Recorder, read_log
from cell.model.robot import RobotModel
from drivers.interfaces import ArmState, Wrench
from sim.cell import SimCell
from sim.drivers import SimArm, SimForceSensor
from sim.plant import Penetration, Plant
from sim.profile import load_profile
from tasks.base import SETUP_STATES
from tasks.peg.config import PegConfig
from tasks.peg.scoring import ERROR_KEYS, wrench_abs_errors
from tasks.peg.task import PegInHoleTask
from tasks.runner import expect_touches

log = logging.getLogger(__name__)

# Turns the opened simulated cell into the one the task runs on (e.g. the virtual sensor as the
# force source with the F/T sensor as ground truth); identity keeps the F/T sensor in the loop.
CellWrapper = Callable[[OpenCell], OpenCell]


@dataclass
class Trial:
    offset_m: tuple[float, float]
    tilt_deg: tuple[float, float]
    outcome: str
    reason: str
    success: bool
    insertion_time_s: float | None
    task_time_s: float
    true_depth_m: float
    peak_force_n: float
    peak_state: str  # the task state in which the peak force was measured
    probes: int
    realignments: int
    abs_err: np.ndarray  # (n, 3) |virtual - measured| of (Mx, My, Fz) during the insertion
    axis_error_deg: float | None = None  # surveyed hole axis vs the fixture's true one
    index: int = 0  # the trial's number in the bench's sequence of draws
    recollided: int = 0  # physics steps the plant took again after a failed collision detection
    penetration: Penetration = field(default_factory=Penetration)  # the plant's deepest contacts


class _Tap:
    """A force source that remembers its last reading (the ground truth the task never sees)."""

    def __init__(self, source: Any, task: PegInHoleTask) -> None:
        self.source = source
        self.task = task
        self.name = source.name
        self.last: Wrench | None = None
        self.peak_force = 0.0  # largest |F| read once the task is past its setup states
        self.peak_state = ""  # the task's state then

    def read(self, state: ArmState) -> Wrench:
        # The peak is taken here, not in the task's step: a reading that trips the safety stop never
        # reaches the task, and it is the one that matters.
        self.last = self.source.read(state)
        f = float(np.linalg.norm(self.last.force))
        now = self.task.state_name
        if now not in SETUP_STATES and np.isfinite(f) and f > self.peak_force:
            self.peak_force, self.peak_state = f, now
        return self.last

    def rebias(self) -> None:
        self.source.rebias()


class _ScoredTask:
    """Wraps the task: per step, the wrench it used, the measured one, and the plant's true depth."""

    def __init__(self, task: PegInHoleTask, truth: _Tap | None, plant: Plant) -> None:
        self.task = task
        self.truth = truth  # the F/T sensor beside another force source (errors are scored), or None
        self.plant = plant
        self.name = task.name
        # Per step with the F/T sensor beside the source: the state, and (Mx, My, Fz) of both.
        self.states: list[str] = []
        self.virtual: list[np.ndarray] = []
        self.measured: list[np.ndarray] = []
        self.true_depth = -math.inf
        site = mujoco.mj_name2id(plant.model, mujoco.mjtObj.mjOBJ_SITE, "hole_top")
        self._mouth = np.array(plant.data.site_xpos[site])
        self._axis = np.array(plant.data.site_xmat[site]).reshape(3, 3)[:, 2]  # up, out of the hole

    @property
    def done(self) -> bool:
        return self.task.done

    @property
    def state_name(self) -> str:
        return self.task.state_name

    def abort(self, reason: str) -> None:
        self.task.abort(reason)

    def summary(self) -> dict[str, Any]:
        return self.task.summary()

    def step(self, obs: Observation) -> Any:
        measured = self.truth.last if self.truth is not None and self.truth.last is not None else obs.wrench
        if self.truth is not None:
            v = obs.wrench
            self.states.append(self.task.state_name)
            self.virtual.append(np.array([v.torque[0], v.torque[1], v.force[2]]))
            self.measured.append(np.array([measured.torque[0], measured.torque[1], measured.force[2]]))
        tip = self.plant.tool_pose()[0]
        self.true_depth = max(self.true_depth, float((self._mouth - tip) @ self._axis))
        return self.task.step(obs)


def run_trial(cfg: CellConfig, robot: RobotModel, pcfg: PegConfig, offset: np.ndarray, tilt: np.ndarray,
              seed: int, peg_diameter: float | None, wrap: CellWrapper | None,
              record_dir: Path | None = None, index: int = 0, view: Any | None = None) -> Trial:
    profile = replace(load_profile(resolve(cfg.plant)), seed=seed)
    if peg_diameter is not None:
        profile = replace(profile, tool=replace(profile.tool, peg_diameter=peg_diameter))
        pcfg = replace(pcfg, peg_diameter_m=peg_diameter)  # the task knows the tool it holds
    nominal = np.asarray(cfg.scene.hole_center, float)
    # The fixture moves; the task still aims at the nominal hole (its belief), as on a real cell.
    scene = replace(cfg.scene, kind="peg", hole_center=list(nominal + offset))
    plant = Plant(resolve(cfg.robot.urdf), profile, scene, np.asarray(cfg.robot.home, float),
                  fixture_tilt=(float(tilt[0]), float(tilt[1])))
    holder = SimCell(plant=plant, arm=SimArm(plant, robot.limits), sensor=SimForceSensor(plant), clock="auto")
    try:
        cell = holder.open()
        if wrap is not None:
            cell = wrap(cell)
        task = PegInHoleTask(pcfg, robot, nominal, cfg.scene.table_height, cfg.loop.period_s,
                             np.asarray(cfg.robot.home, float))
        expect_touches(cell.force, task)  # the virtual sensor reads touches as in a run
        # The F/T sensor's readings, wherever it is (beside the virtual sensor, or in the loop): the peak force
        meter = _Tap(cell.ground_truth if cell.ground_truth is not None else cell.force, task)
        truth = meter if cell.ground_truth is not None else None
        force = cell.force if truth is not None else meter
        scored = _ScoredTask(task, truth, plant)
        recorder = Recorder(record_dir, cfg.recording.chunk_rows) if record_dir is not None else None
        loop = ControlLoop(cell.arm, force, scored, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s),
                           cell.ticker, recorder, cfg.loop.period_s, pcfg.max_duration_s,
                           cfg.loop.slow_cycle_fraction, ground_truth=truth,
                           guard=cell.guard_for(task, cfg.safety.max_tool_force_n),
                           on_row=view.row if view is not None else None)
        result = loop.run()
    finally:
        holder.close()
    raise_if_interrupted(result.outcome)  # Ctrl+C / SIGTERM ends the bench, not just this trial
    s = task.summary()
    if view is not None:
        view.event(f"outcome: {s['outcome']}" + (f" ({s['reason']})" if s.get("reason") else ""),
                   warn=s["outcome"] != "done")
    if recorder is not None and recorder.rows_written and record_dir is not None:
        _write_trial_rrd(record_dir, robot, cell.force.name, s)
    outcome = s["outcome"] if result.outcome in ("done", "failed") else result.outcome
    reason = s["reason"] or result.reason
    success = outcome == "done" and scored.true_depth >= pcfg.target_depth_m - 0.001
    axis_err = None
    if s.get("hole_axis") is not None:
        cos = float(np.clip(np.dot(np.asarray(s["hole_axis"]), scored._axis), -1.0, 1.0))
        axis_err = math.degrees(math.acos(cos))
    return Trial(
        offset_m=(float(offset[0]), float(offset[1])), tilt_deg=tuple(np.degrees(tilt).round(3).tolist()),
        outcome=outcome, reason=reason, success=success, insertion_time_s=s["insertion_time_s"],
        task_time_s=result.sim_time_s, true_depth_m=scored.true_depth, peak_force_n=meter.peak_force,
        peak_state=meter.peak_state,
        probes=s["probes"], realignments=s["realignments"],
        abs_err=wrench_abs_errors(scored.states, np.array(scored.virtual), np.array(scored.measured)),
        axis_error_deg=axis_err, index=index, recollided=plant.recollided,
        penetration=plant.penetration,
    )


@dataclass(frozen=True)
class TrialDraw:
    """One trial's draw: the fixture's offset (m) and tilt (rad), and the plant's noise seed."""

    index: int
    offset: np.ndarray
    tilt: np.ndarray
    seed: int


# Runs the draws (on worker processes, say) and yields their trials in any order.
TrialRunner = Callable[[list[TrialDraw]], Iterator[Trial]]


def trial_draws(trials: int, seed: int, max_offset_m: float, max_tilt_deg: float,
                only: list[int] | None = None) -> list[TrialDraw]:
    """The bench's draws, trial by trial from one generator (`only`: just those trials, the same draws)."""
    rng = np.random.default_rng(seed)
    draws = []
    for i in range(trials):
        offset = rng.uniform(-max_offset_m, max_offset_m, 2)
        tilt = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
        if only is None or i in only:
            draws.append(TrialDraw(i, offset, tilt, seed * 1000 + i))
    return draws


def bench_peg(cfg: CellConfig, robot: RobotModel, pcfg: PegConfig, trials: int, seed: int,
              max_offset_m: float = 0.002, max_tilt_deg: float = 2.0, peg_diameter: float | None = None,
              wrap: CellWrapper | None = None, force_source: str = "sensor", only: list[int] | None = None,
              record: Path | None = None, view: Any | None = None, runner: TrialRunner | None = None
              ) -> dict[str, Any]:
    """`trials` insertions with the hole offset uniformly in +-max_offset_m on x and y and tilted uniformly
    in +-max_tilt_deg about x and y (independently), each on a fresh plant: the same arm (the profile's
    specimen), its own noise seeded from `seed`.  `only` runs just those trial indices (same draws, to
    look at one again); `record` logs every trial run to `record`/trial_NNN (the `run` log format);
    `runner` runs the draws elsewhere (worker processes): each trial depends on its draw alone."""
    draws = trial_draws(trials, seed, max_offset_m, max_tilt_deg, only)
    results: list[Trial] = []
    wall0 = time.perf_counter()

    def here(draws: list[TrialDraw]) -> Iterator[Trial]:
        for d in draws:
            yield run_trial(cfg, robot, pcfg, d.offset, d.tilt, d.seed, peg_diameter, wrap,
                            record / f"trial_{d.index:03d}" if record is not None else None, index=d.index,
                            view=view)

    bar = tqdm(total=len(draws), desc="bench peg-in-hole", unit="trial")
    for tr in (runner or here)(draws):
        log.info("trial %d: %s in %s s (offset %s mm, tilt %s deg, %d probes, %d realignments) %s", tr.index,
                 "ok" if tr.success else "FAILED", tr.insertion_time_s, np.round(np.array(tr.offset_m) * 1e3, 2),
                 tr.tilt_deg, tr.probes, tr.realignments, tr.reason)
        results.append(tr)
        bar.update()
    results.sort(key=lambda r: r.index)
    bar.close()
    ok = [r for r in results if r.success]
    times = [r.insertion_time_s for r in ok if r.insertion_time_s is not None]
    err = np.concatenate([r.abs_err for r in results if r.abs_err.size]) if any(r.abs_err.size for r in results) \
        else np.zeros((0, 3))
    profile = load_profile(resolve(cfg.plant))
    deepest = [r.penetration.as_um() for r in results]  # per trial
    return {
        "trials": len(results),
        "seed": seed,
        "force_source": force_source,
        "peg_diameter_m": peg_diameter if peg_diameter is not None else profile.tool.peg_diameter,
        "hole_diameter_m": cfg.scene.hole_diameter,
        "hole_depth_m": cfg.scene.hole_depth,
        "max_offset_m": max_offset_m,
        "max_tilt_deg": max_tilt_deg,
        "success_rate": len(ok) / len(results) if results else None,
        "median_time_s": float(np.median(times)) if times else None,
        "max_time_s": float(np.max(times)) if times else None,
        "median_task_time_s": float(np.median([r.task_time_s for r in results])) if results else None,
        "peak_force_n": max((r.peak_force_n for r in results), default=None),
        "peak_force_state": max(results, key=lambda r: r.peak_force_n).peak_state if results else None,
        **{key: float(err[:, i].mean()) if err.size else None for i, key in enumerate(ERROR_KEYS)},
        "median_probes": float(np.median([r.probes for r in results])) if results else None,
        "max_axis_error_deg": max((r.axis_error_deg for r in results if r.axis_error_deg is not None),
                                  default=None),
        "max_realignments": max((r.realignments for r in results), default=None),
        # The plant's collision-detection failures, each re-solved (sim/plant.py Plant._physics_step).
        "recollided_steps": sum(r.recollided for r in results),
        # The deepest contact of any physics step; of side contacts (on a wall or the mouth's edge); of side
        # contacts in the bore, whose give widens the fit (its clearance must be far larger)
        **{key: max((um[key] for um in deepest), default=None) for key in Penetration().as_um()},
        "failure_kinds": count_kinds([(r.outcome, r.reason) for r in results if not r.success]),
        "per_trial": [{"trial": r.index, "success": r.success, "time_s": r.insertion_time_s,
                       "peak_force_n": round(r.peak_force_n, 1), "peak_state": r.peak_state,
                       "realignments": r.realignments, "probes": r.probes, "recollided_steps": r.recollided,
                       **{key: round(v, 2) for key, v in um.items()}}
                      for r, um in zip(results, deepest, strict=True)],
        "failures": [{"trial": r.index, "kind": failure_kind(r.outcome, r.reason),
                      "offset_mm": np.round(np.array(r.offset_m) * 1e3, 3).tolist(),
                      "tilt_deg": list(r.tilt_deg), "outcome": r.outcome, "reason": r.reason,
                      "true_depth_mm": round(r.true_depth_m * 1e3, 2)}
                     for r in results if not r.success],
        "wall_time_s": time.perf_counter() - wall0,
    }


def _write_trial_rrd(record_dir: Path, robot: RobotModel, force_source: str, summary: dict[str, Any]) -> None:
    """A recorded trial's Rerun copy beside its step log, as `run` keeps one."""
    try:
        from cell.view.rerun_view import write_rrd

        write_rrd(record_dir, read_log(record_dir), robot, {**summary, "force_source": force_source})
    except Exception as exc:  # the Rerun copy must never lose the trial's result
        log.error("could not write the Rerun recording of %s: %s", record_dir, exc)
