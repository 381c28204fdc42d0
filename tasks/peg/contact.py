"""The peg's contact scenarios (paper Fig. 13), classified from (Mx, My, Fz) and the kinematic depths."""

from __future__ import annotations

import enum
import math

from tasks.peg.config import PegConfig


class Contact(enum.Enum):
    """The paper's contact scenarios (Fig. 13) as the task recognises them."""

    FREE = "free"
    STUCK_OUTSIDE = "stuck_outside"
    STUCK_INSIDE = "stuck_inside"
    ALIGNED = "aligned"


def classify(fz: float, mx: float, my: float, low_depth: float, high_depth: float, cfg: PegConfig) -> Contact:
    """The contact scenario from (Mx, My, Fz) and the kinematic depths of the peg's face below the mouth.

    `low_depth` / `high_depth`: how far the lowest / highest point of the peg's bottom rim is below the
    hole's mouth (forward kinematics of the measured joints).  Free: neither force nor moment.  Outside:
    touching with the whole face above the mouth (it rests on the rim or the plate).  Inside: the lead
    edge is in the hole and the peg touches with one side (its face still on the far rim, or a side
    moment).  Aligned: the whole face in the hole, pushing along the axis without a side load.
    """
    m = math.hypot(mx, my)
    if not (math.isfinite(fz) and math.isfinite(m)):  # a missing reading is never a contact outside
        return Contact.ALIGNED if high_depth >= cfg.engage_depth_m else Contact.FREE
    if fz < cfg.contact_force_n and m < cfg.contact_moment_nm:
        return Contact.FREE
    if low_depth < cfg.inside_depth_m:
        return Contact.STUCK_OUTSIDE
    if high_depth < cfg.engage_depth_m or m >= cfg.side_moment_nm:
        return Contact.STUCK_INSIDE
    return Contact.ALIGNED


# What the strategy acts on in the states a probe chose: the probe's classification (the wrench there is a
# light contact or none, which the per-cycle classification reads as free).
_CHOSEN = {"back_off": Contact.STUCK_OUTSIDE, "slide": Contact.STUCK_INSIDE, "rotate": Contact.STUCK_INSIDE}


def believed(state: str, contact: Contact, high_depth: float, cfg: PegConfig) -> Contact:
    """The classified contact the task works with (the plot's and the view's): the probe's verdict in the
    states it chose, the peg in the bore while inserting (aligned unless a side load says stuck), else this
    cycle's classification."""
    if state in _CHOSEN:
        return _CHOSEN[state]
    if state in ("insert", "realign", "release") and contact == Contact.FREE and high_depth >= cfg.engage_depth_m:
        return Contact.ALIGNED
    return contact
