"""The TM5-700 on its own channels: framing, the Ethernet Slave table, the Listen node, the driver on the emulator."""

from __future__ import annotations

import math
import re
import socket
import struct
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from drivers.errors import (
    CommandRejectedError,
    ConfigError,
    DriverError,
    LifecycleError,
    LinkLostError,
    ProtocolError,
    StaleDataError,
)
from drivers.interfaces import Lifecycle
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.ethernet_slave import (
    SlaveTableError,
    SvrFrame,
    decode_table,
    encode_items,
    encode_state_items,
    encode_svr,
    parse_items,
    parse_svr,
)
from drivers.tm5.listen import (
    CPError,
    EntryMessage,
    ListenError,
    ListenProtocol,
    ListenStatus,
    NotInListenNodeError,
    ScriptError,
    ScriptReply,
    TagStatus,
    queue_tag,
    set_continue_vjog,
)
from drivers.tm5.tm_packet import FrameError, TMFramer, TMPacket, encode_packet
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator
from sim.tm_listen_node import ListenNode
from tests.tm_ethernet_fixtures import DT, LIMITS, connected, make_arm, start, wait_for

# The worked examples of docs/tm-ethernet-listen.md.
VECTORS = [
    ("TMSTA", "00", b"$TMSTA,2,00,*41\r\n"),
    ("TMSCT", "1,OK", b"$TMSCT,4,1,OK,*5C\r\n"),
    ("TMSCT", "1,QueueTag(1,1)", b"$TMSCT,15,1,QueueTag(1,1),*46\r\n"),
    ("TMSVR", "w1,2,Ctrl_DO0=1", b"$TMSVR,15,w1,2,Ctrl_DO0=1,*53\r\n"),
    ("CPERR", "F1", b"$CPERR,2,F1,*3F\r\n"),
    ("TMSCT", "0,Listen1", b"$TMSCT,9,0,Listen1,*4C\r\n"),
]


def doc_table_content() -> bytes:
    """The doc's constructed table: Robot_Link, Joint_Angle (0, 0, 90, 0, 90, 0), Error_Code (72 bytes)."""
    return (b"\x0a\x00Robot_Link\x01\x00\x01" + b"\x0b\x00Joint_Angle\x18\x00" + struct.pack("<6f", 0, 0, 90, 0, 90, 0)
            + b"\x0a\x00Error_Code\x04\x00" + b"\x00" * 4)


# ------------------------------------------------------------------------------------------------ framing
@pytest.mark.parametrize(("header", "data", "wire"), VECTORS)
def test_packet_vectors_encode_and_decode(header: str, data: str, wire: bytes) -> None:
    assert encode_packet(header, data) == wire
    assert TMFramer().packets(wire) == [TMPacket(header, data.encode())]


def test_doc_table_example_frames_with_checksum_2f() -> None:
    content = doc_table_content()
    assert len(content) == 72
    wire = encode_packet("TMSVR", encode_svr("3", 1, content))
    assert wire.startswith(b"$TMSVR,76,3,1,") and wire.endswith(b",*2F\r\n")


def test_lowercase_checksum_is_accepted() -> None:
    wire = encode_packet("TMSTA", "00,", lowercase=True)
    assert wire == b"$TMSTA,3,00,,*6c\r\n"
    assert TMFramer().packets(wire)[0].text == "00,"


def test_coalesced_and_split_packets_frame_by_length() -> None:
    # Binary data holding the delimiters themselves: only LEN can find the end.
    tricky = b"a,*5C\r\n$TMSCT,\x00\xff"
    wires = [encode_packet("TMSVR", b"1,1," + tricky), *(w for _, _, w in VECTORS)]
    stream = b"".join(wires)
    framer = TMFramer()
    assert [p.data for p in framer.packets(stream)][0] == b"1,1," + tricky
    got: list[TMPacket] = []
    for i in range(len(stream)):  # one byte per read
        got += framer.packets(stream[i:i + 1])
    assert len(got) == len(wires) and framer.pending == 0
    assert got[1:] == [TMPacket(h, d.encode()) for h, d, _ in VECTORS]


