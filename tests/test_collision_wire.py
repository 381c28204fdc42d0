"""Collision detection over a wire: repeated reads skipped, thresholds widened by the wire's margin and by a late
host's aliasing, a late jittery wire quiet in free motion, and an impact still caught."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cell.collision.config import TaskContactSafety
from cell.collision.guard import build_guard
from drivers.interfaces import ArmState
from tests.collision_fixtures import posture


def test_over_a_wire_repeated_reads_are_skipped_and_thresholds_widen(vs, model):
    cfg, robot = vs["cfg"], vs["robot"]
    point = np.asarray(cfg.virtual_sensor.wrench_point, float)
    local = build_guard(cfg.collision, model, robot, cfg.loop.period_s, "play", 150.0, point)
    wire = build_guard(cfg.collision, model, robot, cfg.loop.period_s, "play", 150.0, point, over_wire=True)
    assert local is not None and wire is not None
    q = posture(robot, np.asarray(cfg.robot.home, float), [0.45, -0.15, 0.25])
    tau = robot.gravity(q)
    for k in range(5):
        st = ArmState(t=k * cfg.loop.period_s, q=q, dq=np.zeros(6), tau=tau + 0.5 * k)
        local.detector.update(st)
        wire.detector.update(st)
    assert np.allclose(wire.detector.threshold, cfg.collision.detector.wire_margin * local.detector.threshold)
    assert wire.detector.confirm == 2 and local.detector.confirm == 1
    # The same sample read again (no new controller cycle) changes nothing; a new one does.
    before = wire.detector.residual.copy()
    wire.detector.update(ArmState(t=5 * cfg.loop.period_s, q=q, dq=np.zeros(6), tau=tau + 2.0))
    assert np.array_equal(wire.detector.residual, before)
    wire.detector.update(ArmState(t=6 * cfg.loop.period_s, q=q, dq=np.zeros(6), tau=tau + 2.5))
    assert not np.array_equal(wire.detector.residual, before)


# ----------------------------------------------------------------------------------------- over a wire, late
def _late_wire_wipe(vs, model, push_at: int | None = None, force=(0.0, 0.0, 0.0), state: str = "move",
                    host_cycles: int = 260, seed: int = 5):
    """A contact-free wipe-like motion (tool down, back and forth along y) read as a busy host reads a wire.

    The plant runs its own cycle; the host reads every 1 to 6 controller cycles (missed deadlines), time
    stamps its reads a little late, sometimes reads the same sample twice, and streams one target per
    read as if no time had been lost: the controller runs out of targets, then catches up (stop-and-go).
    From host cycle `push_at` a hand pushes the tool with `force` (world frame).  Returns (guard,
    detections, plant cycles)."""
    from sim.cell import make_sim_cell

    cfg, robot = vs["cfg"], vs["robot"]
    dt = cfg.loop.period_s
    coll = dataclasses.replace(cfg.collision, tasks={"play": TaskContactSafety(contact_states=["wipe"])})
    guard = build_guard(coll, model, robot, dt, "play", 150.0, np.asarray(cfg.virtual_sensor.wrench_point, float),
                        over_wire=True)
    assert guard is not None
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free", tool="wipe")
    q0 = posture(robot, np.asarray(cfg.robot.home, float), [0.45, -0.15, 0.25])
    holder.plant.reset(q0)
    cell = holder.open()
    rng = np.random.default_rng(seed)
    detections, ticks = [], 0
    try:
        cell.arm.arm()
        for _ in range(25):  # settle, then zero the residual at rest
            cell.ticker.wait()
            ticks += 1
            guard.detector.update(dataclasses.replace(holder.plant.measured_state(), seq=ticks))
        guard.rebias()
        pose, q = robot.tcp_pose(q0), q0.copy()
        y0 = pose.translation[1]
        for k in range(host_cycles):
            if push_at is not None and k == push_at:
                holder.plant.external_wrench = np.concatenate([np.asarray(force, float), np.zeros(3)])
            st = dataclasses.replace(holder.plant.measured_state(), seq=ticks)
            st = dataclasses.replace(st, t=st.t + rng.uniform(0.0, 0.3 * dt))  # the read's own latency
            for _ in range(2 if rng.random() < 0.1 else 1):  # sometimes the same sample twice
                det = guard.observe(st, k * dt, k, state)
                if det is not None:
                    detections.append(det)
            # The host's path time advances one period per read, however late the read was.
            s = min(1.0, k * dt / 0.25)
            pose.translation = np.array([pose.translation[0], y0 + 0.06 * np.sin(2 * np.pi * k * dt / 1.2)
                                         * 0.5 * (1 - np.cos(np.pi * s)), pose.translation[2]])
            q, _ = robot.ik(pose, q, iters=20)
            cell.arm.send_target(q)
            guard.commanded(q)
            for _ in range(int(rng.choice([1, 1, 2, 2, 3, 4, 6]))):  # the controller's cycles until the next read
                cell.ticker.wait()
                ticks += 1
    finally:
        holder.close()
    return guard, detections, ticks


@pytest.mark.parametrize("state", ["move", "wipe"])
def test_a_late_jittery_wire_is_not_a_collision_and_the_checks_hold_while_late(vs, model, state):
    guard, detections, ticks = _late_wire_wipe(vs, model, state=state)
    d = guard.detector
    assert ticks > 2 * 260 and d.late_samples > 100 and d.repeats > 10  # a busy host: most reads late
    assert not detections, [det.describe() for det in detections]
    summary = guard.summary()
    assert summary["late_samples"] == d.late_samples and summary["repeated_samples"] == d.repeats
    assert summary["max_fast_force_n"] < 150.0


def test_over_a_late_jittery_wire_an_impact_is_still_caught(vs, model):
    guard, detections, _ = _late_wire_wipe(vs, model, push_at=150, force=(0.0, 0.0, 250.0))
    assert detections, guard.summary()
    # Later than on time (the late reads hold the checks, their aliasing widens the thresholds), but caught.
    assert detections[0].cycle < 150 + 25 and detections[0].mode == "free"
