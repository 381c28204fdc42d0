"""What the motion generators return: a `Motion`, joint-position samples at the control period, cut into
segments (moves) and trajectories."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Segment:
    """One move: joint targets at the control period (the first sample is one period after the start)."""

    q: np.ndarray  # (K, n)
    traj: int  # trajectory id (per-trajectory statistics group by it)
    segment: int  # move id, unique within the plan
    speed: float  # the speed fraction it was timed for
    kind: str  # "chain", "fourier", "random"


@dataclass
class Motion:
    """An excitation motion: its moves in the order they run, the control period [s], and how it was made."""

    segments: list[Segment]
    dt: float
    info: dict = field(default_factory=dict)

    @property
    def start(self) -> np.ndarray:
        return self.segments[0].q[0]

    @property
    def samples(self) -> int:
        return sum(len(s.q) for s in self.segments)

    @property
    def labelled_samples(self) -> int:
        """Samples that belong to a trajectory (transfers between motions, traj -1, do not)."""
        return sum(len(s.q) for s in self.segments if s.traj >= 0)

    @property
    def duration_s(self) -> float:
        return self.samples * self.dt

    def stream(self) -> Iterator[tuple[np.ndarray, Segment]]:
        for s in self.segments:
            for row in s.q:
                yield row, s

    def trajectories(self) -> list[int]:
        return sorted({s.traj for s in self.segments})
