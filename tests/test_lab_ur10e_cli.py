"""End to end through the real CLI: synthetic UR10e logs -> `main.py import ur10e` -> `main.py evaluate --robot ur10e`.

The logs are made here (never ../shared): joint motion around the UR10e's home posture, torque from
Pinocchio's RNEA of a slightly heavier arm (+10 % on two links) plus viscous and Coulomb friction and a
little noise, written as motor current (torque / drive gain) in the public logs' 31-column CSV layout.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from cell.model.specs import load_robot_spec, robot_model
from main import main

SPEC = load_robot_spec("ur10e")
GAINS = np.asarray(SPEC.torque_constants, float)
Q0 = np.array([0.0, -1.57, 1.0, -1.57, 0.0, 0.0])
PERIOD_S = 0.01
HEAVIER = {2: 1.10, 3: 1.10}  # pinocchio joint index -> mass factor (upper arm, forearm)
VISCOUS = np.array([6.0, 6.0, 4.0, 1.5, 1.5, 1.2])  # N·m·s/rad
COULOMB = np.array([5.0, 5.0, 3.5, 1.5, 1.5, 1.2])  # N·m
COULOMB_SPEED = 0.02  # rad/s: tanh(q' / this)
NOISE_NM = 0.2
PAYLOAD_KG = 2.805  # the importer's default payload for --loaded files


def _true_arm(payload_kg: float = 0.0) -> tuple[pin.Model, pin.Data]:
    """The 'real' arm: the nominal UR10e with two links 10 % heavier (inertia scaled with the mass),
    optionally a point mass at the flange origin on the last joint (P2Model.with_payload's convention)."""
    robot = robot_model(SPEC)
    model = robot.model.copy()
    for j, factor in HEAVIER.items():
        inertia = model.inertias[j]
        model.inertias[j] = pin.Inertia(inertia.mass * factor, inertia.lever, inertia.inertia * factor)
    if payload_kg:
        flange = model.frames[robot.flange_id]
        point = pin.Inertia(payload_kg, flange.placement.act(np.zeros(3)), np.zeros((3, 3)))
        model.inertias[flange.parentJoint] = model.inertias[flange.parentJoint] + point
    return model, model.createData()


def _sinusoids(rng: np.random.Generator, t: np.ndarray, joints: list[int]) -> tuple[np.ndarray, ...]:
    """q, q', q'' as sums of three sinusoids per moving joint around Q0 (total amplitude 0.3-0.6 rad)."""
    n = len(t)
    q, dq, ddq = np.tile(Q0, (n, 1)), np.zeros((n, 6)), np.zeros((n, 6))
    for j in joints:
        amps = rng.dirichlet(np.ones(3)) * rng.uniform(0.3, 0.6)
        freqs = rng.uniform(0.08, 0.4, 3)  # Hz: peak speed <= 0.6 x 2 pi x 0.4 ~ 1.5 rad/s
        phases = rng.uniform(0, 2 * np.pi, 3)
        for a, f, p in zip(amps, freqs, phases, strict=True):
            w = 2 * np.pi * f
            q[:, j] += a * (np.sin(w * t + p) - np.sin(p))  # starts at Q0
            dq[:, j] += a * w * np.cos(w * t + p)
            ddq[:, j] -= a * w * w * np.sin(w * t + p)
    return q, dq, ddq


def _write_log(path: Path, seed: int, duration_s: float, joints: list[int], payload_kg: float = 0.0) -> Path:
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration_s / PERIOD_S))) * PERIOD_S
    q, dq, ddq = _sinusoids(rng, t, joints)
    model, data = _true_arm(payload_kg)
    rigid = np.array([pin.rnea(model, data, q[k], dq[k], ddq[k]) for k in range(len(t))])
    tau = rigid + VISCOUS * dq + COULOMB * np.tanh(dq / COULOMB_SPEED) + rng.normal(0, NOISE_NM, rigid.shape)
    zeros = np.zeros((len(t), 6))
    rows = np.column_stack([1000.0 + t, q, dq, tau / GAINS, zeros, zeros])  # 31 columns
    assert rows.shape[1] == 31
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, delimiter=",", fmt="%.9g")
    return path


