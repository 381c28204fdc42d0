"""`bench sim`: real-time factor of the plant plus controller in lock-step, measured on the wiping task."""

from __future__ import annotations

import time
from typing import Any

from cell.config import CellConfig, resolve
from cell.loop import ControlLoop
from cell.robot import load_robot
from cell.safety import SafetyMonitor
from sim.cell import make_sim_cell
from tasks.wipe import WipeTask, load_wipe_config


def bench_sim(cfg: CellConfig, seed: int | None = None, repeats: int = 2) -> dict[str, Any]:
    """Runs the whole wiping task (no recording) `repeats` times; RTF = simulated / wall seconds."""
    import numpy as np

    robot = load_robot(resolve(cfg.robot.urdf), cfg.robot.tcp_wipe, cfg.robot.tool_mass, cfg.robot.tool_com)
    wcfg = load_wipe_config(cfg.tasks.get("wipe"), f"{cfg.source}: tasks.wipe")
    sim_s, wall_s, outcomes, compute = 0.0, 0.0, [], []
    plant_step_s = 0.0
    for _ in range(repeats):
        holder = make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="table")
        cell = holder.open()
        task = WipeTask(wcfg, robot, cfg.scene.table_height, cfg.loop.period_s, np.asarray(cfg.robot.home))
        loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s),
                           cell.ticker, None, cfg.loop.period_s, wcfg.max_duration_s)
        result = loop.run()
        holder.close()
        sim_s += result.sim_time_s
        wall_s += result.wall_time_s
        outcomes.append(result.outcome)
        compute.append(result.timing.get("compute_ms_p50", float("nan")))
    # The plant alone, for the split between physics and controller.
    holder = make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="table")
    t0 = time.perf_counter()
    for _ in range(500):
        holder.plant.step()
    plant_step_s = (time.perf_counter() - t0) / 500
    return {
        "real_time_factor": sim_s / wall_s,
        "sim_seconds": sim_s,
        "wall_seconds": wall_s,
        "outcomes": outcomes,
        "controller_compute_ms_p50": float(np.mean(compute)),
        "plant_step_ms": plant_step_s * 1e3,
        "control_period_ms": cfg.loop.period_s * 1e3,
        "physics_substeps": holder.plant.substeps,
    }
