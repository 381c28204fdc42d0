"""The `p` exchange: ask the sensor's sensitivities until two well-formed, believable replies agree."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from drivers.errors import ProtocolError
from drivers.serial_link import SerialLink
from drivers.wacoh.codec import MAX_LINE, SHEET_TOLERANCE, Sensitivities, check_sensitivities, parse_sensitivities
from drivers.wacoh.config import WacohConfig

log = logging.getLogger(__name__)

# The sensitivities set every reading's scale, and the reply has no checksum: a flipped bit in a digit
# (32.800 -> 32.801) is still a plausible reply.  So `p` is asked until two well-formed, believable replies
# agree (a garbled or unbelievable one is asked again), at most this many times; two believable replies
# that disagree show a line that corrupts replies undetectably, and then none of them is believed.
# Believable: within SHEET_TOLERANCE of the configured calibration sheet, or without one within the band
# of the nominal values.  Only the sheet catches a corruption that repeats identically (a reply then
# agrees with itself) or changes a digit within the band: without it no check on the replies can.
P_ATTEMPTS = 6
# `p` is asked at connect, outside the control loop, and nothing promises how soon its reply (about 49 bytes,
# "read to LF") comes: each ask waits this long (or the configured timeout_s if longer) plus the reply's time on
# the wire.  A first ask without a reply is asked once more after the line fell quiet; two without a reply end
# the exchange (some models never answer `p`), and the configured sensitivities are used.
P_TIMEOUT_S = 0.2
P_REPLY_BYTES = 64  # a little more than the usual reply, for the wire-time allowance


def believable_sensitivities(line: bytes, config: WacohConfig) -> Sensitivities:
    """The sensitivities in a reply to `p`; ProtocolError if it is garbled or not believable (see P_ATTEMPTS)."""
    if config.sensitivities is None:
        return parse_sensitivities(line, config.nominal_sensitivities, config.sensitivity_tolerance)
    return check_sensitivities(parse_sensitivities(line), config.sensitivities, SHEET_TOLERANCE,
                               "the calibration sheet's")


def agreed_sensitivities(ask: Callable[[bool], bytes | None], config: WacohConfig,
                         timeout_s: float = P_TIMEOUT_S) -> tuple[Sensitivities | None, str]:
    """Ask `p` until two well-formed, believable replies agree: (those sensitivities, ""), else (None, why not).

    `ask(after_silence)` sends one `p` and returns its reply line, None if none came within `timeout_s`;
    `after_silence` says the previous ask got none (the line is drained first).  A garbled or unbelievable reply
    is asked again; two believable ones that disagree, or no reply to the first two asks (some models never
    answer), end the exchange."""
    problem = ""
    plausible: Sensitivities | None = None
    heard = False
    silent = False
    for _ in range(P_ATTEMPTS):
        line = ask(silent)
        if line is None:
            if silent and not heard:
                problem = f"no reply to 'p' within {timeout_s:.3g} s, asked twice (some models never answer it)"
                break
            silent = True
            problem = f"no reply to 'p' within {timeout_s:.3g} s"
            continue
        heard, silent = True, False
        try:
            sens = believable_sensitivities(line, config)
        except ProtocolError as exc:
            problem = str(exc)
            log.debug("WACOH sensor on %s: %s; asking again", config.port, exc)
            continue
        if plausible is None:
            plausible = sens
            problem = "no second plausible reply to 'p'"
            continue
        if sens == plausible:
            return sens, ""
        problem = f"two plausible replies to 'p' disagree ({plausible.values} and {sens.values})"
        break
    return None, problem


def read_line(link: SerialLink, deadline: float) -> bytes | None:
    """Bytes up to and including the first LF, or None at the deadline."""
    buf = bytearray()
    while True:
        chunk = link.read_chunk(MAX_LINE, deadline)
        if not chunk:
            if time.monotonic() >= deadline:
                return None
            continue
        lf = chunk.find(b"\n")
        if lf >= 0:
            return bytes(buf + chunk[: lf + 1])  # the rest is discarded with the next request
        buf += chunk
        if len(buf) > MAX_LINE:
            return bytes(buf)  # not a reply we know; let the parser reject it


def drain_until_quiet(link: SerialLink, quiet_s: float, limit_s: float) -> None:
    """Read and discard until nothing has arrived for `quiet_s`, for at most `limit_s`."""
    end = time.monotonic() + limit_s
    while True:
        now = time.monotonic()
        if now >= end or not link.read_chunk(MAX_LINE, min(end, now + quiet_s)):
            return
