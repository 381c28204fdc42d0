"""One signal path: SIGTERM stops whatever runs as Ctrl+C does (arm stopped, recording closed), then exit 143."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered as a KeyboardInterrupt so every Ctrl+C path (the control loop's stop and
    shutdown, the recorder's close) handles it the same way."""


_received = False


def received_sigterm() -> bool:
    return _received


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    global _received
    _received = True
    raise Terminated("terminated (SIGTERM)")


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block a SIGTERM raises `Terminated` in the main thread (elsewhere: no change)."""
    global _received
    _received = False
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def raise_if_interrupted(outcome: str) -> None:
    """A run that ended 'interrupted' ends the whole command too (a bench must not go on to its next
    trial, a collection must not report a data error)."""
    if outcome == "interrupted":
        raise Terminated("terminated (SIGTERM)") if _received else KeyboardInterrupt()


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Ctrl+C and SIGTERM wait until the block ends (then raise as usual): for the work after a run
    has stopped the arm (its summary and plot), which an interrupt must not lose.  Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def hold(signum: int, frame: FrameType | None) -> None:
        pending.append(signum)

    old_int = signal.signal(signal.SIGINT, hold)
    old_term = signal.signal(signal.SIGTERM, hold)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)
    if signal.SIGTERM in pending:
        global _received
        _received = True
        raise Terminated("terminated (SIGTERM)")
    if signal.SIGINT in pending:
        raise KeyboardInterrupt
