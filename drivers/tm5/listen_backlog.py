"""Scripts sent to the Listen node and not yet answered: how far the node lags behind the command stream."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

from drivers.errors import LinkLostError

_REMEMBERED_LAGS = 256  # answered scripts whose reply lag stays readable (a burst of doctor's, with room)


class ListenBacklogError(LinkLostError):
    """The Listen node owes replies to too many scripts, or for too long: what it queued acts late or not at all.

    Raised while armed, it faults the arm like a lost link: the fault's stop sends StopAndClearBuffer (which
    discards whatever speeds the node still queues) and StopContinueVmode, without waiting for replies."""


@dataclass(frozen=True)
class ReplyLag:
    """A burst of scripts streamed at a fixed rate: how late their replies came [s]."""

    sent: int
    answered: int
    median_s: float  # nan when none was answered
    max_s: float
    max_unanswered: int  # the most earlier scripts still unanswered when the next one went out

    def summary(self) -> str:
        return (f"{self.answered}/{self.sent} answered, reply lag median {self.median_s * 1e3:.1f} ms, max "
                f"{self.max_s * 1e3:.1f} ms, up to {self.max_unanswered} unanswered when the next was sent")


@dataclass(frozen=True)
class _Pending:
    name: str  # the script's first statement's function name, e.g. SetContinueVJog
    sent_s: float


class ReplyBacklog:
    """The ids of the scripts sent and not yet answered, oldest first, on the host's monotonic clock.

    `check` raises ListenBacklogError when more than `max_unanswered` are outstanding or the oldest is older
    than `max_age_s`.  Replies arrive on later polls; nothing here waits.
    """

    def __init__(self, source: str, max_unanswered: int, max_age_s: float) -> None:
        self.source = source
        self.max_unanswered = max_unanswered
        self.max_age_s = max_age_s
        self._pending: OrderedDict[str, _Pending] = OrderedDict()
        self._lags: OrderedDict[str, float] = OrderedDict()

    @property
    def count(self) -> int:
        return len(self._pending)

    def pending(self, tid: str) -> bool:
        return tid in self._pending

    def sent(self, tid: str, name: str, now: float) -> None:
        self._pending[tid] = _Pending(name, now)

    def answered(self, tid: str, now: float) -> str | None:
        """Mark `tid` answered; its function name, or None for a script this backlog does not hold."""
        entry = self._pending.pop(tid, None)
        if entry is None:
            return None
        self._lags[tid] = now - entry.sent_s
        while len(self._lags) > _REMEMBERED_LAGS:
            self._lags.popitem(last=False)
        return entry.name

    def answer_oldest(self, now: float) -> str | None:
        """A reply that names no script (`$CPERR`) answers the oldest outstanding one: the node answers in order."""
        if not self._pending:
            return None
        return self.answered(next(iter(self._pending)), now)

    def lag(self, tid: str) -> float | None:
        """The reply lag of a recently answered script [s]."""
        return self._lags.get(tid)

    def clear(self) -> None:
        self._pending.clear()

    def check(self, now: float) -> None:
        if not self._pending:
            return
        tid, oldest = next(iter(self._pending.items()))
        age = now - oldest.sent_s
        n = len(self._pending)
        if n > self.max_unanswered:
            raise ListenBacklogError(
                f"{self.source}: {n} scripts unanswered (limit max_unanswered_scripts {self.max_unanswered}), the "
                f"oldest ({oldest.name}, script {tid}) sent {age * 1e3:.0f} ms ago: the Listen node falls behind "
                "the command stream, so the speeds it queues act late")
        if age > self.max_age_s:
            raise ListenBacklogError(
                f"{self.source}: script {tid} ({oldest.name}) unanswered for {age * 1e3:.0f} ms (limit "
                f"max_reply_age_s {self.max_age_s * 1e3:.0f} ms): the Listen node lags or the link stalls")
