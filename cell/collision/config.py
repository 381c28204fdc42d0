"""The collision settings (`collision` in the cell config): the detector's thresholds, the reactions, and the
states in which each task expects contact."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from cell.control.guarded import GuardedSettings
from drivers.configio import join, require

REACTIONS = ("stop", "retract", "comply", "monitor")
GUARDED_TASKS = ("wipe", "peg-in-hole", "play")  # task names (their `name`) the collision settings may name


@dataclass
class DetectorSettings:
    """The collision detector's numbers (cell/collision/detector.py explains the threshold)."""

    observer_gain: float = 100.0  # 1/s: bandwidth of the residual (time constant 1 / gain)
    sigma_factor: float = 6.0  # thresholds: this many model sigmas ...
    rest_sigma_factor: float | None = None  # ... toward this many at rest (below stick_speed); None: sigma_factor
    floor_nm: list[float] = field(default_factory=lambda: [1.5, 1.5, 1.5, 0.6, 0.6, 0.6])  # ... plus this
    payload_uncertainty_kg: float = 0.5  # payload error the thresholds tolerate
    inertia_uncertainty: float = 0.5  # relative error of the inertial torque M(q) q''_cmd the thresholds allow
    # The inertial term also takes the commanded acceleration over this many recent periods: the arm
    # follows its targets a few periods late, and the measured acceleration's estimate lags further.
    command_window_periods: int = 4
    stick_speed: float = 0.05  # rad/s: below it a joint's friction may hold anything in its static band
    coverage_min_count: float = 20.0  # training samples a (q, q', q'') cell needs before the model's own level applies
    confirm_periods: int = 1  # periods in a row over the threshold before it counts
    # These joints (1-based) also count together: the root-sum-square of their residual / threshold ratios over 1
    # is a collision.  A force at the tool loads the joints that carry the wrist through the arm's lever all at
    # once, where the model's errors seldom peak on all of them together; the unit sphere inside the cube of
    # the per-joint checks, so every per-joint detection on these joints is one of this check too.  [] : off.
    combined_joints: list[int] = field(default_factory=lambda: [1, 2, 3])
    # Thresholds x this on a cell read over a wire (emulated, real), and at least 2 periods over them:
    # the host reads at its own pace, not the controller's cycle, so samples repeat, skip and jitter
    # against the targets it streams, and the arm's torques with them.
    wire_margin: float = 3.0
    wire_observer_gain: float = 30.0  # 1/s: the residual's bandwidth over a wire (the jitter is fast)
    rebias_window_s: float = 0.1  # zeroing at rest averages this much of the residual

    def validate(self, where: str) -> None:
        require(0 < self.observer_gain <= 1000, f"{where}.observer_gain", "must lie in (0, 1000] 1/s")
        require(self.sigma_factor >= 0, f"{where}.sigma_factor", "must be >= 0")
        require(self.rest_sigma_factor is None or 0 <= self.rest_sigma_factor <= self.sigma_factor,
                f"{where}.rest_sigma_factor", "must lie in [0, sigma_factor]")
        require(all(v > 0 for v in self.floor_nm), f"{where}.floor_nm", "must all be > 0 N·m")
        require(0 <= self.payload_uncertainty_kg <= 6, f"{where}.payload_uncertainty_kg", "must lie in [0, 6] kg")
        require(self.coverage_min_count >= 0, f"{where}.coverage_min_count", "must be >= 0")
        require(self.stick_speed >= 0, f"{where}.stick_speed", "must be >= 0 rad/s")
        require(0 <= self.inertia_uncertainty <= 2, f"{where}.inertia_uncertainty", "must lie in [0, 2]")
        require(0 < self.wire_observer_gain <= 1000, f"{where}.wire_observer_gain", "must lie in (0, 1000] 1/s")
        require(1 <= self.wire_margin <= 10, f"{where}.wire_margin", "must lie in [1, 10]")
        require(1 <= self.confirm_periods <= 10, f"{where}.confirm_periods", "must lie in 1..10")
        require(all(isinstance(j, int) and j >= 1 for j in self.combined_joints)
                and len(set(self.combined_joints)) == len(self.combined_joints),
                f"{where}.combined_joints", "must be distinct joint numbers from 1")
        require(0 <= self.command_window_periods <= 50, f"{where}.command_window_periods", "must lie in 0..50")
        require(self.rebias_window_s > 0, f"{where}.rebias_window_s", "must be > 0")


@dataclass
class TaskContactSafety:
    """Per task: the states where it expects contact, its contact force limit, and reactions by state."""

    contact_states: list[str] = field(default_factory=list)
    contact_limit_n: float | None = None  # fast tool force limit in contact states (default: safety.max_tool_force_n)
    reactions: dict[str, str] = field(default_factory=dict)  # state -> reaction; others take collision.reaction

    def validate(self, where: str) -> None:
        for state, r in self.reactions.items():
            require(r in REACTIONS, join(where, f"reactions.{state}"),
                    f"unknown reaction '{r}' ({', '.join(REACTIONS)})")
        require(self.contact_limit_n is None or self.contact_limit_n > 0, f"{where}.contact_limit_n",
                "must be > 0 N")


@dataclass
class CollisionConfig:
    """Collision detection and reaction (cell/collision/guard.py): on in every task and plain move."""

    enabled: bool = True
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    reaction: Literal["stop", "retract", "comply", "monitor"] = "stop"  # where a task names none
    retract_m: float = 0.01  # retract: this far back along the estimated contact direction ...
    retract_speed_mps: float = 0.05  # ... at this speed, then stop
    comply_time_s: float = 0.5  # comply: yield to the contact force this long, then stop
    comply_admittance: float = 0.002  # m/s per N of contact force (capped at retract_speed_mps)
    tasks: dict[str, TaskContactSafety] = field(default_factory=dict)
    # The tasks' head-on speeds (cell/control/guarded.py).
    guarded: GuardedSettings = field(default_factory=GuardedSettings)

    def validate(self, where: str) -> None:
        require(0 < self.retract_m <= 0.1, f"{where}.retract_m", "must lie in (0, 0.1] m")
        require(0 < self.retract_speed_mps <= 0.25, f"{where}.retract_speed_mps", "must lie in (0, 0.25] m/s")
        require(0 < self.comply_time_s <= 5, f"{where}.comply_time_s", "must lie in (0, 5] s")
        require(0 < self.comply_admittance <= 0.05, f"{where}.comply_admittance", "must lie in (0, 0.05] m/s/N")
        for task in self.tasks:
            require(task in GUARDED_TASKS, join(where, "tasks"), f"unknown task '{task}' ({', '.join(GUARDED_TASKS)})")

    def for_task(self, task: str) -> TaskContactSafety:
        return self.tasks.get(task, TaskContactSafety())
