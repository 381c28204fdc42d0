"""The Listen node from the driver's side: streamed scripts' replies counted (a lagging node stops the arm), the
stop as two packets, re-arming without waiting, the probes' replies matched and bounded."""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from drivers.errors import LinkLostError, ProtocolError
from drivers.interfaces import Lifecycle
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.listen import ScriptError
from drivers.tm5.listen_backlog import ListenBacklogError
from drivers.tm5.tm_packet import TMFramer, TMPacket, encode_packet
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator
from sim.tm_listen_node import ListenNode
from tasks.setup.doctor import Doctor, DoctorSettings
from tests.tm_ethernet_fixtures import DT, LIMITS, make_arm, start, wait_for


@pytest.fixture
def emulator() -> Iterator[TMEthernetEmulator]:
    emu = start(KinematicPlant(dt=DT))
    yield emu
    emu.stop()


def connected(emu: TMEthernetEmulator, **overrides: float) -> TMEthernetArm:
    arm = make_arm(emu, **overrides)
    arm.connect()
    return arm


def stream(arm: TMEthernetArm, periods: int) -> None:
    """The control loop's calls: read, then hold the current target, every period."""
    for _ in range(periods):
        arm.read_state()
        arm.send_target(arm.last_sent if arm.last_sent is not None else arm.read_state().q)
        time.sleep(DT)


# ------------------------------------------------------------------------------------------------ backlog
@pytest.mark.parametrize(("overrides", "words"), [
    ({"max_reply_age_s": 1.0}, r"^TM Listen node .*: 4 scripts unanswered \(limit max_unanswered_scripts 3\), "
                               r"the oldest \(SetContinueVJog, script h\d+\) sent \d+ ms ago"),
    ({"max_unanswered_scripts": 64}, r"script h\d+ \(SetContinueVJog\) unanswered for \d+ ms \(limit "
                                     r"max_reply_age_s 50 ms\)"),
])
def test_a_listen_node_falling_behind_stops_the_arm(emulator: TMEthernetEmulator, overrides: dict[str, float],
                                                    words: str) -> None:
    arm = connected(emulator, **overrides)
    try:
        arm.arm()
        stream(arm, 3)
        emulator.set_script_interval(0.1)  # the node now takes 100 ms per script, the host sends every 8 ms
        with pytest.raises(ListenBacklogError, match=words) as info:
            stream(arm, 200)
        assert isinstance(info.value, LinkLostError) and arm.lifecycle is Lifecycle.FAULT
        # The fault's stop went out at once; StopAndClearBuffer empties what the node queued when it gets there.
        emulator.set_script_interval(0.0)
        wait_for(lambda: not emulator.node.vmode.active, what="the fault's stop")
        assert arm.unanswered_scripts >= 2  # the stop was sent without waiting for its replies
    finally:
        arm.disconnect()


def test_an_error_reply_to_a_streamed_speed_faults(emulator: TMEthernetEmulator) -> None:
    arm = connected(emulator)
    try:
        arm.arm()
        emulator.node.refuse = {"SetContinueVJog"}
        with pytest.raises(ScriptError, match=r"script h\d+ refused \(ERROR\) at line\(s\) 1: 1: SetContinueVJog\("):
            stream(arm, 100)
        assert arm.lifecycle is Lifecycle.FAULT
    finally:
        arm.disconnect()


def test_the_reply_lag_at_the_loop_rate_is_measured(emulator: TMEthernetEmulator) -> None:
    arm = connected(emulator)
    try:
        quick = arm.script_reply_lag(count=12, period_s=DT)
        assert (quick.sent, quick.answered) == (12, 12) and quick.max_unanswered <= 1
        emulator.set_script_interval(0.05)  # 50 ms per script, one sent every 8 ms: a queue builds
        slow = arm.script_reply_lag(count=12, period_s=DT)
        assert slow.answered == 12 and slow.max_unanswered >= 4 and slow.max_s >= 0.05
        assert "12/12 answered" in slow.summary()
    finally:
        arm.disconnect()


