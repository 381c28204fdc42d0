"""`main.py plan`: plan each path with the baseline and the time-optimal planner, execute both on the cell,
tighten and re-plan where a measured torque exceeds its limit, and report the time saved."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cell.config import CellConfig  # noqa: E402
from cell.control.loop import OpenCell  # noqa: E402
from cell.control.signals import raise_if_interrupted
from cell.data.recorder import read_log  # noqa: E402
from cell.model.robot import RobotModel  # noqa: E402
from cell.planning.baselines import PLANNERS
from cell.planning.config import PlannerConfig
from cell.planning.constraints import ToppraTerms
from cell.planning.planner import PlanningError, TimedTrajectory, TorqueFn  # noqa: E402
from drivers.configio import load_dataclass, read_yaml, require  # noqa: E402
from tasks.runner import run_task  # noqa: E402
from tasks.setup.play import PlayTask  # noqa: E402

log = logging.getLogger(__name__)


@dataclass
class PlanFile:
    """config/plans.yaml: planner settings and named paths of waypoints in degrees."""

    planner: PlannerConfig = field(default_factory=PlannerConfig)
    paths: dict[str, list[list[float]]] = field(default_factory=dict)
    max_validation_rounds: int = 5
    # Free-space moves in a guarded cell are faster than force tasks: the cell's TCP speed limit is
    # raised to this for the plan runs (the joint speed and torque limits are not touched).
    max_tcp_speed: float = 2.5
    # The first validation run of each plan is planned to this share of the planning limit (see
    # plan_and_validate); later runs use the measured model error.
    first_run_torque_scale: float = 0.8

    def validate(self, where: str) -> None:
        require(bool(self.paths), f"{where} paths", "must name at least one path")
        require(0 < self.max_tcp_speed <= 5.0, f"{where} max_tcp_speed", "must lie in (0, 5] m/s")
        require(0.3 <= self.first_run_torque_scale <= 1.0, f"{where} first_run_torque_scale", "must lie in [0.3, 1]")
        require(1 <= self.max_validation_rounds <= 20, f"{where} max_validation_rounds", "must lie in [1, 20]")
        for name, pts in self.paths.items():
            require(len(pts) >= 2, f"{where} paths.{name}", "needs at least a start and an end")
            for i, p in enumerate(pts):
                require(len(p) == 6, f"{where} paths.{name}[{i}]", f"must have 6 joint angles (deg), got {len(p)}")


def load_plan_file(path: Path) -> PlanFile:
    """The plan file; the planner bounds the TCP speed by the plan runs' stop (`max_tcp_speed`) unless the
    file sets `planner.tcp_speed_limit` itself."""
    plan_file = load_dataclass(PlanFile, read_yaml(path), f"{path}:")
    if plan_file.planner.tcp_speed_limit <= 0:
        plan_file.planner = replace(plan_file.planner, tcp_speed_limit=plan_file.max_tcp_speed)
    return plan_file


def parse_waypoints(text: str) -> list[list[float]]:
    """'0,0,90,0,90,0; 30,10,60,0,90,0' (degrees, ';' between waypoints)."""
    try:
        pts = [[float(v) for v in row.split(",")] for row in text.split(";") if row.strip()]
    except ValueError:
        raise PlanningError(f"--waypoints: cannot read '{text}': use 'j1,...,j6; j1,...,j6' in degrees") from None
    if len(pts) < 2 or any(len(p) != 6 for p in pts):
        raise PlanningError("--waypoints: give at least 2 waypoints of 6 joint angles (degrees), ';'-separated")
    return pts


@dataclass
class Execution:
    traj: TimedTrajectory
    outcome: str
    elapsed_s: float | None
    peak_tau: np.ndarray
    run_dir: str | None
    rounds: int
    stops: int = 0  # validation runs that ended in a safety stop


def measured_peak(run_dir: str | None, n: int) -> np.ndarray:
    """Peak |measured joint torque| while the trajectory played, from the run's recording (which also
    holds the sample that tripped a safety stop)."""
    if not run_dir:
        return np.full(n, np.nan)
    d = read_log(Path(run_dir)).to_pydict()
    states = np.asarray(d["state"])
    sel = ~np.isin(states, ["move_to_start", "settle"])
    if not sel.any():
        return np.full(n, np.nan)
    return np.max(np.abs(np.column_stack([np.asarray(d[f"tau{j + 1}"])[sel] for j in range(n)])), axis=0)


def execute(
    traj: TimedTrajectory, cfg: CellConfig, robot: RobotModel, open_cell: Callable[[], tuple[OpenCell, Any]],
) -> dict[str, Any]:
    cell, holder = open_cell()
    try:
        task = PlayTask(traj, cfg.loop.period_s, robot.limits.velocity)
        return run_task(task, cell, cfg, robot, max_duration_s=60.0, record=True)
    finally:
        holder.close()


def plan_and_validate(
    name: str,
    waypoints_deg: list[list[float]],
    planner_name: str,
    cfg: CellConfig,
    robot: RobotModel,
    torque_fn: TorqueFn,
    pcfg: PlannerConfig,
    open_cell: Callable[[], tuple[OpenCell, Any]],
    collisions: Any,
    rounds: int,
    terms: ToppraTerms | None = None,
    first_scale: float = 0.8,
) -> Execution:
    """Plan, execute, measure, correct, re-plan.

    The first run is planned to `first_scale` x the planning limit: the model is least trusted where
    it has not been checked (a time-optimal plan accelerates harder than any training motion), and a
    saturated motor on the first try is a safety stop on a real arm.  Each run measures, per joint,
    how much torque the plant needed against the model's prediction (`factor`); the next plan bounds
    the model's torque by planning limit / factor, so it is as fast as the measured model error
    allows.  It stops when a run was within the limits and the corrected plan would not be faster; a
    run that exceeds a limit is tightened (never kept), and the fastest run within the limits is the result.
    """
    planner = PLANNERS[planner_name](robot, torque_fn, pcfg, collisions, terms)
    w = np.radians(np.asarray(waypoints_deg, float))
    effort = robot.limits.effort
    scale = np.full(robot.n, first_scale)
    good = np.zeros(robot.n)  # per joint: the largest scale that ran within the limits
    bad = np.full(robot.n, np.inf)  # and the smallest that did not
    max_step = 0.1
    best: Execution | None = None
    last: Execution | None = None
    stops = 0
    for r in range(1, rounds + 1):
        try:
            traj = planner.plan(w, scale)
        except PlanningError as exc:
            if last is None:
                raise
            # Tightening for the model's error has made the path infeasible: keep what ran.
            log.warning("%s/%s: re-plan %d impossible (%s); keeping the best run", name, planner_name, r, exc)
            break
        if (last is not None and last.outcome == "done"
                and traj.duration > last.traj.duration - 0.5 * pcfg.sample_period_s):
            break  # the last run was within the limits and the correction buys no time: done
        summary = execute(traj, cfg, robot, open_cell)
        raise_if_interrupted(summary["outcome"])  # Ctrl+C ends `plan`, not just this validation run
        peak = measured_peak(summary.get("run_dir"), robot.n)
        ratio = peak / effort
        ok = summary["outcome"] == "done" and bool(np.all(ratio <= 1.0))
        stops += summary["outcome"] != "done"
        log.info("%s/%s round %d: planned %.3f s, executed %s s, peak torque ratio %.3f (%s)", name, planner_name,
                 r, traj.duration, summary.get("elapsed_s"), float(np.nanmax(ratio)), summary["outcome"])
        last = Execution(traj, summary["outcome"] if ok else "limit_exceeded", summary.get("elapsed_s"),
                         peak, summary.get("run_dir"), r, stops)
        if ok and (best is None or (last.elapsed_s or np.inf) < (best.elapsed_s or np.inf)):
            best = last
        # Per joint: the plant's torque over the model's, where the joint was loaded enough to tell.
        planning_limit = planner.torque_limit()
        predicted = np.max(np.abs(torque_fn(traj.q, traj.dq, traj.ddq)), axis=0)
        factor = peak / np.maximum(predicted, 1e-6)
        loaded = predicted > 0.3 * planning_limit
        if not ok:
            factor = np.where(peak >= 0.99 * effort, factor * 1.5, factor)  # a clamped reading: it needed more
        # The model may use the whole planning limit only where it has been shown not to under-predict.  A joint
        # too lightly loaded to measure its factor keeps its scale, unless the plant needed less than half its
        # planning limit there: then it may rise by a step (a joint cut hard after a stop, say as the arm left
        # rest, would otherwise stay below the "loaded" threshold and hold every later plan back).
        idle = np.where(peak < 0.5 * planning_limit, scale + max_step, scale) if ok else np.ones(robot.n)
        wanted = np.where(loaded, np.minimum(1.0, 0.98 / np.maximum(factor, 1e-6)), np.minimum(idle, 1.0))
        # The error grows with the accelerations, so a factor measured on a slower run is optimistic for
        # a faster one: speed up by at most `max_step` per round and never past half-way to a scale that
        # has already exceeded a limit (bisection between the known-good and the known-bad scale).
        if ok:
            good = np.maximum(good, scale)
            nxt = np.clip(wanted, scale, scale + max_step)
            scale = np.where(np.isfinite(bad), np.minimum(nxt, 0.5 * (good + bad)), nxt)
        else:
            over = peak >= 0.99 * cfg.safety.joint_torque_fraction * effort
            over = over if over.any() else ratio >= np.nanmax(ratio)  # stopped for another reason: the worst joint
            bad = np.where(over, np.minimum(bad, scale), bad)
            # A joint that reached the stop is tightened by its measured error even where its predicted peak
            # was too small to count as loaded: a stop is evidence, and left at its scale the same plan would
            # run again (a steep start under a model that under-predicts).
            cut = np.minimum(1.0, 0.98 / np.maximum(factor, 1e-6))
            scale = np.where(over, np.where(good > 0, 0.5 * (good + scale), np.minimum(cut, scale)), scale)
    assert last is not None  # the first round either ran or raised
    result = best or last  # the fastest run within the limits, else the last attempt
    result.rounds, result.stops = last.rounds, stops
    return result


def run_plans(
    cfg: CellConfig,
    robot: RobotModel,
    torque_fn: TorqueFn,
    model_name: str,
    plan_file: PlanFile,
    open_cell: Callable[[], tuple[OpenCell, Any]],
    collisions: Any,
    out_dir: Path,
    only: list[str] | None = None,
    terms: ToppraTerms | None = None,
) -> dict[str, Any]:
    results: dict[str, Any] = {}
    out_dir.mkdir(parents=True, exist_ok=True)
    names = only or list(plan_file.paths)
    for name in names:
        pts = plan_file.paths[name]
        base = plan_and_validate(name, pts, "uniform", cfg, robot, torque_fn, plan_file.planner, open_cell,
                                 collisions, plan_file.max_validation_rounds, terms, plan_file.first_run_torque_scale)
        opt = plan_and_validate(name, pts, "toppra", cfg, robot, torque_fn, plan_file.planner, open_cell,
                                collisions, plan_file.max_validation_rounds, terms, plan_file.first_run_torque_scale)
        effort = robot.limits.effort
        improvement = None
        if base.elapsed_s and opt.elapsed_s:
            improvement = 100.0 * (1.0 - opt.elapsed_s / base.elapsed_s)
        results[name] = {
            "baseline_s": base.elapsed_s,
            "optimized_s": opt.elapsed_s,
            "baseline_planned_s": base.traj.duration,
            "optimized_planned_s": opt.traj.duration,
            "improvement_vs_uniform_pct": improvement,
            "baseline_outcome": base.outcome,
            "optimized_outcome": opt.outcome,
            "max_torque_ratio": float(np.nanmax(np.concatenate([base.peak_tau / effort, opt.peak_tau / effort]))),
            "peak_torque_ratio_per_joint": (opt.peak_tau / effort).round(3).tolist(),
            "plan_time_s": opt.traj.plan_time_s,
            "planner_iterations": opt.traj.iterations,
            "validation_rounds": opt.rounds,
            "validation_safety_stops": base.stops + opt.stops,
            "runs": [base.run_dir, opt.run_dir],
        }
        plot_path = out_dir / f"{name}.png"
        plot_torques(name, base, opt, robot, torque_fn, plot_path)
        results[name]["plot"] = str(plot_path)
    imp = [r["improvement_vs_uniform_pct"] for r in results.values()]
    return {
        "model": model_name,
        "paths": results,
        "min_improvement_vs_uniform_pct": min(imp) if imp and all(v is not None for v in imp) else None,
        "mean_improvement_vs_uniform_pct": float(np.mean(imp)) if imp and all(v is not None for v in imp) else None,
        "max_torque_ratio": max(r["max_torque_ratio"] for r in results.values()),
        "max_plan_time_s": max(r["plan_time_s"] for r in results.values()),
        "paper_improvement_vs_original_pct": [24.7, 15.3, 21.3],
    }


def plot_torques(name: str, base: Execution, opt: Execution, robot: RobotModel, torque_fn: TorqueFn,
                 path: Path) -> None:
    """Measured (and predicted) joint torques against the limits, baseline vs optimised."""
    effort = robot.limits.effort
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=False)
    for ex, color, label in ((base, "tab:blue", "baseline"), (opt, "tab:red", "time-optimal")):
        measured = None
        if ex.run_dir:
            d = read_log(Path(ex.run_dir)).to_pydict()
            states = np.asarray(d["state"])
            sel = np.isin(states, ["play", "arrive"])
            if sel.any():
                t = np.asarray(d["t"])[sel]
                measured = (t - t[0], np.column_stack([np.asarray(d[f"tau{j + 1}"])[sel] for j in range(6)]))
        predicted = torque_fn(ex.traj.q, ex.traj.dq, ex.traj.ddq)
        for j, ax in enumerate(axes.flat):
            if measured is not None:
                ax.plot(measured[0], measured[1][:, j], color=color, lw=1, label=f"{label} measured")
            ax.plot(ex.traj.t, predicted[:, j], color=color, lw=1, ls="--", alpha=0.7, label=f"{label} predicted")
    for j, ax in enumerate(axes.flat):
        ax.axhline(effort[j], color="k", lw=0.8)
        ax.axhline(-effort[j], color="k", lw=0.8)
        ax.set_title(f"joint {j + 1} (limit {effort[j]:.0f} N·m)")
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
    axes.flat[0].set_ylabel("torque [N·m]")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"{name}: baseline {base.elapsed_s or float('nan'):.3f} s vs time-optimal "
                 f"{opt.elapsed_s or float('nan'):.3f} s")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
