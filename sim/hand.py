"""A scripted hand for the simulated cell: random wrenches at the tool while the arm rests in a posture.

It implements the calibration's load-applier interface (`tasks.setup.calibrate.LoadApplier`): each load is
ramped in over `ramp_s` (a hand does not hit the tool as a step), then held until the next one.  The
plant applies `Plant.external_wrench` (world frame, on the tool at the TCP) every physics step; the
hand sets it from a tool-frame wrench the *tool exerts on the hand*, the cell's sensor convention, so
a load with Fz = 50 N is read by the F/T sensor as +50 N.
"""

from __future__ import annotations

import logging

import numpy as np

from sim.plant import Plant

log = logging.getLogger(__name__)


class ScriptedHand:
    """Random loads: |F| in [0, max_force], tool x/y components within +-max_lateral, pressing along
    the tool's +z; moments at the TCP within +-max_moment (z: half of it)."""

    scripted = True

    def __init__(self, plant: Plant, seed: int = 0, max_force_n: float = 75.0, max_lateral_n: float = 15.0,
                 max_moment_nm: float = 1.0, load_s: float = 1.5, ramp_s: float = 0.25,
                 steady_after_s: float | None = None) -> None:
        self.plant = plant
        self.rng = np.random.default_rng(seed)
        self.max_force = max_force_n
        self.max_lateral = max_lateral_n
        self.max_moment = max_moment_nm
        self.load_s = load_s
        self.ramp_s = min(ramp_s, load_s)
        # Scored once the observers have converged on the held load (their filters lag by ~0.1 s).
        self.steady_after = min(steady_after_s if steady_after_s is not None else 0.6 * load_s, load_s)
        self._loads: list[np.ndarray] = []
        self.current = np.zeros(6)

    def _draw(self) -> np.ndarray:
        f = float(self.rng.uniform(0.0, self.max_force))
        fx, fy = self.rng.uniform(-1, 1, 2) * min(self.max_lateral, f)
        fz = float(np.sqrt(max(f * f - fx * fx - fy * fy, 0.0)))
        m = self.rng.uniform(-1, 1, 3) * self.max_moment * np.array([1.0, 1.0, 0.5])
        return np.array([fx, fy, fz, *m])

    def before_posture(self, index: int, total: int, duration_s: float) -> None:
        """A fresh sequence of loads for this posture; nothing touches the tool until `update`."""
        n = int(np.ceil(duration_s / self.load_s)) + 1
        self._loads = [self._draw() for _ in range(n)]
        self.release()

    def update(self, t: float) -> tuple[int, bool]:
        """Load at `t` s into the loading phase: (load index, whether it is held steady now)."""
        k = min(int(t // self.load_s), len(self._loads) - 1)
        tk = t - k * self.load_s
        prev = self._loads[k - 1] if k > 0 else np.zeros(6)
        a = min(1.0, tk / self.ramp_s) if self.ramp_s > 0 else 1.0
        a = a * a * (3 - 2 * a)  # smoothstep
        w = prev + a * (self._loads[k] - prev)
        self.set_tool_wrench(w)
        return k, tk >= self.steady_after

    def set_tool_wrench(self, w: np.ndarray) -> None:
        """Apply a tool-frame wrench (what the tool exerts on the hand, moments about the TCP)."""
        _, R = self.plant.tool_pose()
        w = np.asarray(w, float)
        self.current = w.copy()
        # The hand pushes the tool with the opposite wrench (world frame for the plant).
        self.plant.external_wrench = np.concatenate([-(R @ w[:3]), -(R @ w[3:])])

    def release(self) -> None:
        self.current = np.zeros(6)
        self.plant.external_wrench = None
