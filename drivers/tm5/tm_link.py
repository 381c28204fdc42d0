"""One non-blocking TCP connection carrying TM packets: connect with a bound, drain what arrived, queue what to send."""

from __future__ import annotations

import logging
import socket

from drivers.errors import DriverError, LinkLostError, ProtocolError
from drivers.tm5.tm_packet import TMFramer, TMPacket

log = logging.getLogger(__name__)

_RECV_BYTES = 65536
_MAX_RECVS_PER_POLL = 64  # bounds one poll's time even when the peer floods us
_MAX_OUTBOX_BYTES = 1 << 16  # the robot stopped reading our scripts long before this much piles up


class TMLink:
    """A connected socket plus its framer and outbox.  Nothing here blocks once `open` has returned."""

    def __init__(self, sock: socket.socket, name: str) -> None:
        self.name = name
        self._sock: socket.socket | None = sock
        self._framer = TMFramer(name)
        self._outbox = bytearray()
        self._deferred: DriverError | None = None

    @classmethod
    def open(cls, host: str, port: int, timeout_s: float, name: str) -> TMLink:
        """Connect within `timeout_s` (LinkLostError naming the endpoint otherwise); TCP_NODELAY, non-blocking."""
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise LinkLostError(f"{name}: cannot connect to {host}:{port} ({exc.strerror or exc})") from None
        # Small packets both ways every cycle: never let Nagle hold one back.
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        log.info("%s: connected to %s:%d", name, host, port)
        return cls(sock, name)

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    def receive(self) -> list[TMPacket]:
        """Every complete packet that arrived since the last call.  A broken frame or a closed link raises,
        but only after the good packets before it were returned (on the next call)."""
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
        try:
            while (packet := self._framer.next_packet()) is not None:
                packets.append(packet)
        except ProtocolError as exc:
            self._deferred = exc
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

    def _require(self) -> socket.socket:
        if self._sock is None:
            raise LinkLostError(f"{self.name}: the link is closed")
        return self._sock

    def _lost(self, reason: str) -> LinkLostError:
        self.close()
        log.warning("%s: link lost: %s", self.name, reason)
        return LinkLostError(f"{self.name}: {reason}")
