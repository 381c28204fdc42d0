"""The peg-in-hole task's states, the transitions between them, and the states that make up the insertion."""

from __future__ import annotations

import enum
from typing import Any

from tasks.base import Trigger


class S(enum.Enum):
    MOVE_TO_START = "move_to_start"
    TARE = "tare"
    SURVEY = "survey"  # touch the fixture's top face at a few points: its normal is the hole's axis
    APPROACH = "approach"  # tilted peg, its lowest rim point over the nominal hole centre, down to contact
    PROBE = "probe"  # hold a light contact force and classify the contact
    BACK_OFF = "back_off"  # stuck outside: lift a little, tilt the lead another way and shift laterally
    SLIDE = "slide"  # stuck inside (lead edge in, face on the far rim): shift toward the lead side
    ROTATE = "rotate"  # stuck inside against the wall: rotate upright about the wall contact while pushing
    INSERT = "insert"  # push to the target depth under impedance control, rotating/shifting to null (Mx, My)
    REALIGN = "realign"  # stalled inside: lift a little and comply at a light force, then push again
    RELEASE = "release"
    RETRACT = "retract"
    DONE = "done"
    FAILED = "failed"


# (trigger, source, destination); `fail` is allowed from anywhere (MachineTask)
TRANSITIONS: list[tuple[str, Any, Any]] = [
    ("arrived", S.MOVE_TO_START, S.TARE),
    ("tared", S.TARE, S.SURVEY),
    ("surveyed", S.SURVEY, S.APPROACH),
    ("touched", S.APPROACH, S.PROBE),
    ("outside", S.PROBE, S.BACK_OFF),
    ("false_alarm", S.PROBE, S.APPROACH),
    ("backed_off", S.BACK_OFF, S.APPROACH),
    ("inside", S.PROBE, S.SLIDE),
    ("blocked", S.SLIDE, S.ROTATE),
    ("upright", S.ROTATE, S.INSERT),
    ("aligned", [S.APPROACH, S.PROBE, S.SLIDE], S.INSERT),
    ("stalled", S.INSERT, S.REALIGN),
    ("realigned", S.REALIGN, S.INSERT),
    ("inserted", S.INSERT, S.RELEASE),
    ("released", S.RELEASE, S.RETRACT),
    ("retracted", S.RETRACT, S.DONE),
]


class PegTriggers:
    """The triggers of TRANSITIONS, declared for the type checker; `transitions` binds them at run time."""

    arrived: Trigger
    tared: Trigger
    surveyed: Trigger
    touched: Trigger
    outside: Trigger
    false_alarm: Trigger
    backed_off: Trigger
    inside: Trigger
    blocked: Trigger
    upright: Trigger
    aligned: Trigger
    stalled: Trigger
    realigned: Trigger
    inserted: Trigger
    released: Trigger
    retracted: Trigger


# The states from the first approach to the end of the insertion: the wrench errors are scored over these.
INSERTION_STATES = (S.APPROACH.value, S.PROBE.value, S.BACK_OFF.value, S.SLIDE.value, S.ROTATE.value,
                    S.INSERT.value, S.REALIGN.value)
