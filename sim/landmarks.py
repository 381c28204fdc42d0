"""Where the simulated cell's fixtures truly are (from the plant's MuJoCo model): what a task file's reports
are scored against on the simulated cell."""

from __future__ import annotations

import mujoco
import numpy as np

from sim.plant import Plant


def landmarks(plant: Plant) -> dict[str, list[float]]:
    """Named points of the scene [m, base frame]: the peg fixture's block corner (+x, +y; its vertical edge
    in xy) and its hole's centre (the mouth, in xy), and the table's top."""
    m, d = plant.model, plant.data
    mujoco.mj_kinematics(m, d)
    out: dict[str, list[float]] = {}
    block = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "hole_bottom")
    if block >= 0:
        R = np.asarray(d.geom_xmat[block]).reshape(3, 3)
        corner = np.asarray(d.geom_xpos[block]) + R @ np.asarray(m.geom_size[block])
        out["fixture_corner_xy"] = corner[:2].tolist()
    mouth = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "hole_top")
    if mouth >= 0:
        out["hole_center_xy"] = np.asarray(d.site_xpos[mouth])[:2].tolist()
    table = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "table")
    if table >= 0:
        out["table_top_z"] = [float(d.geom_xpos[table][2] + m.geom_size[table][2])]
    return out
