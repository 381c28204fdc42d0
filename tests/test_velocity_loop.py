"""The host's velocity loop on TM's route: prediction across the command latency, the simulated cell streaming
speeds as the real route does, and doctor holding the setting to the measured round trip."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cell.config import load_config
from drivers.interfaces import JointLimits
from drivers.tm5.velocity_loop import VelocityLoop
from main import main
from sim.cell import make_sim_cell
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator
from sim.wacoh_emulator import WacohEmulator

ROOT = Path(__file__).resolve().parents[1]
LIMITS = JointLimits(lower=np.full(6, -3.0), upper=np.full(6, 3.0), velocity=np.full(6, 2.0),
                     effort=np.full(6, 100.0))
DT = 0.0156


def test_the_position_loop_counts_the_speeds_still_in_flight():
    loop = VelocityLoop(LIMITS, DT, position_gain=1.0, latency_periods=2)
    q = np.zeros(6)
    target = np.full(6, 0.01)
    v0 = loop.speeds(target, target, q)  # no step, 10 mrad behind: only the position loop speaks
    assert np.allclose(v0, 0.01)
    loop.sent(np.full(6, 0.5))
    loop.sent(np.full(6, 0.25))
    # The joints will still move dt * (0.5 + 0.25) = 11.7 mrad: already past the target, so the loop backs off.
    v = loop.speeds(target, target, q)
    assert np.allclose(v, 1.0 * (0.01 - DT * 0.75))
    loop.sent(np.full(6, 0.1))  # the oldest speed has acted by now: only the last two count
    assert np.allclose(loop.speeds(target, target, q), 0.01 - DT * 0.35)
    loop.reset()
    assert np.allclose(loop.speeds(target, target, q), 0.01)


def test_without_latency_the_loop_closes_on_the_measurement_and_respects_the_limits():
    loop = VelocityLoop(LIMITS, DT, position_gain=0.5, latency_periods=0)
    loop.sent(np.full(6, 1.0))  # nothing is predicted without a latency
    q = np.zeros(6)
    assert np.allclose(loop.speeds(np.full(6, 0.001), q, q), 0.001 / DT + 0.5 * 0.001)
    v = loop.speeds(np.full(6, 0.2), q, q)
    assert np.allclose(v, LIMITS.velocity)  # 0.2 rad in one period asks for 12.9 rad/s: the speed limit
    near = LIMITS.upper - 0.01
    assert np.all(loop.speeds(LIMITS.upper, near, near) <= 0.01 / 0.1 + 1e-9)


def test_the_simulated_cell_on_the_tm_route_moves_the_plant_by_streamed_speeds(robot):
    cfg = load_config(ROOT / "config" / "tm-ethernet.yaml")
    cell = make_sim_cell(cfg, robot.limits, scene_kind="free")
    arm = cell.arm
    assert arm.streaming is not None and arm.streaming.latency_periods == 2
    arm.connect()
    arm.arm()
    q0 = arm.read_state().q.copy()
    goal = q0 + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])
    steps = 64  # a one-second ramp on the wrist
    first = q0 + (goal - q0) / steps
    arm.send_target(first)
    # The servo's target is the controller's integral of one streamed speed from the measured joints.
    v = (first - q0) / DT + arm.streaming.position_gain * (first - q0)
    assert np.allclose(cell.plant.target, q0 + v * DT, atol=1e-12)
    cell.plant.step()
    for k in range(2, steps + 1):
        arm.send_target(q0 + (goal - q0) * k / steps)
        cell.plant.step()
    for _ in range(40):  # the end held: the joints arrive through the speeds alone
        arm.send_target(goal)
        cell.plant.step()
    assert np.allclose(arm.read_state().q, goal, atol=2e-3)
    arm.stop()
    arm.disconnect()


@pytest.mark.parametrize(("latency_setting", "passes"), [(2, False), (5, True)])
def test_doctor_holds_the_latency_setting_to_the_measured_round_trip(tmp_path, capsys, latency_setting, passes):
    plant = KinematicPlant(dt=DT, q0=np.array([0.3, -0.4, 1.2, 0.25, 1.5, -0.7]))
    with TMEthernetEmulator(plant, period_s=DT, command_latency_cycles=3) as arm, \
            WacohEmulator(lambda: np.zeros(6), noise=0.0) as sensor:
        path = tmp_path / "cell.yaml"
        path.write_text(
            f"base: {ROOT / 'config' / 'tm-ethernet.yaml'}\n"
            f"loop: {{period_s: {DT}}}\n"
            "devices:\n"
            f"  arm: {{kind: real, settings: {{protocol: tm-ethernet, host: 127.0.0.1, slave_port: "
            f"{arm.slave_port}, listen_port: {arm.listen_port}, stale_after_s: 0.06, "
            f"command_latency_periods: {latency_setting}}}}}\n"
            f"  sensor: {{kind: real, settings: {{port: {sensor.tty_path}}}}}\n", encoding="utf-8")
        code = main(["-q", "doctor", "--cell", "real", "--config", str(path), "--tare-s", "0.3", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    check = next(c for c in out["checks"] if c["name"] == "command_round_trip")
    if passes:
        assert check["status"] == "pass", check
        assert f"command_latency_periods {latency_setting} covers it" in check["detail"]
    else:
        assert code == 1 and check["status"] == "fail"
        assert "command_latency_periods is 2, this arm needs" in check["detail"]
