"""Poll mode's bookkeeping: which request a record answers, requests still awaiting a reply, what the record number
does, the resync window.  No I/O: the driver reports what it sent and what arrived, and asks whose reply a record
is and whether it may send."""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

# Replies come in order, one per request.  So when no earlier request awaits its reply, the first record after
# a request is its reply, whatever its record number says.  A request whose reply did not come in time stays
# "unsettled" (its reply may still arrive, and must not pass for a later request's) until a record settles it or
# this long has passed: the latest a reply is taken to arrive.
LATE_REPLY_S = 0.1
# The record number (byte 0, a digit 0-9) is a wrapping counter, but what advances it is not known: one per
# reply, one per internal sample, or nothing (constant) are all possible.  Only once the counter has been seen to
# step by exactly one per request over TRUST_STEPS consecutive observations (between replies known by their
# order to answer their requests) does the driver tell a late reply from a current one by its number.
# Otherwise, and whenever the number could belong to several requests (ten or more requests apart), it
# resynchronises: it sends nothing and discards what arrives until every unsettled request has had a reply, or
# until LATE_REPLY_S after its last request and the line is quiet.  Reads meanwhile return no record.  Every
# time the number is seen not to step by one, TRUST_STEPS more are asked for on this connection (up to
# MAX_TRUST_STEPS): a number that follows the sensor's sampling clock steps by one per reply for a while when
# the reads happen to keep pace with it, and must not be trusted for that.
TRUST_STEPS = 10
MAX_TRUST_STEPS = 100


@dataclass(frozen=True)
class Request:
    index: int  # requests sent on this connection before it
    sent: float  # time.monotonic() when it went out


class RecordSync:
    """The requests of poll mode and the record numbers of their replies."""

    def __init__(self) -> None:
        self.last_sent = -math.inf  # when the last `R` was sent
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new connection): the counter's behaviour is learned afresh."""
        self.next_index = 0
        self.unsettled: deque[Request] = deque()  # oldest first
        self.resync_until: float | None = None  # resynchronising: send nothing before this
        # (request index, record number) of the latest reply whose request is known; how many steps between such
        # replies in a row advanced the number by one per request, and how many did not (this connection).
        self._anchor: tuple[int, int] | None = None
        self._steps_by_one = 0
        self._contradictions = 0
        # Set when a record's number contradicts the counter it was trusted to follow while requests were
        # unsettled: the numbers that settled them earlier are no longer believed, so `unsettled` may lack
        # requests whose replies can still come.  Until a quiet line proves otherwise, nothing is accepted.
        self.doubt = False

    # ------------------------------------------------------------------ the record number
    @property
    def trust_steps(self) -> int:
        """How many steps by one in a row make the record number trusted now."""
        return min(MAX_TRUST_STEPS, TRUST_STEPS * (1 + self._contradictions))

    @property
    def counter_steps_by_one(self) -> bool:
        """Whether the record number has advanced by one per request over the last `trust_steps` observations."""
        return self._steps_by_one >= self.trust_steps

    @property
    def counter_known(self) -> bool:
        """Whether the record number's behaviour is settled: it steps by one per request, or the latest observation
        showed that it does not."""
        return self.counter_steps_by_one or (self._contradictions > 0 and self._steps_by_one == 0)

    def expected_no(self, index: int) -> int | None:
        """The record number the reply to request `index` carries if the counter steps by one per request."""
        if self._anchor is None:
            return None
        anchor_index, anchor_no = self._anchor
        return (anchor_no + index - anchor_index) % 10

    def _observe(self, index: int, record_no: int) -> None:
        """A reply known to answer request `index` (by order, not by its number) carries `record_no`."""
        if self._anchor is not None and 0 < index - self._anchor[0] < 10:
            # Requests between the two whose replies were lost or corrupted consumed numbers too.
            if self.expected_no(index) == record_no:
                self._steps_by_one += 1
            else:
                self._contradicted()
        self._anchor = (index, record_no)

    def _contradicted(self) -> None:
        self._steps_by_one = 0
        self._contradictions += 1

    # ------------------------------------------------------------------ requests and replies
    def sent(self, now: float) -> int:
        """A request went out at `now`: its index."""
        index = self.next_index
        self.next_index += 1
        self.last_sent = now
        return index

    def must_wait(self) -> bool:
        """Whether a reply to a new request could not be told from an unsettled request's: resynchronise first."""
        if self.doubt:
            return True
        if not self.unsettled:
            return False
        return not self.counter_steps_by_one or self.next_index - self.unsettled[0].index >= 10

    def answers(self, record_no: int, index: int) -> bool:
        """Whether a valid record numbered `record_no`, arriving while request `index` (the newest) waits, is its
        reply.  False: it answers an unsettled earlier request (which it settles), or it cannot be placed."""
        if self.doubt:
            return False
        if not self.unsettled:
            # Nothing else awaits a reply: by order it is this request's, and it shows what the counter does.
            self._observe(index, record_no)
            return True
        if self.counter_steps_by_one:
            for k, request in enumerate(self.unsettled):
                if self.expected_no(request.index) == record_no:
                    for _ in range(k + 1):  # it and the requests before it, whose replies are lost
                        self.unsettled.popleft()
                    return False
            if record_no == self.expected_no(index):
                self.unsettled.clear()
                self._anchor = (index, record_no)
                return True
            # Neither: the counter does not do what it was seen to do.
            self._contradicted()
            self.doubt = True
            return False
        # Not reached through the driver (it resynchronises first): the oldest unsettled request's reply, the
        # reading that never takes an earlier reply for a later one.
        self.unsettled.popleft()
        return False

    def unanswered(self, index: int, sent: float) -> None:
        """No reply came in time to request `index`: it may still come."""
        self.unsettled.append(Request(index, sent))

    def corrupt_reply(self, index: int, sent: float) -> None:
        """A corrupt reply came while request `index` waited."""
        if not self.unsettled and not self.doubt:
            return  # this request's own reply, corrupted: nothing more will come for it
        # Else it may be an earlier request's (replies keep their order), and this one's may still come.  In
        # doubt the list of unsettled requests may be short: none is taken as answered.
        if not self.doubt:
            self.unsettled.popleft()
        self.unsettled.append(Request(index, sent))

    def expire(self, now: float | None = None) -> None:
        """Settle the requests whose replies are later than any reply is taken to arrive."""
        limit = (time.monotonic() if now is None else now) - LATE_REPLY_S
        while self.unsettled and self.unsettled[0].sent < limit:
            self.unsettled.popleft()

    # ------------------------------------------------------------------ resynchronisation
    @property
    def resyncing(self) -> bool:
        return self.resync_until is not None

    def start_resync(self) -> None:
        """Send nothing until LATE_REPLY_S after the last request (or until every unsettled request is answered)."""
        self.resync_until = self.last_sent + LATE_REPLY_S

    def reply_arrived(self) -> None:
        """While resynchronising a reply (valid or corrupt) arrived: the oldest unsettled request's, in order."""
        if self.unsettled:
            self.unsettled.popleft()

    @property
    def all_answered(self) -> bool:
        """While resynchronising: every unsettled request has had its reply, so none can still come (not in doubt,
        where the list of unsettled requests may be short)."""
        return not self.unsettled and not self.doubt

    def extend_resync(self, until: float) -> None:
        """Something still arrived: keep waiting for the line to fall quiet, at least until `until`."""
        assert self.resync_until is not None
        self.resync_until = max(self.resync_until, until)

    def end_resync(self) -> None:
        """No earlier reply can still come: the next request's reply is the first record after it."""
        self.resync_until = None
        self.unsettled.clear()
        self.doubt = False
