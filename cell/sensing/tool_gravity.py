"""The tool's weight on the F/T sensor: identified from static poses, subtracted so the sensor reads the contact alone.

Model (linear, so a least-squares fit on a few static poses identifies it): with u(q) the gravity
direction (world -z) in the TCP frame, the unloaded sensor reads

    w(q) = w0 + K u(q),   K = [m g R_s^T ; m g [r]x R_s^T]   (6x3)

w0 the sensor's own offset (whatever tare it had), m the tool's mass, r its centre of mass in the
sensor frame and R_s the sensor frame's fixed rotation against the TCP frame (absorbed into K, so the
sensor need not be mounted square).  The compensated wrench is w - K u(q) - w0; after a tare at q_t
the offset is K u(q_t) instead, so `compensate(w, q, q_tare)` = w - K (u(q) - u(q_t)).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cell.data.atomic import write_atomic
from cell.model.robot import RobotModel
from drivers.errors import DataError

G = 9.80665
FILE = "tool_gravity.json"
MIN_POSES = 4  # 12 unknowns of the force part (w0, K), 3 equations a pose: 4 poses, better 9 spread widely


def gravity_direction(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """World -z (the direction gravity pulls) in the TCP frame at posture q."""
    return np.asarray(robot.tcp_pose(np.asarray(q, float)).rotation.T @ np.array([0.0, 0.0, -1.0]))


@dataclass
class ToolGravity:
    """The identified load: K (6x3), the offset w0 (6,), and what they mean (mass, centre of mass)."""

    K: np.ndarray
    w0: np.ndarray
    fit_rms: np.ndarray  # (6,) residual of the fit per axis [N, N·m]

    @property
    def mass_kg(self) -> float:
        # K's force block is m g R_s^T: every singular value is m g.
        return float(np.mean(np.linalg.svd(self.K[:3], compute_uv=False)) / G)

    @property
    def com_m(self) -> np.ndarray:
        """Centre of mass in the sensor frame: K_m = [r]x K_f, so [r]x = K_m K_f^-1."""
        S = self.K[3:] @ np.linalg.pinv(self.K[:3])
        skew = 0.5 * (S - S.T)  # the antisymmetric part: a noisy fit is not exactly a cross product
        return np.array([skew[2, 1], skew[0, 2], skew[1, 0]])

    def wrench(self, u: np.ndarray) -> np.ndarray:
        """The tool's weight as the sensor reads it (no offset) for the gravity direction u (TCP frame)."""
        return self.K @ np.asarray(u, float)

    def compensate(self, w: np.ndarray, u: np.ndarray, u_tare: np.ndarray | None = None) -> np.ndarray:
        """The contact wrench: `w` less the weight at u; after a tare at u_tare (the weight there is the
        zero the tare took), less only the change since.  Without a tare, less the fitted offset too."""
        if u_tare is None:
            return np.asarray(w, float) - self.wrench(u) - self.w0
        return np.asarray(w, float) - self.wrench(np.asarray(u, float) - np.asarray(u_tare, float))

    def summary(self) -> dict[str, Any]:
        return {"mass_kg": round(self.mass_kg, 4), "com_m": np.round(self.com_m, 4).tolist(),
                "fit_rms_force_n": round(float(np.linalg.norm(self.fit_rms[:3])), 4),
                "fit_rms_moment_nm": round(float(np.linalg.norm(self.fit_rms[3:])), 4)}


def fit(us: np.ndarray, wrenches: np.ndarray) -> ToolGravity:
    """Least squares of w = w0 + K u over static unloaded poses: us (n, 3) gravity directions, wrenches (n, 6)."""
    us, wrenches = np.asarray(us, float), np.asarray(wrenches, float)
    if len(us) < MIN_POSES or len(us) != len(wrenches):
        raise DataError(f"tool gravity: {len(us)} poses; the fit needs at least {MIN_POSES} (9 spread widely)")
    A = np.hstack([np.ones((len(us), 1)), us])  # per axis: w_a = w0_a + K_a . u
    if np.linalg.matrix_rank(A, tol=1e-3) < 4:
        raise DataError("tool gravity: the poses do not turn the tool enough (gravity directions span less than "
                        "3-D); use orientations that differ by tens of degrees about different axes")
    coef, *_ = np.linalg.lstsq(A, wrenches, rcond=None)
    resid = wrenches - A @ coef
    return ToolGravity(K=coef[1:].T.copy(), w0=coef[0].copy(), fit_rms=np.sqrt(np.mean(resid**2, axis=0)))


def save(tg: ToolGravity, folder: Path, extra: dict[str, Any] | None = None) -> Path:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"format": "tmcell-tool-gravity", "format_version": 1, "K": tg.K.tolist(), "w0": tg.w0.tolist(),
           "fit_rms": tg.fit_rms.tolist(), **tg.summary(), **(extra or {})}
    return write_atomic(folder / FILE, json.dumps(doc, indent=1))


def load(folder: Path) -> ToolGravity:
    path = Path(folder) / FILE
    try:
        doc = json.loads(path.read_text())
        K, w0, rms = (np.asarray(doc[k], float) for k in ("K", "w0", "fit_rms"))
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(f"{path}: not a tool-gravity file ({exc})") from None
    if doc.get("format") != "tmcell-tool-gravity" or K.shape != (6, 3) or w0.shape != (6,) or \
            not np.all(np.isfinite(K)) or not np.all(np.isfinite(w0)):
        raise DataError(f"{path}: not a tool-gravity file (format, K 6x3 and w0 6 finite numbers)")
    return ToolGravity(K=K, w0=w0, fit_rms=rms)


class GravityCompensatedSource:
    """A `ForceSource` (the F/T sensor's) less the tool's weight: the contact alone in any pose.  Its tare
    (`rebias`) zeroes the sensor where the arm stands and remembers the gravity direction there."""

    def __init__(self, inner: Any, tool: ToolGravity, robot: RobotModel) -> None:
        self.inner, self.tool, self.robot = inner, tool, robot
        self.name = inner.name
        self._u: np.ndarray | None = None
        self._u_tare: np.ndarray | None = None

    def read(self, state: Any) -> Any:
        w = self.inner.read(state)
        self._u = gravity_direction(self.robot, state.q)
        v = self.tool.compensate(w.vector, self._u, self._u_tare)
        return type(w)(t=w.t, force=v[:3], torque=v[3:])

    def rebias(self) -> None:
        self.inner.rebias()
        self._u_tare = self._u  # the last read's pose: the loop re-zeroes right after a cycle's read


# The identification's postures: home with the wrist turned (joints 4-6), so the tool points down, sideways
# and tilted about both axes while the arm itself stays where the task works (degrees about home).
WRIST_TURNS_DEG = ((0, 0, 0), (0, 45, 0), (0, -45, 0), (45, 0, 0), (-45, 0, 0), (45, 45, 90), (-45, -45, -90),
                   (30, -60, 180), (-30, 60, -180))


def identification_postures(robot: RobotModel, home: np.ndarray) -> list[np.ndarray]:
    """The 9 static postures of the identification, within the joint limits."""
    lim = robot.limits
    out = []
    for turn in WRIST_TURNS_DEG:
        q = np.asarray(home, float).copy()
        q[3:6] += np.radians(turn)
        out.append(np.clip(q, lim.lower + 0.02, lim.upper - 0.02))
    return out
