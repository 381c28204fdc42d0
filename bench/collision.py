"""`main.py bench collision`: scripted impacts on rigid and soft obstacles, and free motion at full speed
for false alarms, on the simulated cell with the collision detector of the hybrid model."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
from tqdm import tqdm

from bench.collision_plans import max_tcp_speed, time_optimal_stream
from cell.collision.guard import build_guard
from cell.config import CellConfig, CollisionConfig, TaskContactSafety
from cell.control.loop import Command, ControlLoop, Observation, OpenCell
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.moves import random_moves
from cell.model.dynamics.learned import LearnedModel
from cell.model.robot import RobotModel
from cell.sensing.ft_source import SensorForceSource
from drivers.interfaces import ArmState, Wrench
from sim.cell import make_sim_cell
from sim.mjcf import OBSTACLE_PLATE_KG
from sim.obstacle import Obstacle
from sim.plant import Plant

log = logging.getLogger(__name__)

SPEED_RANGE = (0.05, 0.5)  # m/s at the impact
SOFT_STIFFNESS = (10e3, 75e3)  # N/m: ISO/TS 15066's body-region spring constants span about this
SOFT_DAMPING_RATIO = 0.2
ACCEL = 2.5  # m/s^2: the scripted motion reaches its speed before the plate
HOLD_AFTER_S = 0.3  # the plant runs on, held, after a stop: the peak may come after the detection
REACH = (np.array([0.30, -0.35, 0.22]), np.array([0.55, 0.20, 0.50]))  # start TCP positions [m]
MAX_TILT = np.radians(30.0)
BEYOND_M = 0.05  # the scripted line runs this far past the plate's face
TIME_OPTIMAL_SHARE = 0.25  # of the free motion: time-optimal moves from rest (what `plan` runs)


@dataclass
class ImpactDraw:
    q0: np.ndarray
    rotation: np.ndarray
    p0: np.ndarray
    direction: np.ndarray
    speed: float
    stiffness: float | None  # None: rigid
    payload_error_kg: float

    @property
    def gap(self) -> float:
        return self.speed**2 / ACCEL + 0.01  # the ramp's distance (v * t_ramp / 2) and 10 mm at speed


class LineTask:
    """Moves the TCP along a straight line with a trapezoidal speed profile (the scripted impact)."""

    name = "impact"
    state_name = "approach"

    def __init__(self, robot: RobotModel, draw: ImpactDraw, dt: float) -> None:
        self.robot, self.draw, self.dt = robot, draw, dt
        self.length = draw.gap + BEYOND_M
        self.t = 0.0
        self.q = draw.q0.copy()
        self._done = False
        self.reason = ""

    @property
    def done(self) -> bool:
        return self._done

    def _s(self, t: float) -> float:
        """Distance along the line: a jerk-limited (cosine) speed ramp to the impact speed, then cruise,
        as arm controllers blend their moves."""
        v = self.draw.speed
        t_ramp = 2.0 * v / ACCEL  # the cosine ramp's peak acceleration is ACCEL * pi / 4
        if t < t_ramp:
            return 0.5 * v * (t - t_ramp / np.pi * np.sin(np.pi * t / t_ramp))
        return 0.5 * v * t_ramp + v * (t - t_ramp)

    def step(self, obs: Observation) -> Command:
        self.t += self.dt
        s = min(self._s(self.t), self.length)
        target = pin.SE3(self.draw.rotation, self.draw.p0 + self.draw.direction * s)
        self.q, _ = self.robot.ik(target, self.q, iters=20, tol=1e-8)
        if s >= self.length:
            self._done = True
        return Command(q=self.q.copy())

    def abort(self, reason: str) -> None:
        self._done = True
        self.reason = reason

    def summary(self) -> dict[str, Any]:
        return {"outcome": "done" if not self.reason else "aborted", "reason": self.reason}


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


class PeakTap:
    """The F/T sensor as the loop's force source, keeping the peak force it read."""

    name = "sensor"

    def __init__(self, inner: SensorForceSource) -> None:
        self.inner = inner
        self.peak = 0.0

    def read(self, state: ArmState) -> Wrench:
        w = self.inner.read(state)
        if w.valid:
            self.peak = max(self.peak, float(np.linalg.norm(w.force)))
        return w

    def rebias(self) -> None:
        self.inner.rebias()


