"""Time-efficient joint trajectories through waypoints under speed, acceleration and model-predicted torque limits.

Two planners share one geometric path (a clamped cubic spline through the waypoints, parameterised by
cumulative joint-space chord length), so their times compare like for like:

- `ToppraPlanner`: the provably time-optimal timing (TOPP-RA) along the path.  toppra's torque
  constraint needs torque to be second order in the path speed, which holds for the rigid-body part
  of the model but not for viscous friction or a learned residual; so the rigid-body part with the
  rotor inertia and Coulomb friction (`ToppraTerms`) is the toppra constraint, and the rest of the
  model is handled by iteration: the full model is evaluated on the
  timed trajectory and any joint that exceeds its limit gets its toppra bound lowered by the excess,
  until the full model's torques fit.  The bound holds at both ends of every grid segment
  (`torque_discretization`) and is lowered by `start_margin` while the arm leaves rest, where the
  plant's servo overshoots the model (docs/planning.md, "Start transients").
- `UniformScalingPlanner`: the operator's pendant speed knob: a fixed trapezoidal profile in the path
  parameter, uniformly stretched to the shortest duration whose predicted torques fit (bisection).

Both refuse waypoints outside the joint limits or paths that collide, with a clear message.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import toppra as ta
import toppra.algorithm as ta_algo
import toppra.constraint as ta_con

from cell.collision.geometry import CollisionChecker
from cell.model.robot import RobotModel
from cell.planning.averaging import rest_to_rest_average
from cell.planning.config import PlannerConfig
from cell.planning.constraints import GradedTorqueConstraint, SpeedCapConstraint, ToppraTerms
from drivers.errors import CellError

log = logging.getLogger(__name__)
ta.setup_logging("WARNING")

# The commanded TCP speed is checked as a chord between set-points; planning to 97 % of the stop leaves
# room for the chord and the averaging of the exact step.
TCP_SPEED_SHARE = 0.97

TorqueFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (N,n) x3 -> (N,n)


class PlanningError(CellError):
    """The waypoints cannot be planned (outside limits, colliding, or infeasible)."""

    exit_code = 2


@dataclass
class TimedTrajectory:
    """A joint trajectory sampled every `dt`: t (N,), q, dq, ddq (N, n)."""

    planner: str
    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    plan_time_s: float = 0.0
    iterations: int = 1
    torque_scale: np.ndarray | None = None  # per-joint bound tightening the plan needed
    s: np.ndarray | None = None  # the path parameter of each sample, where the planner knows it

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def at(self, t: float) -> np.ndarray:
        if t <= 0:
            return self.q[0]
        if t >= self.duration:
            return self.q[-1]
        i = min(max(int(np.searchsorted(self.t, t, side="right")) - 1, 0), len(self.t) - 2)
        u = (t - self.t[i]) / (self.t[i + 1] - self.t[i])
        return self.q[i] + u * (self.q[i + 1] - self.q[i])


class Planner(Protocol):
    """Pluggable planner: ToppraPlanner (ours), UniformScalingPlanner, KinematicPlanner, and the paper's PPO
    planner (cell/planning/ppo_planner.py), compared by bench/planning.py."""

    name: str

    def plan(self, waypoints: np.ndarray, torque_scale: np.ndarray | None = None) -> TimedTrajectory:
        """Time the path so the model's torque stays within torque_scale x the planning limit (per joint)."""
        ...


