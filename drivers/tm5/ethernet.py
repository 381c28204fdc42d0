"""TM5-700 on its own channels: `TMEthernetArm` reads the Ethernet Slave and streams joint speeds to the Listen node."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from drivers.errors import (
    CommandRejectedError,
    ConfigError,
    LifecycleError,
    LinkLostError,
    ProtocolError,
    StaleDataError,
)
from drivers.interfaces import Arm, ArmState, ArmStatus, JointLimits, Lifecycle
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.ethernet_slave import (
    MODE_RESPONSE,
    N_JOINTS,
    RESPONSE_CODES,
    SlaveState,
    check_mode,
    decode_table,
    parse_svr,
)
from drivers.tm5.listen import (
    EntryMessage,
    ListenProtocol,
    ListenStatus,
    ScriptReply,
    TagStatus,
    continue_vjog,
    cperr,
    queue_tag,
    set_continue_vjog,
    stop_and_clear_buffer,
    stop_continue_vmode,
)
from drivers.tm5.table_check import check_before_arming
from drivers.tm5.tm_link import TMLink
from drivers.tm5.tm_packet import TMPacket
from drivers.tm5.velocity_loop import VelocityLoop

log = logging.getLogger(__name__)

_POLL_S = 0.002  # sleep between polls while connect() or arm() wait for the robot
_NODE_HINT = "start the project in TMflow and let its flow reach the Listen node, then arm again"


class TMEthernetArm(Arm):
    """The TM5-700 through TM's Ethernet Slave (state, port 5891) and a project waiting in its Listen node
    (motion, port 5890): no robot-side program beyond a Listen node.

    `read_state` drains the broadcast without blocking and returns the latest table (`seq` counts decoded
    tables, `t` is the host's receive time); `send_target` closes the position loop on the host and
    streams one `SetContinueVJog` per control period.  Units are converted here only.
    """

    def __init__(self, config: TMEthernetConfig, limits: JointLimits, dt: float, speed_scale: float = 1.0) -> None:
        super().__init__(limits, dt, speed_scale)
        config.validate()
        if limits.n != N_JOINTS:
            raise ConfigError(f"the TM5-700 has {N_JOINTS} joints, the joint limits describe {limits.n}")
        self.config = config
        self._slave: TMLink | None = None
        self._listen: TMLink | None = None
        self._protocol = ListenProtocol(source=f"TM Listen node {config.host}:{config.listen_port}")
        self._latest: SlaveState | None = None
        self._latest_t = 0.0
        self._seq = 0
        self._listen_status: ListenStatus | None = None
        self._replies: dict[str, ScriptReply] = {}
        self._entry_message: str | None = None
        self._tag_done: bool | None = None
        self._warned_untested = False
        self.velocity_loop = VelocityLoop(limits, dt, config.position_gain, config.command_latency_periods,
                                          speed_scale)

    # ----------------------------------------------------------------------------- public extras
    @property
    def endpoint(self) -> str:
        return f"{self.config.host}:{self.config.slave_port}/{self.config.listen_port}"

    @property
    def link_up(self) -> bool:
        return self._slave is not None and self._slave.is_open

    @property
    def listen_up(self) -> bool:
        return self._listen is not None and self._listen.is_open

    @property
    def latest_table(self) -> SlaveState | None:
        """The last decoded data table (error code, M/A mode, project speed, poses), as of the last poll."""
        return self._latest

    @property
    def entry_message(self) -> str | None:
        """The Listen node's message, once the robot announced entering it on this connection."""
        return self._entry_message

    # ----------------------------------------------------------------------------- bring-up probes
    def probe_listen_node(self) -> ListenStatus:
        """Ask `$TMSTA 00` whether the project is in its Listen node (connects to the node if needed)."""
        if not self.listen_up:
            self._open_listen()
        assert self._listen is not None
        self._listen_status = None
        self._listen.send(ListenProtocol.listen_status_query())
        self._wait_for(lambda: self._listen_status is not None, "a reply to TMSTA 00")
        assert self._listen_status is not None
        return self._listen_status

    def command_round_trip(self, tag: int = 15) -> float:
        """Seconds from sending `QueueTag(tag)` (no motion) to `$TMSTA 01` reporting the tag done: how long a
        command takes to pass the Listen node's queue.  Needs the project in its Listen node."""
        if not self.listen_up:
            self._open_listen()
        assert self._listen is not None
        t0 = time.monotonic()
        tid = self._send_script([queue_tag(tag, 0)])
        self._wait_for(lambda: tid in self._replies, f"the reply to QueueTag({tag})")
        self._tag_done = None
        while self._tag_done is not True:
            self._tag_done = None
            self._listen.send(ListenProtocol.tag_status_query(tag))
            self._wait_for(lambda: self._tag_done is not None, f"a reply to TMSTA 01,{tag}")
            if self._tag_done is None:
                raise ProtocolError(f"TM {self.endpoint}: the robot does not know tag {tag}")
        return time.monotonic() - t0

    # ----------------------------------------------------------------------------- wire: lifecycle
    def _connect(self) -> None:
        if not self._warned_untested:
            log.warning("TMEthernetArm %s: the real-hardware path is UNTESTED on a physical arm (it has only run "
                        "against sim.tm_ethernet_emulator); keep a hand on the E-stop", self.endpoint)
            self._warned_untested = True
        try:
            self._open_slave()
            try:
                self._open_listen()
            except LinkLostError as exc:  # reading needs no Listen node; arming will ask for it again
                log.info("TM Listen node not reachable yet (%s); arm() needs it", exc)
        except BaseException:
            self._disconnect()
            raise

    def _disconnect(self) -> None:
        for link in (self._slave, self._listen):
            if link is not None:
                link.close()
        self._slave = self._listen = None

    def _arm(self) -> None:
        """Both links up, the project in its Listen node, the controller healthy: then enter velocity streaming."""
        if not self.link_up:
            self._open_slave()
        self._poll()  # takes the replies and the node's messages that came in meanwhile (may find it closed)
        if not self.listen_up:
            try:
                self._open_listen()
            except LinkLostError as exc:
                raise LinkLostError(f"{exc}: the Listen node serves this port only while a project runs in it; "
                                    f"{_NODE_HINT}") from None
        assert self._listen is not None
        self._listen_status = None
        self._listen.send(ListenProtocol.listen_status_query())
        self._wait_for(lambda: self._listen_status is not None, "a reply to TMSTA 00 (in the Listen node?)")
        assert self._listen_status is not None
        if not self._listen_status.in_node:
            raise LifecycleError(f"TM {self.endpoint}: the project is not in its Listen node: {_NODE_HINT}")
        status = self._status(self._fresh_table())
        if not status.ok:
            raise LifecycleError(f"cannot arm: controller reports {status}")
        if self.config.modbus_port is not None:  # the controller's own Modbus table must tell the same story
            check_before_arming(self)
        tid = self._send_script([continue_vjog()])
        self._wait_for(lambda: tid in self._replies, f"the reply to ContinueVJog() (script {tid})")
        self.velocity_loop.reset()

    def _stop(self) -> None:
        if self._listen is None or not self._listen.is_open:
            raise LinkLostError(f"TM {self.endpoint}: cannot stop: the Listen node link is down")
        self._send_script([stop_continue_vmode(), stop_and_clear_buffer()])

    # ----------------------------------------------------------------------------- wire: data
    def _read_state(self) -> ArmState:
        self._poll()
        table = self._fresh_table()
        silence = time.monotonic() - self._latest_t
        if self.lifecycle is Lifecycle.ARMED and silence > self.config.stale_after_s:
            raise StaleDataError(f"TM {self.config.host}:{self.config.slave_port}: no new data table for "
                                 f"{silence * 1000:.0f} ms (limit {self.config.stale_after_s * 1000:.0f} ms) "
                                 "while moving: stale state")
        return ArmState(t=self._latest_t, q=table.q, dq=table.dq, tau=table.tau, status=self._status(table),
                        seq=self._seq)

    def _write_target(self, q: np.ndarray) -> None:
        self._poll_listen()  # a refused script or a left node faults before another speed goes out
        table = self._fresh_table()
        assert self._last_sent is not None
        v = self.joint_speeds(q, self._last_sent, table.q)
        if not np.all(np.isfinite(v)):
            raise CommandRejectedError(f"command refused: non-finite joint speeds {v!r}")
        self._send_script([set_continue_vjog(np.degrees(v))])
        self.velocity_loop.sent(v)

    def joint_speeds(self, q: np.ndarray, q_prev: np.ndarray, q_meas: np.ndarray) -> np.ndarray:
        """rad/s to stream for target `q` (see `VelocityLoop`)."""
        return self.velocity_loop.speeds(q, q_prev, q_meas)

    # ----------------------------------------------------------------------------- helpers
    def _open_slave(self) -> None:
        """Connect to the Ethernet Slave and wait for a first table this driver can read."""
        cfg = self.config
        self._slave = TMLink.open(cfg.host, cfg.slave_port, cfg.connect_timeout_s, f"TM Ethernet Slave {cfg.host}:"
                                  f"{cfg.slave_port}")
        before = self._seq
        deadline = time.monotonic() + cfg.connect_timeout_s
        while self._seq == before:
            self._poll_slave()
            if self._seq != before:
                break
            if time.monotonic() > deadline:
                self._slave.close()
                raise LinkLostError(
                    f"TM {cfg.host}:{cfg.slave_port}: no data table within {cfg.connect_timeout_s:g} s: enable the "
                    "Ethernet Slave (TMflow > Setting > Connection > Ethernet Slave) with a transmit data table")
            time.sleep(_POLL_S)

    def _open_listen(self) -> None:
        cfg = self.config
        self._listen = TMLink.open(cfg.host, cfg.listen_port, cfg.connect_timeout_s, self._protocol.source)

    def _poll(self) -> None:
        self._poll_slave()
        self._poll_listen()

    def _poll_slave(self) -> None:
        if self._slave is None:
            raise LinkLostError(f"TM {self.endpoint}: the Ethernet Slave link is down")
        for packet in self._slave.receive():
            self._on_slave_packet(packet)

    def _on_slave_packet(self, packet: TMPacket) -> None:
        if packet.header == "CPERR":
            log.warning("TM Ethernet Slave: %s", cperr(packet.text, "TM Ethernet Slave"))
            return
        if packet.header != "TMSVR":
            raise ProtocolError(f"TM Ethernet Slave: unexpected ${packet.header} packet on port "
                                f"{self.config.slave_port}")
        frame = parse_svr(packet.data)
        if frame.mode == MODE_RESPONSE:
            code = frame.content[:2].decode("ascii", errors="replace")
            if code != "00":
                log.warning("TM Ethernet Slave: response %s (%s) to transaction %s", code,
                            RESPONSE_CODES.get(code, "unknown"), frame.id)
            return
        if frame.mode > 3:
            return  # replies to read requests: this driver sends none
        check_mode(frame)
        self._latest = decode_table(frame)
        self._latest_t = time.monotonic()
        self._seq += 1

    def _poll_listen(self) -> None:
        if self._listen is None:
            return
        try:
            packets = self._listen.receive()
        except LinkLostError:
            self._listen = None
            if self.lifecycle is Lifecycle.ARMED:
                raise
            return  # not commanding: a project stopped in TMflow is no fault of a reading session
        for packet in packets:
            event = self._protocol.handle(packet)
            if isinstance(event, ScriptReply):
                self._replies[event.id] = event
                if len(self._replies) > 64:
                    self._replies.pop(next(iter(self._replies)))
            elif isinstance(event, ListenStatus):
                self._listen_status = event
            elif isinstance(event, TagStatus):
                self._tag_done = event.done
            elif isinstance(event, EntryMessage):
                self._entry_message = event.text
                log.info("TM Listen node entered: %r", event.text)

    def _fresh_table(self) -> SlaveState:
        """The latest table, or LinkLostError when the broadcast has been silent for link_lost_after_s."""
        limit = self.config.link_lost_after_s
        silence = time.monotonic() - self._latest_t
        if self._latest is None or silence > limit:
            if self._slave is not None:
                self._slave.close()
            raise LinkLostError(f"TM {self.config.host}:{self.config.slave_port}: no data table for "
                                f"{silence * 1000:.0f} ms (limit {limit * 1000:.0f} ms): link lost")
        return self._latest

    @staticmethod
    def _status(table: SlaveState) -> ArmStatus:
        running = table.project_run is not False
        paused = bool(table.project_pause)
        # The controller takes no motion without its robot link, or while the project is paused or stopped:
        # to the cell that is a protective stop (the driver faults if it happens while armed).
        not_moving = table.robot_link is False or paused or not running
        return ArmStatus(error=bool(table.robot_error), estop=bool(table.estop), project_running=running,
                         paused=paused, protective_stop=not_moving)

    def _send_script(self, lines: list[str]) -> str:
        if self._listen is None or not self._listen.is_open:
            raise LinkLostError(f"TM {self.endpoint}: the Listen node link is down")
        tid, packet = self._protocol.script(lines)
        self._listen.send(packet)
        return tid

    def _wait_for(self, done: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + self.config.reply_timeout_s
        while not done():
            if time.monotonic() > deadline:
                raise ProtocolError(f"TM {self.endpoint}: no {what} within {self.config.reply_timeout_s:g} s")
            time.sleep(_POLL_S)
            self._poll()
