"""The planners' settings (`config/plans.yaml`): limits, grid, the steps that turn a profile into set-points."""

from __future__ import annotations

from dataclasses import dataclass, field

from cell.planning.constraints import DISCRETIZATIONS
from drivers.configio import require

RETIMINGS = ("exact", "smoothed")
RESIDUALS = ("local", "global")


@dataclass
class PlannerConfig:
    torque_margin: float = 0.10  # plan to (1 - margin) x the effort limit
    velocity_fraction: float = 1.0  # of the URDF speed limits
    acceleration_limits: list[float] = field(default_factory=lambda: [40.0, 40.0, 40.0, 60.0, 60.0, 60.0])
    gridpoints: int = 200  # the kinematic baseline's toppra grid (its calibration and figures were made on it)
    # Ours' toppra grid.  Each grid segment has one path acceleration and its torque bound holds at both ends,
    # and the exact step slows the samples where a speed cap dips below the profile between grid points: a
    # coarse grid costs time on both counts (measured per grid size: docs/notes/planning-history.md).  Planning
    # time grows with it (under a second a path at 800).
    toppra_gridpoints: int = 800
    max_iterations: int = 10
    sample_period_s: float = 0.008
    baseline_blend: float = 0.25  # share of the baseline's duration spent accelerating (and braking)
    collision_samples: int = 200
    # toppra's optimum switches the path acceleration between its bounds instantly; a servo fed such a
    # step overshoots it (the measured torque exceeds the model's for a few cycles).  The path
    # parameter s(t) is averaged over this window (0: off), which bounds the jerk and adds about the
    # window to the duration.
    smoothing_s: float = 0.04
    # Where toppra checks the torque constraint: "interpolation" at both ends of every grid segment,
    # "collocation" (toppra's default) only at its start.  The clamped spline has dp/ds = 0 at s = 0, so a
    # check at the start alone leaves the first segment's acceleration free: the profile shot up and stalled
    # within 20 ms, and first runs overshot a motor there (why: docs/planning.md, "Start transients").
    torque_discretization: str = "interpolation"
    # The plant's torque overshoots the model's as the arm leaves rest (servo lag, friction breaking away,
    # the controller's cubic interpolation of the set-points).  The rigid-body bound can be lowered by this
    # share over the first `start_margin_s` of the motion (back to the full bound over the next half window).
    # The model trust calibrated on the plant (`bench planning`) holds most of the start peaks with the rest;
    # without this margin a torque-bound start still reached the safety stop (joint 2 at 0.91 of its motor
    # limit 32 ms into a short joint 1-3 move), and 0.10 holds it (docs/planning.md).
    start_margin: float = 0.10
    start_margin_s: float = 0.10
    # What turns toppra's profile into set-points for ours: "exact" samples the profile as toppra made it
    # (the speed caps already hold between grid points, so nothing is stretched) and averages it over
    # `exact_smoothing_s` only; "smoothed" is the comparison planners' step (a `smoothing_s` average, a
    # local slow-down where that mixed speeds over a cap, then a uniform stretch for any excess left),
    # which cost ours 0.06-0.12 s a path against its own profile (docs/notes/planning-history.md).
    retiming: str = "exact"
    # The jerk bound of the exact step: the window the joint trajectory is averaged over through the motion.  A
    # centred average leaves the middle of the motion in time and adds half the window at each end, where the
    # arm leaves and reaches rest.  With 16 ms through the motion, mid-path joint-1 peaks reached the safety
    # stop on the plant (0.94 of the motor limit); 40 ms holds them.
    exact_smoothing_s: float = 0.04
    # The same bound where the arm leaves rest (the window gives way to `exact_smoothing_s` over the first
    # 0.2 s).  Half the difference comes off every plan; the start peaks it raises are held by the calibrated
    # trust (docs/planning.md).  Equal windows: one plain average.
    exact_smoothing_start_s: float = 0.024
    # And where the arm reaches rest (`exact_smoothing_s` gives way to it over the last 0.2 s): a shorter window
    # takes half the difference off every plan.  At 24 ms a wrist joint overshoots its model as the arm stops
    # (joint 4 of a trust reference path, loaded through the base joints' braking), which holds the calibrated
    # trust at about 0.82 on every joint; with the lighter start margin that is still the faster whole
    # (docs/notes/planning-history.md).
    exact_smoothing_stop_s: float = 0.024
    # The full model's torque beyond toppra's terms (viscous friction, the learned residual) is taken where
    # it occurs ("local": subtracted from the bound at each grid point, from the previous plan) rather than
    # by lowering a joint's bound along the whole path by its worst excess ("global").
    residual: str = "local"
    # The safety monitor's commanded-TCP-speed stop (m/s, 0: none); ours plans to `TCP_SPEED_SHARE` of it.
    tcp_speed_limit: float = 0.0

    def validate(self, where: str) -> None:
        require(0 <= self.torque_margin < 0.9, f"{where}.torque_margin", "must lie in [0, 0.9)")
        require(0 < self.velocity_fraction <= 1, f"{where}.velocity_fraction", "must lie in (0, 1]")
        require(len(self.acceleration_limits) == 6, f"{where}.acceleration_limits", "must have 6 values")
        require(all(a > 0 for a in self.acceleration_limits), f"{where}.acceleration_limits", "must be > 0")
        require(20 <= self.gridpoints <= 2000, f"{where}.gridpoints", "must lie in [20, 2000]")
        require(20 <= self.toppra_gridpoints <= 4000, f"{where}.toppra_gridpoints", "must lie in [20, 4000]")
        require(0 < self.baseline_blend <= 0.5, f"{where}.baseline_blend", "must lie in (0, 0.5]")
        require(0 <= self.smoothing_s <= 0.5, f"{where}.smoothing_s", "must lie in [0, 0.5] s")
        require(self.torque_discretization in DISCRETIZATIONS, f"{where}.torque_discretization",
                f"must be one of {', '.join(DISCRETIZATIONS)}")
        require(0 <= self.start_margin <= 0.5, f"{where}.start_margin", "must lie in [0, 0.5]")
        require(0 <= self.start_margin_s <= 1.0, f"{where}.start_margin_s", "must lie in [0, 1] s")
        require(self.retiming in RETIMINGS, f"{where}.retiming", f"must be one of {', '.join(RETIMINGS)}")
        require(0 <= self.exact_smoothing_s <= 0.2, f"{where}.exact_smoothing_s", "must lie in [0, 0.2] s")
        require(0 <= self.exact_smoothing_start_s <= self.exact_smoothing_s, f"{where}.exact_smoothing_start_s",
                "must lie in [0, exact_smoothing_s]")
        require(0 <= self.exact_smoothing_stop_s <= self.exact_smoothing_s, f"{where}.exact_smoothing_stop_s",
                "must lie in [0, exact_smoothing_s]")
        require(self.residual in RESIDUALS, f"{where}.residual", f"must be one of {', '.join(RESIDUALS)}")
        require(0 <= self.tcp_speed_limit <= 5.0, f"{where}.tcp_speed_limit", "must lie in [0, 5] m/s (0: none)")