@pytest.mark.parametrize(("wire", "code", "words"), [
    (b"$TMSTA,2,00,*42\r\n", "02", "checksum"),
    (b"$TMSTA,2,00,*4G\r\n", "02", "hex"),
    (b"$TMXYZ,2,00,*41\r\n", "03", "header"),
    (b"$TMSTA,1,00,*41\r\n", "01", "length"),
    (b"$TMSTA,x2,00,*41\r\n", "01", "decimal"),
    (b"TMSTA,2,00,*41\r\n", "01", "'$'"),
])
def test_corrupted_packets_raise_typed_errors(wire: bytes, code: str, words: str) -> None:
    framer = TMFramer("robot")
    good = encode_packet("TMSTA", "00")
    framer.feed(good + wire)
    assert framer.next_packet() == TMPacket("TMSTA", b"00")  # the good packet before the bad one survives
    with pytest.raises(FrameError) as info:
        framer.next_packet()
    assert info.value.cperr_code == code and words in str(info.value) and isinstance(info.value, ProtocolError)
    assert framer.pending == 0


# ------------------------------------------------------------------------------------------------ the table
def test_table_round_trip_to_si() -> None:
    q, dq, tau = np.array([0.1, -0.4, 1.2, 0.3, 1.5, -0.2]), np.linspace(-1, 1, 6), np.array([1, -30, 12, 2, 0.5, 0])
    content = encode_items(encode_state_items(q, dq, tau, estop=True, error_code=0x0A, project_speed=50))
    st = decode_table(parse_svr(encode_svr("7", 1, content)))
    assert st.id == "7"
    np.testing.assert_allclose(st.q, q, atol=1e-6)
    np.testing.assert_allclose(st.dq, dq, atol=1e-6)
    np.testing.assert_allclose(st.tau, tau, atol=1e-6)  # sent as mN·m, read back in N·m
    assert (st.estop, st.robot_error, st.robot_link, st.error_code, st.project_speed, st.ma_mode) == (
        True, False, True, 0x0A, 50, 1)
    raw = parse_items(content)
    assert np.frombuffer(raw["Joint_Torque"], "<f4")[1] == pytest.approx(-30000.0)


def test_doc_table_lacks_speeds_and_torques() -> None:
    items = parse_items(doc_table_content())
    assert list(items) == ["Robot_Link", "Joint_Angle", "Error_Code"]
    np.testing.assert_allclose(np.frombuffer(items["Joint_Angle"], "<f4"), [0, 0, 90, 0, 90, 0])
    with pytest.raises(SlaveTableError, match=r"lacks Joint_Speed, Joint_Torque: .*Data_Table_Setting_TM_ROS_"
                                              r"Default\.xml or tick these items"):
        decode_table(SvrFrame("3", 1, doc_table_content()))


@pytest.mark.parametrize(("mode", "name"), [(2, "STRING"), (3, "JSON")])
def test_string_and_json_tables_are_refused_with_the_setting(mode: int, name: str) -> None:
    with pytest.raises(SlaveTableError) as info:
        decode_table(SvrFrame("0", mode, b"Joint_Angle={0,0,0,0,0,0}"))
    assert str(info.value) == (f"Ethernet Slave data table is {name}: set Communication Mode to BINARY in TMflow > "
                               "Setting > Connection > Ethernet Slave")


@pytest.mark.parametrize("content", [
    b"\x0b\x00Joint_Angle\x18\x00" + b"\x00" * 20,  # value runs past the end
    b"\x0b\x00Joint_Ang",  # name runs past the end
    b"\x05",  # a lone byte
])
def test_truncated_records_raise(content: bytes) -> None:
    with pytest.raises(ProtocolError, match="TMSVR table"):
        parse_items(content)


def test_wrong_sizes_and_non_finite_values_raise() -> None:
    items = dict(encode_state_items(np.zeros(6), np.zeros(6), np.zeros(6)))
    items["Joint_Speed"] = struct.pack("<5f", *range(5))
    with pytest.raises(ProtocolError, match="Joint_Speed has 20 bytes"):
        decode_table(SvrFrame("0", 1, encode_items(items.items())))
    items["Joint_Speed"] = struct.pack("<6f", 0, 0, math.nan, 0, 0, 0)
    with pytest.raises(ProtocolError, match="non-finite"):
        decode_table(SvrFrame("0", 1, encode_items(items.items())))
    with pytest.raises(ProtocolError, match="ID,MODE"):
        parse_svr(b"0")


