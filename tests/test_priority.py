"""A wall-clock loop runs at raised priority where the OS permits it, and gives it back afterwards."""

from __future__ import annotations

import logging
import os
from typing import Any

import pytest

from cell.control import priority


@pytest.fixture
def scheduler(monkeypatch):
    """A fake scheduler: records the policy and nice calls; `refuse` lists what it does not permit."""
    state: dict[str, Any] = {"policy": os.SCHED_OTHER, "nice": 0, "calls": [], "refuse": set()}

    def setscheduler(pid: int, policy: int, param: os.sched_param) -> None:
        if "realtime" in state["refuse"] and policy == os.SCHED_FIFO:
            raise PermissionError("not permitted")
        state["calls"].append(("policy", policy, param.sched_priority))
        state["policy"] = policy

    def setpriority(which: int, who: int, nice: int) -> None:
        if "nice" in state["refuse"]:
            raise PermissionError("not permitted")
        state["calls"].append(("nice", nice))
        state["nice"] = nice

    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: state["policy"])
    monkeypatch.setattr(os, "sched_getparam", lambda pid: os.sched_param(0))
    monkeypatch.setattr(os, "sched_setscheduler", setscheduler)
    monkeypatch.setattr(os, "getpriority", lambda which, who: state["nice"])
    monkeypatch.setattr(os, "setpriority", setpriority)
    monkeypatch.setattr(priority, "_warned", False)
    return state


def test_the_loop_runs_realtime_within_the_block_and_returns_to_normal_after(scheduler):
    with priority.raised_priority() as raised:
        assert raised == "realtime" and scheduler["policy"] == os.SCHED_FIFO
        assert scheduler["calls"] == [("policy", os.SCHED_FIFO, priority.LOOP_RT_PRIORITY)]
    assert scheduler["policy"] == os.SCHED_OTHER and scheduler["nice"] == 0


def test_without_the_realtime_right_the_nice_value_is_raised_and_restored(scheduler):
    scheduler["refuse"].add("realtime")
    with priority.raised_priority(-10) as raised:
        assert raised == "nice" and scheduler["nice"] == -10
    assert scheduler["calls"] == [("nice", -10), ("nice", 0)]


def test_without_permission_the_loop_runs_as_it_is_and_says_so_once(scheduler, caplog):
    scheduler["refuse"].update({"realtime", "nice"})
    with caplog.at_level(logging.INFO, logger="cell.control.priority"):
        for _ in range(2):
            with priority.raised_priority(-10) as raised:
                assert raised == "normal"
    assert sum("CAP_SYS_NICE" in r.message for r in caplog.records) == 1
    assert scheduler["calls"] == []


def test_an_exception_in_the_block_still_restores_the_scheduling(scheduler):
    with pytest.raises(RuntimeError), priority.raised_priority(-10):
        raise RuntimeError("the task failed")
    assert scheduler["policy"] == os.SCHED_OTHER
    scheduler["refuse"].add("realtime")
    scheduler["nice"] = 5
    with pytest.raises(RuntimeError), priority.raised_priority(-10):
        raise RuntimeError("the task failed")
    assert scheduler["nice"] == 5


def test_the_process_threads_are_raised_alike_and_given_back(scheduler, monkeypatch):
    """A driver's reader thread, started before the loop, shares the interpreter lock with it: raised with it."""
    import threading

    policies: dict[int, int] = {}
    nices: dict[int, int] = {}

    def setscheduler(pid: int, policy: int, param: os.sched_param) -> None:
        policies[pid] = policy

    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: policies.get(pid, os.SCHED_OTHER))
    monkeypatch.setattr(os, "sched_setscheduler", setscheduler)
    monkeypatch.setattr(os, "getpriority", lambda which, who: nices.get(who, 0))
    monkeypatch.setattr(os, "setpriority", lambda which, who, nice: nices.__setitem__(who, nice))
    stop = threading.Event()
    reader = threading.Thread(target=stop.wait, name="reader", daemon=True)
    reader.start()
    tid = reader.native_id
    assert tid is not None
    try:
        with priority.raised_priority(other_threads=True) as raised:
            assert raised == "realtime" and policies[0] == os.SCHED_FIFO
            # The reader at nice, not real-time: busy, it would hold a core against every other process.
            assert policies.get(tid, os.SCHED_OTHER) == os.SCHED_OTHER and nices[tid] == priority.LOOP_NICE
        assert policies[0] == os.SCHED_OTHER and nices[tid] == 0
        with priority.raised_priority():  # the loop's thread alone
            assert nices[tid] == 0
    finally:
        stop.set()
        reader.join()
