"""The planners ours is compared with: uniform scaling (the pendant's speed knob) and a kinematic TOPP-RA (joint
speed and acceleration limits only), and the registry of all three."""

from __future__ import annotations

import time

import numpy as np
import toppra.algorithm as ta_algo
import toppra.constraint as ta_con

from cell.planning.planner import GeometricPath, PlannerBase, PlanningError, TimedTrajectory, ToppraPlanner


class UniformScalingPlanner(PlannerBase):
    """Baseline: a trapezoidal profile in s, uniformly time-scaled to the fastest that fits."""

    name = "uniform"

    def profile(self, T: float, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        b = self.cfg.baseline_blend
        v = 1.0 / (T * (1.0 - b))  # cruise ds/dt so that s(T) = 1
        a = v / (b * T)
        tb = b * T
        s = np.where(ts < tb, 0.5 * a * ts**2,
                     np.where(ts < T - tb, 0.5 * a * tb**2 + v * (ts - tb), 1.0 - 0.5 * a * (T - ts) ** 2))
        sd = np.where(ts < tb, a * ts, np.where(ts < T - tb, v, a * (T - ts)))
        sdd = np.where(ts < tb, a, np.where(ts < T - tb, 0.0, -a))
        return np.clip(s, 0, 1), sd, sdd

    def timed(self, path: GeometricPath, T: float) -> TimedTrajectory:
        ts = np.arange(0.0, T + 1e-9, self.cfg.sample_period_s)
        if ts[-1] < T:
            ts = np.append(ts, T)
        s, sd, sdd = self.profile(T, ts)
        p, dp, ddp = path.eval(s)
        dq = dp * sd[:, None]
        ddq = ddp * sd[:, None] ** 2 + dp * sdd[:, None]
        return self.sample(self.name, ts, p, dq, ddq)

    def fits(self, traj: TimedTrajectory, scale: np.ndarray) -> bool:
        if np.any(np.abs(traj.dq) > self.vlim * (1 + 1e-6)) or np.any(np.abs(traj.ddq) > self.alim * (1 + 1e-6)):
            return False
        return bool(np.all(self.excess(traj, scale) <= 1.0))

    def plan(self, waypoints: np.ndarray, torque_scale: np.ndarray | None = None) -> TimedTrajectory:
        t0 = time.perf_counter()
        path = self.check_waypoints(waypoints)
        scale = np.ones(self.robot.n) if torque_scale is None else np.array(torque_scale, float)
        lo, hi = 0.05, 0.5
        while not self.fits(self.timed(path, hi), scale):
            lo, hi = hi, hi * 2
            if hi > 120:
                raise PlanningError("no uniform time-scaling under 120 s keeps the torques within the limits")
        for _ in range(40):  # bisection to ~1 ms
            if hi - lo < 1e-3:
                break
            mid = 0.5 * (lo + hi)
            if self.fits(self.timed(path, mid), scale):
                hi = mid
            else:
                lo = mid
        traj = self.timed(path, hi)
        traj.plan_time_s = time.perf_counter() - t0
        traj.torque_scale = scale
        return traj


class KinematicPlanner(ToppraPlanner):
    """Baseline: TOPP-RA under joint speed and acceleration limits only (what MoveIt's TOTG or ruckig give an
    integrator).  The torque model is not consulted: `cfg.acceleration_limits` must be set conservatively
    enough for the arm's motors (bench/planning_calibration.py chooses them on the plant); `torque_scale`,
    when given, scales those accelerations per joint (torque grows with acceleration)."""

    name = "kinematic"

    def plan(self, waypoints: np.ndarray, torque_scale: np.ndarray | None = None) -> TimedTrajectory:
        t0 = time.perf_counter()
        path = self.check_waypoints(waypoints)
        alim = self.alim if torque_scale is None else self.alim * np.asarray(torque_scale, float)
        vel = ta_con.JointVelocityConstraint(np.column_stack([-self.vlim, self.vlim]))
        acc = ta_con.JointAccelerationConstraint(np.column_stack([-alim, alim]))
        grid = np.linspace(0, 1, self.cfg.gridpoints + 1)
        algo = ta_algo.TOPPRA([vel, acc], path.spline, gridpoints=grid, parametrizer="ParametrizeConstAccel")
        _, sd, _ = algo.compute_parameterization(0.0, 0.0)
        if sd is None or not np.all(np.isfinite(sd)):
            raise PlanningError("no feasible timing under the joint speed and acceleration limits")
        saved = self.alim
        self.alim = alim  # `timed_smoothed` re-checks the accelerations of the smoothed result against these
        try:
            # The baseline keeps the step it was calibrated with (the integrator's TOTG/ruckig output smoothed
            # for the servo); its per-arm accelerations were chosen on the plant with it.
            traj = self.timed_smoothed(path, grid, np.maximum(np.asarray(sd, float), 0.0))
        finally:
            self.alim = saved
        traj.plan_time_s = time.perf_counter() - t0
        return traj


PLANNERS: dict[str, type[ToppraPlanner | UniformScalingPlanner]] = {
    "toppra": ToppraPlanner, "uniform": UniformScalingPlanner, "kinematic": KinematicPlanner,
}