# ------------------------------------------------------------------------------------------------ Listen node
def test_scripts_and_builders() -> None:
    proto = ListenProtocol()
    tid, wire = proto.script(["ContinueVJog()", set_continue_vjog([1, -2.5, 0, 0, 0, 1 / 3])])
    assert tid == "h1"
    packet = TMFramer().packets(wire)[0]
    assert packet.text == ("h1,ContinueVJog()\r\nSetContinueVJog(1.00000,-2.50000,0.00000,0.00000,0.00000,"
                           "0.33333)")
    assert queue_tag(3, 1) == "QueueTag(3,1)"
    with pytest.raises(ValueError):
        set_continue_vjog([math.nan] * 6)
    with pytest.raises(ValueError):
        queue_tag(16)
    with pytest.raises(ValueError):
        proto.script("Pause()", tid="a-1")


def test_replies_and_errors_name_the_line() -> None:
    proto = ListenProtocol()
    tid, _ = proto.script(["StopContinueVmode()", "Bogus(1)"])
    with pytest.raises(ScriptError, match=rf"script {tid} refused \(ERROR\) at line\(s\) 2: 2: Bogus\(1\)"):
        proto.handle(TMPacket("TMSCT", f"{tid},ERROR;2".encode()))
    assert proto.handle(TMPacket("TMSCT", b"h9,OK;1;2")) == ScriptReply("h9", (1, 2))
    assert proto.handle(TMPacket("TMSCT", b"0,Listen1")) == EntryMessage("Listen1")
    assert proto.handle(TMPacket("TMSTA", b"00,true,Listen1")) == ListenStatus(True, "Listen1")
    assert proto.handle(TMPacket("TMSTA", b"00,false,")) == ListenStatus(False, "")
    assert proto.handle(TMPacket("TMSTA", b"01,08,true")) == TagStatus(8, True)
    assert proto.handle(TMPacket("TMSTA", b"01,8,none")) == TagStatus(8, None)
    with pytest.raises(NotInListenNodeError, match="F1.*start the project in TMflow"):
        proto.handle(TMPacket("CPERR", b"F1"))
    with pytest.raises(CPError, match="CPERR 02 \\(checksum error\\)") as info:
        proto.handle(TMPacket("CPERR", b"02"))
    assert info.value.code == "02"
    for bad in (b"h1,MAYBE", b"h1"):
        with pytest.raises(ListenError):
            proto.handle(TMPacket("TMSCT", bad))


def test_emulated_node_answers_refuses_and_delays_motion() -> None:
    node = ListenNode(latency_cycles=2)
    ok = node.handle(TMPacket("TMSCT", b"a1,ContinueVJog()\r\nSetContinueVJog(57.29578,0,0,0,0,0)"))
    assert ok == [encode_packet("TMSCT", "a1,OK")]
    q = np.zeros(6)
    assert node.servo_target(q, 0.01) is None  # nothing due yet: the command latency
    target = node.servo_target(q, 0.01)
    assert target is not None and target[0] == pytest.approx(0.01, rel=1e-4)  # 1 rad/s for 10 ms
    assert node.handle(TMPacket("TMSCT", b"a2,Nope()")) == [encode_packet("TMSCT", "a2,ERROR;1")]
    assert node.handle(TMPacket("TMSTA", b"00,")) == [encode_packet("TMSTA", "00,true,Listen1")]
    node.leave()
    assert node.handle(TMPacket("TMSCT", b"a3,StopContinueVmode()")) == [encode_packet("CPERR", "F1")]
    assert node.handle(TMPacket("TMSTA", b"00,")) == [encode_packet("TMSTA", "00,false,")]
    assert node.servo_target(q, 0.01) is None


# ------------------------------------------------------------------------------------------------ config
def test_config_loads_bounded_with_one_line_errors() -> None:
    cfg = TMEthernetConfig.from_dict({"host": "192.168.1.2"}, "cell.yaml: devices.arm.settings")
    assert (cfg.slave_port, cfg.listen_port, cfg.link_lost_after_s) == (5891, 5890, 1.0)
    for data, words in [({}, "devices.arm.settings.host is required"),
                        ({"host": "x", "slave_prot": 1}, "unknown key 'slave_prot'"),
                        ({"host": "x", "position_gain": 50}, "position_gain must lie in [0, 20]"),
                        ({"host": "x", "listen_port": 5891}, "listen_port must differ"),
                        ({"host": "x", "link_lost_after_s": "1"}, "link_lost_after_s must be a number")]:
        with pytest.raises(ConfigError, match=words.replace("[", r"\[").replace("]", r"\]")):
            TMEthernetConfig.from_dict(data, "cell.yaml: devices.arm.settings")


# ------------------------------------------------------------------------------------------------ on loopback
@pytest.fixture
def plant() -> KinematicPlant:
    return KinematicPlant(dt=DT)