def _tool_down(rng: np.random.Generator) -> np.ndarray:
    down = pin.rpy.rpyToMatrix(np.pi, 0.0, rng.uniform(-np.pi, np.pi))
    axis = np.array([*rng.normal(size=2), 0.0])
    axis /= np.linalg.norm(axis)
    return pin.exp3(axis * rng.uniform(0, MAX_TILT)) @ down


def _joint_speeds_ok(robot: RobotModel, q0: np.ndarray, R: np.ndarray, p0: np.ndarray, d: np.ndarray,
                     length: float, speed: float, limit: np.ndarray) -> bool:
    """Whether the line at `speed` stays within the joint speed limits (no singularity on the way)."""
    step = 0.005
    q = q0
    for s in np.arange(step, length + step, step):
        q_next, ok = robot.ik(pin.SE3(R, p0 + d * s), q, iters=50)
        if not ok or np.any(np.abs(q_next - q) / step * speed > limit):
            return False
        q = q_next
    return True


def draw_impact(robot: RobotModel, home: np.ndarray, rng: np.random.Generator, rigid: bool,
                ws_min: np.ndarray, ws_max: np.ndarray, joint_speed_limit: np.ndarray) -> ImpactDraw:
    """A start pose, direction, speed, obstacle and payload error (redrawn until the IK and the line fit,
    within the joint speed limits with a 20 % margin)."""
    for _ in range(200):
        p0 = rng.uniform(*REACH)
        R = _tool_down(rng)
        q0, ok = robot.ik(pin.SE3(R, p0), home, iters=200)
        if not ok:
            continue
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        toward_base = -p0[:2] / np.linalg.norm(p0[:2])
        if float(d[:2] @ toward_base) > 0.5:  # not into the arm itself
            continue
        speed = float(rng.uniform(*SPEED_RANGE))
        end = p0 + d * (speed**2 / ACCEL + 0.01 + BEYOND_M)
        if np.any(end < ws_min + 0.05) or np.any(end > ws_max - 0.05) or end[2] < 0.12:
            continue
        if not _joint_speeds_ok(robot, q0, R, p0, d, speed**2 / ACCEL + 0.01 + BEYOND_M, speed,
                                0.8 * joint_speed_limit):
            continue
        stiffness = None if rigid else float(np.exp(rng.uniform(*np.log(SOFT_STIFFNESS))))
        return ImpactDraw(q0, R, p0, d, speed, stiffness, float(rng.uniform(-0.5, 0.5)))
    raise RuntimeError("bench collision: no feasible impact set-up in 200 draws")


def _bench_cell_config(cfg: CellConfig) -> CellConfig:
    """The cell with the scripted impacts' speeds allowed and the F/T limit out of the way: what is
    measured is the detector, which never reads the F/T sensor."""
    safety = dataclasses.replace(cfg.safety, max_tcp_speed=max(cfg.safety.max_tcp_speed, SPEED_RANGE[1] * 1.2),
                                 max_tool_force_n=1e6, max_tool_torque_nm=1e6)
    return dataclasses.replace(cfg, safety=safety, scene=dataclasses.replace(cfg.scene, kind="obstacle"))


def _guard(cfg: CellConfig, model: LearnedModel, robot: RobotModel, reaction: str) -> Any:
    free = {"impact": TaskContactSafety(), "free_motion": TaskContactSafety()}  # no contact expected anywhere
    coll: CollisionConfig = dataclasses.replace(cfg.collision, enabled=True, reaction=reaction,  # type: ignore[arg-type]
                                                tasks=free)
    return build_guard(coll, model, robot, cfg.loop.period_s, "impact", cfg.safety.max_tool_force_n,
                       np.asarray(cfg.virtual_sensor.wrench_point, float))


