"""The Listen node connection as `TMEthernetArm` drives it: its link, the scripts awaiting replies, its state."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

from drivers.errors import LinkLostError
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.listen import (
    CPError,
    EntryMessage,
    ListenData,
    ListenError,
    ListenProtocol,
    ListenStatus,
    NotInListenNodeError,
    ScriptError,
    ScriptReply,
    TagStatus,
)
from drivers.tm5.listen_backlog import ReplyBacklog
from drivers.tm5.tm_link import TMLink
from drivers.tm5.tm_packet import TMPacket

log = logging.getLogger(__name__)


class ListenSession:
    """One Listen-node connection at a time.  What was learnt on a connection (the node's state, the scripts
    awaiting replies, tag states) holds for that connection only and is forgotten when it closes.

    `in_node` is what the node said last (TMSTA 00, its entry message, CPERR F1; None: nothing yet);
    `streaming_confirmed` is whether ContinueVJog was answered OK since.  `poll` never waits.
    """

    def __init__(self, config: TMEthernetConfig) -> None:
        self.config = config
        self.protocol = ListenProtocol(source=f"TM Listen node {config.host}:{config.listen_port}")
        self.backlog = ReplyBacklog(self.protocol.source, config.max_unanswered_scripts, config.max_reply_age_s)
        self.link: TMLink | None = None
        self.entry_message: str | None = None  # the node's message, once the robot announced entering it
        self.in_node: bool | None = None
        self.streaming_confirmed = False
        self.status: ListenStatus | None = None  # the last TMSTA 00 reply
        self.tags: dict[int, TagStatus] = {}  # the last TMSTA 01 reply per tag
        self.stop_ids: list[str] = []  # the last stop's scripts

    @property
    def source(self) -> str:
        return self.protocol.source

    @property
    def up(self) -> bool:
        return self.link is not None and self.link.is_open

    def open(self) -> None:
        self.close()
        cfg = self.config
        self.link = TMLink.open(cfg.host, cfg.listen_port, cfg.connect_timeout_s, self.source)

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
        self.link = None
        self.backlog.clear()
        self.in_node = None
        self.streaming_confirmed = False
        self.status = None
        self.tags.clear()
        self.stop_ids = []

    def send(self, packet: bytes) -> None:
        if self.link is None or not self.link.is_open:
            raise LinkLostError(f"{self.source}: the Listen node link is down")
        self.link.send(packet)

    def send_script(self, lines: Sequence[str]) -> str:
        """Send a script and count it as awaiting its reply; its id."""
        tid, packet = self.protocol.script(lines)
        self.send(packet)
        self.backlog.sent(tid, lines[0].split("(", 1)[0], time.monotonic())
        return tid

    def poll(self) -> None:
        """Take the node's packets.  LinkLostError when the link is gone (closed here then); a refusal among
        the packets (ScriptError, CPError) raises once the others were taken in."""
        if self.link is None:
            return
        try:
            packets = self.link.receive()
        except LinkLostError:
            self.close()
            raise
        error: ListenError | None = None
        now = time.monotonic()
        for packet in packets:
            try:
                self._take(packet, now)
            except ListenError as exc:
                error = error or exc
        if error is not None:
            raise error

    def _take(self, packet: TMPacket, now: float) -> None:
        try:
            event = self.protocol.handle(packet)
        except ScriptError as exc:
            name = self.backlog.answered(exc.tid, now)
            if name == "ContinueVJog":
                self.streaming_confirmed = False
            if name == "StopContinueVmode":  # the StopAndClearBuffer sent before it ended the motion already
                log.warning("%s", exc)
                return
            raise
        except CPError as exc:
            # A CPERR names no script: the node answers in order, so it is the oldest one's answer.
            self.backlog.answer_oldest(now)
            if isinstance(exc, NotInListenNodeError):
                self.in_node = False
                self.streaming_confirmed = False
            raise
        if isinstance(event, ScriptReply):
            if self.backlog.answered(event.id, now) == "ContinueVJog":
                self.streaming_confirmed = True
        elif isinstance(event, ListenStatus):
            self.status = event
            self.in_node = event.in_node
            self.streaming_confirmed = self.streaming_confirmed and event.in_node
        elif isinstance(event, TagStatus):
            self.tags[event.tag] = event
        elif isinstance(event, EntryMessage):
            self.entry_message = event.text
            self.in_node = True
            log.info("TM Listen node entered: %r", event.text)
        elif isinstance(event, ListenData):
            log.debug("%s: TMSTA %s data %r", self.source, event.code, event.text[:80])
