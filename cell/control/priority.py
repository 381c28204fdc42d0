"""The process's scheduling priority while a wall-clock control loop runs: raised when the OS permits it."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator

log = logging.getLogger(__name__)

# A wall-clock loop (emulated or real cell) must keep its period on a shared machine: at this nice value the
# kernel gives it about nine times the CPU share of an ordinary process.  Raising priority needs root or
# CAP_SYS_NICE; without them the loop runs as it is and says so once.
LOOP_NICE = -10
_warned = False


@contextlib.contextmanager
def raised_priority(nice: int = LOOP_NICE) -> Iterator[bool]:
    """Within the block the process runs at `nice` (if that is higher priority than now and permitted);
    the old priority comes back after it.  Yields whether the priority was raised."""
    global _warned
    old = os.getpriority(os.PRIO_PROCESS, 0)
    raised = False
    if nice < old:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
            raised = True
        except PermissionError:
            if not _warned:
                log.info("the control loop runs at normal priority (nice %d): raising it needs root or "
                         "CAP_SYS_NICE (e.g. setcap cap_sys_nice+ep on the venv's python)", old)
                _warned = True
    try:
        yield raised
    finally:
        if raised:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, 0, old)
