"""The Listen node's protocol (port 5890): `$TMSCT` scripts and replies, `$TMSTA` queries, `$CPERR` codes (sans I/O)."""

from __future__ import annotations

import logging
import re
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError
from drivers.tm5.tm_packet import TMPacket, encode_packet

log = logging.getLogger(__name__)

N_JOINTS = 6
ENTRY_ID = "0"  # the robot's unsolicited message on entering the node; never used for our scripts
CPERR_CODES = {"00": "OK", "01": "packet error", "02": "checksum error", "03": "header error", "04": "data error",
               "F1": "not in the Listen node"}
_NODE_HINT = "start the project in TMflow and let its flow reach the Listen node"
_REMEMBERED_SCRIPTS = 256  # enough to name the line of a late ERROR reply at a 125 Hz command rate
_REPLY = re.compile(r"^(OK|ERROR)((?:;\d+)*)$")


class ListenError(ProtocolError):
    """The Listen node refused a script, or answered with something this client does not understand."""


class ScriptError(ListenError):
    """A script reply `ID,ERROR;n;...`: the message names the script and its failing lines; `tid` is its id."""

    def __init__(self, message: str, tid: str) -> None:
        super().__init__(message)
        self.tid = tid


class CPError(ListenError):
    """A `$CPERR` packet: the node rejected a packet (code 01-04) or the flow is not in the node (F1)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class NotInListenNodeError(CPError):
    """CPERR F1: scripts are refused because the project's flow is outside its Listen node."""


# ------------------------------------------------------------------------------------------------ scripts
def _num(v: float) -> str:
    return f"{float(v):.5f}"


def continue_vjog() -> str:
    """Enter joint velocity streaming."""
    return "ContinueVJog()"


def set_continue_vjog(speeds_deg_s: Sequence[float] | np.ndarray) -> str:
    """The streamed joint velocity, deg/s, five decimals."""
    values = np.asarray(speeds_deg_s, dtype=float)
    if values.shape != (N_JOINTS,) or not np.all(np.isfinite(values)):
        raise ValueError(f"SetContinueVJog needs {N_JOINTS} finite speeds, got {speeds_deg_s!r}")
    return f"SetContinueVJog({','.join(_num(v) for v in values)})"


def stop_continue_vmode() -> str:
    return "StopContinueVmode()"


def stop_and_clear_buffer() -> str:
    return "StopAndClearBuffer()"


def queue_tag(tag: int, wait: int = 0) -> str:
    """Tag the motion queue (tag 1-15); `wait` 1 blocks the script until the tag is reached."""
    if not 1 <= int(tag) <= 15 or wait not in (0, 1):
        raise ValueError(f"QueueTag needs a tag in 1-15 and wait 0 or 1, got {tag!r}, {wait!r}")
    return f"QueueTag({int(tag)},{wait})"


# ------------------------------------------------------------------------------------------------ replies
@dataclass(frozen=True)
class ScriptReply:
    """`ID,OK[;n;m]`: the script was accepted (not done: motions queue); `warnings` are 1-based lines."""

    id: str
    warnings: tuple[int, ...] = ()


@dataclass(frozen=True)
class EntryMessage:
    """The node was entered; `text` is the node's message."""

    text: str


@dataclass(frozen=True)
class ListenStatus:
    """`$TMSTA 00`: whether the flow is in the Listen node, and the node's message."""

    in_node: bool
    message: str


@dataclass(frozen=True)
class TagStatus:
    """`$TMSTA 01`: tag `tag` is done (True), pending (False) or unknown to the robot (None)."""

    tag: int
    done: bool | None


@dataclass(frozen=True)
class ListenData:
    """`$TMSTA 90-99`: data the project pushed with ListenSend."""

    code: str
    text: str


ListenEvent = ScriptReply | EntryMessage | ListenStatus | TagStatus | ListenData


def cperr(code: str, source: str = "Listen node") -> CPError:
    """The typed error for a `$CPERR` code."""
    code = code.strip().upper()
    meaning = CPERR_CODES.get(code, "unknown code")
    if code == "F1":
        return NotInListenNodeError(code, f"{source}: CPERR F1 ({meaning}): {_NODE_HINT}")
    return CPError(code, f"{source}: CPERR {code} ({meaning})")


