"""The host's joint position loop over TM's velocity streaming: the speeds to send for each position target."""

from __future__ import annotations

from collections import deque

import numpy as np

from drivers.interfaces import JointLimits

# Near a joint limit the streamed speed is capped so that holding it this long still stops inside the
# range: the controller keeps the last speed until told otherwise, and a stalled host tells it nothing.
LIMIT_HORIZON_S = 0.1


class VelocityLoop:
    """Joint speed = feed-forward of the target's step + position_gain * (target - joints ahead).

    "Joints ahead" is the measurement plus what the speeds already sent will still add before they show
    in it (dt times the last `latency_periods` speeds): a loop on the bare measurement pushes again,
    every period of the command latency, for motion already on its way, and with the impedance law's
    own integration that makes a contact force ring (a Smith predictor on a known delay).
    """

    def __init__(self, limits: JointLimits, dt: float, position_gain: float, latency_periods: int = 0,
                 speed_scale: float = 1.0) -> None:
        self.limits = limits
        self.dt = dt
        self.position_gain = position_gain
        self.latency_periods = latency_periods
        self.speed_scale = speed_scale
        self._in_flight: deque[np.ndarray] = deque(maxlen=max(latency_periods, 1))

    def reset(self) -> None:
        """Streaming (re)starts from rest: nothing in flight."""
        self._in_flight.clear()

    def speeds(self, q: np.ndarray, q_prev: np.ndarray, q_meas: np.ndarray) -> np.ndarray:
        """rad/s to stream toward target `q` (the previous target `q_prev`), clipped to the speed limits and
        to what still stops inside the joint range within LIMIT_HORIZON_S."""
        q_ahead = q_meas + self.dt * np.sum(self._in_flight, axis=0) if self._in_flight else q_meas
        v = (q - q_prev) / self.dt + self.position_gain * (q - q_ahead)
        vmax = self.limits.velocity * self.speed_scale
        v = np.clip(v, -vmax, vmax)
        room_up = np.maximum(self.limits.upper - q_meas, 0.0) / LIMIT_HORIZON_S
        room_down = np.maximum(q_meas - self.limits.lower, 0.0) / LIMIT_HORIZON_S
        return np.clip(v, -room_down, room_up)

    def sent(self, v: np.ndarray) -> None:
        """Record speeds that went out (they act over the next periods)."""
        if self.latency_periods > 0:
            self._in_flight.append(np.array(v, dtype=float))
