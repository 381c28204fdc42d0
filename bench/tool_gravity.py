"""The tool's gravity compensation on the simulated F/T sensor: fit on static poses, scored on other random ones."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from cell.config import CellConfig
from cell.model.robot import RobotModel
from cell.sensing.tool_gravity import fit, gravity_direction
from sim.cell import make_plant

log = logging.getLogger(__name__)

WRIST_RANGE_RAD = np.radians([30.0, 30.0, 30.0, 100.0, 100.0, 150.0])  # +- about home: the tool turned widely
SETTLE_STEPS = 40  # 0.32 s at 125 Hz: the servo and the pad spring at rest
MEAN_STEPS = 25  # averaged readings per pose (the sensor's noise down by 5)
FREE_FORCE_TARGET_N = 0.5  # target: |F| in free space after compensation, over 9 random orientations


def random_postures(robot: RobotModel, home: np.ndarray, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """`n` postures about `home` with the tool turned widely, within the joint limits."""
    lim = robot.limits
    out: list[np.ndarray] = []
    while len(out) < n:
        q = np.clip(home + rng.uniform(-1.0, 1.0, robot.n) * WRIST_RANGE_RAD, lim.lower + 0.05, lim.upper - 0.05)
        if robot.tcp_pose(q).translation[2] > 0.25:  # clear of the base and the floor
            out.append(q)
    return out


def static_reading(plant: Any, q: np.ndarray) -> np.ndarray:
    """The sensor's mean reading with the arm held still at q."""
    plant.reset(q)
    plant.set_target(q)
    for _ in range(SETTLE_STEPS):
        plant.step()
    readings = []
    for _ in range(MEAN_STEPS):
        plant.step()
        readings.append(plant.sensor_reading())
    return np.mean(readings, axis=0)


def bench_tool_gravity(cfg: CellConfig, robot: RobotModel, tool: str, poses: int = 9, seed: int = 0) -> dict[str, Any]:
    """Fit the tool's weight on `poses` random static orientations, then tare at home and read `poses` other
    random orientations: |F| and |M| before and after compensation."""
    rng = np.random.default_rng(seed)
    plant = make_plant(cfg, seed, "free", tool=tool)
    home = np.asarray(cfg.robot.home, float)
    fit_q = random_postures(robot, home, poses, rng)
    us = np.array([gravity_direction(robot, q) for q in fit_q])
    tg = fit(us, np.array([static_reading(plant, q) for q in fit_q]))
    tare = static_reading(plant, home)  # a task's tare: the weight at home becomes the zero
    u_tare = gravity_direction(robot, home)
    before, after = [], []
    for q in random_postures(robot, home, poses, rng):
        w = static_reading(plant, q) - tare
        before.append(w)
        after.append(tg.compensate(w, gravity_direction(robot, q), u_tare))
    b, a = np.asarray(before), np.asarray(after)
    return {
        "tool": tool, "poses": poses, "seed": seed, **tg.summary(),
        "robot_tool_mass_kg": float(robot.tool.mass),  # the config's, for the arm's dynamics (sensor included)
        "free_force_max_before_n": float(np.max(np.linalg.norm(b[:, :3], axis=1))),
        "free_force_max_after_n": float(np.max(np.linalg.norm(a[:, :3], axis=1))),
        "free_moment_max_before_nm": float(np.max(np.linalg.norm(b[:, 3:], axis=1))),
        "free_moment_max_after_nm": float(np.max(np.linalg.norm(a[:, 3:], axis=1))),
    }


def bench_tools(cfg: CellConfig, robots: dict[str, RobotModel], poses: int, seed: int) -> dict[str, Any]:
    """Both tools; passed when every compensated free-space force stays within FREE_FORCE_TARGET_N."""
    per_tool = {tool: bench_tool_gravity(cfg, robot, tool, poses, seed) for tool, robot in robots.items()}
    worst = max(r["free_force_max_after_n"] for r in per_tool.values())
    return {"poses": poses, "seed": seed, "target_n": FREE_FORCE_TARGET_N, "free_force_max_after_n": worst,
            "passed": worst <= FREE_FORCE_TARGET_N, **per_tool}