def _settled_guard(cfg: CellConfig, model: LearnedModel, robot: RobotModel, reaction: str, cell: OpenCell,
                   plant: Plant, settled: Callable[[], None] | None = None) -> Any:
    """Let the arm settle at rest (0.3 s), call `settled` (zero a sensor), then give a fresh guard
    0.15 s of the resting arm and zero its residual there."""
    for _ in range(int(0.3 / cfg.loop.period_s)):
        cell.ticker.wait()
    if settled is not None:
        settled()
    guard = _guard(cfg, model, robot, reaction)
    for _ in range(int(0.15 / cfg.loop.period_s)):
        guard.detector.update(plant.measured_state())
        cell.ticker.wait()
    guard.rebias()
    return guard


def run_impact(cfg: CellConfig, robot: RobotModel, model: LearnedModel, draw: ImpactDraw,
               seed: int, reaction: str = "stop", tool: str = "peg") -> dict[str, Any] | None:
    """One scripted impact, or None when the plate, placed, already touches the arm."""
    holder = make_sim_cell(cfg, robot.limits, seed=seed, scene_kind="obstacle", tool=tool)
    plant = holder.plant
    obstacle = Obstacle(plant)
    obstacle.set_payload_error(draw.payload_error_kg)
    plant.reset(draw.q0)
    normal = -draw.direction
    k = draw.stiffness
    damping = 0.0 if k is None else 2 * SOFT_DAMPING_RATIO * np.sqrt(k * OBSTACLE_PLATE_KG)
    obstacle.place(draw.p0 + draw.direction * draw.gap, normal, k, damping)
    if obstacle.touching():
        holder.close()
        return None
    cell = holder.open()
    try:
        tap = PeakTap(cell.force)  # type: ignore[arg-type]
        guard = _settled_guard(cfg, model, robot, reaction, cell, plant, settled=tap.rebias)
        t0 = plant.t
        task = LineTask(robot, draw, cfg.loop.period_s)
        loop = ControlLoop(cell.arm, tap, task, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s), cell.ticker,
                           None, cfg.loop.period_s, 5.0, guard=guard)
        result = loop.run()
        raise_if_interrupted(result.outcome)
        peak_at_stop = obstacle.peak_n
        obstacle.peak_n = 0.0
        fast_peak = guard.stats.max_fast_force_n
        for _ in range(int(HOLD_AFTER_S / cfg.loop.period_s)):  # held: the contact may still build up
            plant.step()
            guard.detector.update(plant.measured_state())
            fast_peak = max(fast_peak, float(np.linalg.norm(guard.detector.force)))
            tap.read(plant.measured_state())
    finally:
        holder.close()
    det = guard.last
    onset = obstacle.onset_t
    latency = force_at_detection = None
    if det is not None and onset is not None:
        latency = (t0 + det.t) - onset
        force_at_detection = obstacle.force_at(t0 + det.t)
    return {"speed_mps": round(draw.speed, 3), "rigid": k is None, "stiffness_n_per_m": k,
            "payload_error_kg": round(draw.payload_error_kg, 3), "outcome": result.outcome,
            "contact": onset is not None, "detected": det is not None,
            "detected_before_contact": det is not None and (onset is None or t0 + det.t < onset),
            "latency_ms": None if latency is None else round(latency * 1e3, 1),
            # The contact force when the detector decided: its sensitivity to this contact
            "force_at_detection_n": None if force_at_detection is None else round(force_at_detection, 1),
            "peak_force_n": round(max(peak_at_stop, obstacle.peak_n), 1), "peak_until_stop_n": round(peak_at_stop, 1),
            "peak_after_stop_n": round(obstacle.peak_n, 1), "ft_peak_n": round(tap.peak, 1),
            "fast_peak_n": round(fast_peak, 1), "joints": det.joints if det else []}


