"""What the Listen node's velocity mode does when the host stops streaming speeds, read off the broadcast."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

# The joint counts as stopped once its broadcast speed falls under this share of the streamed one.
STOPPED_SHARE = 0.2


@dataclass(frozen=True)
class StreamStop:
    """One probe: a joint streamed at `speed_rad_s` for `streamed_s`, then no speed sent for `watch_s`."""

    joint: int  # 0-based
    speed_rad_s: float
    streamed_s: float
    watch_s: float
    reached_rad_s: float  # the largest broadcast speed of the joint while streaming
    stopped_after_s: float | None  # from the last speed sent to the first table under STOPPED_SHARE; None: moving
    travelled_rad: float  # from the last speed sent to the stop (or the end of the watch)

    @property
    def moved(self) -> bool:
        """Whether the streamed speed reached the joint at all (a probe that did not move tells nothing)."""
        return self.reached_rad_s >= 0.5 * abs(self.speed_rad_s)

    def summary(self) -> str:
        what = (f"joint {self.joint + 1} streamed at {math.degrees(self.speed_rad_s):.1f} deg/s for "
                f"{self.streamed_s:.2f} s (broadcast up to {math.degrees(self.reached_rad_s):.1f} deg/s)")
        if self.stopped_after_s is None:
            return (f"{what}: still moving {self.watch_s:.1f} s after the last speed was sent "
                    f"({math.degrees(self.travelled_rad):.1f} deg travelled)")
        return (f"{what}: stopped by itself {self.stopped_after_s * 1e3:.0f} ms after the last speed was sent "
                f"({math.degrees(self.travelled_rad):.2f} deg travelled)")


def stream_stop(joint: int, speed_rad_s: float, streamed_s: float, watch_s: float, reached_rad_s: float,
                samples: Sequence[tuple[float, float, float]]) -> StreamStop:
    """The probe's result from the broadcast tables after the last speed was sent: (seconds since it, joint
    angle, joint speed) each, in order."""
    q0 = samples[0][1] if samples else 0.0
    stopped: float | None = None
    q_end = samples[-1][1] if samples else q0
    for t, q, dq in samples:
        if abs(dq) < STOPPED_SHARE * abs(speed_rad_s):
            stopped, q_end = t, q
            break
    return StreamStop(joint=joint, speed_rad_s=speed_rad_s, streamed_s=streamed_s, watch_s=watch_s,
                      reached_rad_s=reached_rad_s, stopped_after_s=stopped, travelled_rad=abs(q_end - q0))
