"""Poll mode of the WACOH sensor: one `R` per read, each reading the answer to its own request (record_sync.py)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from drivers.serial_link import SerialLink
from drivers.wacoh.codec import CMD_RECORD, MAX_LINE, RECORD_LEN, RecordReader, decode_counts
from drivers.wacoh.record_sync import LATE_REPLY_S, TRUST_STEPS, RecordSync
from drivers.wacoh.stats import FailureRun, ReadStats

log = logging.getLogger(__name__)

# At connect, requests with this much patience each (a reply later than this is taken never to come) show what
# advances the record number, so that reads know from the start whether a late reply can be told by its number.
# The pauses between them vary, so a number that follows the sensor's own sampling clock does not pass for one
# that steps once per reply by keeping pace with the requests.  Probing stops once the counter is known, after
# PROBE_MAX_FAILED requests without a valid reply, or after PROBE_MAX requests.
PROBE_WAIT_S = LATE_REPLY_S
PROBE_PAUSES_S = (0.0, 0.0015, 0.004)
PROBE_MAX = 2 * (TRUST_STEPS + 1)
PROBE_MAX_FAILED = 3


@dataclass(frozen=True)
class Sample:
    seq: int  # increments with every valid record taken (stream mode freshness)
    t: float  # host receive time, time.monotonic()
    counts: np.ndarray  # (6,) raw counts, sensor axes


class Poller:
    """Sends `R` and returns its reply's record; counts into `stats` and `run` (shared with the sensor)."""

    def __init__(self, link: SerialLink, framer: RecordReader, port: str, timeout_s: float, stats: ReadStats,
                 run: FailureRun) -> None:
        self.link = link
        self.framer = framer
        self.port = port
        self.timeout_s = timeout_s
        self.stats = stats
        self.run = run
        self.sync = RecordSync()

    def reset(self) -> None:
        """A new connection: nothing is known of the record number, no request awaits a reply."""
        self.sync.reset()

    @property
    def request_s(self) -> float:
        """What one request may take: the timeout plus the reply's time on the wire."""
        return self.timeout_s + self.link.wire_time(RECORD_LEN)

    # ------------------------------------------------------------------ connect
    def probe(self) -> int:
        """Connect's requests (see PROBE_WAIT_S); the number of valid replies.  Counted in no statistic."""
        replies = failed = 0
        for i in range(PROBE_MAX):
            if i:
                time.sleep(PROBE_PAUSES_S[i % len(PROBE_PAUSES_S)])
            if self.poll(wait_s=PROBE_WAIT_S, count=False) is None:
                failed += 1
                if failed >= PROBE_MAX_FAILED:
                    break
                continue
            replies += 1
            if self.sync.counter_known:
                break
        if self.sync.counter_steps_by_one:
            log.info("WACOH sensor on %s: the record number steps by one per reply; a late reply is told by it",
                     self.port)
        elif replies:
            log.info("WACOH sensor on %s: the record number was not seen to step by one per reply (%d replies); "
                     "after an unanswered request, reads wait until no late reply can still arrive (up to "
                     "%.0f ms)", self.port, replies, LATE_REPLY_S * 1e3)
        return replies

    # ------------------------------------------------------------------ reading
    def poll(self, wait_s: float | None = None, count: bool = True) -> Sample | None:
        """Send one `R` and read until *its* record arrives; None on timeout, a corrupt reply, or while
        resynchronising (no request sent).  A record that answers an earlier request is discarded, never
        returned.  `wait_s` overrides the timeout; `count=False` leaves the statistics alone."""
        sync = self.sync
        if not sync.resyncing:
            sync.expire()
            if sync.must_wait():
                self._start_resync(count)
        if sync.resyncing and not self._resync_read(count):
            self.stats.resync_reads += count
            self.run.resync_reads += count
            return None
        # Clear leftovers first: a partial earlier reply must not pass for this one (pitfall 4).
        self.framer.reset()
        self.link.discard_input()
        self.link.write(CMD_RECORD, "record request")
        sent = time.monotonic()
        index = sync.sent(sent)
        deadline = sent + (self.timeout_s if wait_s is None else wait_s) + self.link.wire_time(RECORD_LEN)
        framer = self.framer
        rejected0, long0 = framer.rejected, framer.long_rejected
        try:
            while True:
                # Ask for exactly what completes the record: the read returns as soon as it is there.
                chunk = self.link.read_chunk(max(1, RECORD_LEN - framer.pending), deadline)
                if not chunk:
                    if time.monotonic() >= deadline:
                        break
                    continue
                for frame in framer.feed(chunk):
                    record_no, counts = decode_counts(frame)
                    if sync.answers(record_no, index):
                        self.stats.records_ok += count
                        return Sample(seq=self.stats.records_ok, t=time.monotonic(), counts=counts)
                    self.stats.records_stale += count
                    self.run.stale += count
                if framer.long_rejected > long0:
                    # A reply came but was corrupt (or it was an earlier request's, and this one's is still
                    # to come: this request stays unsettled).
                    break
            if framer.long_rejected == long0:
                self.stats.timeouts += count
                self.run.timeouts += count
                sync.unanswered(index, sent)
            else:
                self.run.corrupt += count
                sync.corrupt_reply(index, sent)
            return None
        finally:
            self.stats.records_rejected += (framer.rejected - rejected0) * count

    # ------------------------------------------------------------------ resynchronisation
    def _start_resync(self, count: bool) -> None:
        sync = self.sync
        self.stats.resyncs += count
        why = ("the record number contradicted the counter it was seen to follow" if sync.doubt else
               f"{len(sync.unsettled)} unanswered request(s) may still be answered and the record number cannot "
               "tell a late reply from a new one")
        sync.start_resync()
        log.warning("WACOH sensor on %s: %s; resynchronising (no request until they are answered or %.0f ms "
                    "passed)", self.port, why, LATE_REPLY_S * 1e3)

    def _resync_read(self, count: bool) -> bool:
        """One read's share of a resynchronisation: discard what arrives (each arrival answers the oldest unsettled
        request) for at most one request time, so that a read costs no more than one that times out.  True once no
        earlier reply can still come and this read has its whole request time left: it then sends its request."""
        sync = self.sync
        until = sync.resync_until
        assert until is not None
        now = time.monotonic()
        waiting = now < until
        # Past the window only one look, so that this read still has its whole timeout for the request.
        arrived = self._drain(min(until, now + self.request_s) if waiting else now, count)
        if sync.all_answered:
            sync.end_resync()
            return not arrived and not waiting
        if arrived:
            # Still arriving: later than any reply should be, so wait for the line to fall quiet.
            sync.extend_resync(time.monotonic() + self.request_s)
            return False
        if waiting:
            return False
        sync.end_resync()
        return True

    def _drain(self, deadline: float, count: bool) -> bool:
        """Read and discard whatever arrives until `deadline` (looking at least once), or until every unsettled
        request is answered; whether anything arrived."""
        arrived = False
        framer, sync = self.framer, self.sync
        while True:
            chunk = self.link.read_chunk(MAX_LINE, deadline)
            if chunk:
                arrived = True
                long0 = framer.long_rejected
                frames = framer.feed(chunk)
                self.stats.records_stale += len(frames) * count
                self.run.stale += len(frames) * count
                for _ in range(len(frames) + framer.long_rejected - long0):
                    sync.reply_arrived()
                if sync.all_answered:
                    return arrived
            elif time.monotonic() >= deadline:
                return arrived
