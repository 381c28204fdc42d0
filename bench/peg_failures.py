"""The peg bench's failure reasons, sorted into kinds (jams, safety stops, limits, time) and counted."""

from __future__ import annotations

import collections

# (kind, words that name it in a trial's outcome or reason), first match wins; the reasons are the task's
# (tasks/peg/task.py fail_because), the control loop's (timeout, safety stop) and the collision guard's.
KINDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("collision_detection", ("collision",)),
    ("timeout", ("timeout", "did not finish")),
    ("jammed", ("jammed",)),
    ("task_force_limit", ("push force",)),
    ("task_moment_limit", ("tool moment",)),
    ("stuck_outside", ("stuck outside", "no hole within")),
    ("stuck_retracting", ("stuck while retracting",)),
    ("search_lost", ("without meeting the hole's wall",)),
    ("survey", ("fixture face", "survey")),
    ("shallow", ("done",)),  # the task said done, the plant's true depth says otherwise
)


SAFETY_KINDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("safety_stop_force", ("tool force",)),
    ("safety_stop_torque", ("joint", "torque", "saturated")),
)


def failure_kind(outcome: str, reason: str) -> str:
    text = f"{outcome} {reason}".lower()
    if outcome == "safety_stop" or reason.startswith("safety stop"):
        return next((kind for kind, words in SAFETY_KINDS if any(w in text for w in words)), "safety_stop_other")
    for kind, words in KINDS:
        if any(w in text for w in words):
            return kind
    return "other"


def count_kinds(failures: list[tuple[str, str]]) -> dict[str, int]:
    """{kind: count} over (outcome, reason) of the failed trials, most frequent first."""
    counts = collections.Counter(failure_kind(o, r) for o, r in failures)
    return dict(counts.most_common())
