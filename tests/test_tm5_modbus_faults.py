"""The real TM5 Modbus driver against a faulty TM5 emulator: lost links, late and exception replies, stale data."""

from __future__ import annotations

import logging
import socket
import time

import numpy as np
import pytest
from pymodbus.constants import ExcCodes

from drivers.errors import DriverError, LifecycleError, LinkLostError, ProtocolError, StaleDataError
from drivers.interfaces import Lifecycle
from drivers.tm5 import modbus as tm5_modbus
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.modbus import TM5ModbusArm
from drivers.tm5.registers import RobotFlags
from sim.tm5_emulator import TM5Emulator
from tests.tm5_fixtures import DT, LIMITS, Q0, FakePlant, WireWaits, make_arm, read_until_ok, wait_for

pytestmark = [pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning"),
              pytest.mark.usefixtures("no_leaked_threads")]


class _FakeClock:
    """Stands in for the `time` module: `monotonic()` reads `now`, which moves only when a test moves it or
    the code under test sleeps (so its own deadlines still pass)."""

    def __init__(self, now: float) -> None:
        self.now = now

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)
        self.now += seconds

    def __getattr__(self, name: str) -> object:
        return getattr(time, name)  # perf_counter, ...: the real ones


# ------------------------------------------------------------------------------------------------ faults
@pytest.mark.timeout(20)
def test_link_drop_raises_link_lost_fast_and_faults(arm: TM5ModbusArm, emulator: TM5Emulator,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    arm.arm()
    q = arm.read_state().q
    arm.send_target(q)
    emulator.drop_link(0.5)
    waits = WireWaits(arm, monkeypatch)
    with pytest.raises(LinkLostError):
        waits(arm.read_state)
    assert waits.waits <= 1, f"link loss surfaced after {waits.waits} waits on the wire"  # one timeout at most
    assert arm.lifecycle is Lifecycle.FAULT
    with pytest.raises(LifecycleError, match="fault"):
        arm.send_target(q)
    with pytest.raises(LinkLostError):  # while refused: at most one connect attempt, never a backoff wait
        waits(arm.read_state)
    assert waits.waits <= 1


@pytest.mark.timeout(20)
def test_reconnects_when_link_returns_and_rearms(arm: TM5ModbusArm, emulator: TM5Emulator,
                                                 plant: FakePlant) -> None:
    arm.arm()
    seq_before = arm.read_state().seq
    emulator.drop_link(0.3)
    with pytest.raises(LinkLostError):
        arm.read_state()
    s = read_until_ok(arm)  # reading reconnects (with backoff) ...
    assert arm.link_up
    assert s.seq > seq_before  # the sequence keeps counting across links
    assert arm.lifecycle is Lifecycle.FAULT  # ... but commanding needs a re-arm
    with pytest.raises(LifecycleError):
        arm.send_target(s.q)
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED
    target = s.q + 0.01
    arm.send_target(target)
    wait_for(lambda: len(plant.accepted_targets) > 0 and np.allclose(plant.accepted_targets[-1], target,
                                                                      atol=1e-6), what="target after re-arm")


@pytest.mark.timeout(20)
def test_arm_reconnects_by_itself(arm: TM5ModbusArm, emulator: TM5Emulator) -> None:
    arm.arm()
    emulator.drop_link(0.2)
    with pytest.raises(LinkLostError):
        arm.read_state()
    arm.arm()  # waits for the link (up to arm_timeout_s) then does the handshake
    assert arm.lifecycle is Lifecycle.ARMED


@pytest.mark.timeout(20)
def test_no_reply_is_link_lost_within_timeout(arm: TM5ModbusArm, emulator: TM5Emulator,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    arm.arm()
    arm.read_state()
    emulator.delay_replies(200)
    waits = WireWaits(arm, monkeypatch)
    with pytest.raises(LinkLostError, match=f"no valid reply within {arm.config.timeout_s * 1000:.0f} ms"):
        waits(arm.read_state)
    assert waits.waits == 1, f"a silent controller was waited on {waits.waits} times"  # one timeout, no retry
    assert arm.lifecycle is Lifecycle.FAULT
    emulator.clear_faults()
    s = read_until_ok(arm)  # the late reply on the old socket must not be mistaken for a new one
    np.testing.assert_allclose(s.q, Q0, atol=1e-6)


@pytest.mark.timeout(20)
def test_frozen_counter_raises_stale_data(arm: TM5ModbusArm, emulator: TM5Emulator,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    # The driver's clock is a fake one that moves only when told, so the staleness window is checked to
    # the microsecond whatever the machine's load.
    clock = _FakeClock(time.monotonic())
    monkeypatch.setattr(tm5_modbus, "time", clock)
    arm.arm()
    arm.read_state()
    emulator.freeze()
    for _ in range(5):  # a counter step still in flight at the freeze restarts the window at the same instant
        arm.read_state()
        time.sleep(DT)
    stale = arm.config.stale_after_s
    clock.now += stale - 1e-6
    arm.read_state()  # stuck just under the limit: still fresh
    clock.now += 2e-6
    with pytest.raises(StaleDataError, match="stuck"):
        arm.read_state()
    assert arm.lifecycle is Lifecycle.FAULT
    with pytest.raises(StaleDataError):  # re-arming cannot hide a hung robot-side program
        arm.arm()
    emulator.unfreeze()
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED


@pytest.mark.timeout(20)
def test_modbus_exception_reply_is_protocol_error(arm: TM5ModbusArm, emulator: TM5Emulator,
                                                  plant: FakePlant) -> None:
    arm.arm()
    q = arm.read_state().q
    emulator.inject_exceptions(code=ExcCodes.DEVICE_BUSY)
    with pytest.raises(ProtocolError, match="exception reply code 6"):
        arm.read_state()
    # A malformed or refused reply faults the arm like a lost link: no commands until re-armed.
    assert arm.lifecycle is Lifecycle.FAULT
    with pytest.raises(LifecycleError, match="exception reply code 6"):
        arm.send_target(q)
    assert arm.link_up  # an exception reply is an answer: the link itself is fine
    emulator.clear_faults()
    arm.arm()
    s = arm.read_state()
    np.testing.assert_allclose(s.q, plant.q, atol=1e-6)
    arm.send_target(q)


@pytest.mark.timeout(20)
def test_robot_watchdog_holds_plant_when_host_goes_quiet(arm: TM5ModbusArm, emulator: TM5Emulator,
                                                         plant: FakePlant, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="sim.tm5_program")
    arm.arm()
    q = arm.read_state().q
    for i in range(10):
        arm.send_target(q + 0.002 * i)
        time.sleep(DT)
    assert plant.hold_calls == 0
    wait_for(lambda: plant.hold_calls == 1, timeout=0.5, what="the robot-side watchdog")  # 6 cycles = 48 ms
    # The emulator says why at warning level: the host sees only the protective-stop flag.
    assert any(r.levelno == logging.WARNING and "heartbeat stalled" in r.getMessage() for r in caplog.records)
    s = arm.read_state()
    assert s.status.protective_stop and not s.status.ok
    assert arm.robot_side is not None and RobotFlags.WATCHDOG in arm.robot_side.flags
    accepted = len(plant.accepted_targets)
    # The host wakes up: its driver, having read the protective stop, refuses the target itself
    # (and the tripped robot would ignore it until re-armed).
    with pytest.raises(LifecycleError, match="controller reports protective_stop"):
        arm.send_target(q)
    time.sleep(5 * DT)
    assert len(plant.accepted_targets) == accepted
    arm.arm()
    assert plant.release_calls == 1
    assert arm.read_state().status.ok
    arm.send_target(q)
    wait_for(lambda: len(plant.accepted_targets) > accepted, what="targets after re-arm")


@pytest.mark.timeout(20)
def test_a_stop_whose_reply_is_lost_gets_through_when_retried(arm: TM5ModbusArm, emulator: TM5Emulator,
                                                              plant: FakePlant,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    # The control loop commands a stop up to three times.  A first attempt whose reply is late loses the
    # link; the retry must open a fresh one at once and get the stop through, not fail on "link is down"
    # (a CI run of the Ctrl+C test logged "could not command a stop" that way).
    arm.arm()
    arm.read_state()
    emulator.delay_replies(200, seconds=0.05)
    with pytest.raises(LinkLostError, match="no valid reply"):
        arm.stop()
    time.sleep(0.06)
    emulator.clear_faults()
    waits = WireWaits(arm, monkeypatch)
    waits(arm.stop)
    assert waits.waits <= 2  # a fresh link at once (one connect) and the stop's write: no backoff, no retry
    wait_for(lambda: plant.hold_calls >= 1, what="the hold")
    assert read_until_ok(arm).status.protective_stop


@pytest.mark.timeout(20)
def test_connect_refused_is_link_lost_quickly(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound but not listening: connections are refused
        arm = TM5ModbusArm(TM5ModbusConfig(host="127.0.0.1", port=port), LIMITS, DT)
        waits = WireWaits(arm, monkeypatch)
        with pytest.raises(LinkLostError, match="cannot connect"):
            waits(arm.connect)
        assert waits.waits == 1  # one connect attempt, bounded by timeout_s: no retry, no backoff wait
    assert arm.lifecycle is Lifecycle.DISCONNECTED


@pytest.mark.timeout(20)
def test_rearming_after_a_lost_write_reply_uses_a_new_host_sequence(arm: TM5ModbusArm, emulator: TM5Emulator,
                                                                    plant: FakePlant, monkeypatch) -> None:
    # A write whose reply is lost may still have reached the robot-side program, which then acted on its
    # host sequence: that number is used up.  Re-arming must send the next one (the robot ignores a
    # repeated number, so its latched stop would never clear and arming would fail every time).
    arm.arm()
    q = arm.read_state().q
    for i in range(5):
        arm.send_target(q + 0.001 * i)
        time.sleep(DT)
    real_call = arm._call

    def acted_but_reply_lost(op, address, fn, *, may_reconnect):
        rr = real_call(op, address, fn, may_reconnect=may_reconnect)
        if op == "write holding":
            raise arm._link_lost(f"{op} {address}: no valid reply (the robot acted on it)")
        return rr

    monkeypatch.setattr(arm, "_call", acted_but_reply_lost)
    with pytest.raises(DriverError):
        arm.send_target(q)
    monkeypatch.setattr(arm, "_call", real_call)
    wait_for(lambda: plant.hold_calls >= 1, what="the robot-side watchdog")  # the host went quiet
    arm.arm()  # first attempt: the IDLE must carry a new sequence to clear the hold
    assert read_until_ok(arm).status.ok
    accepted = len(plant.accepted_targets)
    arm.send_target(q)
    wait_for(lambda: len(plant.accepted_targets) > accepted, what="targets after re-arm")


@pytest.mark.timeout(30)
def test_a_lost_link_is_reported_within_one_timeout_every_time(emulator: TM5Emulator,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    # A fault's own stop never waits on the link; a stop that failed before a successful re-arm must not
    # make the next fault's stop reconnect and wait a second timeout (21 ms for a 10 ms timeout).
    arm = make_arm(emulator, timeout_s=0.01)
    with arm:
        arm.arm()
        # A faulting read may wait on the link it has, once; its stop must not open another and wait on it.
        waits = WireWaits(arm, monkeypatch)
        counted = []
        for _ in range(6):
            emulator.delay_replies(200)  # until cleared: every reply misses the 10 ms timeout
            with pytest.raises(DriverError):
                waits(arm.read_state)
            counted.append(waits.waits)
            emulator.clear_faults()
            arm.arm()
        assert counted == [1] * 6, f"links used per lost-link read: {counted}"


@pytest.mark.timeout(20)
def test_a_state_read_slower_than_two_periods_is_stale(emulator: TM5Emulator, monkeypatch: pytest.MonkeyPatch) -> None:
    # Each transaction answers within its own timeout, but three of them in a row would leave the loop on data
    # several periods old.  The driver's clock is a fake one moved by each transaction's (pretended) length.
    arm = make_arm(emulator, timeout_s=0.01)  # the budget: max(2 periods, timeout_s) = 16 ms
    with arm:
        arm.arm()
        clock = _FakeClock(time.monotonic())
        monkeypatch.setattr(tm5_modbus, "time", clock)
        real_call = arm._call
        spent: list[float] = []

        def slow_call(*args: object, **kwargs: object) -> object:
            clock.now += spent[-1]
            return real_call(*args, **kwargs)  # type: ignore[arg-type]

        monkeypatch.setattr(arm, "_call", slow_call)
        spent.append(0.005)  # 5 ms a transaction: 10 ms before the last read, under the budget
        arm.read_state()
        assert arm.lifecycle is Lifecycle.ARMED
        spent.append(0.009)  # 9 ms: 18 ms spent before the robot-side block
        with pytest.raises(StaleDataError, match=r"took 18\.0 ms before the robot-side block \(limit 16\.0 ms"):
            arm.read_state()
        assert arm.lifecycle is Lifecycle.FAULT
        assert "\n" not in str(arm.fault_reason)


@pytest.mark.timeout(20)
def test_a_controller_without_the_undocumented_inputs_is_read_input_by_input(
        arm: TM5ModbusArm, emulator: TM5Emulator, caplog: pytest.LogCaptureFixture) -> None:
    emulator.serve_documented_inputs_only()
    arm.arm()
    with caplog.at_level(logging.WARNING, logger="drivers.tm5.modbus"):
        assert arm.read_state().status.ok  # refused as a block once, then read run by run
        emulator.press_estop()
        wait_for(lambda: arm.read_state().status.estop, what="input 7208 read on its own")
    assert arm.lifecycle is Lifecycle.FAULT  # an E-stop faults an armed arm, as with the block read
    refusals = [r for r in caplog.records if "refuses discrete inputs" in r.getMessage()]
    assert len(refusals) == 1 and "7200-7202, 7204, 7208" in refusals[0].getMessage()
    # Any other exception reply to the block is still an error.
    emulator.clear_faults()
    fresh = make_arm(emulator)
    with fresh:
        emulator.serve_documented_inputs_only(False)
        emulator.inject_exceptions(code=ExcCodes.DEVICE_BUSY)
        with pytest.raises(ProtocolError, match="exception reply code 6"):
            fresh.read_state()


@pytest.mark.timeout(20)
def test_the_stop_coil_is_pulsed(emulator: TM5Emulator) -> None:
    arm = make_arm(emulator, stop_coil=True)
    with arm:
        arm.arm()
        arm.stop()
        assert emulator.stop_coil_writes == [True, False]  # set, then released: a rising edge for the next stop
    assert emulator.stop_coil_writes == [True, False] * 2  # disconnecting stops again, with its own edge


def test_a_non_finite_value_in_a_message_stays_on_one_line(arm: TM5ModbusArm) -> None:
    arm.arm()
    target = np.array([0.1, np.nan, 0.3, 1e-9, -2.5, 1234567.0])
    with pytest.raises(DriverError) as info:
        arm.send_target(target)
    assert "\n" not in str(info.value) and "nan" in str(info.value)
