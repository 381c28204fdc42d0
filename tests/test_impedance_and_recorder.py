"""The discretised impedance law (paper eq. 24) and the crash-safe chunked recording."""

from __future__ import annotations

import time

import numpy as np
import pyarrow.parquet as pq
import pytest

from cell.control.impedance import CartesianImpedance, DiscreteImpedance, ImpedanceParams
from cell.data.recorder import Recorder, new_run_dir, read_log


def test_law_is_equation_24():
    p = ImpedanceParams(m=2.0, b=30.0, k_tau=0.5, k_v=0.01)
    dt = 0.008
    law = DiscreteImpedance(p, dt)
    first = law.update(4.0)[0]
    assert first == pytest.approx(0.5 * 4.0 / (2.0 / dt**2 + 30.0 / dt))
    second = law.update(5.0)[0]
    assert second == pytest.approx((0.5 * 5.0 + 0.01 * (5.0 - 4.0) / dt) / (2.0 / dt**2 + 30.0 / dt))


@pytest.mark.parametrize("stiffness", [5e3, 25e3, 60e3])
def test_law_regulates_force_on_a_spring_without_steady_state_error(stiffness):
    """Contact as a spring F = k * penetration; the law integrates the error to zero."""
    dt, setpoint = 0.008, 60.0
    law = DiscreteImpedance(ImpedanceParams(), dt)
    depth = 0.0
    for _ in range(600):
        force = stiffness * max(depth, 0.0)
        depth += law.update(setpoint - force)[0]
    assert stiffness * depth == pytest.approx(setpoint, abs=0.05)


def test_joint_space_law_acts_per_joint():
    law = DiscreteImpedance(ImpedanceParams(m=1.0, b=10.0, k_tau=1.0), 0.008, n=6)
    out = law.update(np.array([1.0, -2.0, 0.0, 0.0, 0.5, 0.0]))
    assert out.shape == (6,)
    assert out[0] > 0 > out[1] and out[2] == 0 and out[4] == pytest.approx(out[0] / 2)


def test_cartesian_direction_moves_the_tcp_along_it(robot, home):
    from cell.control.trajectory import tool_down_pose

    q, _ = robot.ik(tool_down_pose(np.array([0.45, -0.1, 0.2])), home)
    imp = CartesianImpedance(robot, ImpedanceParams(m=0.0, b=1.0, k_tau=1e-3), 0.008, np.array([0, 0, -1.0]))
    dq, dx = imp.step(q, 10.0)
    before = robot.tcp_pose(q).translation
    after = robot.tcp_pose(q + dq).translation
    np.testing.assert_allclose(after - before, [0, 0, -dx], atol=1e-6)
    assert dx > 0


def test_recording_survives_a_kill_between_chunks(tmp_path):
    run = new_run_dir(tmp_path, "wipe")
    rec = Recorder(run, chunk_rows=10)
    for i in range(35):
        rec.append({"t": i * 0.008, "state": "wipe", "fz": float(i)})
    # No close(): as if the process died here, once the writer has taken in the three whole chunks handed to it.
    deadline = time.monotonic() + 60
    while rec.rows_written < 30 and time.monotonic() < deadline:
        time.sleep(0.01)
    table = read_log(run)
    assert table.num_rows == 30
    assert table.column("fz").to_pylist() == [float(i) for i in range(30)]
    rec.close()
    assert read_log(run).num_rows == 35


def test_a_half_written_chunk_does_not_spoil_the_log(tmp_path):
    run = new_run_dir(tmp_path, "wipe")
    rec = Recorder(run, chunk_rows=5)
    for i in range(5):
        rec.append({"t": float(i)})
    rec.flush()
    (run / "log" / ".part-00001.parquet.tmp").write_bytes(b"PAR1 truncated")
    assert read_log(run).num_rows == 5
    assert pq.read_table(run / "log" / "part-00000.parquet").num_rows == 5


def test_run_dirs_never_collide(tmp_path):
    a = new_run_dir(tmp_path, "wipe")
    b = new_run_dir(tmp_path, "wipe")
    assert a != b and a.exists() and b.exists()
