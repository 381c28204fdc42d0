"""The shared skeleton of task state machines: Enum states, a `transitions` machine, done/failed, abort."""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from typing import Any

from transitions import Machine

log = logging.getLogger(__name__)

# A task's states before it can touch anything (moving to its start, re-zeroing): scores such as the peak
# contact force leave them out.
SETUP_STATES = ("move_to_start", "tare")

# A trigger method: `transitions` binds one per transition name onto the model at run time (it returns
# whether the transition happened).  Subclasses declare theirs as class annotations, never assigned: an
# attribute that already exists on the model would stop `transitions` from binding the trigger.
Trigger = Callable[[], bool]


class MachineTask:
    """A task whose states are an Enum with DONE and FAILED members; `fail` is allowed from anywhere.

    Subclasses list their forward transitions as (trigger, source, dest) and implement one method
    per state, `_<state value>(obs, ...)`, that the task's `step` dispatches to.  `t_state` is the
    time spent in the current state (reset on entry; the subclass advances it by dt per step).
    Each trigger is declared in the class body as `name: Trigger` (annotation only) so that it is typed.
    """

    name = "task"
    States: type[enum.Enum]
    # The states in which the task works on its workpiece, after its tare: only there are the virtual sensor
    # and the F/T sensor compared (before the tare the F/T sensor still carries its unloaded offset, and in
    # free moves both read noise).  Every task declares its own; () scores nothing.
    working_states: tuple[str, ...] = ()
    # The states in which a touch is expected (the virtual sensor reads fast there, and the run reports how
    # much of a touch's peak it saw); () for a task that never touches on purpose.
    touch_states: tuple[str, ...] = ()
    state_log_level = logging.INFO  # state changes are logged at this level (long data runs: DEBUG)
    fail: Trigger

    def __init__(self, initial: enum.Enum, transitions: list[tuple[str, Any, Any]]) -> None:
        self.state: Any = initial
        self.machine = Machine(model=self, states=type(initial), initial=initial, auto_transitions=False,
                               after_state_change="_entered")
        for trigger, source, dest in transitions:
            self.machine.add_transition(trigger, source, dest)
        self.machine.add_transition("fail", "*", type(initial)["FAILED"])
        self.reason = ""
        self.t_state = 0.0

    @property
    def done(self) -> bool:
        return self.state.name in ("DONE", "FAILED")

    @property
    def state_name(self) -> str:
        return str(self.state.value)

    @property
    def outcome(self) -> str:
        return {"DONE": "done", "FAILED": "failed"}.get(self.state.name, "running")

    def abort(self, reason: str) -> None:
        if not self.done:
            self.fail_because(reason)

    def fail_because(self, reason: str) -> None:
        self.reason = reason
        self.fail()

    def _entered(self) -> None:
        self.t_state = 0.0
        log.log(self.state_log_level, "%s: %s", self.name, self.state_name)
