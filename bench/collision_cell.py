"""The collision bench's cell pieces: a streamed free motion, a payload error on the plant's tool, and the guard
given a settled, zeroed start."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from cell.collision.config import CollisionConfig, TaskContactSafety
from cell.collision.guard import build_guard
from cell.config import CellConfig
from cell.control.loop import Command, Observation, OpenCell
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from sim.plant import Plant


class StreamTask:
    """Streams joint targets (free motion)."""

    name = "free_motion"
    state_name = "move"

    def __init__(self, q: np.ndarray) -> None:
        self.q = q
        self.k = 0

    @property
    def done(self) -> bool:
        return self.k >= len(self.q)

    def step(self, obs: Observation) -> Command:
        q = self.q[min(self.k, len(self.q) - 1)]
        self.k += 1
        return Command(q=q)

    def abort(self, reason: str) -> None:
        self.k = len(self.q)

    def summary(self) -> dict[str, Any]:
        return {"outcome": "done"}


def set_payload_error(plant: Plant, kg: float, reset: bool = False) -> None:
    """The tool carries `kg` more (or less) than the controller's model says (any scene); `reset`: restart the
    plant at rest where it is, its servo holding the new weight from the first instant."""
    import mujoco

    m = plant.model
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "tool")
    m.body_mass[body] = max(0.01, float(m.body_mass[body]) + kg)
    mujoco.mj_setConst(m, plant.data)
    if reset:
        plant.reset(np.array(plant.true_state().q, float))


def bench_guard(cfg: CellConfig, model: LearnedModel, robot: RobotModel, reaction: str) -> Any:
    free = {"impact": TaskContactSafety(), "free_motion": TaskContactSafety()}  # no contact expected anywhere
    coll: CollisionConfig = dataclasses.replace(cfg.collision, enabled=True, reaction=reaction,  # type: ignore[arg-type]
                                                tasks=free)
    return build_guard(coll, model, robot, cfg.loop.period_s, "impact", cfg.safety.max_tool_force_n,
                       np.asarray(cfg.virtual_sensor.wrench_point, float))


def settled_guard(cfg: CellConfig, model: LearnedModel, robot: RobotModel, reaction: str, cell: OpenCell,
                   plant: Plant, settled: Callable[[], None] | None = None) -> Any:
    """Let the arm settle at rest (0.3 s), call `settled` (zero a sensor), then give a fresh guard
    0.15 s of the resting arm and zero its residual there."""
    for _ in range(int(0.3 / cfg.loop.period_s)):
        cell.ticker.wait()
    if settled is not None:
        settled()
    guard = bench_guard(cfg, model, robot, reaction)
    for _ in range(int(0.15 / cfg.loop.period_s)):
        guard.detector.update(plant.measured_state())
        cell.ticker.wait()
    guard.rebias()
    return guard
