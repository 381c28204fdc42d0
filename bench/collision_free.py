"""The collision bench's free motion: the cell's own moves, plans and tasks with a payload error, where every
detection is a false alarm."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from bench.collision_cell import StreamTask, set_payload_error, settled_guard
from bench.collision_plans import BenchPlanners, max_tcp_speed, plan_stream, planning_paths, time_optimal_stream
from cell.config import CellConfig
from cell.control.loop import ControlLoop
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.moves import random_moves
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from sim.cell import make_sim_cell

log = logging.getLogger(__name__)

# Of the free motion: time-optimal moves from rest between random poses, and the plans `bench planning` makes
# (time-optimal on the model, kinematic, PPO) on its own kind of paths; the rest is random moves.
TIME_OPTIMAL_SHARE = 0.15
PLANS_SHARE = 0.25
PLAN_KINDS = ("model", "kinematic", "ppo")
FREE_TASKS = ("wipe", "peg-in-hole")  # the tasks' own motions, run once each with a payload error
# Runs a task on the simulated cell with the guard recording only: (task, seed, payload error [kg]) -> its summary.
TaskRun = Callable[[str, int, float], dict[str, Any]]


@dataclass
class FreeMotion:
    """What the free motion saw: false alarms, the largest residual/threshold by kind of motion, the seconds
    played, and the chunks that ended before their end (a safety limit: their remainder was not watched)."""

    alarms: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    max_ratio: dict[str, float] = dataclasses.field(default_factory=dict)
    max_at: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)  # where each kind's largest was
    played_s: float = 0.0
    cut_short: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    chunk: int = 0

    def add(self, kind: str, error: float, guard_stats: dict[str, Any], seconds: float, outcome: str,
            reason: str) -> None:
        for d in guard_stats.get("detections", []):
            self.alarms.append({"chunk": self.chunk, "motion": kind, "payload_error_kg": round(error, 3), **d})
        ratio = float(guard_stats.get("max_free_ratio", 0.0))
        if ratio >= self.max_ratio.get(kind, 0.0):
            self.max_ratio[kind] = ratio
            self.max_at[kind] = {"chunk": self.chunk, "payload_error_kg": round(error, 3),
                                 **guard_stats.get("max_free_at", {})}
        self.played_s += seconds
        if outcome != "done":
            log.warning("free motion chunk %d (%s) ended %s: %s", self.chunk, kind, outcome, reason)
            self.cut_short.append({"chunk": self.chunk, "motion": kind, "outcome": outcome, "reason": reason})
        self.chunk += 1

    def summary(self) -> dict[str, Any]:
        by_kind = {k: round(v, 3) for k, v in self.max_ratio.items()}
        return {"seconds": round(self.played_s, 1), "alarms": self.alarms,
                "max_ratio": max(by_kind.values(), default=0.0), "max_ratio_by_kind": by_kind,
                "max_ratio_at": self.max_at, "max_ratio_time_optimal": by_kind.get("time_optimal"),
                "cut_short": self.cut_short}


def _play(cfg: CellConfig, robot: RobotModel, model: LearnedModel, q: np.ndarray, seed: int, error: float,
          tool: str, start: np.ndarray | None = None) -> tuple[dict[str, Any], float, str, str]:
    """Stream `q` on a fresh simulated cell from rest at `start` (default q[0]), the guard recording only; (guard
    summary, seconds played, outcome, reason)."""
    dt = cfg.loop.period_s
    holder = make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="obstacle", tool=tool)
    set_payload_error(holder.plant, error)
    holder.plant.reset(q[0] if start is None else start)
    cell = holder.open()
    try:
        guard = settled_guard(cfg, model, robot, "monitor", cell, holder.plant)
        loop = ControlLoop(cell.arm, cell.force, StreamTask(q), SafetyMonitor(cfg.safety, robot, dt),
                           cell.ticker, None, dt, len(q) * dt + 1.0, guard=guard)
        result = loop.run()
    finally:
        holder.close()
    raise_if_interrupted(result.outcome)
    return guard.summary(), result.cycles * dt, result.outcome, result.reason


def run_free_motion(cfg: CellConfig, robot: RobotModel, model: LearnedModel, seconds: float, seed: int,
                    chunk_s: float = 120.0, tool: str = "peg", planners: BenchPlanners | None = None,
                    task_run: TaskRun | None = None, task_cfg: CellConfig | None = None) -> dict[str, Any]:
    """The cell's own motion, each chunk with a payload error of its own; every detection is a false alarm (the
    guard only records them):

    * random point-to-point moves at the cell's full allowed speed;
    * time-optimal moves from rest between random poses, as `plan` makes them (TIME_OPTIMAL_SHARE);
    * with `planners`: the plans `bench planning` makes on its paths, each path by each of its model, kinematic and
      PPO planners, each from rest (PLANS_SHARE; without them that share is time-optimal moves too);
    * with `task_run`: one run of each task in FREE_TASKS (their approach, contact and retreat motions; in their
      contact states the guard holds the fast force to the task's contact limit), beyond `seconds`."""
    dt = cfg.loop.period_s
    rng = np.random.default_rng(seed + 7919)
    free = FreeMotion()
    plans_s = seconds * PLANS_SHARE if planners is not None else 0.0
    optimal_s = seconds * TIME_OPTIMAL_SHARE + (seconds * PLANS_SHARE if planners is None else 0.0)
    random_s = seconds - plans_s - optimal_s
    fast_cfg = dataclasses.replace(cfg, safety=dataclasses.replace(
        cfg.safety, max_tcp_speed=max(cfg.safety.max_tcp_speed, max_tcp_speed())))
    with tqdm(total=round(seconds), unit="sim s", desc="free motion", leave=False) as bar:
        scheduled = 0.0  # the planned seconds so far (a chunk cut short still advances the schedule)
        while scheduled < random_s + optimal_s - 1e-9:
            kind = "random" if scheduled < random_s - 1e-9 else "time_optimal"
            want = min(chunk_s, (random_s if kind == "random" else random_s + optimal_s) - scheduled)
            if want < 1.0:  # a remainder too short for a move: the next kind of motion
                scheduled += want
                continue
            if kind == "random":
                plan = random_moves(robot, cfg, ExcitationConfig(), dt, 1, max(2, int(want / 2.0)), [1.0],
                                    seed=seed * 1000 + free.chunk)
                q = np.vstack([s.q for s in plan.segments])[: int(round(want / dt))]
                start, run_cfg = plan.start, cfg
            else:
                q = time_optimal_stream(robot, cfg, model, want, seed * 1000 + free.chunk)
                start, run_cfg = q[0], fast_cfg
            if len(q) < 2:
                scheduled += want
                continue
            error = float(rng.uniform(-0.5, 0.5))
            stats, played, outcome, reason = _play(run_cfg, robot, model, q, seed + free.chunk, error, tool, start)
            free.add(kind, error, stats, played, outcome, reason)
            scheduled += len(q) * dt
            bar.update(round(len(q) * dt))
        if planners is not None and plans_s > 0:
            paths = planning_paths(planners, cfg, max(3, int(plans_s / 4.0)), seed)
            planned = 0.0
            for name, w in paths:
                for kind in PLAN_KINDS:
                    planner, scale = planners.planners[kind]
                    planned_q = plan_stream(planner, scale, w, dt)
                    if planned_q is None:
                        continue
                    q = planned_q
                    error = float(rng.uniform(-0.5, 0.5))
                    stats, played, outcome, reason = _play(fast_cfg, robot, model, q, seed + free.chunk, error, tool)
                    free.add(f"plan_{kind}", error, stats, played, outcome, f"{name}: {reason}" if reason else reason)
                    planned += len(q) * dt
                    bar.update(round(len(q) * dt))
                if planned >= plans_s:
                    break
    if task_run is not None:
        for name in FREE_TASKS:
            error = float(rng.uniform(-0.5, 0.5))
            out = task_run(name, seed * 1000 + free.chunk, error)
            raise_if_interrupted(str(out.get("outcome")))
            free.add(f"task_{name}", error, out.get("collision") or {}, float(out.get("sim_time_s", 0.0)),
                     str(out.get("outcome")), str(out.get("reason", "")))
    return free.summary()