@pytest.fixture
def emulator(plant: KinematicPlant) -> Iterator[TMEthernetEmulator]:
    emu = start(plant)
    yield emu
    emu.stop()


@pytest.fixture
def arm(emulator: TMEthernetEmulator) -> Iterator[TMEthernetArm]:
    yield from connected(emulator)


def test_state_is_what_is_broadcast(arm: TMEthernetArm, emulator: TMEthernetEmulator,
                                    plant: KinematicPlant) -> None:
    first = arm.read_state()
    wait_for(lambda: arm.read_state().seq >= first.seq + 3, what="three more tables")
    st = arm.read_state()
    np.testing.assert_allclose(st.q, plant.q, atol=1e-6)  # float32 degrees on the wire
    np.testing.assert_allclose(st.tau, plant.torque(), atol=1e-4)
    assert any(np.allclose(p.q, st.q, atol=1e-6) for p in emulator.published)
    assert st.status.ok and st.t > first.t and arm.latest_table is not None
    assert arm.latest_table.id in "0123456789"


@pytest.mark.parametrize("latency_cycles", [0, 4])
def test_arm_stream_a_move_and_stop(arm: TMEthernetArm, emulator: TMEthernetEmulator, plant: KinematicPlant,
                                    latency_cycles: int) -> None:
    emulator.node.latency_cycles = latency_cycles
    with pytest.raises(LifecycleError):
        arm.send_target(arm.read_state().q)
    arm.arm()
    wait_for(lambda: emulator.node.vmode.active, what="streaming started")
    q0 = arm.read_state().q.copy()
    goal = q0 + np.array([0.15, -0.1, 0.0, 0.05, 0.0, 0.0])
    lag = 0.0
    for i in range(150):  # 1.2 s: a 0.4 s ramp, then hold the goal
        arm.read_state()
        target = q0 + (goal - q0) * min(1.0, i / 50)
        arm.send_target(target)
        lag = max(lag, float(np.max(np.abs(plant.q - target))))
        time.sleep(DT)
    assert lag < 0.1  # the plant followed the ramp (0.15 rad at 0.375 rad/s); left behind, it would lag 0.15
    # What the speeds' timing left of the ramp's start and end decays at the loop's gain: hold the goal.
    deadline = time.monotonic() + 5.0 / arm.config.position_gain
    while np.max(np.abs(plant.q - goal)) >= 2e-3 and time.monotonic() < deadline:
        arm.read_state()
        arm.send_target(goal)
        time.sleep(DT)
    assert np.max(np.abs(plant.q - goal)) < 2e-3, "the plant at the goal"
    arm.stop()
    assert arm.lifecycle is Lifecycle.CONNECTED
    wait_for(lambda: not emulator.node.vmode.active, what="streaming stopped")
    with pytest.raises(LifecycleError):
        arm.send_target(goal)