def run_free_motion(cfg: CellConfig, robot: RobotModel, model: LearnedModel, seconds: float, seed: int,
                    chunk_s: float = 120.0, tool: str = "peg",
                    time_optimal_share: float = TIME_OPTIMAL_SHARE) -> dict[str, Any]:
    """Random point-to-point moves at the cell's full allowed speed, then (the last `time_optimal_share`)
    time-optimal moves from rest as `plan` makes them, in chunks with a payload error each; every
    detection is a false alarm (the guard only records them)."""
    dt = cfg.loop.period_s
    rng = np.random.default_rng(seed + 7919)
    alarms: list[dict[str, Any]] = []
    played = 0.0
    max_ratio = {"random": 0.0, "time_optimal": 0.0}
    chunk = 0
    random_s = seconds * (1.0 - time_optimal_share)
    fast_cfg = dataclasses.replace(cfg, safety=dataclasses.replace(
        cfg.safety, max_tcp_speed=max(cfg.safety.max_tcp_speed, max_tcp_speed())))
    with tqdm(total=round(seconds), unit="sim s", desc="free motion", leave=False) as bar:
        while played < seconds - 1e-9:
            kind = "random" if played < random_s - 1e-9 else "time_optimal"
            want = min(chunk_s, (random_s if kind == "random" else seconds) - played)
            if kind == "random":
                plan = random_moves(robot, cfg, ExcitationConfig(), dt, 1, max(2, int(want / 2.0)), [1.0],
                                    seed=seed * 1000 + chunk)
                q = np.vstack([s.q for s in plan.segments])[: int(round(want / dt))]
                start, run_cfg = plan.start, cfg
            else:
                q = time_optimal_stream(robot, cfg, model, want, seed * 1000 + chunk)
                start, run_cfg = q[0], fast_cfg
            holder = make_sim_cell(run_cfg, robot.limits, seed=seed + chunk, scene_kind="obstacle", tool=tool)
            obstacle = Obstacle(holder.plant)
            error = float(rng.uniform(-0.5, 0.5))
            obstacle.set_payload_error(error)
            holder.plant.reset(start)
            cell = holder.open()
            try:
                guard = _settled_guard(run_cfg, model, robot, "monitor", cell, holder.plant)
                loop = ControlLoop(cell.arm, cell.force, StreamTask(q), SafetyMonitor(run_cfg.safety, robot, dt),
                                   cell.ticker, None, dt, len(q) * dt + 1.0, guard=guard)
                result = loop.run()
            finally:
                holder.close()
            raise_if_interrupted(result.outcome)
            if result.outcome != "done":
                log.warning("free motion chunk %d ended %s: %s", chunk, result.outcome, result.reason)
            for d in guard.stats.detections:
                alarms.append({"chunk": chunk, "motion": kind, "payload_error_kg": round(error, 3), **d})
            max_ratio[kind] = max(max_ratio[kind], guard.stats.max_free_ratio)
            played += len(q) * dt
            bar.update(round(len(q) * dt))
            chunk += 1
    return {"seconds": round(played, 1), "alarms": alarms, "max_ratio": round(max(max_ratio.values()), 3),
            "max_ratio_time_optimal": round(max_ratio["time_optimal"], 3)}


def bench_collision(cfg: CellConfig, robot: RobotModel, model: LearnedModel, impacts: int = 40, seed: int = 0,
                    free_s: float = 600.0, reaction: str = "stop", tool: str = "peg") -> dict[str, Any]:
    wall0 = time.perf_counter()
    bcfg = _bench_cell_config(cfg)
    rng = np.random.default_rng(seed)
    home = np.asarray(cfg.robot.home, float)
    ws_min, ws_max = np.asarray(cfg.safety.workspace_min, float), np.asarray(cfg.safety.workspace_max, float)
    trials = []
    for i in tqdm(range(impacts), desc="impacts", unit="impact", leave=False):
        r = None
        while r is None:
            draw = draw_impact(robot, home, rng, rigid=i % 2 == 0, ws_min=ws_min, ws_max=ws_max,
                               joint_speed_limit=robot.limits.velocity * cfg.safety.joint_speed_fraction)
            r = run_impact(bcfg, robot, model, draw, seed=seed * 1000 + i, reaction=reaction, tool=tool)
        r["trial"] = i
        trials.append(r)
        log.info("impact %d: %s", i, r)
    free: dict[str, Any] = {"seconds": 0.0, "alarms": [], "max_ratio": 0.0}
    if free_s > 0:
        free = run_free_motion(bcfg, robot, model, free_s, seed, tool=tool)
    return summarise(trials, free, seed, time.perf_counter() - wall0)