class ListenProtocol:
    """Builds the packets a client sends and interprets the packets it receives.

    Script ids are `<prefix><n>`; the last scripts are remembered so an ERROR reply names its line.
    `handle` returns an event, or raises ScriptError / CPError (typed, one line).
    """

    def __init__(self, source: str = "Listen node", prefix: str = "h") -> None:
        if not prefix.isalnum() or prefix.isdigit():
            raise ValueError(f"script id prefix must be alphanumeric and not a number, got {prefix!r}")
        self.source = source
        self._prefix = prefix
        self._n = 0
        self._scripts: OrderedDict[str, tuple[str, ...]] = OrderedDict()

    def script(self, lines: str | Sequence[str], tid: str | None = None) -> tuple[str, bytes]:
        """(id, packet) of a `$TMSCT` script of one statement per line."""
        body = (lines,) if isinstance(lines, str) else tuple(lines)
        if not body or any(("\r" in s or "\n" in s or not s.strip()) for s in body):
            raise ValueError(f"a script is one non-empty statement per line, got {lines!r}")
        if tid is None:
            self._n += 1
            tid = f"{self._prefix}{self._n}"
        if not tid.isalnum() or tid == ENTRY_ID:
            raise ValueError(f"script id must be alphanumeric and not {ENTRY_ID!r}, got {tid!r}")
        self._scripts[tid] = body
        while len(self._scripts) > _REMEMBERED_SCRIPTS:
            self._scripts.popitem(last=False)
        return tid, encode_packet("TMSCT", f"{tid}," + "\r\n".join(body))

    @staticmethod
    def listen_status_query() -> bytes:
        return encode_packet("TMSTA", "00")

    @staticmethod
    def tag_status_query(tag: int) -> bytes:
        return encode_packet("TMSTA", f"01,{int(tag)}")

    def handle(self, packet: TMPacket) -> ListenEvent:
        if packet.header == "CPERR":
            raise cperr(packet.text, self.source)
        if packet.header == "TMSCT":
            return self._script_reply(packet.text)
        if packet.header == "TMSTA":
            return self._status(packet.text)
        raise ListenError(f"{self.source}: unexpected ${packet.header} packet on the Listen port")

    def _script_reply(self, text: str) -> ScriptReply | EntryMessage:
        tid, sep, rest = text.partition(",")
        if tid == ENTRY_ID:
            return EntryMessage(rest)
        m = _REPLY.match(rest) if sep else None
        if m is None:
            raise ListenError(f"{self.source}: script reply {text[:60]!r} is not ID,OK or ID,ERROR")
        lines = tuple(int(n) for n in m.group(2).split(";")[1:])
        body = self._scripts.pop(tid, None)
        if m.group(1) == "OK":
            if lines:
                log.warning("%s: script %s accepted with warnings on line(s) %s: %s", self.source, tid,
                            ", ".join(map(str, lines)), _show_lines(body, lines))
            return ScriptReply(tid, lines)
        raise ScriptError(f"{self.source}: script {tid} refused (ERROR) at line(s) "
                          f"{', '.join(map(str, lines)) or '?'}: {_show_lines(body, lines)}", tid)

    def _status(self, text: str) -> ListenStatus | TagStatus | ListenData:
        code, _, rest = text.partition(",")
        if code == "00":
            flag, _, message = rest.partition(",")
            if flag not in ("true", "false"):
                raise ListenError(f"{self.source}: TMSTA 00 reply {text[:60]!r} is not 00,true|false,<message>")
            return ListenStatus(flag == "true", message)
        if code == "01":
            tag, _, state = rest.partition(",")
            if not tag.strip().isdigit() or state not in ("true", "false", "none"):
                raise ListenError(f"{self.source}: TMSTA 01 reply {text[:60]!r} is not 01,<tag>,true|false|none")
            return TagStatus(int(tag), None if state == "none" else state == "true")
        if len(code) == 2 and code.startswith("9") and code.isdigit():
            return ListenData(code, rest)
        raise ListenError(f"{self.source}: unknown TMSTA reply {text[:60]!r}")


def _show_lines(body: tuple[str, ...] | None, lines: tuple[int, ...]) -> str:
    if body is None:
        return "(script not remembered)"
    shown = [f"{n}: {body[n - 1]}" for n in lines if 1 <= n <= len(body)]
    return "; ".join(shown) if shown else " | ".join(body)[:200]