class GeometricPath:
    """Clamped cubic spline through the waypoints, s in [0, 1] by cumulative chord length."""

    def __init__(self, waypoints: np.ndarray) -> None:
        w = np.asarray(waypoints, float)
        chord = np.linalg.norm(np.diff(w, axis=0), axis=1)
        if np.any(chord < 1e-6):
            raise PlanningError("two consecutive waypoints are identical")
        s = np.concatenate([[0.0], np.cumsum(chord)]) / chord.sum()
        self.waypoints = w
        self.spline = ta.SplineInterpolator(s, w, bc_type="clamped")

    def eval(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.spline(s), self.spline(s, 1), self.spline(s, 2)


def sample_profile(grid: np.ndarray, sd: np.ndarray, dt: float) -> tuple[np.ndarray, float, np.ndarray, np.ndarray,
                                                                           np.ndarray]:
    """Sample times every `dt` of the path speed profile sd(s) (constant path acceleration between grid points):
    (times, the profile's end time, each sample's grid segment, the time into it, each segment's acceleration)."""
    ds = np.diff(grid)
    seg_t = 2.0 * ds / np.maximum(sd[:-1] + sd[1:], 1e-9)
    t_nodes = np.concatenate([[0.0], np.cumsum(seg_t)])
    seg_a = (sd[1:] ** 2 - sd[:-1] ** 2) / (2.0 * ds)
    ts = np.arange(0.0, t_nodes[-1] + dt, dt)
    i = np.clip(np.searchsorted(t_nodes, ts, side="right") - 1, 0, len(ds) - 1)
    tau = np.clip(ts - t_nodes[i], 0.0, seg_t[i])
    return ts, float(t_nodes[-1]), i, tau, seg_a


class PlannerBase:
    def __init__(
        self,
        robot: RobotModel,
        torque_fn: TorqueFn,
        cfg: PlannerConfig,
        collisions: CollisionChecker | None = None,
        terms: ToppraTerms | None = None,
    ) -> None:
        self.robot = robot
        self.torque_fn = torque_fn
        self.terms = terms or ToppraTerms(robot.rnea)
        self.cfg = cfg
        self.collisions = collisions
        lim = robot.limits
        self.effort = lim.effort
        self.vlim = lim.velocity * cfg.velocity_fraction
        self.alim = np.asarray(cfg.acceleration_limits, float)

    def torque_limit(self, scale: np.ndarray | None = None) -> np.ndarray:
        base = self.effort * (1.0 - self.cfg.torque_margin)
        return base if scale is None else base * scale

    def check_waypoints(self, waypoints: np.ndarray) -> GeometricPath:
        w = np.asarray(waypoints, float)
        n = self.robot.n
        if w.ndim != 2 or w.shape[1] != n or w.shape[0] < 2:
            raise PlanningError(f"waypoints must be at least 2 rows of {n} joint angles, got shape {w.shape}")
        if not np.all(np.isfinite(w)):
            raise PlanningError("waypoints contain NaN or inf")
        lim = self.robot.limits
        for i, q in enumerate(w):
            bad = np.where((q < lim.lower) | (q > lim.upper))[0]
            if bad.size:
                j = int(bad[0])
                raise PlanningError(
                    f"waypoint {i}: joint {j + 1} at {np.degrees(q[j]):.1f} deg is outside its limits "
                    f"[{np.degrees(lim.lower[j]):.0f}, {np.degrees(lim.upper[j]):.0f}] deg"
                )
        path = GeometricPath(w)
        if self.collisions is not None:
            s = np.linspace(0, 1, self.cfg.collision_samples)
            qs = path.eval(s)[0]
            if np.any(qs < lim.lower) or np.any(qs > lim.upper):
                raise PlanningError("the spline through the waypoints leaves the joint limits between waypoints")
            hit = self.collisions.path_collisions(qs, tool_may_touch=False)
            if hit is not None:
                k, what = hit
                raise PlanningError(
                    f"the path collides at {100 * s[k]:.0f} % of its length: {', '.join(map(str, what))}"
                )
        return path

    def sample(self, name: str, ts: np.ndarray, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> TimedTrajectory:
        return TimedTrajectory(planner=name, t=ts, q=q, dq=dq, ddq=ddq)

    @staticmethod
    def stamp(traj: TimedTrajectory, t0: float, iterations: int, scale: np.ndarray) -> TimedTrajectory:
        """The accepted plan with how it was made: wall time since `t0`, iterations, the bound scale."""
        traj.plan_time_s = time.perf_counter() - t0
        traj.iterations = iterations
        traj.torque_scale = scale
        return traj

    def excess(self, traj: TimedTrajectory, scale: np.ndarray | None = None) -> np.ndarray:
        """Per joint: peak |predicted torque| / planning limit (<= 1 means it fits)."""
        tau = self.torque_fn(traj.q, traj.dq, traj.ddq)
        return np.max(np.abs(tau), axis=0) / self.torque_limit(scale)


class ToppraPlanner(PlannerBase):
    name = "toppra"

    def plan(self, waypoints: np.ndarray, torque_scale: np.ndarray | None = None) -> TimedTrajectory:
        t0 = time.perf_counter()
        path = self.check_waypoints(waypoints)
        n = self.robot.n
        scale = np.ones(n) if torque_scale is None else np.array(torque_scale, float)
        grid = np.linspace(0, 1, self.cfg.toppra_gridpoints + 1)
        cap = self.speed_cap(path, grid)
        bound = scale.copy()  # the toppra constraint's share of the limit, lowered while the full model exceeds
        offset: np.ndarray | None = None  # the full model's torque beyond toppra's terms, per grid point
        local = np.ones((len(grid), n))  # per grid point and joint: the share of the bound left where it exceeded
        limit = self.torque_limit(scale)
        use_local = self.cfg.residual == "local"
        for it in range(1, self.cfg.max_iterations + 1):
            try:
                sd = self.speed_profile(path, grid, self.torque_limit(bound), offset, cap, local)
            except PlanningError:
                if offset is None and np.all(local == 1.0):
                    raise
                # The local terms made a point infeasible (a residual measured at speed, where the arm must
                # hold or pass slowly): the global rule takes over from the plain bound.
                log.info("planner: the local torque terms left no feasible timing; lowering joint bounds instead")
                offset, local, use_local = None, np.ones_like(local), False
                sd = self.speed_profile(path, grid, self.torque_limit(bound), None, cap, None)
            traj = self.timed(path, grid, sd)
            over = np.abs(self.torque_fn(traj.q, traj.dq, traj.ddq)) / limit
            ratio = np.max(over, axis=0)
            if np.all(ratio <= 1.0 + 1e-3):
                return self.stamp(traj, t0, it, scale)
            if use_local and it < self.cfg.max_iterations // 2:
                # Where the plan was: the next plan takes the full model's torque beyond toppra's terms as
                # known at each grid point; from the second round, what still exceeds (the residual moved with
                # the speed gained, or the rigid-body torque between grid points) lowers the bound there alone.
                if it > 1:
                    local = local * self.local_tightening(traj, grid, over)
                offset = self.residual_on_grid(traj, grid)
                continue
            # Lower the rigid-body bound of each violating joint by its excess and try again.
            bound = np.where(ratio > 1.0, bound / ratio * 0.995, bound)
        if self.cfg.residual == "local":
            # The local terms did not settle (a residual that grows faster than the speed it costs): the
            # global rule alone, from the start, always converges by lowering whole bounds.
            log.info("planner: the local torque terms did not converge (worst ratio %.3f); planning with the "
                     "global rule", float(np.max(ratio)))
            fallback = ToppraPlanner(self.robot, self.torque_fn, replace(self.cfg, residual="global"),
                                     None, self.terms)
            fallback.name = self.name
            return self.stamp(fallback.plan(waypoints, torque_scale), t0, 2 * self.cfg.max_iterations, scale)
        raise PlanningError(
            f"the full model's torques still exceed the limits after {self.cfg.max_iterations} re-plans "
            f"(worst ratio {float(np.max(ratio)):.3f})"
        )

    def rigid_torque(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """toppra's terms (inv_dyn and Coulomb friction) on samples (N, n)."""
        tau = np.array([self.terms.inv_dyn(a, b, c) for a, b, c in zip(q, dq, ddq, strict=True)])
        return tau if self.terms.coulomb is None else tau + self.terms.coulomb * np.sign(dq)

    @staticmethod
    def local_tightening(traj: TimedTrajectory, grid: np.ndarray, over: np.ndarray, reach: int = 2) -> np.ndarray:
        """Per grid point and joint, 1 / the excess of the samples over their limit within `reach` grid cells
        (1 elsewhere): the share of the bound the next plan keeps there."""
        assert traj.s is not None
        out = np.ones((len(grid), over.shape[1]))
        cell = np.clip(np.searchsorted(grid, traj.s, side="right") - 1, 0, len(grid) - 2)
        for k, j in zip(*np.nonzero(over > 1.0), strict=True):
            lo, hi = max(cell[k] - reach + 1, 0), min(cell[k] + reach + 1, len(grid) - 1)
            out[lo:hi + 1, j] = np.minimum(out[lo:hi + 1, j], 1.0 / (over[k, j] * 1.005))
        return out

    def residual_on_grid(self, traj: TimedTrajectory, grid: np.ndarray) -> np.ndarray:
        """The full model's torque minus toppra's terms along the trajectory, at the grid points (by s)."""
        assert traj.s is not None
        r = self.torque_fn(traj.q, traj.dq, traj.ddq) - self.rigid_torque(traj.q, traj.dq, traj.ddq)
        s, keep = np.unique(traj.s, return_index=True)
        return np.column_stack([np.interp(grid, s, r[keep, j]) for j in range(r.shape[1])])

    def speed_cap(self, path: GeometricPath, grid: np.ndarray) -> np.ndarray | None:
        """The exact step's path-speed cap per grid point (None for the smoothed step, which keeps toppra's
        joint speed constraint): the joint speed limits and the TCP speed limit at the grid points.  Between
        grid points a cap can dip below toppra's chord (sd^2 is linear in s on a segment); `timed_exact`
        slows the profile there alone.  Holding the caps over each grid point's neighbourhood instead lowers
        them wherever they slope, which cost 2 % of a speed-bound path."""
        if self.cfg.retiming != "exact":
            return None
        q, dp, _ = path.eval(grid)
        cap = np.min(self.vlim[None, :] / np.maximum(np.abs(dp), 1e-9), axis=1)
        if self.cfg.tcp_speed_limit > 0:
            v = np.array([np.linalg.norm(self.robot.tcp_jacobian(a)[:3] @ b) for a, b in zip(q, dp, strict=True)])
            cap = np.minimum(cap, TCP_SPEED_SHARE * self.cfg.tcp_speed_limit / np.maximum(v, 1e-9))
        return cap

    def speed_profile(self, path: GeometricPath, grid: np.ndarray, limit: np.ndarray,
                      offset: np.ndarray | None = None, cap: np.ndarray | None = None,
                      local: np.ndarray | None = None) -> np.ndarray:
        """toppra's fastest path speed sd at the grid points (from rest to rest) under the joint speed and
        acceleration limits and the rigid-body torque bound +-`limit` (N·m per joint; `offset`, torque known
        beyond toppra's terms per grid point, counts against it), lowered by `start_margin` over the motion's
        first `start_margin_s`.  Where that window ends along the path is taken from the profile without the
        margin (the margin only makes the start slower, so the window in time is at least as long as
        configured).  `cap`: a path-speed cap per grid point instead of toppra's joint speed constraint;
        `local`: a share of the bound per grid point and joint (1: all of it)."""
        shares = np.ones((len(grid), self.robot.n)) if local is None else local
        sd = self._toppra(path, grid, limit, shares, offset, cap)
        if self.cfg.start_margin <= 0 or self.cfg.start_margin_s <= 0:
            return sd
        try:
            return self._toppra(path, grid, limit, self.start_factor(grid, sd)[:, None] * shares, offset, cap)
        except PlanningError:
            # Holding the start pose alone takes more than (1 - start_margin) of the bound: plan without it.
            log.warning("planner: the start margin leaves no feasible timing here; planned without it")
            return sd

    def start_factor(self, grid: np.ndarray, sd: np.ndarray) -> np.ndarray:
        """Per grid point, the share of the torque bound toppra may use: 1 - start_margin until
        start_margin_s into the profile sd, rising linearly to 1 over the next half window."""
        ds = np.diff(grid)
        t = np.concatenate([[0.0], np.cumsum(2.0 * ds / np.maximum(sd[:-1] + sd[1:], 1e-9))])
        window = self.cfg.start_margin_s
        rise = np.clip((t - window) / (0.5 * window), 0.0, 1.0)
        return 1.0 - self.cfg.start_margin * (1.0 - rise)

    def _toppra(self, path: GeometricPath, grid: np.ndarray, limit: np.ndarray, factor: np.ndarray,
                offset: np.ndarray | None = None, cap: np.ndarray | None = None) -> np.ndarray:
        n = self.robot.n
        vel: ta_con.LinearConstraint = (ta_con.JointVelocityConstraint(np.column_stack([-self.vlim, self.vlim]))
                                        if cap is None else SpeedCapConstraint(cap))
        acc = ta_con.JointAccelerationConstraint(np.column_stack([-self.alim, self.alim]))
        friction = np.zeros(n) if self.terms.coulomb is None else self.terms.coulomb
        torque = GradedTorqueConstraint(self.terms.inv_dyn, np.column_stack([-limit, limit]), friction, factor,
                                        self.cfg.torque_discretization, offset)
        algo = ta_algo.TOPPRA([vel, acc, torque], path.spline, gridpoints=grid, parametrizer="ParametrizeConstAccel")
        _, sd, _ = algo.compute_parameterization(0.0, 0.0)
        if sd is None or not np.all(np.isfinite(sd)):
            raise PlanningError("no feasible timing: the torque limits cannot hold the arm on this path")
        return np.maximum(np.asarray(sd, float), 0.0)

    def timed(self, path: GeometricPath, grid: np.ndarray, sd: np.ndarray) -> TimedTrajectory:
        """The set-points of the path speed profile sd(s) (constant path acceleration between grid points),
        by the configured step (`retiming`)."""
        if self.cfg.retiming == "exact":
            return self.timed_exact(path, grid, sd)
        return self.timed_smoothed(path, grid, sd)

    def speed_over(self, path: GeometricPath, s: np.ndarray, s_d: np.ndarray) -> np.ndarray:
        """Per sample: the largest joint speed / limit, and the TCP speed / its planning share if set."""
        q, dp, _ = path.eval(s)
        over = np.max(np.abs(dp * s_d[:, None]) / self.vlim, axis=1)
        if self.cfg.tcp_speed_limit > 0:
            v = np.array([np.linalg.norm(self.robot.tcp_jacobian(a)[:3] @ b) for a, b in zip(q, dp, strict=True)])
            over = np.maximum(over, v * np.abs(s_d) / (TCP_SPEED_SHARE * self.cfg.tcp_speed_limit))
        return over

    def timed_exact(self, path: GeometricPath, grid: np.ndarray, sd: np.ndarray) -> TimedTrajectory:
        """Sample toppra's profile every period as it is (s, its speed and acceleration from the profile's own
        constant-acceleration segments, not from differences).  Where a speed cap dips below the profile
        between grid points, time is dilated there alone, by the excess.  Then the joint trajectory (not s)
        is averaged over `exact_smoothing_start_s` as it leaves rest, `exact_smoothing_s` through the motion and
        `exact_smoothing_stop_s` as it reaches rest (`rest_to_rest_average`): every joint's speed and
        acceleration are averages of the planned ones, so neither grows past its bound (averaging s instead
        mixes the large path accelerations near the path's ends, where dp/ds -> 0, into points where they are
        not small); the path is left by well under a milliradian.  A uniform stretch is the last resort, logged."""
        dt = self.cfg.sample_period_s
        ts, t_end, i, tau, seg_a = sample_profile(grid, sd, dt)
        moving = ts < t_end
        s = np.clip(grid[i] + sd[i] * tau + 0.5 * seg_a[i] * tau**2, 0.0, 1.0)
        s_d = np.where(moving, sd[i] + seg_a[i] * tau, 0.0)
        s_dd = np.where(moving, seg_a[i], 0.0)
        s[-1] = 1.0
        for _ in range(3):
            over = self.speed_over(path, s, s_d)
            if np.max(over) <= 1.0 + 1e-4:
                break
            # Time runs slower by the excess at the samples over a cap, and only there: the speeds there
            # become speed / excess; the rest of the profile is untouched.  Resampling can leave a sliver of
            # excess between old samples, so this repeats.
            dilation = np.where(over > 1.0, over * 1.0005, 1.0)
            t_new = np.concatenate([[0.0], np.cumsum(0.5 * (dilation[1:] + dilation[:-1]) * dt)])
            t_out = np.arange(0.0, t_new[-1] + dt, dt)
            s, s_d = np.interp(t_out, t_new, s), np.interp(t_out, t_new, s_d / dilation)
            s[-1] = 1.0
            s_dd = np.gradient(s_d, dt)
            log.debug("planner: exact step dilated %d samples (speed up to %.4f of a cap)",
                      int(np.sum(over > 1.0)), float(np.max(over)))
        k = float(np.max(self.speed_over(path, s, s_d)))
        if k > 1.001:
            log.info("planner: exact step stretched uniformly by %.4f (speed over a cap after dilation)", k)
            t_old = np.arange(len(s)) * dt
            t_out = np.arange(0.0, t_old[-1] * k + dt, dt)
            s, s_d = np.interp(t_out / k, t_old, s), np.interp(t_out / k, t_old, s_d) / k
            s[-1] = 1.0
            s_dd = np.gradient(s_d, dt)
        s_d[0] = s_d[-1] = 0.0
        q, dp, ddp = path.eval(s)
        dq = dp * s_d[:, None]
        ddq = ddp * s_d[:, None] ** 2 + dp * s_dd[:, None]
        if self.cfg.exact_smoothing_s > 0:
            q, dq, ddq, s = rest_to_rest_average(q, dq, ddq, s, path.waypoints[-1], dt,
                                                 self.cfg.exact_smoothing_start_s, self.cfg.exact_smoothing_s,
                                                 self.cfg.exact_smoothing_stop_s)
        traj = self.sample(self.name, np.arange(len(s)) * dt, q, dq, ddq)
        traj.s = s
        return traj

    def timed_smoothed(self, path: GeometricPath, grid: np.ndarray, sd: np.ndarray) -> TimedTrajectory:
        """The comparison planners' step: the path speed profile sd(s) (constant path acceleration between grid
        points) sampled every period, smoothed over `smoothing_s`, then stretched where a limit is exceeded."""
        dt = self.cfg.sample_period_s
        ts, t_end, i, tau, seg_a = sample_profile(grid, sd, dt)
        s = np.clip(grid[i] + sd[i] * tau + 0.5 * seg_a[i] * tau**2, 0.0, 1.0)
        w = int(round(self.cfg.smoothing_s / dt))
        if w >= 2:
            # A moving average of s(t) (held at its ends): velocity and acceleration of the result are
            # averages of the original's, so no bound is exceeded, and the jerk is bounded.
            # (The first output averages the padding alone; the second holds the first input sample, s = 0 as
            # well: dropping the first keeps one sample at rest, not two.)
            s = np.convolve(np.concatenate([np.zeros(w), s, np.ones(w)]), np.ones(w) / w, mode="valid")[1:]
            s = s[: np.nonzero(s >= 1.0 - 1e-12)[0][0] + 1] if np.any(s >= 1.0 - 1e-12) else s
        s[-1] = 1.0
        # toppra holds the speed limits at its grid points only, and the averaging above mixes in the
        # speeds of neighbouring path points: where a joint is over its speed limit, time is dilated
        # locally by the excess (smoothed the same way), then whatever is left is scaled out uniformly.
        s_d = np.gradient(s, dt)
        over = np.max(np.abs(path.eval(s)[1] * s_d[:, None]) / self.vlim, axis=1)
        dilation = np.maximum(1.0, over * 1.002)
        if w >= 2:
            dilation = np.convolve(np.pad(dilation, w, mode="edge"), np.ones(w) / w, mode="same")[w:-w]
        if np.any(dilation > 1.0):
            t_new = np.concatenate([[0.0], np.cumsum(0.5 * (dilation[1:] + dilation[:-1]) * dt)])
            s = np.interp(np.arange(0.0, t_new[-1] + dt, dt), t_new, s)
            s[-1] = 1.0
        for attempt in range(4):
            s_d = np.gradient(s, dt)
            s_dd = np.gradient(s_d, dt)
            s_d[0] = s_d[-1] = 0.0
            p, dp, ddp = path.eval(s)
            dq = dp * s_d[:, None]
            ddq = ddp * s_d[:, None] ** 2 + dp * s_dd[:, None]
            k = max(1.0, float(np.max(np.abs(dq) / self.vlim)), float(np.sqrt(np.max(np.abs(ddq) / self.alim))))
            if k <= 1.0 or attempt == 3:
                break
            t_old = np.arange(len(s)) * dt
            s = np.interp(np.arange(0.0, t_old[-1] * k * 1.001 + dt, dt) / (k * 1.001), t_old, s)
            s[-1] = 1.0
        return self.sample(self.name, np.arange(len(s)) * dt, p, dq, ddq)
