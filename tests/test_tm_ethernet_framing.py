"""TM framing after a bad frame: the framer skips to the next `$` and re-verifies, the link logs each burst once,
an implausible LEN is refused at once, the checksum is exactly two hex digits."""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Iterator

import pytest

from drivers.errors import ProtocolError
from drivers.tm5.tm_link import TMLink
from drivers.tm5.tm_packet import FrameError, TMFramer, TMPacket, checksum, encode_packet

GOOD = [encode_packet("TMSTA", "00,true,Listen1"), encode_packet("TMSCT", "h1,OK"), encode_packet("TMSTA", "01,3,true")]


def corrupt(wire: bytes) -> bytes:
    """The packet with a wrong (but well-formed) checksum."""
    wrong = (int(wire[-4:-2], 16) ^ 0x5A) & 0xFF
    return wire[:-4] + f"{wrong:02X}".encode("ascii") + b"\r\n"


def drain(framer: TMFramer) -> tuple[list[TMPacket], list[FrameError]]:
    packets: list[TMPacket] = []
    errors: list[FrameError] = []
    while True:
        try:
            packet = framer.next_packet()
        except FrameError as exc:
            errors.append(exc)
            continue
        if packet is None:
            return packets, errors
        packets.append(packet)


def test_good_packets_after_a_bad_one_survive() -> None:
    bad = corrupt(encode_packet("TMSVR", b"1,1,\x00\x01\x02"))
    framer = TMFramer("robot")
    framer.feed(GOOD[0] + bad + GOOD[1] + GOOD[2])
    packets, errors = drain(framer)
    assert [p.text for p in packets] == ["00,true,Listen1", "h1,OK", "01,3,true"]
    assert len(errors) == 1 and errors[0].cperr_code == "02" and "checksum" in str(errors[0])
    assert errors[0].dropped == len(bad) == framer.dropped_bytes and framer.pending == 0


def test_garbage_and_a_fake_packet_inside_a_bad_one_are_skipped() -> None:
    # A packet whose LEN is one short: its end is unknown, and its data holds a `$` starting a packet whose
    # checksum is wrong.  The framer tries that `$` too, refuses it, and finds the next real packet.
    data = b"1,1,\x00$TMSTA,2,00,*42\r\n\x07"
    wire = encode_packet("TMSVR", data)
    short = wire.replace(f",{len(data)},".encode(), f",{len(data) - 1},".encode(), 1)
    framer = TMFramer()
    framer.feed(b"noise," + short + GOOD[1])
    packets, errors = drain(framer)
    assert packets == [TMPacket("TMSCT", b"h1,OK")]
    assert len(errors) == 3  # the noise, the short packet, the fake one inside it
    assert framer.dropped_bytes == len(b"noise,") + len(short)


def test_a_len_beyond_the_plausible_maximum_fails_at_once_naming_the_field() -> None:
    framer = TMFramer("slave", max_len=100)
    framer.feed(b"$TMSVR,500,")  # nothing more has come: a waiting framer would stall for 500 bytes
    with pytest.raises(FrameError, match=r"^slave: \$TMSVR LEN field 500 exceeds the plausible maximum of 100 bytes$"):
        framer.next_packet()
    framer.feed(b"$TMSVR,123456789")  # more digits than any plausible length, before its comma arrives
    with pytest.raises(FrameError, match=r"LEN field 1234\.\.\. exceeds the plausible maximum of 100 bytes$"):
        framer.next_packet()
    framer.feed(b"$TMSVR,12a4")
    with pytest.raises(FrameError, match=r"LEN field b'12a4' is not a decimal number$"):
        framer.next_packet()
    framer.feed(GOOD[1])
    assert framer.next_packet() == TMPacket("TMSCT", b"h1,OK")


def with_checksum_text(header: str, cs_text: bytes, value: int) -> bytes:
    """A packet whose checksum is written as `cs_text` (which int(., 16) reads as `value`) and whose body's
    real checksum is `value`: only the format of the field is wrong."""
    for i in range(256):
        data = b"00," + bytes([i])
        body = header.encode() + b"," + str(len(data)).encode() + b"," + data + b","
        if checksum(body) == value:
            return b"$" + body + b"*" + cs_text + b"\r\n"
    raise AssertionError("no body with that checksum")


@pytest.mark.parametrize("cs_text", [b"+1", b" 1", b"1 "])
def test_the_checksum_is_exactly_two_hex_digits(cs_text: bytes) -> None:
    assert int(cs_text, 16) == 1  # Python's int() would take it
    framer = TMFramer()
    framer.feed(with_checksum_text("TMSTA", cs_text, 1) + GOOD[0])
    with pytest.raises(FrameError, match="is not two hex digits") as info:
        framer.next_packet()
    assert info.value.cperr_code == "02"
    assert framer.next_packet() == TMPacket("TMSTA", b"00,true,Listen1")


# ------------------------------------------------------------------------------------------------ the link
@pytest.fixture
def link_pair() -> Iterator[tuple[TMLink, socket.socket]]:
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        link = TMLink.open("127.0.0.1", port, 2.0, "test link")
        peer, _ = server.accept()
    try:
        yield link, peer
    finally:
        link.close()
        peer.close()


def receive_until(link: TMLink, n: int) -> list[TMPacket]:
    got: list[TMPacket] = []
    deadline = time.monotonic() + 3.0
    while len(got) < n and time.monotonic() < deadline:
        got += link.receive()
        time.sleep(0.002)
    return got


def test_the_link_resyncs_and_logs_each_burst_once(link_pair: tuple[TMLink, socket.socket],
                                                   caplog: pytest.LogCaptureFixture) -> None:
    link, peer = link_pair
    # The junk goes with the bad packet before it: both lie between its `$` and the next one.
    bursts = [corrupt(GOOD[0]) + b"junk" + corrupt(GOOD[2]), corrupt(GOOD[1])]
    caplog.set_level(logging.WARNING, logger="drivers.tm5.tm_link")
    peer.sendall(GOOD[0] + bursts[0] + GOOD[1] + bursts[1] + GOOD[2])
    got = receive_until(link, 3)
    assert [p.text for p in got] == ["00,true,Listen1", "h1,OK", "01,3,true"]
    lines = [r.getMessage() for r in caplog.records if "bad frame" in r.getMessage()]
    assert len(lines) == 2, lines  # one line per burst, not per bad frame
    assert f"skipped {len(bursts[0])} bytes in 2 bad frame(s)" in lines[0] and "checksum" in lines[0]
    assert link.dropped_bytes == sum(map(len, bursts)) and link.bad_frames == 3 and link.is_open


def test_a_long_burst_of_bad_frames_is_a_broken_stream(link_pair: tuple[TMLink, socket.socket]) -> None:
    link, peer = link_pair
    link.max_bad_burst_bytes = 200
    bad = corrupt(encode_packet("TMSVR", b"1,1," + b"\x00" * 60))
    peer.sendall(GOOD[1] + bad * 5)
    got: list[TMPacket] = []
    with pytest.raises(ProtocolError, match=r"^test link: \d+ bytes in \d bad frame\(s\) with no good packet "
                                            r"between them \(limit 200\); first: \$TMSVR checksum"):
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            got += link.receive()
            time.sleep(0.002)
    assert got == [TMPacket("TMSCT", b"h1,OK")]  # the good packet before the burst came out first
