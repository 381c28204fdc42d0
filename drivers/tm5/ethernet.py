"""TM5-700 on its own channels: `TMEthernetArm` reads the Ethernet Slave and streams joint speeds to the Listen node."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from drivers.errors import (
    CommandRejectedError,
    ConfigError,
    DriverError,
    LifecycleError,
    LinkLostError,
    ProtocolError,
    StaleDataError,
)
from drivers.interfaces import Arm, ArmState, ArmStatus, JointLimits, Lifecycle, vector_text
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.ethernet_slave import (
    MODE_RESPONSE,
    N_JOINTS,
    RESPONSE_CODES,
    SlaveState,
    SlaveTableError,
    check_mode,
    decode_table,
    missing_items_message,
    parse_svr,
)
from drivers.tm5.listen import (
    ListenProtocol,
    ListenStatus,
    continue_vjog,
    cperr,
    queue_tag,
    set_continue_vjog,
    stop_and_clear_buffer,
    stop_continue_vmode,
)
from drivers.tm5.listen_backlog import ReplyLag
from drivers.tm5.listen_session import ListenSession
from drivers.tm5.stream_stop import StreamStop, stream_stop
from drivers.tm5.table_check import check_before_arming
from drivers.tm5.tm_link import TMLink
from drivers.tm5.tm_packet import TMPacket
from drivers.tm5.velocity_loop import VelocityLoop

log = logging.getLogger(__name__)

_POLL_S = 0.002  # sleep between polls while connect(), a first arm() or doctor's probes wait for the robot
_NODE_HINT = "start the project in TMflow and let its flow reach the Listen node, then arm again"
_RECONNECT = "reconnect (disconnect, then connect) outside the control loop"
# The largest data table believed: TM's default items make ~1 kB.  A LEN above it is a broken field, refused
# at once instead of waited for.
SLAVE_MAX_LEN = 8192
LAG_PROBE_SCRIPTS = 32  # doctor's burst of scripts streamed at the loop rate to measure the reply lag
_LAG_PROBE_TAG = 15


class TMEthernetArm(Arm):
    """The TM5-700 through TM's Ethernet Slave (state, port 5891) and a project waiting in its Listen node
    (motion, port 5890): no robot-side program beyond a Listen node.

    `read_state` drains the broadcast without blocking and returns the latest table (`seq` counts decoded
    tables, `t` is the host's receive time); `send_target` closes the position loop on the host and
    streams one `SetContinueVJog` per control period, whose replies are counted on later polls (too many
    or too old unanswered stops the arm).  Units are converted here only.

    `arm` never reopens a link (a link that is down fails at once; `connect` reopens).  It waits on the wire
    only for what this Listen connection has not shown yet: the first arm asks `$TMSTA 00` and waits for
    ContinueVJog's reply (bounded by reply_timeout_s; before a control loop starts).  A re-arm on the same
    connection (the control loop's, after a stop) waits for nothing: the node's state is known from its
    messages and ContinueVJog's reply is checked on later polls like a streamed script's.  The optional
    Modbus cross-check (modbus_port) blocks on its request, so it runs on the first arm after the links open
    (before a control loop starts): it establishes that the Ethernet Slave's table is this controller's, which
    holds while the links stay up; `connect` after a drop checks again.
    """

    def __init__(self, config: TMEthernetConfig, limits: JointLimits, dt: float, speed_scale: float = 1.0) -> None:
        super().__init__(limits, dt, speed_scale)
        config.validate()
        if limits.n != N_JOINTS:
            raise ConfigError(f"the TM5-700 has {N_JOINTS} joints, the joint limits describe {limits.n}")
        self.config = config
        self._slave: TMLink | None = None
        self._node = ListenSession(config)
        self._backlog = self._node.backlog
        self._latest: SlaveState | None = None
        self._latest_t = 0.0
        self._seq = 0
        self._cross_checked = False  # the Modbus cross-check passed on these links
        self._warned_speed: int | None = None
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
        return self._node.up

    @property
    def latest_table(self) -> SlaveState | None:
        """The last decoded data table (error code, M/A mode, project speed, poses), as of the last poll."""
        return self._latest

    @property
    def entry_message(self) -> str | None:
        """The Listen node's message, once the robot announced entering it on this connection."""
        return self._node.entry_message

    @property
    def unanswered_scripts(self) -> int:
        """Scripts sent to the Listen node whose reply has not come in yet (as of the last poll)."""
        return self._backlog.count

    # ----------------------------------------------------------------------------- bring-up probes
    def probe_listen_node(self) -> ListenStatus:
        """Ask `$TMSTA 00` whether the project is in its Listen node (connects to the node if needed)."""
        if not self.listen_up:
            self._node.open()
        return self._query_listen_status()

    def command_round_trip(self, tag: int = _LAG_PROBE_TAG) -> float:
        """Seconds from sending `QueueTag(tag)` (no motion) to `$TMSTA 01` reporting the tag done: how long a
        command takes to pass the Listen node's queue.  Needs the project in its Listen node; the whole exchange
        is bounded by reply_timeout_s (each status query's answer by as much again)."""
        if not self.listen_up:
            self._node.open()
        timeout = self.config.reply_timeout_s
        t0 = time.monotonic()
        deadline = t0 + timeout
        tid = self._node.send_script([queue_tag(tag, 0)])
        self._wait_for(lambda: not self._backlog.pending(tid), f"QueueTag({tag}) (script {tid})", deadline)
        while True:
            self._node.tags.pop(tag, None)
            self._node.send(ListenProtocol.tag_status_query(tag))
            self._wait_for(lambda: tag in self._node.tags, f"TMSTA 01,{tag}")
            done = self._node.tags[tag].done
            if done is None:
                raise ProtocolError(f"TM {self.endpoint}: TMSTA 01 answers that tag {tag} does not exist, though "
                                    f"QueueTag({tag}) (script {tid}) was accepted")
            if done:
                return time.monotonic() - t0
            if time.monotonic() > deadline:
                raise ProtocolError(f"TM {self.endpoint}: tag {tag} still pending {timeout:g} s after QueueTag({tag}) "
                                    "was accepted: the project is paused, or its motion queue does not run")
            time.sleep(_POLL_S)

    def script_reply_lag(self, count: int = LAG_PROBE_SCRIPTS, period_s: float | None = None) -> ReplyLag:
        """Stream `count` QueueTag scripts (no motion) one per `period_s` (default: the control period) and
        measure how late each reply comes: whether the node keeps up with the loop's rate.  Blocks for the
        burst plus up to reply_timeout_s for its last replies; refused while armed (doctor runs it)."""
        if self.lifecycle is Lifecycle.ARMED:
            raise LifecycleError(f"TM {self.endpoint}: the reply lag is measured only while not armed")
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count!r}")
        if not self.listen_up:
            self._node.open()
        period = self.dt if period_s is None else period_s
        ids: list[str] = []
        most = 0
        next_t = time.monotonic()
        for _ in range(count):
            self._poll()
            most = max(most, self._backlog.count)
            ids.append(self._node.send_script([queue_tag(_LAG_PROBE_TAG, 0)]))
            next_t += period
            while (now := time.monotonic()) < next_t:  # polled finely: a reply's lag counts to its arrival
                time.sleep(min(_POLL_S, next_t - now))
                self._poll()
        deadline = time.monotonic() + self.config.reply_timeout_s
        while any(self._backlog.pending(t) for t in ids) and time.monotonic() < deadline:
            time.sleep(_POLL_S)
            self._poll()
        lags = sorted(lag for t in ids if (lag := self._backlog.lag(t)) is not None)
        median = float(np.median(lags)) if lags else float("nan")
        return ReplyLag(sent=count, answered=len(lags), median_s=median, max_s=lags[-1] if lags else float("nan"),
                        max_unanswered=most)

    def stream_stop_probe(self, joint: int = 5, speed_rad_s: float = 0.05, stream_s: float = 0.3,
                          watch_s: float = 1.0) -> StreamStop:
        """MOVES THE ARM: arm, stream `speed_rad_s` on one joint (0-based; default the last wrist joint) for
        `stream_s` at the control period, then send nothing for `watch_s` while reading the broadcast, then stop:
        what velocity mode does when the host falls silent (a killed host, a pulled cable), which no public
        source says.  The joint turns towards the side with more room; at most speed x (stream + watch) of
        travel.  Refused while armed, and when the joint lacks that room."""
        if self.lifecycle is Lifecycle.ARMED:
            raise LifecycleError(f"TM {self.endpoint}: the stream-stop probe arms the arm itself: stop first")
        if not 0 <= joint < N_JOINTS or not 0 < speed_rad_s <= 0.2 or stream_s <= 0 or watch_s <= 0:
            raise ValueError("stream_stop_probe: a joint 0-5, a speed in (0, 0.2] rad/s and positive durations")
        q = self.read_state().q[joint]
        lo, hi = self.limits.lower[joint], self.limits.upper[joint]
        direction = 1.0 if hi - q >= q - lo else -1.0
        travel = speed_rad_s * (stream_s + watch_s) + 0.05
        if (hi - q if direction > 0 else q - lo) < travel:
            raise LifecycleError(f"TM {self.endpoint}: joint {joint + 1} has under {travel:.2f} rad of room on "
                                 "either side for the stream-stop probe: move it towards mid-range first")
        speeds = np.zeros(N_JOINTS)
        speeds[joint] = direction * speed_rad_s
        self.arm()
        try:
            reached, next_t = 0.0, time.monotonic()
            last = next_t
            end = next_t + stream_s
            while next_t < end:
                self._node.send_script([set_continue_vjog(np.degrees(speeds))])
                last = time.monotonic()
                next_t += self.dt
                while (now := time.monotonic()) < next_t:
                    time.sleep(min(_POLL_S, next_t - now))
                    self._poll()
                    if self._latest is not None:
                        reached = max(reached, abs(float(self._latest.dq[joint])))
            samples: list[tuple[float, float, float]] = []
            seen = self._seq
            while (now := time.monotonic()) < last + watch_s:
                time.sleep(_POLL_S)
                self._poll()
                if self._seq != seen and self._latest is not None:
                    seen = self._seq
                    samples.append((self._latest_t - last, float(self._latest.q[joint]),
                                    float(self._latest.dq[joint])))
        finally:
            self.stop()
            self.confirm_stop()
        return stream_stop(joint, direction * speed_rad_s, stream_s, watch_s, reached, samples)

    def confirm_stop(self) -> None:
        """Wait (bounded by reply_timeout_s) for the Listen node's replies to the last stop's two scripts:
        ProtocolError when they do not come, ScriptError when StopAndClearBuffer is refused.  Blocks: for
        closing, never inside a control loop."""
        ids, self._node.stop_ids = self._node.stop_ids, []
        if ids:
            self._wait_for(lambda: not any(self._backlog.pending(t) for t in ids),
                           f"the stop (scripts {', '.join(ids)})", listen_only=True)

    # ----------------------------------------------------------------------------- wire: lifecycle
    def _connect(self) -> None:
        if not self._warned_untested:
            log.warning("TMEthernetArm %s: the real-hardware path is UNTESTED on a physical arm (it has only run "
                        "against sim.tm_ethernet_emulator); keep a hand on the E-stop", self.endpoint)
            self._warned_untested = True
        self._cross_checked = False  # new links: the first arm checks the Modbus table again
        try:
            self._open_slave()
            try:
                self._node.open()
            except LinkLostError as exc:  # reading needs no Listen node; arming will ask for it
                log.info("TM Listen node not reachable yet (%s); arm() needs it (connect again)", exc)
        except BaseException:
            self._disconnect()
            raise

    def _disconnect(self) -> None:
        if self.listen_up and self._node.stop_ids:
            try:
                self.confirm_stop()
            except DriverError as exc:  # closing goes on: the node's own state is what it is
                log.warning("TM %s: the stop before closing is unconfirmed: %s", self.endpoint, exc)
        if self._slave is not None:
            self._slave.close()
        self._slave = None
        self._node.close()

    def _arm(self) -> None:
        """Both links up, a fresh table with every safety item, the controller healthy, the project in its
        Listen node: then enter velocity streaming.  Refusals seen locally come first and wait for nothing."""
        if not self.link_up:
            raise LinkLostError(f"TM {self.endpoint}: cannot arm: the Ethernet Slave link is down: {_RECONNECT}")
        if not self.listen_up:
            raise LinkLostError(
                f"TM {self.endpoint}: cannot arm: the Listen node link is down (port {self.config.listen_port} is "
                f"served only while a project runs in its Listen node): {_NODE_HINT}; {_RECONNECT}")
        self._poll()  # the replies and the node's messages that came in meanwhile (may find a link closed)
        table = self._armable_table()
        status = self._status(table)
        if not status.ok:
            raise LifecycleError(f"cannot arm: controller reports {status}")
        self._backlog.check(time.monotonic())  # a node still owing replies would queue the new stream too
        known = self._node.streaming_confirmed and self._node.in_node is True
        if not known and not self._query_listen_status().in_node:
            raise LifecycleError(f"TM {self.endpoint}: the project is not in its Listen node: {_NODE_HINT}")
        if self.config.modbus_port is not None and not self._cross_checked:
            check_before_arming(self)  # the controller's own Modbus table must tell the same story
            self._cross_checked = True
        tid = self._node.send_script([continue_vjog()])
        if not known:
            self._wait_for(lambda: not self._backlog.pending(tid), f"ContinueVJog() (script {tid})")
        self.velocity_loop.reset()

    def _stop(self) -> None:
        """StopAndClearBuffer() then StopContinueVmode(), as two packets, sent without waiting (`confirm_stop`
        waits; closing does).  Apart, because StopAndClearBuffer ignores motions in its own packet; in this
        order, because it discards the node's queue: the speeds a lagging node still holds go, and the
        StopContinueVmode sent after it is not among them."""
        if not self.listen_up:
            raise LinkLostError(f"TM {self.endpoint}: cannot stop: the Listen node link is down")
        self._node.stop_ids = [self._node.send_script([stop_and_clear_buffer()]),
                               self._node.send_script([stop_continue_vmode()])]

    # ----------------------------------------------------------------------------- wire: data
    def _read_state(self) -> ArmState:
        self._poll()
        table = self._fresh_table()
        now = time.monotonic()
        if self.lifecycle is Lifecycle.ARMED:
            silence = now - self._latest_t
            if silence > self.config.stale_after_s:
                raise StaleDataError(f"TM {self.config.host}:{self.config.slave_port}: no new data table for "
                                     f"{silence * 1000:.0f} ms (limit {self.config.stale_after_s * 1000:.0f} ms) "
                                     "while moving: stale state")
            missing = table.missing_safety_items
            if missing:
                raise SlaveTableError(missing_items_message(missing, "the table changed while armed, and the cell "
                                                            "no longer sees the controller's stops"))
            self._backlog.check(now)
        return ArmState(t=self._latest_t, q=table.q, dq=table.dq, tau=table.tau, status=self._status(table),
                        seq=self._seq)

    def _write_target(self, q: np.ndarray) -> None:
        self._poll_listen()  # a refused script or a left node faults before another speed goes out
        self._backlog.check(time.monotonic())
        table = self._fresh_table()
        assert self._last_sent is not None
        v = self.joint_speeds(q, self._last_sent, table.q)
        if not np.all(np.isfinite(v)):
            raise CommandRejectedError(f"command refused: non-finite joint speeds {vector_text(v)}")
        self._node.send_script([set_continue_vjog(np.degrees(v))])
        self.velocity_loop.sent(v)

    def joint_speeds(self, q: np.ndarray, q_prev: np.ndarray, q_meas: np.ndarray) -> np.ndarray:
        """rad/s to stream for target `q` (see `VelocityLoop`)."""
        return self.velocity_loop.speeds(q, q_prev, q_meas)

    # ----------------------------------------------------------------------------- helpers
    def _open_slave(self) -> None:
        """Connect to the Ethernet Slave and wait for a first table this driver can read."""
        cfg = self.config
        self._slave = TMLink.open(cfg.host, cfg.slave_port, cfg.connect_timeout_s, f"TM Ethernet Slave {cfg.host}:"
                                  f"{cfg.slave_port}", SLAVE_MAX_LEN)
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
        speed = self._latest.project_speed
        if speed is not None and speed != 100 and speed != self._warned_speed:
            log.warning("TM %s: Project_Speed is %d %%, not 100 %%: the controller scales the streamed joint speeds "
                        "and the host's position loop assumes them as sent; set the project speed to 100 %% in TMflow",
                        self.endpoint, speed)
        self._warned_speed = speed

    def _poll_listen(self) -> None:
        try:
            self._node.poll()
        except LinkLostError:
            if self.lifecycle is Lifecycle.ARMED:
                raise
            # not commanding: a project stopped in TMflow is no fault of a reading session

    def _query_listen_status(self) -> ListenStatus:
        """`$TMSTA 00` and its reply (waits up to reply_timeout_s)."""
        self._node.status = None
        self._node.send(ListenProtocol.listen_status_query())
        self._wait_for(lambda: self._node.status is not None, "TMSTA 00 (is the project in its Listen node?)")
        assert self._node.status is not None
        return self._node.status

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

    def _armable_table(self) -> SlaveState:
        """The latest table when it is no older than stale_after_s and carries every safety item."""
        table = self._fresh_table()
        age = time.monotonic() - self._latest_t
        limit = self.config.stale_after_s
        if age > limit:
            raise StaleDataError(f"TM {self.config.host}:{self.config.slave_port}: cannot arm: the latest data table "
                                 f"is {age * 1000:.0f} ms old (limit stale_after_s {limit * 1000:.0f} ms)")
        missing = table.missing_safety_items
        if missing:
            raise SlaveTableError(f"cannot arm: {missing_items_message(missing, 'the cell could not see the stops')}")
        return table

    @staticmethod
    def _status(table: SlaveState) -> ArmStatus:
        running = table.project_run is True
        paused = table.project_pause is True
        # The controller takes no motion without its robot link, while the project is paused or stopped, or
        # with its safeguard input triggered: to the cell each is a protective stop (the driver faults if
        # one happens while armed).  A safety item the table lacks reads as one too: the cell cannot tell.
        not_moving = (table.robot_link is not True or paused or not running or table.safeguard is not False
                      or bool(table.missing_safety_items))
        return ArmStatus(error=table.robot_error is True, estop=table.estop is True, project_running=running,
                         paused=paused, protective_stop=not_moving)

    def _wait_for(self, done: Callable[[], bool], what: str, deadline: float | None = None,
                  listen_only: bool = False) -> None:
        """Poll until `done()`; ProtocolError naming `what` at `deadline` (default: reply_timeout_s from now; the
        callers' deadlines are reply_timeout_s from their start too)."""
        end = time.monotonic() + self.config.reply_timeout_s if deadline is None else deadline
        while not done():
            if time.monotonic() > end:
                raise ProtocolError(f"TM {self.endpoint}: no answer to {what} within "
                                    f"{self.config.reply_timeout_s:g} s (reply_timeout_s)")
            time.sleep(_POLL_S)
            if listen_only:
                self._poll_listen()
            else:
                self._poll()
