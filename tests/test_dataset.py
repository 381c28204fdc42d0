"""The dataset format: strict validation with errors naming file and column, derivatives, manifests, subsets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml

from cell.data.dataset import Trajectory, load_split, load_trajectories, write_trajectory
from cell.data.recorder import Recorder
from cell.data.samples import stack, subsample_segments
from cell.sensing.derivatives import CausalDerivatives, FilterConfig, zero_phase_derivatives
from drivers.errors import ConfigError, DataError

DT = 0.008


def sine_traj(n: int = 6, samples: int = 600, seed: int = 0, with_dq: bool = True) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.arange(samples) * DT
    w = rng.uniform(1.0, 4.0, n)
    a = rng.uniform(0.2, 0.8, n)
    q = a * np.sin(w * t[:, None])
    dq = a * w * np.cos(w * t[:, None])
    tau = rng.normal(size=(samples, n))
    return Trajectory("x", t, q, tau, dq if with_dq else None, segment=(np.arange(samples) // 100))


def dq_of(traj: Trajectory) -> np.ndarray:
    """The velocities of a trajectory that has them."""
    assert traj.dq is not None
    return traj.dq


def table_of(traj: Trajectory) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {"t": traj.t}
    for i in range(traj.n):
        cols[f"q{i + 1}"] = traj.q[:, i]
    for i in range(traj.n):
        cols[f"tau{i + 1}"] = traj.tau[:, i]
    return cols


def write(path: Path, cols: dict[str, np.ndarray]) -> Path:
    pq.write_table(pa.table(cols), path)
    return path


# ------------------------------------------------------------------------------------------ validation
def test_valid_file_loads_with_and_without_dq(tmp_path):
    tr = sine_traj()
    write_trajectory(tmp_path / "a.parquet", tr)
    (loaded,) = load_trajectories(tmp_path / "a.parquet", 6)
    np.testing.assert_allclose(loaded.q, tr.q)
    np.testing.assert_allclose(dq_of(loaded), dq_of(tr))
    write(tmp_path / "b.parquet", table_of(tr))
    (no_dq,) = load_trajectories(tmp_path / "b.parquet", 6)
    assert no_dq.dq is None


def test_missing_column_names_file_and_column(tmp_path):
    cols = table_of(sine_traj())
    del cols["tau3"]
    path = write(tmp_path / "bad.parquet", cols)
    with pytest.raises(DataError, match=r"bad\.parquet.*'tau3'"):
        load_trajectories(path, 6)


def test_missing_time_column(tmp_path):
    cols = table_of(sine_traj())
    del cols["t"]
    with pytest.raises(DataError, match=r"bad\.parquet.*'t'"):
        load_trajectories(write(tmp_path / "bad.parquet", cols), 6)


def test_nan_rows_name_file_column_and_row(tmp_path):
    cols = table_of(sine_traj())
    cols["q2"] = cols["q2"].copy()
    cols["q2"][[17, 40]] = np.nan
    with pytest.raises(DataError, match=r"nan\.parquet: column 'q2' has 2 NaN/inf rows \(first at row 17\)"):
        load_trajectories(write(tmp_path / "nan.parquet", cols), 6)


def test_non_monotonic_time_names_file_and_row(tmp_path):
    cols = table_of(sine_traj())
    cols["t"] = cols["t"].copy()
    cols["t"][50] = cols["t"][48]
    with pytest.raises(DataError, match=r"time\.parquet: column 't' is not strictly increasing at row 50"):
        load_trajectories(write(tmp_path / "time.parquet", cols), 6)


def test_wrong_joint_count_names_the_missing_or_extra_column(tmp_path):
    five = write(tmp_path / "five.parquet", table_of(sine_traj(n=5)))
    with pytest.raises(DataError, match=r"five\.parquet: missing column 'q6'.*5 joints.*URDF has 6"):
        load_trajectories(five, 6)
    seven = write(tmp_path / "seven.parquet", table_of(sine_traj(n=7)))
    with pytest.raises(DataError, match=r"seven\.parquet: unexpected column 'q7'"):
        load_trajectories(seven, 6)


def test_partial_dq_columns_are_refused(tmp_path):
    cols = table_of(sine_traj())
    cols["dq1"] = cols["q1"]
    with pytest.raises(DataError, match=r"'dq2'"):
        load_trajectories(write(tmp_path / "dq.parquet", cols), 6)


def test_unreadable_file(tmp_path):
    bad = tmp_path / "junk.parquet"
    bad.write_text("not parquet")
    with pytest.raises(DataError, match="junk.parquet"):
        load_trajectories(bad, 6)
    with pytest.raises(DataError, match="missing.parquet: no such file"):
        load_trajectories(tmp_path / "missing.parquet", 6)


def test_time_gaps_and_traj_ids_split_trajectories(tmp_path):
    tr = sine_traj(samples=300)
    cols = table_of(tr)
    cols["t"] = cols["t"].copy()
    cols["t"][150:] += 1.0  # a dropped chunk
    cols["traj"] = np.r_[np.zeros(200, np.int64), np.ones(100, np.int64)]
    trajs = load_trajectories(write(tmp_path / "g.parquet", cols), 6)
    assert [len(t) for t in trajs] == [150, 50, 100]


def test_control_loop_step_log_is_a_dataset(tmp_path):
    """The columns ControlLoop._record writes (plus task columns) load as they are."""
    rec = Recorder(tmp_path / "run", chunk_rows=40)
    tr = sine_traj(samples=100)
    for k in range(100):
        row = {"t": k * DT, "cycle": k, "state": "play"}
        row.update({f"q{i + 1}": float(tr.q[k, i]) for i in range(6)})
        row.update({f"dq{i + 1}": float(dq_of(tr)[k, i]) for i in range(6)})
        row.update({f"tau{i + 1}": float(tr.tau[k, i]) for i in range(6)})
        row.update({f"q_cmd{i + 1}": 0.0 for i in range(6)})
        row.update(clipped=False, fx=0.0, fz=1.0, compute_ms=0.1, traj=0.0, segment=float(k // 50))
        rec.append(row)
    rec.close()
    (loaded,) = load_trajectories(tmp_path / "run" / "log", 6)
    assert len(loaded) == 100
    np.testing.assert_allclose(loaded.tau, tr.tau)


def test_manifest_lists_train_and_test_relative_to_itself(tmp_path):
    write_trajectory(tmp_path / "d" / "tr.parquet", sine_traj(seed=1))
    write_trajectory(tmp_path / "d" / "te.parquet", sine_traj(seed=2))
    man = tmp_path / "d" / "dataset.yaml"
    man.write_text(yaml.safe_dump({"train": ["tr.parquet"], "test": ["te.parquet"], "joints": 6}))
    assert len(load_split(man, "train", 6)) == 1
    assert len(load_split(man, "test", 6)) == 1
    with pytest.raises(DataError, match="URDF has 7"):
        load_split(man, "train", 7)
    man.write_text(yaml.safe_dump({"train": ["tr.parquet"], "tset": []}))
    with pytest.raises(ConfigError, match="unknown key 'tset'"):
        load_split(man, "train", 6)


# ------------------------------------------------------------------------------------------ derivatives
def test_zero_phase_acceleration_has_no_lag():
    t = np.arange(1000) * DT
    w = 2 * np.pi * 1.0
    q = np.sin(w * t)[:, None]
    dq = w * np.cos(w * t)[:, None]
    v, a = zero_phase_derivatives(t, q, dq)
    truth = -(w**2) * np.sin(w * t)
    inner = slice(50, -50)
    assert np.max(np.abs(a[inner, 0] - truth[inner])) < 0.02 * w**2
    # Without a measured dq the velocity comes from q, also without lag.
    v2, _ = zero_phase_derivatives(t, q, None)
    assert np.max(np.abs(v2[inner, 0] - dq[inner, 0])) < 0.01 * w


def test_causal_pipeline_batch_equals_per_sample_and_lags_a_little():
    tr = sine_traj(samples=400)
    c = CausalDerivatives(6, DT, FilterConfig(cutoff_hz=20.0))
    v_batch, a_batch = c.run(tr.q, tr.dq)
    c2 = CausalDerivatives(6, DT, FilterConfig(cutoff_hz=20.0))
    for k in range(len(tr)):
        v, a = c2.step(tr.q[k], dq_of(tr)[k])
        np.testing.assert_array_equal(v, v_batch[k])
        np.testing.assert_array_equal(a, a_batch[k])
    _, a_zero = zero_phase_derivatives(tr.t, tr.q, tr.dq)
    err = np.sqrt(np.mean((a_batch[100:] - a_zero[100:]) ** 2))
    scale = np.sqrt(np.mean(a_zero[100:] ** 2))
    assert 0.01 * scale < err < 0.5 * scale  # a causal filter lags: close, but not equal


def test_causal_from_positions_only():
    tr = sine_traj(samples=400, with_dq=False)
    v, _ = CausalDerivatives(6, DT).run(tr.q, None)
    truth = dq_of(sine_traj(samples=400))
    assert np.sqrt(np.mean((v[50:] - truth[50:]) ** 2)) < 0.15 * np.sqrt(np.mean(truth**2))


def test_subsample_by_whole_segments_never_exceeds_the_budget():
    s = stack([sine_traj(samples=1000, seed=k) for k in range(5)])
    sub = subsample_segments(s, 1234, seed=3)
    assert len(sub) == 1234
    seg, counts = np.unique(sub.segment, return_counts=True)
    assert np.sum(counts == 100) >= len(seg) - 1  # whole segments, at most one cut
    assert len(subsample_segments(s, 10**9)) == len(s)
