"""The peg-in-hole task's states, the transitions between them, and the states that make up the insertion."""

from __future__ import annotations

import enum
from typing import Any

from tasks.base import Trigger


class PegState(enum.Enum):
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
    ("arrived", PegState.MOVE_TO_START, PegState.TARE),
    ("tared", PegState.TARE, PegState.SURVEY),
    ("surveyed", PegState.SURVEY, PegState.APPROACH),
    ("touched", PegState.APPROACH, PegState.PROBE),
    ("outside", PegState.PROBE, PegState.BACK_OFF),
    ("false_alarm", PegState.PROBE, PegState.APPROACH),
    ("backed_off", PegState.BACK_OFF, PegState.APPROACH),
    ("inside", PegState.PROBE, PegState.SLIDE),
    ("blocked", PegState.SLIDE, PegState.ROTATE),
    ("upright", PegState.ROTATE, PegState.INSERT),
    ("aligned", [PegState.APPROACH, PegState.PROBE, PegState.SLIDE], PegState.INSERT),
    ("stalled", PegState.INSERT, PegState.REALIGN),
    ("realigned", PegState.REALIGN, PegState.INSERT),
    ("inserted", PegState.INSERT, PegState.RELEASE),
    ("released", PegState.RELEASE, PegState.RETRACT),
    ("retracted", PegState.RETRACT, PegState.DONE),
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
INSERTION_STATES = tuple(s.value for s in (PegState.APPROACH, PegState.PROBE, PegState.BACK_OFF, PegState.SLIDE,
                                             PegState.ROTATE, PegState.INSERT, PegState.REALIGN))