def summarise(trials: list[dict[str, Any]], free: dict[str, Any], seed: int, wall_s: float) -> dict[str, Any]:
    hits = [t for t in trials if t["contact"]]
    lat = [t["latency_ms"] for t in hits if t["latency_ms"] is not None]
    missed = [t["trial"] for t in hits if not t["detected"]]
    peaks = [t["peak_force_n"] for t in hits]
    ratios = [t["fast_peak_n"] / t["ft_peak_n"] for t in hits if t["ft_peak_n"] > 1.0]
    rigid_025 = [t["peak_force_n"] for t in hits if t["rigid"] and abs(t["speed_mps"] - 0.25) <= 0.05]
    minutes = free["seconds"] / 60.0

    def p95(rows: list[dict[str, Any]], key: str, q: float = 95.0) -> float | None:
        """The q-th percentile of `key` over `rows` (95th unless told), None where none has it."""
        vals = [t[key] for t in rows if t[key] is not None]
        return float(np.percentile(vals, q)) if vals else None

    rigid = [t for t in hits if t["rigid"]]
    soft = [t for t in hits if not t["rigid"]]
    # Peak force per unit speed on the rigid plates: what guarded motion (cell/control/guarded.py) bounds speeds by.
    per_speed = [t["peak_force_n"] / t["speed_mps"] for t in rigid]
    impact = float(np.percentile(per_speed, 95)) if per_speed else None
    return {
        "seed": seed,
        "impacts": len(trials),
        "contacts": len(hits),
        "missed": missed,
        "detection_latency_ms_p95": float(np.percentile(lat, 95)) if lat else None,
        "detection_latency_ms_median": float(np.median(lat)) if lat else None,
        "detection_latency_ms_p95_rigid": p95(rigid, "latency_ms"),
        "detection_latency_ms_p95_soft": p95(soft, "latency_ms"),
        "force_at_detection_n_median_soft": p95(soft, "force_at_detection_n", q=50.0),
        "force_at_detection_n_p95_soft": p95(soft, "force_at_detection_n"),
        "peak_force_n_p95": float(np.percentile(peaks, 95)) if peaks else None,
        "peak_force_n_p95_rigid": p95(rigid, "peak_force_n"),
        "peak_force_n_p95_soft": p95(soft, "peak_force_n"),
        "ft_peak_n_p95_rigid": p95(rigid, "ft_peak_n"),
        "peak_force_n_max": float(np.max(peaks)) if peaks else None,
        "peak_force_n_rigid_025": float(np.max(rigid_025)) if rigid_025 else None,
        "rigid_impact_n_per_mps_p95": impact,
        "guarded_speed_mps_150n": 150.0 / impact if impact else None,
        "virtual_peak_ratio": float(np.median(ratios)) if ratios else None,
        "virtual_peak_ratio_p5": float(np.percentile(ratios, 5)) if ratios else None,
        "false_alarms": len(free["alarms"]) * (10.0 / minutes) if minutes > 0 else None,
        "false_alarm_events": free["alarms"],
        "free_motion_s": free["seconds"],
        "free_motion_max_ratio": free["max_ratio"],
        "free_motion_max_ratio_time_optimal": free.get("max_ratio_time_optimal"),
        "per_impact": trials,
        "wall_time_s": round(wall_s, 1),
    }
