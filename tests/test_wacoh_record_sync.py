"""Poll mode's bookkeeping without I/O: whose reply a record is, what its number is trusted to say, when to resync."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from drivers.wacoh.record_sync import LATE_REPLY_S, MAX_TRUST_STEPS, TRUST_STEPS, RecordSync

Counter = Callable[[int], int]  # request index -> the record number of its reply

PER_REPLY: Counter = lambda i: (3 + i) % 10  # noqa: E731
CONSTANT: Counter = lambda i: 7  # noqa: E731
# A sampling clock read every 1.5 requests' time: steps of 1 and 2 alternate.
PER_SAMPLE: Counter = lambda i: (3 * i // 2) % 10  # noqa: E731


def answered_in_turn(sync: RecordSync, counter: Counter, n: int, t: float = 0.0) -> float:
    """`n` requests, each answered before the next is sent; the time after them."""
    for _ in range(n):
        index = sync.sent(t)
        assert sync.answers(counter(index), index)
        t += 0.001
    return t


@pytest.mark.parametrize("counter", [PER_REPLY, CONSTANT, PER_SAMPLE])
def test_with_nothing_unsettled_the_first_record_answers_whatever_its_number(counter: Counter) -> None:
    sync = RecordSync()
    answered_in_turn(sync, counter, 50)
    assert sync.counter_steps_by_one is (counter is PER_REPLY)
    assert not sync.unsettled and not sync.must_wait()


def test_the_number_is_trusted_only_after_trust_steps_observed_steps_by_one() -> None:
    sync = RecordSync()
    answered_in_turn(sync, PER_REPLY, TRUST_STEPS)  # the first reply is no step: TRUST_STEPS - 1 steps
    assert not sync.counter_steps_by_one and not sync.counter_known
    answered_in_turn(sync, PER_REPLY, 1)
    assert sync.counter_steps_by_one and sync.counter_known


def test_a_step_not_by_one_withdraws_trust_and_asks_for_more_next_time() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, PER_REPLY, TRUST_STEPS + 1)
    index = sync.sent(t)
    assert sync.answers(PER_REPLY(index) + 1, index)  # nothing unsettled: its reply, but the number jumped
    assert not sync.counter_steps_by_one and sync.counter_known
    assert sync.trust_steps == 2 * TRUST_STEPS
    shifted: Counter = lambda i: (PER_REPLY(i) + 1) % 10  # noqa: E731
    t = answered_in_turn(sync, shifted, 2 * TRUST_STEPS - 1, t + 0.001)
    assert not sync.counter_steps_by_one
    answered_in_turn(sync, shifted, 1, t)
    assert sync.counter_steps_by_one


def test_a_clock_driven_number_that_keeps_pace_for_a_while_is_not_trusted_for_it() -> None:
    """Reads in step with the sensor's sampling clock see one step per reply for a while; every slip shows the
    truth, and each asks for a longer run before the number is trusted again."""
    sync = RecordSync()
    t, no = 0.0, 0
    for burst in range(12):
        for _ in range(TRUST_STEPS + 1):
            index = sync.sent(t)
            assert sync.answers(no % 10, index)
            no += 1
        no += 1  # the reads slip behind the clock by a sample
        if burst:
            assert not sync.counter_steps_by_one, burst
    assert sync.trust_steps == MAX_TRUST_STEPS


@pytest.mark.parametrize("counter", [CONSTANT, PER_SAMPLE])
def test_without_trust_any_unsettled_request_means_wait(counter: Counter) -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, counter, 30)
    index = sync.sent(t)
    sync.unanswered(index, t)
    assert sync.must_wait()


def test_with_trust_a_late_reply_is_told_by_its_number() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, PER_REPLY, TRUST_STEPS + 1)
    late = sync.sent(t)
    sync.unanswered(late, t)
    assert not sync.must_wait()  # one unsettled request: its number differs from the next one's
    index = sync.sent(t + 0.006)
    assert not sync.answers(PER_REPLY(late), index)  # the late reply: stale
    assert not sync.unsettled
    assert sync.answers(PER_REPLY(index), index)


def test_with_trust_a_lost_reply_is_skipped_by_the_next_ones_number() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, PER_REPLY, TRUST_STEPS + 1)
    lost = sync.sent(t)
    sync.unanswered(lost, t)
    index = sync.sent(t + 0.006)
    assert sync.answers(PER_REPLY(index), index)
    assert not sync.unsettled and sync.counter_steps_by_one


def test_ten_unsettled_requests_use_up_the_numbers() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, PER_REPLY, TRUST_STEPS + 1)
    for k in range(10):
        assert not sync.must_wait()
        index = sync.sent(t + k * 0.001)
        sync.unanswered(index, t + k * 0.001)
    assert sync.must_wait()  # the next request's number is the oldest unsettled request's


def test_a_number_that_contradicts_the_trusted_counter_puts_everything_in_doubt() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, PER_REPLY, TRUST_STEPS + 1)
    late = sync.sent(t)
    sync.unanswered(late, t)
    index = sync.sent(t + 0.006)
    assert not sync.answers((PER_REPLY(index) + 5) % 10, index)  # neither the late one's nor this one's
    assert sync.doubt and not sync.counter_steps_by_one
    assert not sync.answers(PER_REPLY(index), index)  # nothing is accepted in doubt, not even the expected number
    sync.unanswered(index, t + 0.006)
    assert sync.must_wait()
    sync.start_resync()
    for _ in range(5):
        sync.reply_arrived()
    assert not sync.all_answered  # in doubt the list of unsettled requests may be short: only a quiet line ends it
    sync.end_resync()
    assert not sync.doubt and not sync.must_wait()


def test_a_resync_ends_early_once_every_unsettled_request_is_answered() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, CONSTANT, 5)
    for k in range(2):
        index = sync.sent(t + k * 0.006)
        sync.unanswered(index, t + k * 0.006)
    sync.start_resync()
    assert sync.resync_until == pytest.approx(t + 0.006 + LATE_REPLY_S)
    sync.reply_arrived()
    assert not sync.all_answered
    sync.reply_arrived()
    assert sync.all_answered


def test_a_corrupt_reply_with_requests_unsettled_keeps_the_newest_unsettled() -> None:
    sync = RecordSync()
    t = answered_in_turn(sync, PER_REPLY, TRUST_STEPS + 1)
    late = sync.sent(t)
    sync.unanswered(late, t)
    index = sync.sent(t + 0.006)
    sync.corrupt_reply(index, t + 0.006)  # the late one's reply, corrupted; or this one's, and the late one lost
    assert [r.index for r in sync.unsettled] == [index]
    fresh = RecordSync()
    index = fresh.sent(0.0)
    fresh.corrupt_reply(index, 0.0)  # nothing else awaited a reply: this one's, and nothing more comes
    assert not fresh.unsettled


def test_unsettled_requests_expire_after_the_late_reply_window() -> None:
    sync = RecordSync()
    index = sync.sent(1.0)
    sync.unanswered(index, 1.0)
    sync.expire(now=1.0 + LATE_REPLY_S / 2)
    assert sync.unsettled
    sync.expire(now=1.0 + LATE_REPLY_S * 1.01)
    assert not sync.unsettled
