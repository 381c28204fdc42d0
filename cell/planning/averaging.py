"""The exact step's jerk bound: a joint trajectory averaged over one window through the motion and shorter ones
where the arm leaves rest and where it reaches rest."""

from __future__ import annotations

import numpy as np

# The start's window gives way to the motion's over this much of the motion (s), and the motion's to the stop's
# over as much before its end: past the start's acceleration ramp, so the middle of the motion has the motion's
# jerk bound; slow enough that the positions' derivative stays within about 0.01 rad/s of the blended speeds.
BLEND_S = 0.2


def box_average(x: np.ndarray, centre: np.ndarray, width: int, first: np.ndarray | float,
                last: np.ndarray | float) -> np.ndarray:
    """The average of the piecewise-constant samples x (sample i covering [i, i + 1)) over `width` samples
    centred on each of `centre` (in samples, may be fractional), x held at first / last beyond its ends."""
    beyond = max(float(np.max(centre)) - len(x), -float(np.min(centre)), 0.0)  # how far the centres leave x
    pad = width + int(np.ceil(beyond)) + 2
    xs = np.concatenate([np.broadcast_to(first, (pad,) + x.shape[1:]), x,
                         np.broadcast_to(last, (pad,) + x.shape[1:])])
    cum = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(xs, axis=0)])
    u = np.arange(len(cum), dtype=float) - pad
    lo, hi = centre - 0.5 * width, centre + 0.5 * width
    if x.ndim == 1:
        return (np.interp(hi, u, cum) - np.interp(lo, u, cum)) / width
    return np.column_stack([(np.interp(hi, u, cum[:, j]) - np.interp(lo, u, cum[:, j])) / width
                            for j in range(x.shape[1])])


def rest_to_rest_average(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, s: np.ndarray, end: np.ndarray, dt: float,
                         start_s: float, motion_s: float, stop_s: float | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The trajectory (q, dq, ddq, the path parameter s; samples every dt from rest to rest at `end`) averaged
    over `start_s` where it leaves rest, `motion_s` through the motion and `stop_s` (None: `motion_s`) where it
    reaches rest: centred averages on one timeline, the start's giving way to the motion's over the motion's
    first `BLEND_S` and the motion's to the stop's over its last.  A centred average adds half its window at
    each end (its acceleration ramps over the window), so a shorter window at either end saves half the
    difference there; equal windows give the plain moving average.  Every output is a convex combination of
    input samples, so no joint speed or acceleration grows past its bound; the blended positions' derivative
    differs from the blended speeds by the blend's rate times the averages' difference (of order
    ddq w^2 / 24 / BLEND_S).  Returns the averaged q, dq, ddq, s, ending at rest at `end`."""
    w_mid = int(round(motion_s / dt))
    w_start = min(max(int(round(start_s / dt)), 1), w_mid)
    w_stop = w_mid if stop_s is None else min(max(int(round(stop_s / dt)), 1), w_mid)
    if w_mid < 2:
        return q, dq, ddq, s
    n = len(s)
    # Output sample k averages around input time k + 1 - w_start / 2: sample 0 is the start pose at rest, and
    # sample 1 already holds the first moving input sample (one sample later, the motion would wait a period).
    k = np.arange(n + w_mid + 2)
    centre = k + 1.0 - 0.5 * w_start
    ramp = max(min(n, BLEND_S / dt), 1.0)
    lam = np.clip((k - 1.0) / ramp, 0.0, 1.0)  # the start's window alone at rest
    # The stop's window alone from the first output its average can end on (its box past the last input sample).
    k_stop = n - 2 + 0.5 * (w_start + w_stop)
    mu = np.clip((k - (k_stop - ramp)) / ramp, 0.0, 1.0)

    def blend(x: np.ndarray, first: np.ndarray | float, last: np.ndarray | float) -> np.ndarray:
        def col(w: np.ndarray) -> np.ndarray:
            return w if x.ndim == 1 else w[:, None]

        a = box_average(x, centre, w_start, first, last)
        if w_start == w_mid == w_stop:
            return a
        b = box_average(x, centre, w_mid, first, last)
        if w_stop != w_mid:
            b = (1.0 - col(mu)) * b + col(mu) * box_average(x, centre, w_stop, first, last)
        return (1.0 - col(lam)) * a + col(lam) * b

    s_avg = blend(s, 0.0, 1.0)
    stop = int(np.nonzero(s_avg >= 1.0 - 1e-12)[0][0]) + 1
    q = blend(q, q[0], q[-1])[:stop]
    dq, ddq = blend(dq, 0.0, 0.0)[:stop], blend(ddq, 0.0, 0.0)[:stop]
    s_avg = s_avg[:stop]
    q[-1], dq[-1], ddq[-1], s_avg[-1] = end, 0.0, 0.0, 1.0
    return q, dq, ddq, s_avg