def test_bad_targets_never_reach_the_robot(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    arm.arm()
    scripts = emulator.node.scripts
    with pytest.raises(CommandRejectedError):
        arm.send_target(np.full(6, math.nan))
    q = arm.read_state().q
    sent = arm.send_target(q + 10.0)  # far away: clipped to one period's step at the speed limit
    assert sent.clipped
    v = arm.joint_speeds(sent.q, q, q)
    assert np.all(np.abs(v) <= LIMITS.velocity + 1e-9)
    wait_for(lambda: emulator.node.scripts > scripts, what="the clipped target's script")
    time.sleep(0.05)
    assert emulator.node.scripts == scripts + 1  # and nothing for the NaN target
    near = LIMITS.upper - 0.01  # next to the limit: only what stops inside the range in LIMIT_HORIZON_S
    assert np.all(arm.joint_speeds(LIMITS.upper, near, near) <= 0.01 / 0.1 + 1e-9)


def test_arm_refused_outside_the_listen_node(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    emulator.leave_node()
    with pytest.raises(LifecycleError, match="not in its Listen node: start the project in TMflow"):
        arm.arm()
    emulator.enter_node()
    wait_for(lambda: (arm.read_state(), arm.entry_message)[1] == "Listen1", what="the entry message")
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED


def test_silence_while_moving_is_stale_state_and_stops(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    """Armed, a broadcast silent for stale_after_s (a few periods) stops the arm: it must not move blind
    for the second TM's own drivers wait before calling the link lost."""
    arm.arm()
    emulator.go_silent()
    with pytest.raises(StaleDataError, match="no new data table"):
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            arm.read_state()
            time.sleep(DT)
    assert arm.lifecycle is Lifecycle.FAULT
    wait_for(lambda: not emulator.node.vmode.active, what="the fault's stop through the Listen node")
    emulator.clear_faults()
    seq = arm.read_state().seq  # arming takes a table no older than stale_after_s, and waits for none
    wait_for(lambda: arm.read_state().seq > seq, what="the broadcast again")
    arm.arm()
    assert arm.lifecycle is Lifecycle.ARMED


def test_silence_while_reading_is_a_lost_link(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    """Connected but not moving (status, doctor), the link is lost after link_lost_after_s of silence."""
    arm.read_state()
    emulator.go_silent()
    with pytest.raises(LinkLostError, match="no data table") as exc:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            arm.read_state()
            time.sleep(DT)
    # Not before the limit, by the driver's own count of the silence (the message names both).
    silence_ms, limit_ms = re.search(r"for (\d+) ms \(limit (\d+) ms\)", str(exc.value)).groups()  # type: ignore[union-attr]
    assert int(silence_ms) >= int(limit_ms) == round(arm.config.link_lost_after_s * 1000)


def test_estop_faults_and_refuses_commands(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    arm.arm()
    emulator.press_estop()
    wait_for(lambda: arm.read_state().status.estop, what="ESTOP in the table")
    assert arm.lifecycle is Lifecycle.FAULT and "estop" in (arm.fault_reason or "")
    with pytest.raises(LifecycleError):
        arm.send_target(arm.read_state().q)
    with pytest.raises(LifecycleError, match="cannot arm"):
        arm.arm()


def test_dropped_link_is_lost(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    arm.arm()
    emulator.drop_link(0.2)
    with pytest.raises(LinkLostError):
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            arm.read_state()
            time.sleep(DT)
    assert arm.lifecycle is Lifecycle.FAULT


def test_coalesced_split_broadcast_reads_every_table(plant: KinematicPlant) -> None:
    emu = start(plant, coalesce=3, split=4)
    try:
        arm = make_arm(emu)
        arm.connect()
        first = arm.read_state().seq
        wait_for(lambda: arm.read_state().seq >= first + 9, what="nine more tables")
        assert arm.read_state().status.ok
        arm.disconnect()
    finally:
        emu.stop()


def test_corrupted_broadcast_faults(arm: TMEthernetArm, emulator: TMEthernetEmulator) -> None:
    emulator.set_fault_rates(corrupt=1.0)
    with pytest.raises(ProtocolError, match="checksum"):
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            arm.read_state()
            time.sleep(DT)
    with pytest.raises(ConfigError, match=r"drop_probability must lie in \[0, 1\]"):
        emulator.set_fault_rates(drop=1.5)


@pytest.mark.parametrize(("kw", "words"), [
    ({"mode": "string"}, "is STRING: set Communication Mode to BINARY"),
    ({"mode": "json"}, "is JSON"),
    ({"items": ["Robot_Link", "Joint_Angle", "ESTOP"]}, "lacks Joint_Speed, Joint_Torque"),
])
def test_unusable_tables_refuse_to_connect(plant: KinematicPlant, kw: dict[str, Any], words: str) -> None:
    emu = start(plant, **kw)
    try:
        arm = make_arm(emu)
        with pytest.raises(SlaveTableError, match=words):
            arm.connect()
        assert arm.lifecycle is Lifecycle.DISCONNECTED
    finally:
        emu.stop()


def test_emulator_answers_a_broken_packet_with_cperr(emulator: TMEthernetEmulator) -> None:
    with socket.create_connection(("127.0.0.1", emulator.listen_port), timeout=2.0) as s:
        s.sendall(b"$TMSCT,4,1,OK,*00\r\n")
        framer = TMFramer()
        packets: list[TMPacket] = []
        deadline = time.monotonic() + 2.0
        while not packets and time.monotonic() < deadline:
            packets = framer.packets(s.recv(256))
    assert packets == [TMPacket("CPERR", b"02")]


def test_unreachable_controller_is_one_line(plant: KinematicPlant) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, never listening: refused
        arm = TMEthernetArm(TMEthernetConfig(host="127.0.0.1", slave_port=port, listen_port=port + 1 if port < 65535
                                             else port - 1, connect_timeout_s=0.5), LIMITS, DT)
        with pytest.raises(DriverError, match=f"cannot connect to 127.0.0.1:{port}") as info:
            arm.connect()
        assert "\n" not in str(info.value)
