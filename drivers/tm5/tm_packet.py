"""TM's packet framing `$HDR,LEN,DATA,*CS\r\n` (Listen node and Ethernet Slave): encoder and incremental framer."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NoReturn

from drivers.errors import ProtocolError

HEADERS = ("TMSVR", "TMSCT", "TMSTA", "CPERR")
MAX_DATA_LEN = 1 << 20  # the largest DATA `encode_packet` builds (a long script is a few tens of kB)
# The largest LEN a framer believes by default: a data table is ~1 kB, a reply or status a few bytes.  A LEN
# beyond what a link can carry is a broken field, refused at once rather than waited for.
DEFAULT_MAX_LEN = 1 << 16
_HEADER_LEN = 5
_TRAILER_LEN = 6  # ",*" + two hex digits + CR LF
_HEX_DIGITS = frozenset(b"0123456789abcdefABCDEF")


class FrameError(ProtocolError):
    """A packet that breaks the framing; `cperr_code` is what the Listen node answers to it (01, 02 or 03)."""

    def __init__(self, message: str, cperr_code: str, dropped: int = 0) -> None:
        super().__init__(message)
        self.cperr_code = cperr_code
        self.dropped = dropped  # bytes the framer skipped to get past the bad packet


@dataclass(frozen=True)
class TMPacket:
    """One packet: its header (`TMSVR`, `TMSCT`, `TMSTA` or `CPERR`) and its DATA bytes."""

    header: str
    data: bytes

    @property
    def text(self) -> str:
        """DATA as text (scripts, replies, status); binary tables use `data`."""
        return self.data.decode("utf-8", errors="replace")


def checksum(body: bytes) -> int:
    """XOR of every byte of `body` (everything after `$` up to and including the comma before `*`)."""
    cs = 0
    for b in body:
        cs ^= b
    return cs


def encode_packet(header: str, data: bytes | str, *, lowercase: bool = False) -> bytes:
    """The full packet for `data` under `header`, checksum in uppercase hex (lowercase on request)."""
    if header not in HEADERS:
        raise ValueError(f"unknown TM packet header {header!r} (expected one of {list(HEADERS)})")
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    if len(raw) > MAX_DATA_LEN:
        raise ValueError(f"TM packet data of {len(raw)} bytes exceeds {MAX_DATA_LEN}")
    body = header.encode("ascii") + b"," + str(len(raw)).encode("ascii") + b"," + raw + b","
    cs = f"{checksum(body):02x}" if lowercase else f"{checksum(body):02X}"
    return b"$" + body + b"*" + cs.encode("ascii") + b"\r\n"


class TMFramer:
    """Cuts a byte stream into packets by their LEN field (DATA may hold commas, CR LF and binary).

    `feed` appends bytes; `next_packet` returns the next complete packet, None while one is incomplete,
    and raises FrameError (a ProtocolError) for a bad header, length, trailer or checksum.  Before raising it
    skips to the next `$` after the bad packet's start (its LEN was not to be trusted, so its end is unknown):
    the next call parses from there, verifying that packet's length, trailer and checksum in turn, so good
    packets behind a bad one survive.  `dropped_bytes` counts what was skipped.
    """

    def __init__(self, source: str = "TM", max_len: int = DEFAULT_MAX_LEN) -> None:
        if not 1 <= max_len <= MAX_DATA_LEN:
            raise ValueError(f"max_len must lie in 1..{MAX_DATA_LEN}, got {max_len!r}")
        self.source = source
        self.max_len = max_len
        self.dropped_bytes = 0
        self._max_len_digits = len(str(max_len))
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        """Bytes received but not yet framed."""
        return len(self._buf)

    def reset(self) -> None:
        self._buf.clear()

    def feed(self, data: bytes) -> None:
        self._buf += data

    def packets(self, data: bytes = b"") -> list[TMPacket]:
        """Feed `data` and return every complete packet now buffered (raises on the first bad one)."""
        self.feed(data)
        out: list[TMPacket] = []
        while (packet := self.next_packet()) is not None:
            out.append(packet)
        return out

    def next_packet(self) -> TMPacket | None:
        buf = self._buf
        if not buf:
            return None
        if buf[0] != ord("$"):
            self._fail(f"expected '$' at the start of a packet, got {bytes(buf[:16])!r}")
        comma1 = buf.find(b",", 1, 2 + _HEADER_LEN)
        if comma1 < 0:
            if len(buf) >= 2 + _HEADER_LEN:
                self._fail(f"no header in {bytes(buf[:16])!r}", "03")
            return None
        header = bytes(buf[1:comma1]).decode("ascii", errors="replace")
        if header not in HEADERS:
            self._fail(f"unknown header {header!r} (expected one of {', '.join(HEADERS)})", "03")
        comma2 = buf.find(b",", comma1 + 1, comma1 + 2 + self._max_len_digits)
        if comma2 < 0:
            if len(buf) >= comma1 + 2 + self._max_len_digits:
                seg = bytes(buf[comma1 + 1:comma1 + 2 + self._max_len_digits])
                if not seg.isdigit():
                    self._fail(f"${header} LEN field {seg!r} is not a decimal number")
                self._fail(f"${header} LEN field {seg.decode('ascii')}... exceeds the plausible maximum of "
                           f"{self.max_len} bytes")
            return None
        len_field = bytes(buf[comma1 + 1:comma2])
        if not len_field.isdigit():
            self._fail(f"${header} LEN field {len_field!r} is not a decimal number")
        length = int(len_field)
        if length > self.max_len:
            self._fail(f"${header} LEN field {length} exceeds the plausible maximum of {self.max_len} bytes")
        end_data = comma2 + 1 + length
        end = end_data + _TRAILER_LEN
        if len(buf) < end:
            return None
        trailer = bytes(buf[end_data:end])
        if trailer[:2] != b",*" or trailer[4:] != b"\r\n":
            self._fail(f"${header} packet of length {length} ends in {trailer!r}, expected ',*XX\\r\\n' "
                       "(wrong LEN field?)")
        if trailer[2] not in _HEX_DIGITS or trailer[3] not in _HEX_DIGITS:
            self._fail(f"${header} checksum {trailer[2:4]!r} is not two hex digits", "02")
        received = int(trailer[2:4].decode("ascii"), 16)
        expected = checksum(bytes(buf[1:end_data + 1]))
        if received != expected:
            self._fail(f"${header} checksum {received:02X} does not match the packet's {expected:02X}", "02")
        data = bytes(buf[comma2 + 1:end_data])
        del buf[:end]
        return TMPacket(header, data)

    def _fail(self, message: str, cperr_code: str = "01") -> NoReturn:
        # The bad packet's own `$` is skipped: whatever follows up to the next `$` belongs to no packet
        # this framer can trust.
        nxt = self._buf.find(b"$", 1)
        dropped = len(self._buf) if nxt < 0 else nxt
        del self._buf[:dropped]
        self.dropped_bytes += dropped
        raise FrameError(f"{self.source}: {message}", cperr_code, dropped)