def _strict(text: str) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"bare {name} in JSON")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Imported through the CLI: 4 harmonic training logs, 2 joint-wise test logs, 1 loaded log."""
    root = tmp_path_factory.mktemp("ur10e")
    csv = root / "csv"
    train = [_write_log(csv / f"ur-harm{k}.csv", seed=k, duration_s=15.0, joints=list(range(6))) for k in range(4)]
    test = [_write_log(csv / f"ur-joint_{j + 1}.csv", seed=10 + j, duration_s=10.0, joints=[j]) for j in (1, 2)]
    loaded = _write_log(csv / "ur-harm50secLoad.csv", seed=20, duration_s=10.0, joints=list(range(6)),
                        payload_kg=PAYLOAD_KG)
    out = root / "ds"
    code = main(["-q", "import", "ur10e", "--train", *map(str, train), "--test", *map(str, test),
                 "--loaded", str(loaded), "--out", str(out), "--json"])
    assert code == 0
    imported = _strict((out / "import.json").read_text())
    assert imported["robot"] == "ur10e" and imported["rows_dropped"] == 0 and imported["period_s"] == PERIOD_S
    assert imported["trajectories"] == {"train": 4, "test": 2, "loaded": 1}
    return out / "dataset.yaml"


def test_import_then_evaluate_ur10e_end_to_end(dataset, tmp_path, capsys):
    capsys.readouterr()
    ev = tmp_path / "ev"
    # One XGBoost thread (the consistent P2 fit limits BLAS to one itself): on 2 cores with another job
    # running, XGBoost on 2 threads made this 468 s (D alone 54 s against 0.9).
    code = main(["-q", "evaluate", "--robot", "ur10e", "--data", str(dataset), "--out", str(ev), "--no-curve",
                 "--lofo", "--train-samples", "4000", "--large-samples", "6000", "--max-trees", "30",
                 "--nthread", "1", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    out = _strict(captured.out.strip().splitlines()[-1])

    six = ("P1", "P2", "D", "H1", "H2", "H3")
    for name in six:
        assert math.isfinite(out["mean_rmse_j123"][name]), name
        per_joint = out["models"][name]["rmse_mean"]
        assert len(per_joint) == 6, name
        if name in ("P2", "H1", "H2", "H3"):
            assert None not in per_joint, (name, per_joint)
            assert all(math.isfinite(v) for v in per_joint), (name, per_joint)
    assert out["noise_floor_j123_nm"] is None  # a real robot's logs: no known noise floor
    assert out["identified_p2"]["physically_consistent"] is True
    # The synthetic arm is the URDF up to two link masses and friction: P2 must halve P1's error.
    assert out["p2_over_p1"] < 0.5, out["mean_rmse_j123"]

    p2_payload = out["payload_transfer"]["models"]["P2"]
    assert p2_payload["rmse_j123_with_payload"] < 0.5 * p2_payload["rmse_j123_without_payload"], p2_payload

    lofo = out["leave_one_file_out"]
    assert len(lofo["folds"]) == 4
    assert math.isfinite(lofo["h1_over_p2_mean"]) and math.isfinite(lofo["h1_over_p2_worst"])

    assert set(six) <= set(out["regimes"]["models"])
    assert "within_2_sigma" in out["uncertainty"]["H1"], out["uncertainty"]["H1"]

    written = _strict((ev / "evaluation.json").read_text())
    assert written["mean_rmse_j123"] == out["mean_rmse_j123"]


def test_evaluating_a_ur10e_dataset_as_another_robot_is_refused(dataset, tmp_path, capsys):
    capsys.readouterr()
    code = main(["evaluate", "--robot", "tm5-700", "--data", str(dataset), "--out", str(tmp_path / "ev"),
                 "--no-curve", "--json"])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert code == 2, captured.err
    assert len(err) == 1, err
    assert err[0] == f"error: {dataset}: the dataset is of robot 'ur10e' but --robot is 'tm5-700'"
    assert "Traceback" not in captured.err
    assert captured.out == ""
    assert not (tmp_path / "ev").exists()  # a refused evaluation leaves no report folder behind
