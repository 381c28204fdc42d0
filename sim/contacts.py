"""The collider's contacts in the plant: the deepest penetration, and the checks of a convex-collider step
(`sim.plant.Plant._physics_step` takes a step that fails them again; config/plants/README.md)."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

# A contact deeper than this is a failed collision detection (Plant._physics_step): the stiff contacts here
# stay within 0.05 mm (99.99 % of contact steps under 0.013 mm: docs/peg.md, "The simulator at tight fits").
MAX_CONTACT_DEPTH_M = 1e-4
RECOLLIDE_TOLERANCE = 1e-10
# The geom types whose contacts MuJoCo's convex collider (CCD) may compute: what `failed_contact` guards
# against.  Sphere, capsule and box pairs among themselves (the wiping pad on the table, the collision
# bench's plates against the pad) have closed-form colliders that cannot fail that way.
CONVEX_COLLIDER_GEOMS = (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                         mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SDF)
BORE_MARGIN_M = 1e-4  # a side contact this far below the hole's mouth is in the bore (Penetration.bore)


def deepest_contact(data: mujoco.MjData) -> float:
    """The deepest penetration [m] among the current contacts (0 without contact)."""
    return -float(np.min(data.contact.dist[:data.ncon])) if data.ncon else 0.0


@dataclasses.dataclass
class Penetration:
    """The deepest contact penetration [m] over the physics steps so far: of any contact; of side contacts
    (normal more than 60 deg from vertical: on a wall, not a touch on a top face or the table); and of side
    contacts more than `BORE_MARGIN_M` below the hole's mouth, where a contact's give widens the fit."""

    any: float = 0.0
    side: float = 0.0
    bore: float = 0.0

    def update(self, data: mujoco.MjData, mouth_site: int = -1) -> None:
        n = data.ncon
        if n == 0:
            return
        # (Python floats first: every physics step with a contact comes here, and most have one or two.)
        c = data.contact
        self.any = max(self.any, -min(c.dist.tolist()))
        if not any(abs(z) < 0.5 for z in c.frame[:, 2].tolist()):
            return
        side = np.abs(c.frame[:n, 2]) < 0.5
        depth = -c.dist[:n]
        self.side = max(self.side, float(depth[side].max()))
        if mouth_site >= 0:
            axis = data.site_xmat[mouth_site].reshape(3, 3)[:, 2]  # out of the hole
            below = (data.site_xpos[mouth_site] - data.contact.pos[:n]) @ axis > BORE_MARGIN_M
            if (side & below).any():
                self.bore = max(self.bore, float(depth[side & below].max()))

    def as_um(self) -> dict[str, float]:
        """The three depths in micrometres, under the bench's keys."""
        return {"max_penetration_um": self.any * 1e6, "max_side_penetration_um": self.side * 1e6,
                "max_bore_penetration_um": self.bore * 1e6}


def failed_contact(model: mujoco.MjModel, data: mujoco.MjData) -> str | None:
    """Why the collider's contacts of the step just taken cannot be right, or None.

    Every geom here is convex, so at a true contact the normal (from geom1 to geom2) supports both: each
    geom's centre lies on its own side of the contact point, to within the penetration.  Two failures of
    MuJoCo's convex collider are caught: a contact far deeper than the bodies' motion allows, and a normal
    pointing the wrong way (a peg on the bore's wall got a +y normal where the wall faces -y: its 133 N
    and its neighbour's opposite 150 N squeezed the peg, and their friction read 87 N at the F/T sensor)."""
    n = data.ncon
    if n == 0:
        return None
    c = data.contact
    depth = deepest_contact(data)
    if depth > MAX_CONTACT_DEPTH_M:
        return f"a {depth * 1e3:.2f} mm deep contact"
    normal, pos, geoms = c.frame[:n, :3], c.pos[:n], c.geom[:n]
    own1 = np.einsum("ij,ij->i", data.geom_xpos[geoms[:, 0]] - pos, normal)
    own2 = np.einsum("ij,ij->i", data.geom_xpos[geoms[:, 1]] - pos, normal)
    if np.any(own1 > MAX_CONTACT_DEPTH_M) or np.any(own2 < -MAX_CONTACT_DEPTH_M):
        return "a contact normal pointing the wrong way"
    return None
