"""Independent bench trials on worker processes: each worker builds its set-up once, then runs trials as they come.

A trial that builds its own plant and cell depends on nothing but its draw, so its result is the same on any
worker; the pool only changes the wall time.  Workers are spawned (a fresh interpreter each: no thread pool or
open device of the parent is inherited), and the set-up and trial functions travel by name, so they must be
module-level functions and the recipe plain data.
"""

from __future__ import annotations

import logging
import multiprocessing
import signal
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any, TypeVar

Item = TypeVar("Item")
Result = TypeVar("Result")

_setup: Any = None


def _init(setup: Callable[[Any], Any], recipe: Any, level: int) -> None:
    global _setup
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # Ctrl+C reaches the whole process group: the parent cancels what is left and stops its workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _setup = setup(recipe)


def _run(trial: Callable[[Any, Any], Any], item: Any) -> Any:
    return trial(_setup, item)


def run_pooled(items: Sequence[Item], jobs: int, setup: Callable[[Any], Any], recipe: Any,
               trial: Callable[[Any, Item], Result]) -> Iterator[Result]:
    """`trial(setup(recipe), item)` for every item on `jobs` workers; results in the order they finish.

    An exception in a trial (an interrupted run included) ends the pool and is raised here; so is Ctrl+C."""
    context = multiprocessing.get_context("spawn")
    level = logging.getLogger().getEffectiveLevel()
    pool = ProcessPoolExecutor(max_workers=jobs, mp_context=context, initializer=_init,
                               initargs=(setup, recipe, level))
    try:
        pending: set[Future[Any]] = {pool.submit(_run, trial, item) for item in items}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
