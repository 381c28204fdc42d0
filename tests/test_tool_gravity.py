"""Gravity compensation of the tool on the F/T sensor: the fit recovers the load, then the sensor reads contact."""

from __future__ import annotations

import numpy as np
import pytest

from cell.sensing.tool_gravity import G, GravityCompensatedSource, ToolGravity, fit, gravity_direction, load, save
from drivers.errors import DataError
from drivers.interfaces import ArmState, Wrench


def skew(r):
    return np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])


def synthetic(mass, com, R_s, us, offset, noise, rng):
    """What a sensor turned by R_s against the TCP reads for a tool of `mass` at `com` (sensor frame)."""
    K = np.vstack([mass * G * R_s.T, skew(com) @ (mass * G * R_s.T)])
    return np.array([offset + K @ u + rng.normal(0, noise, 6) for u in us])


def random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_fit_recovers_mass_and_centre_of_mass_of_a_tilted_sensor():
    rng = np.random.default_rng(3)
    c, s = np.cos(0.3), np.sin(0.3)
    R_s = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    com = np.array([0.01, -0.02, 0.09])
    us = random_unit(rng, 9)
    tg = fit(us, synthetic(1.25, com, R_s, us, np.array([3, -2, 5, 0.1, 0.2, -0.1]), 0.02, rng))
    assert tg.mass_kg == pytest.approx(1.25, abs=0.01)
    np.testing.assert_allclose(tg.com_m, com, atol=2e-3)
    # Another orientation, tared at a third: the compensated wrench is the noise only.
    u_t, u = random_unit(rng, 2)
    w_t, w = synthetic(1.25, com, R_s, [u_t, u], np.zeros(6), 0.0, rng)
    assert np.linalg.norm(tg.compensate(w - w_t, u, u_t)[:3]) < 0.05
    assert np.linalg.norm((w - w_t)[:3]) > 1.0  # without compensation the weight shows


def test_fit_refuses_too_few_or_too_similar_poses():
    rng = np.random.default_rng(0)
    with pytest.raises(DataError, match="at least 4"):
        fit(random_unit(rng, 3), np.zeros((3, 6)))
    same = np.tile([0.0, 0.0, -1.0], (6, 1)) + rng.normal(0, 1e-6, (6, 3))
    with pytest.raises(DataError, match="do not turn the tool enough"):
        fit(same, np.zeros((6, 6)))


def test_save_and_load_round_trip_and_a_broken_file_is_refused(tmp_path):
    tg = ToolGravity(K=np.arange(18.0).reshape(6, 3), w0=np.ones(6), fit_rms=np.zeros(6))
    back = load(save(tg, tmp_path).parent)
    np.testing.assert_array_equal(back.K, tg.K)
    (tmp_path / "tool_gravity.json").write_text('{"format": "other"}')
    with pytest.raises(DataError, match="not a tool-gravity file"):
        load(tmp_path)


def test_compensated_source_reads_contact_alone_after_its_tare(robot, home):
    rng = np.random.default_rng(1)
    com = np.array([0.0, 0.0, 0.08])
    tg = ToolGravity(K=np.vstack([1.2 * G * np.eye(3), skew(com) * 1.2 * G]), w0=np.zeros(6), fit_rms=np.zeros(6))
    contact = np.array([0.0, 0.0, 20.0, 0.0, 0.0, 0.0])

    class Sensor:
        name = "sensor"
        contact_on = False
        zero = np.zeros(6)
        q = home  # where the arm stands when the source re-zeroes

        def raw(self, q):
            return tg.wrench(gravity_direction(robot, q)) + (contact if self.contact_on else 0.0)

        def read(self, state):
            v = self.raw(state.q) - self.zero
            return Wrench(t=state.t, force=v[:3], torque=v[3:])

        def rebias(self):
            self.zero = self.raw(self.q)

    inner = Sensor()
    src = GravityCompensatedSource(inner, tg, robot)
    src.read(ArmState(t=0.0, q=home, dq=np.zeros(6), tau=np.zeros(6)))
    src.rebias()
    q = home + rng.uniform(-1, 1, 6) * np.radians([10, 10, 10, 80, 80, 80])
    free = src.read(ArmState(t=1.0, q=q, dq=np.zeros(6), tau=np.zeros(6))).vector
    assert np.linalg.norm(free[:3]) < 1e-9 and np.linalg.norm(inner.read(ArmState(
        t=1.0, q=q, dq=np.zeros(6), tau=np.zeros(6))).force) > 1.0
    inner.contact_on = True
    np.testing.assert_allclose(src.read(ArmState(t=2.0, q=q, dq=np.zeros(6), tau=np.zeros(6))).vector, contact,
                               atol=1e-9)


def test_simulated_sensor_reads_under_half_a_newton_in_free_space_after_compensation(cfg):
    """The issue's figure on the simulated plant: 9 random orientations after the fit on 9 others."""
    from app.tasks_registry import robot_for
    from bench.tool_gravity import bench_tool_gravity

    out = bench_tool_gravity(cfg, robot_for(cfg, "wipe"), "wipe", poses=9, seed=5)
    assert out["free_force_max_before_n"] > 5.0  # the tool's weight turning with it
    assert out["free_force_max_after_n"] <= 0.5
    assert 0.5 < out["mass_kg"] < 3.0


def test_identification_on_the_simulated_cell_and_the_sensor_source_compensated(cfg, tmp_path):
    """calibrate's step on a cell: 9 wrist postures through the control loop, the fit saved, then every task's
    F/T source of that tool wrapped."""
    import dataclasses

    from app.cells import calibration_cells
    from app.sensing import with_tool_gravity
    from app.tasks_registry import robot_for
    from cell.control.loop import OpenCell
    from tasks.setup.weigh_tool import identify_tool_gravity

    vs = dataclasses.replace(cfg.virtual_sensor, calibration_dir=str(tmp_path / "{tool}"))
    cfg = dataclasses.replace(cfg, virtual_sensor=vs)
    robot = robot_for(cfg, "peg")
    opener, _ = calibration_cells(cfg, "sim", "peg", robot, None)
    class Sensor:
        name = "sensor"

    plain = OpenCell(kind="sim", arm=None, force=Sensor(), ticker=None)  # type: ignore[arg-type]
    assert with_tool_gravity(cfg, "peg", plain, robot) is plain  # nothing identified yet: as it was
    out = identify_tool_gravity(cfg, "peg", robot, opener, tmp_path / "peg")
    assert out["outcome"] == "done" and out["mass_kg"] == pytest.approx(0.6, abs=0.05)
    assert out["fit_rms_force_n"] < 0.1
    wrapped = with_tool_gravity(cfg, "peg", plain, robot)
    assert isinstance(wrapped.force, GravityCompensatedSource) and wrapped.force.inner is plain.force
