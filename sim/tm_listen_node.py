"""The Listen node as the TM Ethernet emulator runs it: scripts, status queries, velocity streaming, queue tags."""

from __future__ import annotations

import logging
import math
import re
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivers.tm5.tm_packet import TMPacket, encode_packet

log = logging.getLogger(__name__)

# TM5-700 joint speed limits: J1-J3 pi rad/s, J4-J6 1.25 pi rad/s.
TM5_SPEED_LIMITS = np.array([math.pi] * 3 + [1.25 * math.pi] * 3)
_CALL = re.compile(r"^\s*([A-Za-z_]\w*)\((.*)\)\s*$")


@dataclass
class VelocityMode:
    """What the controller remembers of joint velocity streaming."""

    active: bool = False
    speeds: np.ndarray = field(default_factory=lambda: np.zeros(6))  # rad/s
    q_cmd: np.ndarray | None = None  # the integrated servo target, rad
    last_set_s: float = 0.0  # controller time of the last SetContinueVJog


class ListenNode:
    """Answers the packets of a Listen-node client and keeps the node's motion state.

    Motion statements are not applied at once: they wait `latency_cycles` servo cycles in a queue (the
    controller's command latency), then act on the velocity state that `servo_target` integrates.
    StopAndClearBuffer acts on receipt (it empties that queue) and ignores the other statements of its packet.
    Statements whose function is in `refuse` are answered ERROR.  `scripts_seen` keeps the function names of
    the last accepted scripts, one tuple per packet; `executed` the functions run, in order.
    """

    def __init__(self, message: str = "Listen1", latency_cycles: int = 0, vjog_timeout_s: float | None = None) -> None:
        self.message = message
        self.in_node = True
        self.latency_cycles = latency_cycles
        self.vjog_timeout_s = vjog_timeout_s  # None: a silent host leaves the last speed running
        self.vmode = VelocityMode()
        self.cycle = 0
        self.time_s = 0.0
        self.scripts = 0
        self.status_queries = 0  # TMSTA 00 asked
        self.ignored_speeds = 0
        self.tags: dict[int, bool] = {}
        self.refuse: set[str] = set()
        self.scripts_seen: deque[tuple[str, ...]] = deque(maxlen=64)
        self.executed: deque[str] = deque(maxlen=256)
        self._queue: deque[tuple[int, Callable[[], None]]] = deque()

    # ----------------------------------------------------------------------------- packets
    def entry_packet(self) -> bytes:
        return encode_packet("TMSCT", f"0,{self.message}")

    def handle(self, packet: TMPacket) -> list[bytes]:
        """The replies to one packet."""
        if packet.header == "TMSTA":
            return [self._status(packet.text)]
        if packet.header != "TMSCT":
            return [encode_packet("CPERR", "03")]
        tid, sep, script = packet.text.partition(",")
        if not sep or not tid.isalnum():
            return [encode_packet("CPERR", "04")]
        if not self.in_node:
            return [encode_packet("CPERR", "F1")]
        self.scripts += 1
        lines = script.split("\r\n")
        actions: list[tuple[str, Callable[[], None]]] = []
        bad = []
        for n, line in enumerate(lines, start=1):
            action = self._compile(line)
            m = _CALL.match(line)
            name = m.group(1) if m else ""
            if action is None or name in self.refuse:
                bad.append(n)
            else:
                actions.append((name, action))
        if bad:
            return [encode_packet("TMSCT", f"{tid},ERROR;" + ";".join(map(str, bad)))]
        names = tuple(name for name, _ in actions)
        self.scripts_seen.append(names)
        exits = "ScriptExit" in names
        if "StopAndClearBuffer" in names:  # acts now, and the rest of its packet is ignored
            self._run("StopAndClearBuffer", self._stop_all)
        else:
            for name, action in actions:
                self._queue.append((self.cycle + self.latency_cycles, self._runner(name, action)))
        reply = [encode_packet("TMSCT", f"{tid},OK")]
        if exits:
            self.leave()
        return reply

    def _status(self, text: str) -> bytes:
        code, _, rest = text.partition(",")
        if code == "00":
            self.status_queries += 1
            return encode_packet("TMSTA", f"00,true,{self.message}" if self.in_node else "00,false,")
        if code == "01" and rest.strip().isdigit():
            tag = int(rest)
            state = "none" if tag not in self.tags else ("true" if self.tags[tag] else "false")
            return encode_packet("TMSTA", f"01,{tag:02d},{state}")  # padded, as the robot may
        return encode_packet("CPERR", "04")

    def _compile(self, line: str) -> Callable[[], None] | None:
        m = _CALL.match(line)
        if m is None:
            return None
        name, raw = m.group(1), m.group(2).strip()
        args = [a.strip() for a in raw.split(",")] if raw else []
        try:
            values = [float(a) for a in args]
        except ValueError:
            return None
        if not all(math.isfinite(v) for v in values):
            return None
        if name == "ContinueVJog" and not values:
            return self._start_vjog
        if name == "SetContinueVJog" and len(values) == 6:
            speeds = np.radians(values)
            return lambda: self._set_speeds(speeds)
        if name == "StopContinueVmode" and not values:
            return self._stop_vjog
        if name == "StopAndClearBuffer" and len(values) <= 1:
            return self._stop_all
        if name == "QueueTag" and 1 <= len(values) <= 2 and values[0] == int(values[0]) and 1 <= values[0] <= 15:
            tag = int(values[0])
            self.tags[tag] = False
            return lambda: self.tags.__setitem__(tag, True)
        if name == "ScriptExit" and len(values) <= 1:
            return lambda: None
        return None

    def _runner(self, name: str, action: Callable[[], None]) -> Callable[[], None]:
        return lambda: self._run(name, action)

    def _run(self, name: str, action: Callable[[], None]) -> None:
        self.executed.append(name)
        action()

    # ----------------------------------------------------------------------------- node and motion
    def enter(self) -> None:
        self.in_node = True

    def leave(self) -> None:
        """The flow leaves the node: queued motion is dropped and streaming ends."""
        self.in_node = False
        self._stop_all()

    def stop_now(self) -> None:
        """E-stop or controller error: no streaming, nothing queued."""
        self._stop_all()

    def _start_vjog(self) -> None:
        self.vmode.active = True
        self.vmode.speeds = np.zeros(6)
        self.vmode.q_cmd = None  # taken from the measured joints on the next servo cycle
        self.vmode.last_set_s = self.time_s

    def _set_speeds(self, speeds: np.ndarray) -> None:
        if not self.vmode.active:
            self.ignored_speeds += 1
            return
        self.vmode.speeds = np.clip(speeds, -TM5_SPEED_LIMITS, TM5_SPEED_LIMITS)
        self.vmode.last_set_s = self.time_s

    def _stop_vjog(self) -> None:
        self.vmode.active = False
        self.vmode.speeds = np.zeros(6)

    def _stop_all(self) -> None:
        self._queue.clear()
        self._stop_vjog()

    def servo_target(self, q_meas: np.ndarray, dt: float) -> np.ndarray | None:
        """One servo cycle: run the statements now due, integrate the streamed speed; the new joint target
        (None when not streaming: the plant keeps its own)."""
        self.cycle += 1
        self.time_s += dt
        while self._queue and self._queue[0][0] <= self.cycle:
            self._queue.popleft()[1]()
        vm = self.vmode
        if not vm.active:
            return None
        if self.vjog_timeout_s is not None and self.time_s - vm.last_set_s > self.vjog_timeout_s:
            vm.speeds = np.zeros(6)
        if vm.q_cmd is None:
            vm.q_cmd = np.array(q_meas, dtype=float)
        vm.q_cmd = vm.q_cmd + vm.speeds * dt
        return vm.q_cmd
