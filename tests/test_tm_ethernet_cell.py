"""The cell on TM's channels end to end: `status` and `doctor --cell real` against the TM Ethernet emulator."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from main import main
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator
from sim.wacoh_emulator import WacohEmulator

ROOT = Path(__file__).resolve().parents[1]
Q0 = np.array([0.3, -0.4, 1.2, 0.25, 1.5, -0.7])  # rad: every joint distinct


@pytest.fixture
def tm_cell(tmp_path):
    """A TM Ethernet emulator on a kinematic plant and a WACOH emulator; yields (config factory, emulator)."""
    plant = KinematicPlant(dt=0.0156, q0=Q0)
    with TMEthernetEmulator(plant, period_s=0.0156, coalesce=2) as arm, \
            WacohEmulator(lambda: np.zeros(6), noise=0.0) as sensor:

        def config(period_s: float) -> Path:
            path = tmp_path / f"cell-{period_s}.yaml"
            path.write_text(
                f"base: {ROOT / 'config' / 'tm-ethernet.yaml'}\n"
                f"loop: {{period_s: {period_s}}}\n"
                "devices:\n"
                f"  arm: {{kind: real, settings: {{protocol: tm-ethernet, host: 127.0.0.1, slave_port: "
                f"{arm.slave_port}, listen_port: {arm.listen_port}, stale_after_s: 0.06}}}}\n"
                f"  sensor: {{kind: real, settings: {{port: {sensor.tty_path}}}}}\n", encoding="utf-8")
            return path

        yield config, arm


def test_status_reports_the_table_as_broadcast(tm_cell, capsys):
    config, arm = tm_cell
    assert main(["-q", "status", "--cell", "real", "--config", str(config(0.0156)), "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    sent = arm.published[-1]
    # float32 on the wire: degrees to 1e-4, mN·m to 1e-3.
    assert np.allclose(out["q_deg"], np.degrees(Q0), atol=1e-4)
    assert np.allclose(out["tau_nm"], sent.tau, atol=2e-3)
    assert np.allclose(out["dq_deg_s"], np.degrees(sent.dq), atol=1e-3)
    assert out["status"] == {"error": False, "estop": False, "project_running": True, "paused": False,
                             "protective_stop": False}


def test_doctor_measures_the_broadcast_rate_and_fails_a_faster_loop(tm_cell, capsys):
    config, _ = tm_cell
    main(["-q", "doctor", "--cell", "real", "--config", str(config(0.0156)), "--tare-s", "0.3", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    checks = {c["name"]: c for c in out["checks"]}
    for name in ("slave_table", "project_speed", "joint_data", "state_rate", "estop_and_errors", "listen_node",
                 "command_round_trip"):
        assert checks[name]["status"] == "pass", checks[name]
    # The reply lag of a burst streamed at the loop's rate is measured and reported.
    assert "32 scripts at 64 Hz: 32/32 answered, reply lag median" in checks["command_round_trip"]["detail"]
    hz = float(checks["state_rate"]["detail"].split(" Hz")[0].split()[-1])
    assert abs(hz - 1 / 0.0156) <= 0.1 / 0.0156
    # The same arm with a loop asking for a state every 8 ms: the rate check fails and says what to change.
    assert main(["-q", "doctor", "--cell", "real", "--config", str(config(0.008)), "--tare-s", "0.3", "--json"]) == 1
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rate = next(c for c in out["checks"] if c["name"] == "state_rate")
    assert out["passed"] is False and rate["status"] == "fail" and "loop.period_s" in rate["fix"]
