"""What every bench reports about the machine it ran on: its load, its processor and a reference speed."""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path

import numpy as np

REFERENCE_REPEATS = 5


def machine_load() -> list[float]:
    """The 1, 5 and 15 minute load averages (what else the cores were doing: wall times depend on it)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # not available on this platform
        return []


def cpu_model() -> str:
    """The processor's model name as the kernel reports it (`platform.processor()` where there is no /proc)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _reference_work() -> float:
    """A fixed piece of work shaped like a control period: per-joint Python float arithmetic (the plant's
    substep loop) and small numpy products (the model and the observer)."""
    acc = 0.0
    m = np.eye(6) * 1.01
    v = np.linspace(0.1, 0.6, 6)
    for k in range(2000):
        for j in range(6):
            acc += math.sin(0.001 * k + j) * (1.0 + 2.5 * abs(acc) / (1.0 + abs(acc)))
        v = m @ v
        v /= float(np.linalg.norm(v))
    return acc + float(v.sum())


def reference_ms(repeats: int = REFERENCE_REPEATS) -> float:
    """The fastest of `repeats` runs of the reference work, in ms: this machine's own speed, so that a bench's
    figures from two machines can be compared (a slow run on a fast machine from a run on a slow one).  The
    fastest run is the one least disturbed by other processes."""
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        _reference_work()
        best = min(best, time.perf_counter() - t0)
    return round(1e3 * best, 3)
