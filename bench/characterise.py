"""Measures the plant's error budget: how far the nominal model and an ideal textbook loss model miss."""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from cell.config import CellConfig, resolve
from cell.control.trajectory import JointMove
from cell.model.specs import cell_robot
from sim.cell import make_plant

# "Ordinary motions": random point-to-point moves inside this workspace restriction (the paper's
# J2 +-80 deg, J3 +-150 deg) at 30-80 % of the joint speed limits.
RANGES_DEG = np.array([[-150, 150], [-80, 80], [-150, 150], [-150, 150], [-150, 150], [-180, 180]])


def ordinary_motions(rng: np.random.Generator, n: int, limits_v: np.ndarray, q0: np.ndarray) -> list[JointMove]:
    moves, q = [], q0
    lo, hi = np.radians(RANGES_DEG[:, 0]), np.radians(RANGES_DEG[:, 1])
    for _ in range(n):
        q1 = rng.uniform(lo, hi)
        moves.append(JointMove(q, q1, limits_v * rng.uniform(0.3, 0.8)))
        q = q1
    return moves


def characterise_plant(cfg: CellConfig, seed: int | None = None, n_moves: int = 12) -> dict[str, Any]:
    """Run ordinary motions on the free-space plant; report per-joint RMSE of
    - P1: the controller's nominal rigid-body model (URDF + nominal tool) against the measured torque;
    - ideal P2: the plant's *true* rigid body plus a least-squares textbook loss model
      (B_m q'' + C_m q' + f_c sign(q'), per joint) against the measured torque;
    - noise: the torque-sensing noise alone."""
    plant = make_plant(cfg, seed=seed, scene_kind="free")
    robot = cell_robot(cfg)
    rng = np.random.default_rng(plant.profile.seed + 1000)
    m, d = plant.model, plant.data
    lim_v = robot.limits.velocity
    moves = ordinary_motions(rng, n_moves, lim_v, np.asarray(cfg.robot.home, float))
    rows: list[list[np.ndarray]] = []
    rb_true = np.zeros(m.nv)
    for move in moves:
        traj: list[np.ndarray] = []
        steps = int(np.ceil(move.duration / plant.dt)) + 25
        for k in range(steps):
            plant.set_target(move.at((k + 1) * plant.dt))
            plant.step()
            s = plant.true_state()
            measured = plant._history[-1].tau  # same instant as the true state: latency is not model error
            qacc = np.array(d.qacc[:6])
            mujoco.mj_rne(m, d, 1, rb_true)  # true rigid body (no armature, no friction)
            nominal = robot.rnea(s.q, s.dq, qacc)
            traj.append(np.concatenate([s.q, s.dq, qacc, measured, rb_true[:6], nominal,
                                        plant.true_motor_torque()]))
        rows.append(traj)
    data = [np.asarray(t) for t in rows]
    allrows = np.concatenate(data)
    dq, ddq, tau = allrows[:, 6:12], allrows[:, 12:18], allrows[:, 18:24]
    rb = allrows[:, 24:30]
    # Ideal textbook loss model on the true rigid body, least squares per joint.
    coef = []
    for j in range(6):
        A = np.column_stack([ddq[:, j], dq[:, j], np.sign(dq[:, j])])
        c, *_ = np.linalg.lstsq(A, tau[:, j] - rb[:, j], rcond=None)
        coef.append(c)

    def per_traj_rmse(pred_fn) -> np.ndarray:
        out = []
        for t in data:
            err = t[:, 18:24] - pred_fn(t)
            out.append(np.sqrt(np.mean(err**2, axis=0)))
        return np.asarray(out)

    def ideal(t: np.ndarray) -> np.ndarray:
        return t[:, 24:30] + np.column_stack([
            coef[j][0] * t[:, 12 + j] + coef[j][1] * t[:, 6 + j] + coef[j][2] * np.sign(t[:, 6 + j])
            for j in range(6)
        ])

    p1 = per_traj_rmse(lambda t: t[:, 30:36])
    p2 = per_traj_rmse(ideal)
    noise = per_traj_rmse(lambda t: t[:, 36:42])
    samples = int(allrows.shape[0])
    return {
        "plant": str(resolve(cfg.plant)),
        "seed": plant.profile.seed,
        "trajectories": len(data),
        "samples": samples,
        "p1_rmse_j123_nm": float(p1[:, :3].mean()),
        "ideal_p2_rmse_j123_nm": float(p2[:, :3].mean()),
        "noise_rmse_j123_nm": float(noise[:, :3].mean()),
        "p1_rmse_per_joint_nm": p1.mean(axis=0).round(3).tolist(),
        "ideal_p2_rmse_per_joint_nm": p2.mean(axis=0).round(3).tolist(),
        "noise_rmse_per_joint_nm": noise.mean(axis=0).round(3).tolist(),
        "ideal_p2_fit": {"B_m": [c[0] for c in coef], "C_m": [c[1] for c in coef], "f_c": [c[2] for c in coef]},
        "paper_p1_nm": 9.554,
        "paper_p2_nm": 3.990,
    }
