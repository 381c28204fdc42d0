"""A wall-clock loop runs at raised priority where the OS permits it, and gives it back afterwards."""

from __future__ import annotations

import logging
import os

import pytest

from cell.control import priority


def test_the_priority_is_raised_within_the_block_and_restored_after(monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(os, "getpriority", lambda which, who: 0)
    monkeypatch.setattr(os, "setpriority", lambda which, who, nice: calls.append(nice))
    with priority.raised_priority(-10) as raised:
        assert raised and calls == [-10]
    assert calls == [-10, 0]


def test_without_permission_the_loop_runs_as_it_is_and_says_so_once(monkeypatch, caplog):
    def refuse(which: int, who: int, nice: int) -> None:
        raise PermissionError("not permitted")

    monkeypatch.setattr(os, "getpriority", lambda which, who: 0)
    monkeypatch.setattr(os, "setpriority", refuse)
    monkeypatch.setattr(priority, "_warned", False)
    with caplog.at_level(logging.INFO, logger="cell.control.priority"):
        for _ in range(2):
            with priority.raised_priority(-10) as raised:
                assert not raised
    assert sum("CAP_SYS_NICE" in r.message for r in caplog.records) == 1


def test_an_exception_in_the_block_still_restores_the_priority(monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(os, "getpriority", lambda which, who: 5)
    monkeypatch.setattr(os, "setpriority", lambda which, who, nice: calls.append(nice))
    with pytest.raises(RuntimeError), priority.raised_priority(-10):
        raise RuntimeError("the task failed")
    assert calls == [-10, 5]
