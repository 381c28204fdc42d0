"""The estimated wrench for other programs: one UDP datagram of JSON per control step (`run --publish HOST:PORT`).

Datagram (UTF-8 JSON, one object): `t` (s since the loop started), `cycle`, `state` (the task's),
`wrench` [Fx, Fy, Fz, Mx, My, Mz] (N, N·m, tool frame, the tool on the environment: what the task
regulates with, the virtual sensor's by default), `sensor` (the F/T sensor's beside it, or null),
`q` (rad).  UDP because a reader that is slow or absent must never hold the control loop up: a datagram
that cannot be sent is dropped and counted.
"""

from __future__ import annotations

import json
import logging
import math
import socket
from collections.abc import Mapping, Sequence
from typing import Any

from drivers.errors import ConfigError

log = logging.getLogger(__name__)

AXES = ("fx", "fy", "fz", "mx", "my", "mz")


def parse_endpoint(text: str) -> tuple[str, int]:
    """'HOST:PORT' (or ':PORT' for 127.0.0.1) -> (host, port); anything else is refused in one line."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"--publish {text}: expected HOST:PORT (e.g. 127.0.0.1:5005)")
    return host or "127.0.0.1", int(port)


def resolve_endpoint(host: str, port: int) -> tuple[socket.AddressFamily, tuple[Any, ...]]:
    """(address family, numeric socket address) of HOST:PORT, looked up once before the loop starts: a
    name given to `sendto` is looked up again on every datagram, which can block for seconds."""
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise ConfigError(f"--publish {host}:{port}: cannot resolve '{host}' ({exc})") from None
    if not found:
        raise ConfigError(f"--publish {host}:{port}: '{host}' has no address")
    family, _, _, _, address = found[0]
    return family, address


def _vector(row: Mapping[str, Any], prefix: str) -> list[float | None] | None:
    keys = [prefix + a for a in AXES]
    if any(k not in row for k in keys):
        return None
    # JSON has no NaN: a missing reading goes out as null.
    return [float(row[k]) if row[k] is not None and math.isfinite(float(row[k])) else None for k in keys]


class WrenchPublisher:
    """Sends each control step's wrench to `endpoint` over UDP; never raises into the loop."""

    def __init__(self, endpoint: tuple[str, int], joints: int = 6) -> None:
        self.endpoint = endpoint
        self.joints = joints
        family, self.address = resolve_endpoint(*endpoint)
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.sock.setblocking(False)  # a full send buffer drops the datagram instead of waiting
        self.sent = 0
        self.dropped = 0

    def row(self, row: Mapping[str, Any]) -> None:
        msg = {"t": float(row["t"]), "cycle": int(row["cycle"]), "state": str(row.get("state", "")),
               "wrench": _vector(row, ""), "sensor": _vector(row, "sensor_"),
               "q": [float(row[f"q{i + 1}"]) for i in range(self.joints) if f"q{i + 1}" in row]}
        try:
            self.sock.sendto(json.dumps(msg).encode(), self.address)
            self.sent += 1
        except OSError:  # no reader, a full buffer: the loop goes on
            self.dropped += 1

    def event(self, text: str, warn: bool = False) -> None:
        """The task's outcome as a last datagram: {"event": text}."""
        try:
            self.sock.sendto(json.dumps({"event": text}).encode(), self.address)
        except OSError:
            self.dropped += 1

    def close(self) -> None:
        self.sock.close()
        log.info("published %d wrench datagrams to %s:%d (%d dropped)", self.sent, *self.endpoint, self.dropped)


class RowSinks:
    """Several row consumers (the live view, the publisher) as one: what the control loop's `on_row` calls."""

    def __init__(self, sinks: Sequence[Any]) -> None:
        self.sinks = list(sinks)

    def row(self, row: Mapping[str, Any]) -> None:
        for s in self.sinks:
            s.row(row)

    def event(self, text: str, warn: bool = False) -> None:
        for s in self.sinks:
            s.event(text, warn)
