"""Identifies the tool's weight on the F/T sensor on a cell: static postures, the sensor averaged at rest, the fit."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cell.config import CellConfig
from cell.control.loop import Command, Observation
from cell.control.trajectory import JointMove
from cell.model.robot import RobotModel
from cell.sensing.tool_gravity import fit, gravity_direction, identification_postures, save
from tasks.runner import run_task

log = logging.getLogger(__name__)

SPEED_FRACTION = 0.2  # of the joint speed limits: the wrist turns slowly, the tool unloaded in free space
SETTLE_S = 0.6  # after a move: the servo and the tool at rest
MEAN_S = 0.4  # the sensor averaged over this at each rest


class ToolGravityTask:
    """Moves to each posture, rests, averages the F/T sensor's wrench there (the task's force source)."""

    name = "tool-gravity"

    def __init__(self, postures: list[np.ndarray], speed: np.ndarray, dt: float) -> None:
        self.postures, self.speed, self.dt = postures, speed, dt
        self.k = 0
        self.t = 0.0
        self.move: JointMove | None = None
        self.readings: list[np.ndarray] = []
        self.qs: list[np.ndarray] = []
        self._acc: list[np.ndarray] = []
        self.reason = ""

    @property
    def done(self) -> bool:
        return self.k >= len(self.postures) or bool(self.reason)

    @property
    def state_name(self) -> str:
        if self.done:
            return "done" if not self.reason else "failed"
        return "move" if self.move is None or self.t < self.move.duration + SETTLE_S else "measure"

    def step(self, obs: Observation) -> Command:
        target = self.postures[self.k]
        if self.move is None:
            self.move = JointMove(obs.q_cmd, target, self.speed)
            self.t = 0.0
        q = self.move.at(self.t)
        if self.t >= self.move.duration + SETTLE_S:
            w = obs.wrench.vector
            if np.all(np.isfinite(w)):
                self._acc.append(w)
            if self.t >= self.move.duration + SETTLE_S + MEAN_S:
                if not self._acc:
                    self.abort(f"no valid F/T reading at posture {self.k + 1}")
                else:
                    self.readings.append(np.mean(self._acc, axis=0))
                    self.qs.append(np.asarray(obs.state.q, float).copy())
                self._acc, self.move, self.k = [], None, self.k + 1
        self.t += self.dt
        return Command(q=q, log={"posture": float(self.k)})

    def abort(self, reason: str) -> None:
        self.reason = self.reason or reason

    def summary(self) -> dict[str, Any]:
        return {"task": self.name, "outcome": "failed" if self.reason else "done", "reason": self.reason,
                "postures": len(self.readings)}


def identify_tool_gravity(cfg: CellConfig, tool: str, robot: RobotModel, opener: Any, out_dir: Path) -> dict[str, Any]:
    """Run the identification on a cell opened by `opener()` (free space, the tool mounted, the F/T sensor as
    its force source), fit and save `tool_gravity.json` in `out_dir`; returns the fit's summary."""

    postures = identification_postures(robot, np.asarray(cfg.robot.home, float))
    task = ToolGravityTask(postures, robot.limits.velocity * SPEED_FRACTION, cfg.loop.period_s)
    holder = opener()
    try:
        cell = holder.open()
        out = run_task(task, cell, cfg, robot, max_duration_s=len(postures) * 10.0, record=False)
    finally:
        holder.close()
    if out["outcome"] != "done":
        return {"outcome": out["outcome"], "reason": out.get("reason", "")}
    tg = fit(np.array([gravity_direction(robot, q) for q in task.qs]), np.array(task.readings))
    path = save(tg, out_dir, {"tool": tool, "postures": len(task.qs)})
    log.info("tool gravity of the %s tool: %.3f kg at %s m (sensor frame), saved to %s", tool, tg.mass_kg,
             np.round(tg.com_m, 4).tolist(), path)
    return {"outcome": "done", "path": str(path), **tg.summary()}
