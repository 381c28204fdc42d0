"""`main.py bench collision`: scripted impacts on rigid and soft obstacles, and the cell's own motion for false
alarms, on the simulated cell with the collision detector of the hybrid model."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
from tqdm import tqdm

from bench.collision_cell import settled_guard
from bench.collision_free import TaskRun, run_free_motion
from bench.collision_plans import BenchPlanners
from cell.config import CellConfig
from cell.control.loop import Command, ControlLoop, Observation
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
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


class SpringWatch:
    """The force the sprung plate's spring and damper carry (k x + c x'), every physics step from the contact's
    onset: the load on the body region that ISO/TS 15066's model represents by the spring.  The tool-plate
    contact force (the obstacle's own trace) also carries the light plate's inertia, which at a hard brake
    shows as one step without contact and the next at twice the force."""

    def __init__(self, obstacle: Obstacle, plant: Plant) -> None:
        m = plant.model
        self.obstacle, self.plant = obstacle, plant
        self.qadr, self.vadr = int(m.jnt_qposadr[obstacle.slide]), int(m.jnt_dofadr[obstacle.slide])
        self.trace: list[tuple[float, float]] = []
        self._inner = plant.after_physics_step
        plant.after_physics_step = self._watch

    def _watch(self) -> None:
        if self._inner is not None:
            self._inner()
        if self.obstacle.onset_t is None:
            return
        m, d = self.plant.model, self.plant.data
        # The slide's axis is the plate's outward normal: compression is -x.
        f = -(float(m.jnt_stiffness[self.obstacle.slide]) * float(d.qpos[self.qadr])
              + float(m.dof_damping[self.vadr]) * float(d.qvel[self.vadr]))
        self.trace.append((float(d.time), f))


def contact_figures(trace: list[tuple[float, float]], decided: float, dt: float) -> dict[str, float]:
    """From a force trace (t, N) and the instant the detector decided: the force then, the largest over the
    period before it (what the contact had reached), the peak from then on, and whether the force still rose
    more than one control period after the decision (by over 2 %: the reaction had not cut it)."""
    t = np.array([x[0] for x in trace])
    f = np.array([x[1] for x in trace])
    if t.size == 0:
        return {}
    i = int(np.searchsorted(t, decided + 1e-9)) - 1
    at = float(f[i]) if i >= 0 else 0.0
    before = f[(t > decided - dt - 1e-9) & (t <= decided + 1e-9)]
    reached = float(before.max()) if before.size else at
    after = f[t > decided + 1e-9]
    upto = f[t <= decided + dt + 1e-9]
    later = f[t > decided + dt + 1e-9]
    return {"at": at, "reached": reached, "peak_after": float(after.max()) if after.size else at,
            "rising": bool(later.size and upto.size and later.max() > 1.02 * upto.max())}


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
    spring = SpringWatch(obstacle, plant) if k is not None else None
    cell = holder.open()
    try:
        tap = PeakTap(cell.force)  # type: ignore[arg-type]
        guard = settled_guard(cfg, model, robot, reaction, cell, plant, settled=tap.rebias)
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
        force_at_end = obstacle.force()  # what the reaction left pressing on the plate
    finally:
        holder.close()
    det = guard.last
    onset = obstacle.onset_t
    dt = cfg.loop.period_s
    latency = force_at_detection = None
    extra: dict[str, Any] = {}
    if onset is not None:
        extra["force_at_end_n"] = round(force_at_end, 1)
        # The earliest decision any detector on this loop could make: the first period whose state (one period
        # old: the torque-sensing latency) was sampled after the onset.  The contact force then is a floor.
        first = t0 + np.ceil((onset + dt - t0) / dt - 1e-9) * dt
        floor = obstacle.force_at(first)
        extra["force_at_first_decision_n"] = None if floor is None else round(floor, 1)
    if det is not None and onset is not None:
        latency = (t0 + det.t) - onset
        force_at_detection = obstacle.force_at(t0 + det.t)
        c = contact_figures(obstacle.trace, t0 + det.t, dt)
        extra.update(force_reached_at_detection_n=round(c["reached"], 1),
                     peak_from_detection_n=round(c["peak_after"], 1), rising_after_one_period=c["rising"])
        if spring is not None and spring.trace:
            s_ = contact_figures(spring.trace, t0 + det.t, dt)
            extra.update(spring_force_at_detection_n=round(s_["at"], 1),
                         spring_peak_n=round(max(f for _, f in spring.trace), 1),
                         spring_peak_from_detection_n=round(s_["peak_after"], 1),
                         spring_rising_after_one_period=s_["rising"])
    return {"speed_mps": round(draw.speed, 3), "rigid": k is None, "stiffness_n_per_m": k,
            "payload_error_kg": round(draw.payload_error_kg, 3), "outcome": result.outcome,
            "contact": onset is not None, "detected": det is not None,
            "detected_before_contact": det is not None and (onset is None or t0 + det.t < onset),
            "latency_ms": None if latency is None else round(latency * 1e3, 1),
            # The contact force when the detector decided: its sensitivity to this contact
            "force_at_detection_n": None if force_at_detection is None else round(force_at_detection, 1),
            "peak_force_n": round(max(peak_at_stop, obstacle.peak_n), 1), "peak_until_stop_n": round(peak_at_stop, 1),
            "peak_after_stop_n": round(obstacle.peak_n, 1), "ft_peak_n": round(tap.peak, 1),
            "fast_peak_n": round(fast_peak, 1), "joints": det.joints if det else [],
            "reaction": guard.stats.reactions[-1] if guard.stats.reactions else None, **extra}


def bench_collision(cfg: CellConfig, robot: RobotModel, model: LearnedModel, impacts: int = 40, seed: int = 0,
                    free_s: float = 600.0, reaction: str = "stop", tool: str = "peg",
                    planners: BenchPlanners | None = None, task_run: TaskRun | None = None) -> dict[str, Any]:
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
        free = run_free_motion(bcfg, robot, model, free_s, seed, tool=tool, planners=planners, task_run=task_run)
    out = summarise(trials, free, seed, time.perf_counter() - wall0)
    if planners is not None:
        out["free_motion_planners"] = planners.sources
    return out


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
        vals = [t[key] for t in rows if t.get(key) is not None]
        return float(np.percentile(vals, q)) if vals else None

    def over(rows: list[dict[str, Any]], peak: str, base: str) -> list[dict[str, Any]]:
        """Per impact: the peak from the decision on over the force the contact had reached when it was made."""
        return [{"r": t[peak] / t[base]} for t in rows if t.get(peak) is not None and (t.get(base) or 0.0) > 1.0]

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
        # The contact force when the first period that could see the contact decided (its state, one period old,
        # sampled after the onset): what no detector on this loop can go under.
        "force_at_first_decision_n_p95_soft": p95(soft, "force_at_first_decision_n"),
        "force_at_first_decision_n_median_soft": p95(soft, "force_at_first_decision_n", q=50.0),
        # What the reaction did: the peak from the decision on over the force the contact had reached by then (its
        # largest over the period before the decision), and the impacts whose force still rose more than one
        # control period after the decision.
        "peak_over_detection_p95_soft": p95(over(soft, "peak_from_detection_n", "force_reached_at_detection_n"), "r"),
        "rising_after_one_period_soft": sum(bool(t.get("rising_after_one_period")) for t in soft),
        # The same on the spring the sprung plate stands on (the load on the body region it models).
        "spring_force_at_detection_n_median_soft": p95(soft, "spring_force_at_detection_n", q=50.0),
        "spring_force_at_detection_n_p95_soft": p95(soft, "spring_force_at_detection_n"),
        "spring_peak_n_p95_soft": p95(soft, "spring_peak_n"),
        "spring_peak_over_detection_p95_soft": p95(over(soft, "spring_peak_from_detection_n",
                                                        "spring_force_at_detection_n"), "r"),
        "spring_rising_after_one_period_soft": sum(bool(t.get("spring_rising_after_one_period")) for t in soft),
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
        "free_motion_max_ratio_by_kind": free.get("max_ratio_by_kind", {}),
        "free_motion_max_ratio_at": free.get("max_ratio_at", {}),
        "free_motion_cut_short": free.get("cut_short", []),
        "per_impact": trials,
        "wall_time_s": round(wall_s, 1),
    }
