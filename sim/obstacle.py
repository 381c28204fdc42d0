"""The collision bench's obstacles: a rigid plate, or a plate on a linear spring, placed on mocap bodies;
their contact forces on the arm are watched every physics step (onset and peak fall between control
periods)."""

from __future__ import annotations

import bisect
import math

import mujoco
import numpy as np

from sim.plant import Plant

PARKED = {"rigid": (5.0, 5.0, -5.0), "soft": (-5.0, 5.0, -5.0)}


class Obstacle:
    """Places a plate, sets the spring of the soft one and the tool's payload error, tracks contact forces."""

    def __init__(self, plant: Plant) -> None:
        m = plant.model
        self.plant = plant
        self.geoms = {k: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"obstacle_{k}") for k in PARKED}
        if min(self.geoms.values()) < 0:
            raise ValueError("the plant has no obstacles (build it with scene kind 'obstacle')")
        self.mocap = {
            "rigid": int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "obstacle_rigid")]),
            "soft": int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "obstacle_soft_base")]),
        }
        self.slide = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "obstacle_slide")
        self.tool_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "tool")
        self.tool_mass = float(m.body_mass[self.tool_body])
        self.geom = self.geoms["rigid"]
        self._f6 = np.zeros(6)
        self.reset_watch()
        plant.after_physics_step = self._watch

    def place(self, position: np.ndarray, normal: np.ndarray, stiffness_n_per_m: float | None = None,
              damping_ns_per_m: float = 0.0) -> None:
        """A plate's face through `position` with outward `normal` (toward the arm): the rigid one (None),
        or the one on a spring of this stiffness; the other is parked."""
        kind = "rigid" if stiffness_n_per_m is None else "soft"
        other = "soft" if kind == "rigid" else "rigid"
        m, d = self.plant.model, self.plant.data
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        z = np.array([0.0, 0.0, 1.0])
        axis = np.cross(z, n)
        s = float(np.linalg.norm(axis))
        quat = np.zeros(4)
        mujoco.mju_axisAngle2Quat(quat, axis / s if s > 1e-12 else np.array([1.0, 0.0, 0.0]),
                                  float(np.arctan2(s, float(z @ n))))
        d.mocap_pos[self.mocap[kind]] = np.asarray(position, float)
        d.mocap_quat[self.mocap[kind]] = quat
        d.mocap_pos[self.mocap[other]] = PARKED[other]
        if kind == "soft":
            m.jnt_stiffness[self.slide] = float(stiffness_n_per_m)  # type: ignore[arg-type]
            m.dof_damping[int(m.jnt_dofadr[self.slide])] = float(damping_ns_per_m)
            d.qpos[int(m.jnt_qposadr[self.slide])] = 0.0
            d.qvel[int(m.jnt_dofadr[self.slide])] = 0.0
        self.geom = self.geoms[kind]
        mujoco.mj_forward(m, d)
        self.reset_watch()

    def set_payload_error(self, kg: float) -> None:
        """The tool carries `kg` more (or less) than the controller's model says."""
        m = self.plant.model
        m.body_mass[self.tool_body] = max(0.01, self.tool_mass + kg)
        mujoco.mj_setConst(m, self.plant.data)

    def reset_watch(self) -> None:
        self.onset_t: float | None = None
        self.peak_n = 0.0
        self.trace: list[tuple[float, float]] = []  # (t, contact force [N]) of every physics step from the onset

    def force_at(self, t: float) -> float | None:
        """The contact force [N] at the last physics step at or before `t`, or None before the onset."""
        i = bisect.bisect_right(self.trace, (t, math.inf)) - 1
        return self.trace[i][1] if i >= 0 else None

    def touching(self) -> bool:
        """Whether the placed plate is in contact with anything now."""
        d = self.plant.data
        return any(d.contact[i].geom1 == self.geom or d.contact[i].geom2 == self.geom for i in range(d.ncon))

    def force(self) -> float:
        """|sum of the placed plate's contact forces| on the arm now [N]."""
        m, d = self.plant.model, self.plant.data
        total = np.zeros(3)
        for i in range(d.ncon):
            c = d.contact[i]
            if c.geom1 != self.geom and c.geom2 != self.geom:
                continue
            mujoco.mj_contactForce(m, d, i, self._f6)
            total += c.frame.reshape(3, 3).T @ self._f6[:3]
        return float(np.linalg.norm(total))

    def _watch(self) -> None:
        f = self.force() if self.plant.data.ncon else 0.0
        if f > 0.5 and self.onset_t is None:
            self.onset_t = float(self.plant.data.time)
        if self.onset_t is not None:
            self.trace.append((float(self.plant.data.time), f))
        self.peak_n = max(self.peak_n, f)
