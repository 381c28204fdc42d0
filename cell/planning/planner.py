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
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import toppra as ta
import toppra.algorithm as ta_algo
import toppra.constraint as ta_con
from toppra.constraint.linear_constraint import canlinear_colloc_to_interpolate

from cell.collision.geometry import CollisionChecker
from cell.model.dynamics.rigid_body import P2Model
from cell.model.robot import RobotModel
from drivers.configio import require
from drivers.errors import CellError

log = logging.getLogger(__name__)
ta.setup_logging("WARNING")
DISCRETIZATIONS = {"interpolation": ta_con.DiscretizationType.Interpolation,
                   "collocation": ta_con.DiscretizationType.Collocation}

TorqueFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (N,n) x3 -> (N,n)
InvDyn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (n,) x3 -> (n,), second order in the path speed


@dataclass
class ToppraTerms:
    """The part of a torque model toppra can take as its constraint: `inv_dyn` must be quadratic in the
    path speed (rigid body, rotor inertia), `coulomb` the per-joint f_c of `f_c sign(q')`."""

    inv_dyn: InvDyn
    coulomb: np.ndarray | None = None


def toppra_terms(model: object) -> ToppraTerms | None:
    """The identified physics of a model-lab model (P2, or the physics part of H1-H3), or None (P1, D).

    Rotor inertia matters most: at the accelerations a time-optimal plan reaches, `B_m q''` is as large
    as the rigid body's torque, and leaving it to the iteration would make the path look infeasible.
    """
    p2 = model if isinstance(model, P2Model) else getattr(model, "physics", None)
    if not isinstance(p2, P2Model):
        return None
    B_m = np.asarray(p2.params.B_m, float)

    def inv_dyn(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        return p2.rigid_one(q, dq, ddq) + B_m * ddq

    return ToppraTerms(inv_dyn, np.asarray(p2.params.f_c, float))


class GradedTorqueConstraint(ta_con.JointTorqueConstraint):
    """toppra's joint torque constraint with the bound scaled by `factor` (one per grid point): the torque
    coefficients a, b, c of each grid point are divided by its factor, which keeps F and g the same at every
    grid point (so toppra's solvers take it as they take the plain constraint)."""

    def __init__(self, inv_dyn: InvDyn, tau_lim: np.ndarray, coulomb: np.ndarray, factor: np.ndarray,
                 discretization: str) -> None:
        super().__init__(inv_dyn, tau_lim, coulomb, discretization_scheme=DISCRETIZATIONS["collocation"])
        self.factor = np.asarray(factor, float)
        self.interpolate = discretization == "interpolation"

    def compute_constraint_params(self, path: object, gridpoints: np.ndarray) -> tuple[object, ...]:
        a, b, c, F, g, _, _ = super().compute_constraint_params(path, gridpoints)
        f = self.factor[:, None]
        a, b, c = a / f, b / f, c / f
        if self.interpolate:
            return tuple(canlinear_colloc_to_interpolate(a, b, c, F, g, None, None, gridpoints, identical=True))
        return a, b, c, F, g, None, None


class PlanningError(CellError):
    """The waypoints cannot be planned (outside limits, colliding, or infeasible)."""

    exit_code = 2


@dataclass
class PlannerConfig:
    torque_margin: float = 0.10  # plan to (1 - margin) x the effort limit
    velocity_fraction: float = 1.0  # of the URDF speed limits
    acceleration_limits: list[float] = field(default_factory=lambda: [40.0, 40.0, 40.0, 60.0, 60.0, 60.0])
    gridpoints: int = 200
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
    # the controller's cubic interpolation of the set-points): the highest first-run peaks were all 64-88 ms
    # into the motion.  The rigid-body bound is lowered by this share over the first `start_margin_s` of the
    # motion (back to the full bound over the next half window); it costs 0-16 ms a path (docs/planning.md).
    start_margin: float = 0.15
    start_margin_s: float = 0.10

    def validate(self, where: str) -> None:
        require(0 <= self.torque_margin < 0.9, f"{where}.torque_margin", "must lie in [0, 0.9)")
        require(0 < self.velocity_fraction <= 1, f"{where}.velocity_fraction", "must lie in (0, 1]")
        require(len(self.acceleration_limits) == 6, f"{where}.acceleration_limits", "must have 6 values")
        require(all(a > 0 for a in self.acceleration_limits), f"{where}.acceleration_limits", "must be > 0")
        require(20 <= self.gridpoints <= 2000, f"{where}.gridpoints", "must lie in [20, 2000]")
        require(0 < self.baseline_blend <= 0.5, f"{where}.baseline_blend", "must lie in (0, 0.5]")
        require(0 <= self.smoothing_s <= 0.5, f"{where}.smoothing_s", "must lie in [0, 0.5] s")
        require(self.torque_discretization in DISCRETIZATIONS, f"{where}.torque_discretization",
                f"must be one of {', '.join(DISCRETIZATIONS)}")
        require(0 <= self.start_margin <= 0.5, f"{where}.start_margin", "must lie in [0, 0.5]")
        require(0 <= self.start_margin_s <= 1.0, f"{where}.start_margin_s", "must lie in [0, 1] s")


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


class _Base:
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


class ToppraPlanner(_Base):
    name = "toppra"

    def plan(self, waypoints: np.ndarray, torque_scale: np.ndarray | None = None) -> TimedTrajectory:
        t0 = time.perf_counter()
        path = self.check_waypoints(waypoints)
        n = self.robot.n
        scale = np.ones(n) if torque_scale is None else np.array(torque_scale, float)
        grid = np.linspace(0, 1, self.cfg.gridpoints + 1)
        bound = scale.copy()  # the toppra constraint's share of the limit, lowered while the full model exceeds
        for it in range(1, self.cfg.max_iterations + 1):
            traj = self.timed(path, grid, self.speed_profile(path, grid, self.torque_limit(bound)))
            ratio = self.excess(traj, scale)
            if np.all(ratio <= 1.0 + 1e-3):
                return self.stamp(traj, t0, it, scale)
            # Lower the rigid-body bound of each violating joint by its excess and try again.
            bound = np.where(ratio > 1.0, bound / ratio * 0.995, bound)
        raise PlanningError(
            f"the full model's torques still exceed the limits after {self.cfg.max_iterations} re-plans "
            f"(worst ratio {float(np.max(ratio)):.3f})"
        )

    def speed_profile(self, path: GeometricPath, grid: np.ndarray, limit: np.ndarray) -> np.ndarray:
        """toppra's fastest path speed sd at the grid points (from rest to rest) under the joint speed and
        acceleration limits and the rigid-body torque bound +-`limit` (N·m per joint), lowered by
        `start_margin` over the motion's first `start_margin_s`.  Where that window ends along the path is
        taken from the profile without the margin (the margin only makes the start slower, so the window in
        time is at least as long as configured)."""
        sd = self._toppra(path, grid, limit, np.ones(len(grid)))
        if self.cfg.start_margin <= 0 or self.cfg.start_margin_s <= 0:
            return sd
        try:
            return self._toppra(path, grid, limit, self.start_factor(grid, sd))
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

    def _toppra(self, path: GeometricPath, grid: np.ndarray, limit: np.ndarray, factor: np.ndarray) -> np.ndarray:
        n = self.robot.n
        vel = ta_con.JointVelocityConstraint(np.column_stack([-self.vlim, self.vlim]))
        acc = ta_con.JointAccelerationConstraint(np.column_stack([-self.alim, self.alim]))
        friction = np.zeros(n) if self.terms.coulomb is None else self.terms.coulomb
        torque = GradedTorqueConstraint(self.terms.inv_dyn, np.column_stack([-limit, limit]), friction, factor,
                                        self.cfg.torque_discretization)
        algo = ta_algo.TOPPRA([vel, acc, torque], path.spline, gridpoints=grid, parametrizer="ParametrizeConstAccel")
        _, sd, _ = algo.compute_parameterization(0.0, 0.0)
        if sd is None or not np.all(np.isfinite(sd)):
            raise PlanningError("no feasible timing: the torque limits cannot hold the arm on this path")
        return np.maximum(np.asarray(sd, float), 0.0)

    def timed(self, path: GeometricPath, grid: np.ndarray, sd: np.ndarray) -> TimedTrajectory:
        """Sample the path speed profile sd(s) (constant path acceleration between grid points) every
        period, smoothed over `smoothing_s`."""
        ds = np.diff(grid)
        seg_t = 2.0 * ds / np.maximum(sd[:-1] + sd[1:], 1e-9)
        t_nodes = np.concatenate([[0.0], np.cumsum(seg_t)])
        seg_a = (sd[1:] ** 2 - sd[:-1] ** 2) / (2.0 * ds)
        dt = self.cfg.sample_period_s
        ts = np.arange(0.0, t_nodes[-1] + dt, dt)
        i = np.clip(np.searchsorted(t_nodes, ts, side="right") - 1, 0, len(ds) - 1)
        tau = np.clip(ts - t_nodes[i], 0.0, seg_t[i])
        s = np.clip(grid[i] + sd[i] * tau + 0.5 * seg_a[i] * tau**2, 0.0, 1.0)
        w = int(round(self.cfg.smoothing_s / dt))
        if w >= 2:
            # A moving average of s(t) (held at its ends): velocity and acceleration of the result are
            # averages of the original's, so no bound is exceeded, and the jerk is bounded.
            s = np.convolve(np.concatenate([np.zeros(w), s, np.ones(w)]), np.ones(w) / w, mode="valid")
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


class UniformScalingPlanner(_Base):
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
        self.alim = alim  # `timed` re-checks the accelerations of the smoothed result against these
        try:
            traj = self.timed(path, grid, np.maximum(np.asarray(sd, float), 0.0))
        finally:
            self.alim = saved
        traj.plan_time_s = time.perf_counter() - t0
        return traj


PLANNERS: dict[str, type[ToppraPlanner | UniformScalingPlanner]] = {
    "toppra": ToppraPlanner, "uniform": UniformScalingPlanner, "kinematic": KinematicPlanner,
}
