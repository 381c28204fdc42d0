"""The exact step's jerk bound: a joint trajectory averaged over a short window where the arm leaves rest and a
longer one where it reaches rest."""

from __future__ import annotations

import numpy as np

# The start's window gives way to the end's over this much of the motion (s): past the start's acceleration
# ramp, so the rest of the motion has the end's jerk bound; slow enough that the positions' derivative stays
# within about 0.01 rad/s of the blended speeds.
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
                         start_s: float, end_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The trajectory (q, dq, ddq, the path parameter s; samples every dt from rest to rest at `end`) averaged
    over `start_s` where it leaves rest and `end_s` where it reaches rest: two centred averages on one
    timeline, the first giving way to the second over the motion's first `BLEND_S`.  A centred average adds
    half its window at each end (its acceleration ramps over the window), so a shorter window at the start
    saves half the difference; equal windows give the plain moving average.  Every output is a convex
    combination of input samples, so no joint speed or acceleration grows past its bound; the blended
    positions' derivative differs from the blended speeds by the blend's rate times the two averages'
    difference (of order ddq w^2 / 24 / BLEND_S).  Returns the averaged q, dq, ddq, s, ending at rest at `end`."""
    w_end = int(round(end_s / dt))
    w_start = min(max(int(round(start_s / dt)), 1), w_end)
    if w_end < 2:
        return q, dq, ddq, s
    n = len(s)
    # Output sample k averages around input time k + 1 - w_start / 2: sample 0 is the start pose at rest, and
    # sample 1 already holds the first moving input sample (one sample later, the motion would wait a period).
    k = np.arange(n + w_end + 2)
    centre = k + 1.0 - 0.5 * w_start
    lam = np.clip((k - 1.0) / max(min(n, BLEND_S / dt), 1.0), 0.0, 1.0)  # the start's window alone at rest

    def blend(x: np.ndarray, first: np.ndarray | float, last: np.ndarray | float) -> np.ndarray:
        a = box_average(x, centre, w_start, first, last)
        if w_start == w_end:
            return a
        b = box_average(x, centre, w_end, first, last)
        weight = lam if x.ndim == 1 else lam[:, None]
        return (1.0 - weight) * a + weight * b

    s_avg = blend(s, 0.0, 1.0)
    stop = int(np.nonzero(s_avg >= 1.0 - 1e-12)[0][0]) + 1
    q = blend(q, q[0], q[-1])[:stop]
    dq, ddq = blend(dq, 0.0, 0.0)[:stop], blend(ddq, 0.0, 0.0)[:stop]
    s_avg = s_avg[:stop]
    q[-1], dq[-1], ddq[-1], s_avg[-1] = end, 0.0, 0.0, 1.0
    return q, dq, ddq, s_avg
