"""One non-blocking TCP connection carrying TM packets: connect with a bound, drain what arrived, queue what to send."""

from __future__ import annotations

import logging
import socket

from drivers.errors import DriverError, LinkLostError, ProtocolError
from drivers.tm5.tm_packet import DEFAULT_MAX_LEN, FrameError, TMFramer, TMPacket

log = logging.getLogger(__name__)

_RECV_BYTES = 65536
_MAX_RECVS_PER_POLL = 64  # bounds one poll's time even when the peer floods us
_MAX_OUTBOX_BYTES = 1 << 16  # the robot stopped reading our scripts long before this much piles up
# Bad frames are skipped (the framer resynchronises on the next `$`); this many bytes of them with no good
# packet in between is a broken stream, not noise, and raises.  About eight data tables' worth.
MAX_BAD_BURST_BYTES = 8192


class TMLink:
    """A connected socket plus its framer and outbox.  Nothing here blocks once `open` has returned.

    A bad frame is skipped and the stream resynchronised on the next `$`; each run of bad frames (a burst,
    ended by the next good packet) is logged once with the bytes it cost.  `bad_frames` and `dropped_bytes`
    count them over the link's life.  A burst above `max_bad_burst_bytes` raises ProtocolError.
    """

    def __init__(self, sock: socket.socket, name: str, max_len: int = DEFAULT_MAX_LEN,
                 max_bad_burst_bytes: int = MAX_BAD_BURST_BYTES) -> None:
        self.name = name
        self.max_bad_burst_bytes = max_bad_burst_bytes
        self.bad_frames = 0
        self.dropped_bytes = 0
        self._sock: socket.socket | None = sock
        self._framer = TMFramer(name, max_len)
        self._outbox = bytearray()
        self._deferred: DriverError | None = None
        self._burst_bytes = 0
        self._burst_frames = 0
        self._burst_first = ""

    @classmethod
    def open(cls, host: str, port: int, timeout_s: float, name: str, max_len: int = DEFAULT_MAX_LEN) -> TMLink:
        """Connect within `timeout_s` (LinkLostError naming the endpoint otherwise); TCP_NODELAY, non-blocking."""
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise LinkLostError(f"{name}: cannot connect to {host}:{port} ({exc.strerror or exc})") from None
        # Small packets both ways every cycle: never let Nagle hold one back.
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        log.info("%s: connected to %s:%d", name, host, port)
        return cls(sock, name, max_len)

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def receive(self) -> list[TMPacket]:
        """Every complete packet that arrived since the last call.  A closed link, or a burst of bad frames
        over `max_bad_burst_bytes`, raises, but only after the good packets before it were returned (on the
        next call)."""
        if self._deferred is not None:
            err, self._deferred = self._deferred, None
            raise err
        sock = self._require()
        lost: str | None = None
        for _ in range(_MAX_RECVS_PER_POLL):
            try:
                chunk = sock.recv(_RECV_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                lost = f"receive failed ({exc.strerror or exc})"
                break
            if not chunk:
                lost = "the robot closed the connection"
                break
            self._framer.feed(chunk)
        packets: list[TMPacket] = []
        while True:
            try:
                packet = self._framer.next_packet()
            except FrameError as exc:  # the framer skipped past it: parse on from the next `$`
                self._bad_frame(exc)
                continue
            if packet is None:
                break
            self._end_burst()
            packets.append(packet)
        if lost is not None and self._deferred is None:
            self._deferred = self._lost(lost)
        if not packets and self._deferred is not None:
            err, self._deferred = self._deferred, None
            raise err
        return packets

    def send(self, data: bytes) -> None:
        """Queue `data` and send as much as the socket takes now."""
        self._require()
        self._outbox += data
        self.flush()

    def flush(self) -> None:
        sock = self._require()
        while self._outbox:
            try:
                n = sock.send(self._outbox)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                raise self._lost(f"send failed ({exc.strerror or exc})") from None
            del self._outbox[:n]
        if len(self._outbox) > _MAX_OUTBOX_BYTES:
            raise self._lost(f"{len(self._outbox)} bytes wait to be sent: the robot stopped reading")

    def close(self) -> None:
        sock, self._sock = self._sock, None
        self._outbox.clear()
        self._framer.reset()
        if sock is not None:
            sock.close()

    def _bad_frame(self, exc: FrameError) -> None:
        self.bad_frames += 1
        self.dropped_bytes += exc.dropped
        if not self._burst_frames:
            self._burst_first = str(exc)
        self._burst_frames += 1
        self._burst_bytes += exc.dropped
        if self._burst_bytes > self.max_bad_burst_bytes and self._deferred is None:
            self._deferred = ProtocolError(
                f"{self.name}: {self._burst_bytes} bytes in {self._burst_frames} bad frame(s) with no good packet "
                f"between them (limit {self.max_bad_burst_bytes}); first: {_after_name(self._burst_first, self.name)}")
            self._burst_bytes = self._burst_frames = 0

    def _end_burst(self) -> None:
        if self._burst_frames:
            log.warning("%s: skipped %d bytes in %d bad frame(s) before the next good packet; first: %s", self.name,
                        self._burst_bytes, self._burst_frames, _after_name(self._burst_first, self.name))
            self._burst_bytes = self._burst_frames = 0

    def _require(self) -> socket.socket:
        if self._sock is None:
            raise LinkLostError(f"{self.name}: the link is closed")
        return self._sock

    def _lost(self, reason: str) -> LinkLostError:
        self.close()
        log.warning("%s: link lost: %s", self.name, reason)
        return LinkLostError(f"{self.name}: {reason}")


def _after_name(message: str, name: str) -> str:
    """A framer's message without the link name it starts with (the caller's message names it once)."""
    prefix = f"{name}: "
    return message[len(prefix):] if message.startswith(prefix) else message
