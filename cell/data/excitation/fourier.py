"""Identification-grade excitation: finite Fourier series per joint within the limits, the best-conditioned of
random candidates kept."""

from __future__ import annotations

import logging

import numpy as np

from cell.config import CellConfig
from cell.control.trajectory import quintic_blend
from cell.data.excitation.config import ExcitationConfig
from cell.data.excitation.limits import Workspace, excitation_checker, rad_ranges, trajectory_ok
from cell.data.excitation.motion import Motion, Segment
from cell.data.excitation.moves import transfer
from cell.model.dynamics.physics import base_parameters, full_regressor
from cell.model.robot import RobotModel

log = logging.getLogger(__name__)


def fourier_trajectory(coef_a: np.ndarray, coef_b: np.ndarray, q0: np.ndarray, wf: float, t: np.ndarray,
                       ramp_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q(t) = q0 + env(t) * sum_l a_l/(l wf) sin(l wf t) - b_l/(l wf) cos(l wf t), with a quintic fade
    env at both ends (start and end at rest).  Returns q, dq, ddq (numerical derivatives of the fade)."""
    L = coef_a.shape[1]
    lw = wf * np.arange(1, L + 1)
    s, c = np.sin(np.outer(t, lw)), np.cos(np.outer(t, lw))
    f = s @ (coef_a / lw).T - c @ (coef_b / lw).T
    f = f - f[0]  # start exactly at q0
    T = t[-1]
    u = np.clip(np.minimum(t, T - t) / ramp_s, 0.0, 1.0)
    env = quintic_blend(u)
    q = q0 + env[:, None] * f
    dt = t[1] - t[0]
    dq = np.gradient(q, dt, axis=0)
    ddq = np.gradient(dq, dt, axis=0)
    return q, dq, ddq


def fourier_excitation(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float,
                       traj_base: int = 0, segment_base: int = 0, centres: np.ndarray | None = None,
                       speed_fraction: float = 1.0) -> Motion:
    """Identification-grade excitation: per trajectory, random Fourier coefficients scaled into the
    position / speed / acceleration limits; among the collision-free candidates the one whose base
    regressor (column-scaled) has the lowest condition number is kept.  Trajectories are joined by
    quintic moves (which are segments too).  `speed_fraction` < 1 caps the joint speeds at that
    fraction of the limits (slow, small-amplitude excitation: the friction's low-speed regime)."""
    fc = ex.fourier
    cc = excitation_checker(robot, cfg, ex)
    ws = Workspace(robot, cfg, ex)
    lo, hi = rad_ranges(ex.ranges_deg, robot)
    n = robot.n
    rng = np.random.default_rng(ex.seed + 17)
    wf = 2 * np.pi * fc.base_hz
    duration = fc.periods / fc.base_hz + 2 * fc.ramp_s
    t = np.arange(0.0, duration + dt / 2, dt)
    bp = base_parameters(robot.model)
    data = robot.model.createData()
    def random_centre() -> np.ndarray:
        while True:
            c = rng.uniform(lo + fc.centre_margin * (hi - lo), hi - fc.centre_margin * (hi - lo))
            if cc.free(c) and ws.inside(c):
                return c

    def best_around(q0: np.ndarray) -> tuple[float, np.ndarray] | None:
        best: tuple[float, np.ndarray] | None = None
        room = np.minimum(q0 - lo, hi - q0) * fc.amplitude_fraction
        for _ in range(fc.candidates):
            a = rng.normal(size=(n, fc.harmonics))
            b = rng.normal(size=(n, fc.harmonics))
            q, dq, ddq = fourier_trajectory(a, b, q0, wf, t, fc.ramp_s)
            dev = np.abs(q - q0).max(axis=0)
            scale = np.min([
                np.min(room / np.maximum(dev, 1e-9)),
                np.min(ws.vmax * speed_fraction / np.maximum(np.abs(dq).max(axis=0), 1e-9)),
                np.min(ws.amax / np.maximum(np.abs(ddq).max(axis=0), 1e-9)),
            ])
            q = q0 + (q - q0) * scale
            dq, ddq = dq * scale, ddq * scale
            stride = max(1, int(0.05 / dt))
            tcp = np.array([ws.tcp(x) for x in q[::stride]])
            tcp_speed = float(np.max(np.linalg.norm(np.diff(tcp, axis=0), axis=1)) / (dt * stride))
            if tcp_speed > ws.tcp_vmax:  # the TCP speed is about linear in the amplitude: shrink once more
                shrink = 0.95 * ws.tcp_vmax / tcp_speed
                q, dq, ddq = q0 + (q - q0) * shrink, dq * shrink, ddq * shrink
            if not trajectory_ok(q, cc, ws, dt, stride=stride):
                continue
            rows = np.linspace(0, len(t) - 1, 150).astype(np.int64)
            Y = full_regressor(robot.model, data, q[rows], dq[rows], ddq[rows], 0.005)[:, bp.base]
            Y = Y / np.maximum(np.linalg.norm(Y, axis=0), 1e-12)
            cond = float(np.linalg.cond(Y))
            if best is None or cond < best[0]:
                best = (cond, q)
        return best

    segments: list[Segment] = []
    seg_id = segment_base
    prev = np.asarray(cfg.robot.home, float)
    conds = []
    count = len(centres) if centres is not None else fc.trajectories
    for k in range(count):
        # A centre whose every candidate leaves the limits or collides, or that cannot be reached,
        # is replaced by another (given centres are tried first).
        found = None
        for attempt in range(8):
            q0 = centres[k] if centres is not None and attempt == 0 else random_centre()
            best = best_around(q0)
            if best is None:
                continue
            try:
                lead = transfer(prev, best[1][0], robot, cfg, ex, dt, speed=0.7)
            except ValueError:
                continue
            found = (best, lead)
            break
        if found is None:
            log.warning("Fourier trajectory %d: no centre gave a free trajectory within the limits", k)
            continue
        (cond, q), lead = found
        conds.append(cond)
        for seg in lead:  # the way to the start is motion data too: it belongs to this trajectory
            seg.traj, seg.segment, seg.kind = traj_base + k, seg_id, "fourier"
            seg_id += 1
            segments.append(seg)
        # Cut the excitation into one-period segments (whole-segment subsampling stays meaningful).
        per = max(1, int(round(1.0 / fc.base_hz / dt)))
        body = q[1:]
        for c0 in range(0, len(body), per):
            segments.append(Segment(body[c0:c0 + per], traj_base + k, seg_id, 1.0, "fourier"))
            seg_id += 1
        prev = q[-1]
    return Motion(segments, dt, {"trajectories": len(conds), "condition_numbers": [round(c, 1) for c in conds],
                               "duration_s": round(duration, 2)})
