"""The `p` exchange: ask the sensor's sensitivities until two well-formed, believable replies agree."""

from __future__ import annotations

import logging
from collections.abc import Callable

from drivers.errors import ProtocolError
from drivers.wacoh.codec import SHEET_TOLERANCE, Sensitivities, check_sensitivities, parse_sensitivities
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


def believable_sensitivities(line: bytes, config: WacohConfig) -> Sensitivities:
    """The sensitivities in a reply to `p`; ProtocolError if it is garbled or not believable (see P_ATTEMPTS)."""
    if config.sensitivities is None:
        return parse_sensitivities(line, config.nominal_sensitivities, config.sensitivity_tolerance)
    return check_sensitivities(parse_sensitivities(line), config.sensitivities, SHEET_TOLERANCE,
                               "the calibration sheet's")


def agreed_sensitivities(ask: Callable[[], bytes | None], config: WacohConfig) -> tuple[Sensitivities | None, str]:
    """Ask `p` (`ask` sends one and returns its reply line, None if none came in time) until two well-formed,
    believable replies agree: (those sensitivities, ""), else (None, why not).  A garbled or unbelievable
    reply is asked again; two believable ones that disagree, or no reply at all to the first request (some
    models never answer), end the exchange."""
    problem = ""
    plausible: Sensitivities | None = None
    for attempt in range(P_ATTEMPTS):
        line = ask()
        if line is None:
            problem = f"no reply to 'p' within {config.timeout_s:.3g} s"
            if attempt == 0:
                break
            continue
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
