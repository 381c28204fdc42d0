"""The scheduling priority of a wall-clock control loop's thread: raised while it runs, where the OS permits it."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator

log = logging.getLogger(__name__)

# A wall-clock loop (emulated or real cell) must keep its period on a shared machine.  First choice: the
# real-time FIFO class at a low real-time priority, as robot controllers run their loops (it preempts every
# ordinary process the moment its period is due; it sleeps most of each period, and the kernel's real-time
# throttling keeps 5 % of the CPU for the rest).  Threads the loop's thread starts inherit it.  Without
# that right, nice -10 (about nine times an ordinary process's CPU share); without either, as it is.
LOOP_RT_PRIORITY = 10
LOOP_NICE = -10
_warned = False


@contextlib.contextmanager
def raised_priority(nice: int = LOOP_NICE, rt_priority: int | None = LOOP_RT_PRIORITY) -> Iterator[str]:
    """Within the block the calling thread runs real-time (FIFO at `rt_priority`) or at `nice`, whichever the
    OS permits first; the old scheduling comes back after it.  Yields "realtime", "nice" or "normal"."""
    global _warned
    raised = "normal"
    old_policy = os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None
    old_param = os.sched_getparam(0) if old_policy is not None else None
    old_nice = os.getpriority(os.PRIO_PROCESS, 0)
    if rt_priority is not None and old_policy == os.SCHED_OTHER:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
            raised = "realtime"
        except (PermissionError, OSError):
            pass
    if raised == "normal" and nice < old_nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
            raised = "nice"
        except PermissionError:
            pass
    if raised == "normal" and not _warned:
        log.info("the control loop runs at normal priority (nice %d): raising it needs root, CAP_SYS_NICE "
                 "(e.g. setcap cap_sys_nice+ep on the venv's python) or an rtprio limit", old_nice)
        _warned = True
    try:
        yield raised
    finally:
        if raised == "realtime":
            with contextlib.suppress(OSError):
                assert old_policy is not None and old_param is not None
                os.sched_setscheduler(0, old_policy, old_param)
        elif raised == "nice":
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, 0, old_nice)
