"""Benchmarks: the simulated cell's real-time factor and the wire drivers' cycle times over loopback."""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

import numpy as np

from cell.config import CellConfig
from cell.control.loop import ControlLoop
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.model.specs import cell_robot
from drivers.interfaces import JointLimits
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.modbus import TM5ModbusArm
from drivers.tm5.registers import N_JOINTS
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor
from sim.cell import make_sim_cell
from sim.kinematic_plant import KinematicPlant
from sim.tm5_emulator import TM5Emulator
from sim.wacoh_emulator import WacohEmulator
from tasks.wipe import WipeTask, load_wipe_config


def bench_sim(cfg: CellConfig, seed: int | None = None, repeats: int = 2) -> dict[str, Any]:
    """Runs the whole wiping task (no recording) `repeats` times; RTF = simulated / wall seconds."""
    robot = cell_robot(cfg)
    wcfg = load_wipe_config(cfg.tasks.get("wipe"), f"{cfg.source}: tasks.wipe")
    sim_s, wall_s, outcomes, compute = 0.0, 0.0, [], []
    plant_step_s = 0.0
    in_task = {"plant_s": 0.0, "periods": 0}
    rtfs = []
    cpu_s = 0.0
    for _ in range(repeats):
        holder = make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="table")
        step = holder.plant.step

        def timed_step(step: Any = step) -> None:
            t0 = time.perf_counter()
            step()
            in_task["plant_s"] += time.perf_counter() - t0
            in_task["periods"] += 1

        holder.plant.step = timed_step  # type: ignore[method-assign]
        cell = holder.open()
        task = WipeTask(wcfg, robot, cfg.scene.table_height, cfg.loop.period_s, np.asarray(cfg.robot.home))
        loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s),
                           cell.ticker, None, cfg.loop.period_s, wcfg.max_duration_s)
        cpu0 = time.process_time()
        result = loop.run()
        cpu_s += time.process_time() - cpu0
        holder.close()
        raise_if_interrupted(result.outcome)  # a cut-short run would report a real-time factor of part of it
        sim_s += result.sim_time_s
        wall_s += result.wall_time_s
        rtfs.append(result.sim_time_s / result.wall_time_s)
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
        # The plant's share inside the task (contact, friction, the wiping head), per control period.
        "plant_in_task_ms": 1e3 * in_task["plant_s"] / max(1, in_task["periods"]),
        "real_time_factor_per_repeat": rtfs,
        # Simulated seconds per CPU second of this process: what the wall-clock figure would be with a core
        # to itself (on a shared machine the wall clock also counts other processes' turns).
        "real_time_factor_cpu": sim_s / cpu_s if cpu_s > 0 else float("nan"),
        "cpu_seconds": cpu_s,
        "control_period_ms": cfg.loop.period_s * 1e3,
        "physics_substeps": holder.plant.substeps,
    }


def bench_modbus(n: int = 500, period_s: float | None = None, timeout_s: float = 0.01) -> dict[str, float | int]:
    """Time `n` cycles of read_state + send_target against the local emulator (KinematicPlant).

    `period_s=None` runs the cycles back to back (pure communication cost); a period paces them like the
    control loop.  `timeout_s`: the driver's reply deadline (the cell's default; a reply later than it ends the
    bench as a lost link would end a run).  Returns median and 99th percentile of the cycle time in ms.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    plant = KinematicPlant()
    limits = JointLimits(lower=np.full(N_JOINTS, -2 * np.pi), upper=np.full(N_JOINTS, 2 * np.pi),
                         velocity=np.full(N_JOINTS, np.pi), effort=np.full(N_JOINTS, 150.0))
    times: list[float] = []
    with TM5Emulator(plant) as emu:
        arm = TM5ModbusArm(TM5ModbusConfig(host="127.0.0.1", port=emu.port, timeout_s=timeout_s), limits, plant.dt)
        with arm:
            arm.arm()
            q0 = arm.read_state().q
            for i in range(n):
                t0 = time.perf_counter()
                arm.read_state()
                arm.send_target(q0 + 0.05 * math.sin(2 * math.pi * i / 250))
                times.append(time.perf_counter() - t0)
                if period_s is not None:
                    time.sleep(max(0.0, period_s - (time.perf_counter() - t0)))
    ms = sorted(t * 1000.0 for t in times)
    p99 = ms[min(len(ms) - 1, math.ceil(0.99 * len(ms)) - 1)]
    return {"modbus_cycle_median_ms": statistics.median(ms), "modbus_cycle_p99_ms": p99, "n": n}


def bench_serial(n: int = 500) -> dict[str, float | int]:
    """Time n polled reads (`R` -> parsed Wrench) against the emulator on a pseudo-terminal."""
    load = np.array([1.0, -2.0, 30.0, 0.1, -0.05, 0.02])
    with WacohEmulator(lambda: load, seed=0) as emulator:
        sensor = WacohSensor(WacohConfig(port=emulator.tty_path))
        with sensor:
            for _ in range(20):  # warm-up: first reads pay for imports and caches
                sensor.read()
            times: list[float] = []
            for _ in range(n):
                t0 = time.perf_counter()
                sensor.read()
                times.append(time.perf_counter() - t0)
    ms = sorted(1e3 * t for t in times)
    return {
        "serial_read_median_ms": statistics.median(ms),
        "serial_read_p99_ms": ms[min(len(ms) - 1, math.ceil(0.99 * len(ms)) - 1)],
        "n": n,
    }


def bench_drivers(n: int = 500) -> dict[str, Any]:
    """`main.py bench drivers`: one Modbus state read + target write, and one serial `R` to a parsed wrench."""
    return {**bench_modbus(n), **bench_serial(n)}
