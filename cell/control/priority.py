"""The scheduling priority of a wall-clock control loop's thread: raised while it runs, where the OS permits it."""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Callable, Iterator

log = logging.getLogger(__name__)

# A wall-clock loop (emulated or real cell) must keep its period on a shared machine.  First choice: the
# real-time FIFO class at a low real-time priority, as robot controllers run their loops (it preempts every
# ordinary process the moment its period is due; it sleeps most of each period, and the kernel's real-time
# throttling keeps 5 % of the CPU for the rest).  Threads the loop's thread starts inherit it.  Without
# that right, nice -10 (about nine times an ordinary process's CPU share); without either, as it is.
LOOP_RT_PRIORITY = 10
LOOP_NICE = -10
_warned = False


def _raise_thread(tid: int, nice: int, rt_priority: int | None) -> tuple[str, Callable[[], None]]:
    """Raise one thread (`tid`, 0: the calling one) to FIFO at `rt_priority` or to `nice`, whichever the OS permits
    first; returns what it got and how to give it back."""
    old_policy = os.sched_getscheduler(tid) if hasattr(os, "sched_getscheduler") else None
    old_param = os.sched_getparam(tid) if old_policy is not None else None
    old_nice = os.getpriority(os.PRIO_PROCESS, tid)
    if rt_priority is not None and old_policy == os.SCHED_OTHER:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(rt_priority))

            def back_to_normal() -> None:
                assert old_policy is not None and old_param is not None
                os.sched_setscheduler(tid, old_policy, old_param)
            return "realtime", back_to_normal
        except (PermissionError, OSError):
            pass
    if nice < old_nice:
        try:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
            return "nice", lambda: os.setpriority(os.PRIO_PROCESS, tid, old_nice)
        except (PermissionError, OSError):
            pass
    return "normal", lambda: None


@contextlib.contextmanager
def raised_priority(nice: int = LOOP_NICE, rt_priority: int | None = LOOP_RT_PRIORITY,
                    other_threads: bool = False) -> Iterator[str]:
    """Within the block the calling thread runs real-time (FIFO at `rt_priority`) or at `nice`, whichever the
    OS permits first; the old scheduling comes back after it.  Yields "realtime", "nice" or "normal".

    `other_threads`: the process's other Python threads (a driver's stream reader, started when the cell
    connected) run at `nice` for the block.  They take the interpreter lock in turns with the loop: one left at
    normal priority, preempted by other processes while it holds the lock, would stall the loop for as long as
    it waits (a priority inversion).  Not real-time: a thread that turned busy (a viewer's backlog) would then
    hold a core against every other process."""
    global _warned
    raised, restore = _raise_thread(0, nice, rt_priority)
    restores = [restore]
    if other_threads and raised != "normal":
        me = threading.get_ident()
        for thread in threading.enumerate():
            if thread.ident != me and thread.native_id is not None:
                with contextlib.suppress(OSError):  # a thread that ended meanwhile
                    restores.append(_raise_thread(thread.native_id, nice, None)[1])
    if raised == "normal" and not _warned:
        log.info("the control loop runs at normal priority (nice %d): raising it needs root, CAP_SYS_NICE "
                 "(e.g. setcap cap_sys_nice+ep on the venv's python) or an rtprio limit",
                 os.getpriority(os.PRIO_PROCESS, 0))
        _warned = True
    try:
        yield raised
    finally:
        for back in restores:
            with contextlib.suppress(OSError):  # a thread that ended meanwhile has nothing to give back
                back()
