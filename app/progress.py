"""Progress of long jobs on stderr: tqdm bars on a terminal; off a terminal (logs, CI) a log line every ~10 %.

The bars themselves are plain `tqdm` in the layers below (collect, calibrate, the benches); this module only
decides, once per command, how they show, so those layers need not know whether a person is watching.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

from tqdm import std, tqdm

log = logging.getLogger("tmcell")
LOG_STEP_PCT = 10  # off a terminal: one line per this share of the job
UNKNOWN_TOTAL_EVERY_S = 30.0  # a bar without a total: one line this often
_installed = False


class _Discard:
    """The bar's output off a terminal: its drawing goes nowhere; `_report` logs the lines instead."""

    def write(self, text: str) -> None:
        pass

    def flush(self) -> None:
        pass


def _report(bar: Any, final: bool = False) -> None:
    """Log `bar`'s k/N, elapsed time and ETA when it crossed the next 10 % (or ends)."""

    total, n = bar.total, bar.n
    elapsed = time.monotonic() - bar._tmcell_t0
    desc = bar.desc or "progress"
    if not total:
        if final or elapsed >= bar._tmcell_next:
            bar._tmcell_next = elapsed + UNKNOWN_TOTAL_EVERY_S
            log.info("%s: %g %s, %s elapsed%s", desc, n, bar.unit, tqdm.format_interval(elapsed),
                     " (done)" if final else "")
        return
    pct = 100.0 * n / total
    if pct < bar._tmcell_next and not (final and n != bar._tmcell_logged_n):
        return
    bar._tmcell_next = (int(pct // LOG_STEP_PCT) + 1) * LOG_STEP_PCT
    bar._tmcell_logged_n = n
    eta = elapsed * (total - n) / n if n > 0 else float("nan")
    log.info("%s: %g/%g %s (%.0f %%), %s elapsed, ETA %s", desc, n, total, bar.unit, pct,
             tqdm.format_interval(elapsed), tqdm.format_interval(eta) if eta == eta else "?")


def quiet_bars_off_terminal() -> None:
    """When stderr is not a terminal, every tqdm bar (here and below) logs a line per ~10 % instead of
    redrawing itself (a redraw is a line of its own in a log file).  On a terminal: untouched."""
    global _installed
    if _installed or sys.stderr.isatty():
        return

    cls = std.tqdm
    init, update, close = cls.__init__, cls.update, cls.close

    def quiet_init(self: Any, *args: Any, **kwargs: Any) -> None:
        mine = kwargs.get("file") in (None, sys.stderr) and not kwargs.get("disable")
        if mine:
            kwargs["file"] = _Discard()
        init(self, *args, **kwargs)
        self._tmcell_log = mine
        self._tmcell_t0 = time.monotonic()
        self._tmcell_next = LOG_STEP_PCT if self.total else UNKNOWN_TOTAL_EVERY_S
        self._tmcell_logged_n = None

    def quiet_update(self: Any, n: float | None = 1) -> Any:
        out = update(self, n)
        if getattr(self, "_tmcell_log", False):
            _report(self)
        return out

    def quiet_close(self: Any) -> None:
        if getattr(self, "_tmcell_log", False) and not self.disable:
            self._tmcell_log = False
            _report(self, final=True)
        close(self)

    cls.__init__, cls.update, cls.close = quiet_init, quiet_update, quiet_close
    _installed = True


@contextlib.contextmanager
def heartbeat(desc: str, every_s: float = 10.0) -> Iterator[None]:
    """A job with no count to show (a model fit): a log line every `every_s` seconds that it is still working,
    so a long fit is never silent.  Log lines, not a redrawn timer, so that a bar shown meanwhile (collect's)
    keeps its line on a terminal."""
    done = threading.Event()
    t0 = time.monotonic()

    def beat() -> None:
        while not done.wait(every_s):
            log.info("%s: still working, %.0f s elapsed", desc, time.monotonic() - t0)

    thread = threading.Thread(target=beat, name="heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join(timeout=2.0)
        log.info("%s: took %.0f s", desc, time.monotonic() - t0)
