"""The peg's compliant motions in the hole: the impedance law's step along the peg (eq. 24), the rotate-and-shift
that nulls the side load, the rotation upright about the wall, and dropping the servo's wound-up lag; each moves
the task's reference pose (hole frame) in place."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from cell.control.impedance import DiscreteImpedance
from tasks.peg.config import PegConfig
from tasks.peg.geometry import EZ


def relieve(ref: pin.SE3, tip: pin.SE3, law: DiscreteImpedance) -> None:
    """Move the reference back to the measured tip along the peg axis (drop the servo's lag windup)."""
    axis = ref.rotation[:, 2]
    ahead = float((ref.translation - tip.translation) @ axis)
    if ahead > 0:
        ref.translation -= axis * ahead
    law.reset()


def regulate(ref: pin.SE3, law: DiscreteImpedance, fz: float, setpoint: float, direction: np.ndarray,
             vmax: float) -> None:
    """One step of the discretised impedance law (eq. 24) along `direction` (into the hole), at most `vmax`."""
    if not np.isfinite(fz):
        return  # hold on a missing reading; the safety monitor counts them
    dz = float(law.update(setpoint - fz)[0])
    dz = float(np.clip(dz, -vmax, vmax))
    ref.translation += direction * dz


def comply(ref: pin.SE3, mx: float, my: float, cfg: PegConfig, dt: float, scale: float = 1.0) -> None:
    """Rotate about the tip and shift it so the side load goes away (the paper's rotate and shift)."""
    if not (np.isfinite(mx) and np.isfinite(my)):
        return
    c = cfg
    m = np.array([mx, my])
    if np.linalg.norm(m) < c.comply_deadband_nm:
        return  # inside the force source's error band: hold
    rot_tool = np.array([m[0], m[1], 0.0]) * c.rotation_gain * scale * dt
    shift_tool = np.array([-m[1], m[0], 0.0]) * c.shift_gain * scale * dt
    R = ref.rotation
    ref.translation += R @ shift_tool
    ref.rotation = R @ pin.exp3(rot_tool)


def rotate_upright(ref: pin.SE3, pivot: np.ndarray, ref_tilt: float, fz: float, cfg: PegConfig, dt: float) -> float:
    """Rotate the reference toward upright (by at most its tilt `ref_tilt`) about the wall contact `pivot` on the
    lead side; the push Fz as a share of rotate_max_force_n (over 1: the rotation is blocked)."""
    c = cfg
    z = ref.rotation[:, 2]
    axis = np.cross(z, -EZ)
    axis /= np.linalg.norm(axis)
    # Slow the rotation as the push builds (the hole's own tilt is unknown: the far side may touch).
    push = fz / c.rotate_max_force_n if np.isfinite(fz) else 1.0
    da = min(math.radians(c.rotate_rate_dps) * dt * max(0.0, 1.0 - push), ref_tilt)
    Rw = pin.exp3(axis * da)
    ref.translation = pivot + Rw @ (ref.translation - pivot)
    ref.rotation = Rw @ ref.rotation
    return push