def test_doctor_fails_a_node_whose_replies_come_later_than_the_driver_allows(emulator: TMEthernetEmulator) -> None:
    # Every reply comes 8 ms after its script; the driver allows 5 ms here: arming would stream into a fault.
    emulator.set_script_interval(0.008)
    arm = make_arm(emulator, max_reply_age_s=0.005, command_latency_periods=10)
    checks = {c.name: c for c in Doctor(arm, None, LIMITS, DoctorSettings(period_s=0.0156, timing_steps=5,
                                                                            tail_periods=3.0)).run()}
    arm.disconnect()
    check = checks["command_round_trip"]
    assert check.status == "fail", check
    assert "32 scripts at 64 Hz: 32/32 answered" in check.detail and "the driver would stop the arm" in check.detail


# ------------------------------------------------------------------------------------------------ the stop
def test_the_stop_is_two_packets_clear_first(emulator: TMEthernetEmulator) -> None:
    arm = connected(emulator)
    try:
        arm.arm()
        stream(arm, 3)
        arm.stop()
        wait_for(lambda: "StopContinueVmode" in emulator.node.executed, what="the stop's second packet run")
        assert list(emulator.node.scripts_seen)[-2:] == [("StopAndClearBuffer",), ("StopContinueVmode",)]
        assert list(emulator.node.executed)[-2:] == ["StopAndClearBuffer", "StopContinueVmode"]
        assert not emulator.node.vmode.active
        arm.confirm_stop()
        assert arm.unanswered_scripts == 0
    finally:
        arm.disconnect()


def test_the_emulated_node_ignores_motions_packed_with_stop_and_clear_buffer() -> None:
    node = ListenNode()
    node.handle(TMPacket("TMSCT", b"a1,ContinueVJog()"))
    node.servo_target(np.zeros(6), DT)
    assert node.vmode.active
    assert node.handle(TMPacket("TMSCT", b"a2,ContinueVJog()\r\nStopAndClearBuffer()")) == [
        encode_packet("TMSCT", "a2,OK")]
    node.servo_target(np.zeros(6), DT)
    assert list(node.executed) == ["ContinueVJog", "StopAndClearBuffer"] and not node.vmode.active


def test_the_fault_path_waits_for_nothing_and_closing_checks_the_replies(
        emulator: TMEthernetEmulator, caplog: pytest.LogCaptureFixture) -> None:
    arm = connected(emulator)
    arm.arm()
    emulator.set_script_interval(0.3)
    arm.fault("test fault")
    assert arm.unanswered_scripts == 2  # both stop packets out, neither reply awaited
    emulator.set_script_interval(0.0)
    wait_for(lambda: (arm.read_state(), arm.unanswered_scripts)[1] == 0, what="the fault's stop answered")
    emulator.node.refuse = {"StopAndClearBuffer"}  # the stop disconnect() sends is refused
    caplog.set_level(logging.WARNING, logger="drivers.tm5.ethernet")
    arm.disconnect()
    unconfirmed = [r.getMessage() for r in caplog.records if "stop before closing is unconfirmed" in r.getMessage()]
    assert len(unconfirmed) == 1 and "refused (ERROR)" in unconfirmed[0] and "StopAndClearBuffer" in unconfirmed[0]


# ------------------------------------------------------------------------------------------------ arming
def test_rearming_after_a_stop_waits_for_no_reply(emulator: TMEthernetEmulator) -> None:
    arm = connected(emulator, max_reply_age_s=1.0)
    try:
        arm.arm()
        arm.stop()
        arm.confirm_stop()
        queries = emulator.node.status_queries
        emulator.set_script_interval(0.3)  # any wait for the node would last 300 ms
        arm.arm()  # what the control loop does after a reaction's stop
        assert arm.lifecycle is Lifecycle.ARMED
        assert arm.unanswered_scripts == 1  # ContinueVJog went out and arm() returned without its reply
        wait_for(lambda: (arm.read_state(), arm.unanswered_scripts)[1] == 0, what="ContinueVJog answered")
        assert emulator.node.status_queries == queries  # and without asking TMSTA 00
    finally:
        arm.disconnect()


