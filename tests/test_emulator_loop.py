"""The emulators' loop thread: bound before it serves, code from other threads run on it, errors handed back."""

from __future__ import annotations

import asyncio
import threading

import pytest

from sim.emulator_loop import EmulatorLoop


class _Tiny(EmulatorLoop):
    def __init__(self, fail_bind: bool = False) -> None:
        super().__init__("tiny-emulator", "tiny emulator")
        self.fail_bind = fail_bind
        self.closed = False
        self.ticks = 0

    async def _bind(self) -> None:
        if self.fail_bind:
            raise OSError("address in use")

    def _serve(self) -> list[asyncio.Task[None]]:
        async def tick() -> None:
            while True:
                self.ticks += 1
                await asyncio.sleep(0.001)
        return [asyncio.create_task(tick())]

    async def _close(self) -> None:
        self.closed = True


def test_calls_run_on_the_loop_thread_and_hand_their_errors_back():
    emu = _Tiny()
    assert emu._start_loop() is None and emu.started
    where: list[str] = []
    emu._call(lambda: where.append(threading.current_thread().name))
    assert where == ["tiny-emulator"]

    def broken() -> None:
        raise ValueError("bad fault setting")
    with pytest.raises(ValueError, match="bad fault setting"):
        emu._call(broken)

    async def answer() -> int:
        return 42
    assert emu._run_coroutine(answer()) == 42
    emu._stop_loop()
    assert emu.closed and emu.ticks > 0
    # Stopped: a call runs directly, a coroutine is refused.
    emu._call(lambda: where.append(threading.current_thread().name))
    assert where[-1] == threading.current_thread().name
    with pytest.raises(RuntimeError, match="not running"):
        emu._run_coroutine(answer())


def test_a_bind_failure_is_handed_to_the_starting_thread():
    emu = _Tiny(fail_bind=True)
    error = emu._start_loop()
    assert isinstance(error, OSError) and "address in use" in str(error)
    assert not emu.closed  # nothing was served, so nothing is closed
