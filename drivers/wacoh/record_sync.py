"""Poll mode's record-number bookkeeping: which request a reply answers, unsettled requests, the resync window."""

from __future__ import annotations

import math
import time
from collections import deque

# Poll mode matches each reply's record number (a digit 0-9 the sensor increments per record) to its
# request.  A request whose reply did not come in time stays "unsettled" (its reply may still arrive,
# and must not pass for a later request's) until a later record settles it or this long has passed: the
# latest a reply is taken to arrive.
LATE_REPLY_S = 0.1
# The number wraps after ten records: once the next request's number is an unsettled request's too (ten
# unanswered requests within LATE_REPLY_S, or any while the numbering is not known) no reply could be
# told from a late one, and accepting one would present a stale record as current.  The driver then
# resynchronises: it sends nothing and discards whatever arrives until LATE_REPLY_S after its last
# request, and until nothing has arrived for one request time (a reply later still is not taken for the
# next request's), then learns the numbering afresh from a new request.  Reads meanwhile return no record.


class RecordSync:
    """The record numbers of poll mode's requests and replies.  No I/O: the driver reports what it sent and
    what arrived, and asks whose reply a record is and whether it may send."""

    def __init__(self) -> None:
        self.last_sent = -math.inf  # when the last `R` was sent
        self.reset()

    def reset(self) -> None:
        """Forget the numbering (a new connection): the next reply teaches it."""
        # The record number the sensor gives its next record (None: not known), and the (record number,
        # send time) of earlier requests whose replies may still arrive.
        self.next_no: int | None = None
        self.unsettled: deque[tuple[int | None, float]] = deque()
        self.resync_until: float | None = None  # resynchronising: send nothing before this

    # ------------------------------------------------------------------ requests and replies
    def sent(self, now: float) -> int | None:
        """A request went out at `now`: the record number its reply will carry (None: not known)."""
        expected = self.next_no
        self.last_sent = now
        if expected is not None:
            self.next_no = (expected + 1) % 10
        return expected

    def answers(self, record_no: int, expected: int | None) -> bool:
        """Whether a record numbered `record_no` answers the request just sent (expecting `expected`).

        A record that answers an unsettled earlier request settles it and every request before it; one
        that answers this request settles them all (replies come in order), and teaches the numbering.
        """
        if expected is None:
            # Nothing unsettled (see WacohSensor._poll_once): whatever comes answers this request.
            self.unsettled.clear()
            self.next_no = (record_no + 1) % 10
            return True
        earlier = [no for no, _ in self.unsettled]
        if record_no in earlier:
            # An earlier request's reply (or, if `expected` too, ambiguous after a wrap: refused).
            for _ in range(earlier.index(record_no) + 1):  # the oldest it may answer: settle the fewest
                self.unsettled.popleft()
            return False
        if record_no == expected:
            self.unsettled.clear()
            return True
        return False

    def unanswered(self, expected: int | None, sent: float) -> None:
        """No reply came in time to the request sent at `sent`: it may still come."""
        self.unsettled.append((expected, sent))

    def corrupt_reply(self, expected: int | None, sent: float) -> None:
        """A corrupt reply came while waiting for the request sent at `sent`."""
        if self.unsettled:
            # A corrupt reply is a reply: the oldest unsettled request's (replies keep their order), and
            # this one's may still come.
            self.unsettled.popleft()
            self.unsettled.append((expected, sent))
        # else it was this request's own reply, corrupted: nothing more will come for it.

    def expire(self) -> None:
        """Settle the requests whose replies are later than any reply is taken to arrive."""
        limit = time.monotonic() - LATE_REPLY_S
        while self.unsettled and self.unsettled[0][1] < limit:
            self.unsettled.popleft()

    # ------------------------------------------------------------------ resynchronisation
    def ambiguous(self) -> bool:
        """Whether a reply to the next request could not be told from an unsettled request's."""
        if not self.unsettled:
            return False
        return self.next_no is None or any(no == self.next_no for no, _ in self.unsettled)

    @property
    def resyncing(self) -> bool:
        return self.resync_until is not None

    def start_resync(self) -> None:
        """Send nothing until LATE_REPLY_S after the last request."""
        self.resync_until = self.last_sent + LATE_REPLY_S

    def extend_resync(self, until: float) -> None:
        """Something still arrived: keep waiting for the line to fall quiet, at least until `until`."""
        assert self.resync_until is not None
        self.resync_until = max(self.resync_until, until)

    def end_resync(self) -> None:
        """The line is quiet: no earlier reply can still come, and the next reply teaches the numbering."""
        self.resync_until, self.next_no = None, None
        self.unsettled.clear()