def test_arming_with_a_link_down_fails_at_once_and_connect_recovers(emulator: TMEthernetEmulator) -> None:
    arm = connected(emulator)
    try:
        emulator.drop_link(0.2)
        with pytest.raises(LinkLostError):
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:
                arm.read_state()
                time.sleep(DT)
        time.sleep(0.25)  # the emulator takes connections again
        with pytest.raises(LinkLostError, match=r"cannot arm: the Ethernet Slave link is down: reconnect "
                                                r"\(disconnect, then connect\) outside the control loop"):
            arm.arm()
        assert not arm.link_up  # arm() did not reconnect
        arm.disconnect()
        arm.connect()
        arm.arm()
        assert arm.lifecycle is Lifecycle.ARMED
    finally:
        arm.disconnect()


# ------------------------------------------------------------------------------------------------ probes
class FakeNode:
    """A Listen node on 127.0.0.1 answering each packet with `answer(packet)` (a list of DATA per header)."""

    def __init__(self, answer: Callable[[TMPacket], list[tuple[str, str]]]) -> None:
        self.answer = answer
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.server.getsockname()[1])
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        try:
            conn, _ = self.server.accept()
        except OSError:
            return
        framer = TMFramer("fake node")
        with conn, contextlib.suppress(OSError):  # the client closing ends it
            while chunk := conn.recv(4096):
                for packet in framer.packets(chunk):
                    conn.sendall(b"".join(encode_packet(h, d) for h, d in self.answer(packet)))

    def close(self) -> None:
        self.server.close()
        self._thread.join(timeout=2.0)


def script_ok_then(tag_reply: Callable[[int], str]) -> Callable[[TMPacket], list[tuple[str, str]]]:
    calls = {"n": 0}

    def answer(packet: TMPacket) -> list[tuple[str, str]]:
        if packet.header == "TMSCT":
            return [("TMSCT", packet.text.split(",", 1)[0] + ",OK")]
        if packet.text.startswith("01,"):
            calls["n"] += 1
            return [("TMSTA", tag_reply(calls["n"]))]
        return []  # TMSTA 00: never answered
    return answer


def arm_with_fake_node(emulator: TMEthernetEmulator, fake: FakeNode) -> TMEthernetArm:
    cfg = TMEthernetConfig(host="127.0.0.1", slave_port=emulator.slave_port, listen_port=fake.port,
                           connect_timeout_s=2.0, reply_timeout_s=0.2)
    arm = TMEthernetArm(cfg, LIMITS, DT)
    arm.connect()
    return arm


@pytest.mark.parametrize(("tag_reply", "words"), [
    (lambda n: "01,15,none", r"TMSTA 01 answers that tag 15 does not exist, though QueueTag\(15\) \(script h1\) "
                             r"was accepted$"),
    (lambda n: "01,15,false", r"tag 15 still pending 0\.2 s after QueueTag\(15\) was accepted: the project is "
                              r"paused"),
    (lambda n: "01,07,true", r"no answer to TMSTA 01,15 within 0\.2 s \(reply_timeout_s\)$"),  # another tag's
])
def test_the_round_trip_matches_its_tag_and_ends(emulator: TMEthernetEmulator, tag_reply: Callable[[int], str],
                                                 words: str) -> None:
    fake = FakeNode(script_ok_then(tag_reply))
    arm = arm_with_fake_node(emulator, fake)
    try:
        with pytest.raises(ProtocolError, match=words):
            arm.command_round_trip()
    finally:
        arm.disconnect()
        fake.close()


def test_the_round_trip_takes_a_padded_tag_after_pending_replies(emulator: TMEthernetEmulator) -> None:
    fake = FakeNode(script_ok_then(lambda n: "01,15,true" if n >= 3 else "01,015,false"))
    arm = arm_with_fake_node(emulator, fake)
    try:
        assert arm.command_round_trip() > 0
    finally:
        arm.disconnect()
        fake.close()


def test_an_unanswered_status_query_names_it_in_one_line(emulator: TMEthernetEmulator) -> None:
    fake = FakeNode(script_ok_then(lambda n: "01,15,true"))
    arm = arm_with_fake_node(emulator, fake)
    try:
        with pytest.raises(ProtocolError) as info:
            arm.probe_listen_node()
        assert str(info.value) == (f"TM {arm.endpoint}: no answer to TMSTA 00 (is the project in its Listen node?) "
                                   "within 0.2 s (reply_timeout_s)")
    finally:
        arm.disconnect()
        fake.close()
