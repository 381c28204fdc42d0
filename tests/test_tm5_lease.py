"""The control lease: two TM5 drivers against one emulator; one host at a time controls the arm."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from drivers.errors import DriverError, LifecycleError
from drivers.interfaces import Lifecycle
from drivers.tm5.contract import UserAreaLayout
from drivers.tm5.modbus import TM5ModbusArm
from drivers.tm5.registers import Command, floats_to_regs, int32_to_regs, wrap_int32
from sim.tm5_emulator import TM5Emulator
from tests.tm5_fixtures import DT, Q0, FakePlant, make_arm, wait_for

pytestmark = [pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning"),
              pytest.mark.usefixtures("no_leaked_threads"), pytest.mark.timeout(30)]

LEASE_S = 0.2  # short, so a lapsed lease is quick to wait for


@pytest.fixture
def leased(plant: FakePlant) -> Iterator[TM5Emulator]:
    with TM5Emulator(plant, watchdog_cycles=6, lease_timeout_s=LEASE_S) as emu:
        yield emu


class Streamer:
    """Drives `arm` from a thread as a control loop does: read, send a target, every period."""

    def __init__(self, arm: TM5ModbusArm) -> None:
        self.arm = arm
        self.cycles = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="streamer")

    def _run(self) -> None:
        try:
            q = self.arm.read_state().q
            while not self._stop.is_set():
                self.arm.read_state()
                self.arm.send_target(q + 0.01 * np.sin(self.cycles * DT))
                self.cycles += 1
                time.sleep(DT)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc

    def __enter__(self) -> Streamer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)


def _disconnect(*arms: TM5ModbusArm) -> None:
    for a in arms:
        with contextlib.suppress(DriverError):
            a.disconnect()


def test_second_host_is_refused_while_the_first_runs_then_arms_after_the_lease_lapses(
        leased: TM5Emulator, plant: FakePlant, caplog: pytest.LogCaptureFixture) -> None:
    first, second = make_arm(leased), make_arm(leased, arm_timeout_s=0.1)
    try:
        first.connect()
        second.connect()  # reading is allowed: only control is exclusive
        first.arm()
        assert leased.program.lease_token == first.token
        with Streamer(first) as loop:
            wait_for(lambda: loop.cycles > 20, what="the first host streaming")
            with pytest.raises(LifecycleError) as exc:
                second.arm()
            msg = str(exc.value)
            assert f"arm is held by another controller (token 0x{first.token:08x}, renewed " in msg
            renewed_ms = int(msg.split("renewed ")[1].split(" ms ago")[0])
            assert 0 <= renewed_ms < 1000 * LEASE_S
            assert "\n" not in msg
            assert second.lifecycle is not Lifecycle.ARMED
            before = loop.cycles
            wait_for(lambda: loop.cycles > before + 20, what="the first host still streaming")
        assert loop.error is None, loop.error
        assert first.lifecycle is Lifecycle.ARMED and not plant.hold_calls
        assert leased.program.refused_writes == 0  # the refused host wrote nothing at all
        first.disconnect()  # stops the arm; the lease lapses LEASE_S after its last write
        second.config = replace(second.config, arm_timeout_s=1.0)
        with caplog.at_level(logging.INFO, logger="sim.tm5_program"):
            second.arm()  # waits for the lapse, then takes control
        # The robot side's own clock decides: the first lease expired before the second host was granted.
        events = [r.getMessage() for r in caplog.records if r.name == "sim.tm5_program"]
        expired = next(i for i, m in enumerate(events) if f"lease of host 0x{first.token:08x} expired" in m)
        granted = next(i for i, m in enumerate(events) if f"control granted to host 0x{second.token:08x}" in m)
        assert expired < granted, events
        assert second.lifecycle is Lifecycle.ARMED and leased.program.lease_token == second.token
        q = second.read_state().q
        for _ in range(10):  # the jitter buffer plays a target two periods after it arrives
            second.send_target(q + 0.01)
            time.sleep(DT)
        wait_for(lambda: np.allclose(plant.target, q + 0.01, atol=1e-5), what="the second host's target")
    finally:
        _disconnect(first, second)


def test_a_write_with_another_token_is_refused_whole(leased: TM5Emulator, plant: FakePlant) -> None:
    # Two hosts that both saw the lease free race their writes: the robot side acts on the holder's only,
    # a STOP included (an E-stop or the stop coil stops any arm).
    first = make_arm(leased)
    layout = UserAreaLayout()
    start, count = layout.host_block
    try:
        first.connect()
        first.arm()
        with Streamer(first) as loop:
            wait_for(lambda: loop.cycles > 10, what="the first host streaming")
            other = ModbusTcpClient("127.0.0.1", port=leased.port, timeout=1.0)
            try:
                assert other.connect()
                # The holder overwrites the block every period: write until the robot side has seen ours.
                deadline = time.monotonic() + 2.0
                while leased.program.refused_writes == 0 and time.monotonic() < deadline:
                    regs = [0] * count
                    seq = wrap_int32(leased.program.last_host_seq + 1000)
                    regs[layout.slice_in("host_seq", start)] = int32_to_regs(seq)
                    regs[layout.slice_in("targets", start)] = floats_to_regs(np.degrees(Q0))
                    regs[layout.slice_in("command", start)] = [int(Command.STOP)]
                    regs[layout.slice_in("host_token", start)] = int32_to_regs(wrap_int32(first.token ^ 0x5A5A5A5A))
                    assert not other.write_registers(start, regs, device_id=1).isError()
                    time.sleep(0.001)
            finally:
                other.close()
            assert leased.program.refused_writes >= 1
            before = loop.cycles
            wait_for(lambda: loop.cycles > before + 20, what="the first host still streaming")
        assert loop.error is None, loop.error
        assert plant.hold_calls == 0 and first.lifecycle is Lifecycle.ARMED
    finally:
        _disconnect(first)


def test_a_host_whose_lease_lapsed_and_was_taken_faults(leased: TM5Emulator) -> None:
    first, second = make_arm(leased), make_arm(leased)
    try:
        first.connect()
        second.connect()
        first.arm()
        time.sleep(LEASE_S + 0.1)  # armed but silent: the lease lapses
        second.arm()
        with pytest.raises(LifecycleError, match=rf"control was taken by another controller \(token "
                                                 rf"0x{second.token:08x}"):
            first.read_state()
        assert first.lifecycle is Lifecycle.FAULT
        assert second.lifecycle is Lifecycle.ARMED and leased.program.lease_token == second.token
    finally:
        _disconnect(first, second)
