"""What a WACOH sensor's reads met: totals for diagnostics, and the current run of failed reads (lost-link error)."""

from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass
class ReadStats:
    """Totals since the sensor object was made (the stream reader updates them under the sensor's lock)."""

    records_ok: int = 0  # valid records taken (poll: replies returned; stream: records received)
    records_rejected: int = 0  # lines that were not a valid record (corrupted, cut short, garbage)
    records_saturated: int = 0  # returned records with a channel at the end of the 14-bit range
    timeouts: int = 0  # poll: requests with no reply in time; stream: reads with no new record in time
    records_stale: int = 0  # poll: valid records that answered an earlier request (discarded, never returned)
    resyncs: int = 0  # poll: resynchronisations started (see record_sync.py)
    resync_reads: int = 0  # poll: reads spent resynchronising, sending no request

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class FailureRun:
    """The reads since the last one that returned a record: what each met, for the lost-link error."""

    timeouts: int = 0  # poll: a request went unanswered in time; stream: no new record came in time
    corrupt: int = 0  # a reply came, but corrupted
    resync_reads: int = 0  # no request: waiting for the line to fall quiet (record_sync.py)
    stale: int = 0  # valid records that arrived in these reads but answered earlier requests

    def clear(self) -> None:
        self.timeouts = self.corrupt = self.resync_reads = self.stale = 0

    def describe(self, counter_steps_by_one: bool | None) -> str:
        """One clause: what the failed reads met (`counter_steps_by_one`: poll mode's finding on the record
        number, None in stream mode)."""
        if counter_steps_by_one is None:
            return f"{self.timeouts} read(s) found no new record in time"
        parts = [f"{self.timeouts} request(s) unanswered in time"]
        if self.corrupt:
            parts.append(f"{self.corrupt} corrupted reply(ies)")
        if self.resync_reads:
            parts.append(f"{self.resync_reads} read(s) resynchronising without a request")
        if self.stale:
            parts.append(f"{self.stale} late record(s) that answered earlier requests, discarded as stale")
        text = ", ".join(parts)
        if self.resync_reads and counter_steps_by_one is False:
            text += ("; the record number was not seen to step by one per reply, so after an unanswered request "
                     "reads wait until no late reply can still arrive")
        return text
