"""The wire-level emulators' asyncio loop on a background thread: started once, ready once its listeners are
bound, stopped from any thread, and how other threads run code on it."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

log = logging.getLogger(__name__)
T = TypeVar("T")


class EmulatorLoop:
    """One asyncio loop on a daemon thread.  A subclass binds its listeners in `_bind` (any exception there is
    a startup error, handed to the thread that called `_start_loop`), names the tasks that run while it serves
    in `_serve`, and closes what it opened in `_close` (its tasks are cancelled and awaited first)."""

    def __init__(self, thread_name: str, what: str) -> None:
        self._thread_name = thread_name
        self._what = what  # how the logs name the emulator
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._ready = threading.Event()
        self._startup_error: BaseException | None = None

    # ----------------------------------------------------------------------------- the subclass's part
    async def _bind(self) -> None:
        raise NotImplementedError

    def _serve(self) -> list[asyncio.Task[None]]:
        return []

    async def _close(self) -> None:
        return None

    # ----------------------------------------------------------------------------- lifecycle
    @property
    def started(self) -> bool:
        return self._thread is not None

    def _start_loop(self) -> BaseException | None:
        """Start the thread and wait until the listeners are bound; returns the startup error (None: serving)."""
        self._thread = threading.Thread(target=self._thread_main, name=self._thread_name, daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError(f"the {self._what} thread did not start within 10 s")
        if self._startup_error is not None:
            self._thread.join(5.0)
            return self._startup_error
        return None

    def _stop_loop(self) -> None:
        """Ask the loop to stop and join its thread (a loop that already ended is fine)."""
        loop, ev, thread = self._loop, self._stop_event, self._thread
        if loop is not None and ev is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop may just have finished on its own
                loop.call_soon_threadsafe(ev.set)
        if thread is not None:
            thread.join(10.0)
            if thread.is_alive():
                log.error("%s thread did not stop within 10 s", self._what)

    # ----------------------------------------------------------------------------- other threads' calls
    def _call(self, fn: Callable[[], None]) -> None:
        """Run `fn` on the loop thread and wait, its exception raised here (directly when the loop is not
        running)."""
        loop = self._loop
        if loop is None or loop.is_closed() or not loop.is_running():
            fn()
            return

        async def run() -> None:
            fn()
        self._run_coroutine(run())

    def _run_coroutine(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run `coro` on the loop and wait for its result (RuntimeError when the loop is not running or does not
        answer within 5 s)."""
        loop = self._loop
        if loop is None or loop.is_closed() or not loop.is_running():
            coro.close()
            raise RuntimeError(f"the {self._what} is not running")
        try:
            return asyncio.run_coroutine_threadsafe(coro, loop).result(5.0)
        except concurrent.futures.TimeoutError:
            raise RuntimeError(f"the {self._what} loop did not answer within 5 s") from None

    # ----------------------------------------------------------------------------- the loop thread
    def _thread_main(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - startup failures go to the starting thread; the rest is logged
            if not self._ready.is_set():
                self._startup_error = exc
            else:
                log.exception("%s loop crashed", self._what)
        finally:
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        try:
            await self._bind()
        except Exception as exc:  # noqa: BLE001 - handed to the starting thread
            self._startup_error = exc
            self._ready.set()
            return
        tasks = self._serve()
        self._ready.set()
        try:
            await self._stop_event.wait()
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            await self._close()
