"""Collision detection on the hybrid model: a fast momentum-observer residual per joint against thresholds
set by the model's own uncertainty, checked every control period.

The residual r (N·m, the external joint torque in the cell's convention) comes from a generalised
momentum observer of its own, with a far higher bandwidth than the virtual sensor's (that one is tuned
for steady contact forces and filters short impacts away).  Per joint the threshold is

    thr_j = floor_j + sigma_factor * sigma_j(|q'_j|) + band_j * held_j + |f_j(q'_j)| * held_cmd_j
            + inertia * max(|(M(q) q'')_j|, |(M(q) q''_cmd)_j|)
            + payload_kg * (|g1_j(q) - g1_j(q_zero)| + sum_i |J_ij| |a_i|)

* sigma_j: the model's one-sigma residual at that joint speed (the model lab's held-out levels, stored
  with the model; wider where the model is less sure, e.g. at high speed), and the physics part's
  level where the training data did not cover the joint's (q, q', q'');
* band_j: the joint's static friction band (the model's Coulomb level): a joint at or near rest holds
  whatever torque its friction allows, which no model of the state predicts; twice that for a joint that has
  moved since the residual was zeroed (its friction may stick as far as the band's other edge).  held_j is
  the larger of max(0, 1 - |q'_j| / stick_speed) and held_cmd_j: a joint its command holds stays in its band
  while the other joints' accelerations drag it into a creep;
* f_j(q'_j): the friction the model predicts from the measured speed beyond what it predicts at the commanded
  speed, a full Coulomb level for a joint commanded still that creeps a few mrad/s, which a held joint's
  friction need not follow.  held_cmd_j = max(0, 1 - |q'_cmd,j| / v_held) x clip(2 - |q'_j| / stick_speed, 0, 1):
  commanded still (v_held: the width of the model's smoothed friction sign), and creeping rather than jolted
  into sliding; so an impact that stops a joint its command moves, or jolts a held one, does not widen its own
  threshold (0 without a command stream: a detector fed states only cannot tell a held joint);
* inertia: the relative error of the rigid body's inertial torque (mass errors, and the measured
  torque's latency against the joint positions, which shows while the arm accelerates).  q'' is the
  causal estimate from the measured speeds, q''_cmd the largest commanded acceleration of the last few
  periods: the estimate lags a move's start by periods while the torques already change (the rigid
  body's part of the residual acts through the momentum at once, the learned part through the lagging
  estimate).  The command is the arm's intent, so an impact, which changes the measured motion but
  not the command, does not widen its own threshold;
* g1: the joint torques of 1 kg of payload at the tool's centre of mass (an unknown payload error
  moves the gravity torque by this per kg, relative to where the residual was last zeroed); J, a: that
  point's Jacobian and commanded acceleration (the same error's inertial load, which showed as a 1.06x
  joint-5 alarm while braking with +0.45 kg);
* floor_j: what is left (quantisation, the servo's transients) and the configured margin.

In free motion a joint over its threshold for `confirm_periods` periods in a row is a collision, and so are
the `combined_joints` (1-3: the ones a tool force loads through the arm's lever) when the root-sum-square of
their ratios |r_j| / thr_j is over 1 as long: a contact pushes them all at once, which the model's errors seldom
do, so three joints at 0.6-0.8 of their thresholds together count.  In a
state where the task expects contact the joint residual carries the task's own force, so there the
fast residual is mapped to a tool wrench and its force checked against the task's contact limit: a
short impact the task's filtered wrench would hide still counts.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from cell.collision.config import DetectorSettings
from cell.model.dynamics.learned import LearnedModel
from cell.model.dynamics.uncertainty import Coverage
from cell.model.robot import RobotModel
from cell.sensing.model_step import ModelStep
from cell.sensing.observer import MomentumObserver
from cell.sensing.wrench_map import JacobianMap
from drivers.errors import SafetyStopError
from drivers.interfaces import ArmState

GRAVITY = np.array([0.0, 0.0, 9.81])


@dataclass
class Detection:
    """One collision: when, where and how clearly."""

    t: float  # s since the loop started
    cycle: int
    state: str  # the task's state
    mode: str  # "free" (joint thresholds) or "contact" (tool force against the contact limit)
    joints: list[int]  # 1-based joints over their thresholds (free mode)
    ratio: float  # largest |r_j| / thr_j or the combined joints' root-sum-square (free), |F| / limit (contact)
    residual_nm: list[float]
    threshold_nm: list[float]
    force_n: list[float]  # the fast tool force at detection, tool frame (as the F/T sensor; tool on environment)
    together: bool = False  # free mode: no joint alone was over, the combined joints' root-sum-square was

    def describe(self) -> str:
        if self.mode == "free":
            js = ", ".join(str(j) for j in self.joints)
            what = "together near their thresholds" if self.together else "over threshold"
            return (f"collision in state {self.state} at t={self.t:.3f} s: joint{'s' if len(self.joints) > 1 else ''} "
                    f"{js} {what} ({self.ratio:.1f}x)")
        return (f"collision in state {self.state} at t={self.t:.3f} s: fast tool force "
                f"{np.linalg.norm(self.force_n):.0f} N over the contact limit ({self.ratio:.1f}x)")

    def to_dict(self) -> dict[str, Any]:
        return {"t": round(self.t, 4), "cycle": self.cycle, "state": self.state, "mode": self.mode,
                "joints": list(self.joints), "ratio": round(self.ratio, 3), "together": self.together,
                "residual_nm": [round(v, 3) for v in self.residual_nm],
                "threshold_nm": [round(v, 3) for v in self.threshold_nm],
                "force_n": [round(v, 2) for v in self.force_n]}


def _beyond_coverage(coverage: Coverage | None, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Per joint: the fastest trained speed (rad/s, the coverage grid's |q'| reach) and the physics
    part's level in its speed bin; None without coverage."""
    if coverage is None:
        return None
    v_max = np.full(n, np.inf)
    js = coverage.joints
    lo, hi = coverage.lo[:, 1], coverage.lo[:, 1] + coverage.bins * coverage.width[:, 1]
    v_max[js] = np.maximum(np.abs(lo), np.abs(hi))
    finite = np.where(np.isfinite(v_max), v_max, 0.0)
    # Trust 0 with blending: the physics part's level in that speed bin.
    edge = dataclasses.replace(coverage, blend=True).sigma(finite[None, :], np.zeros((1, n)))[0]
    return v_max, edge


def _window_max(window: Iterable[np.ndarray]) -> np.ndarray:
    """The element-wise largest of a window's arrays (pairwise: cheaper than stacking them every period)."""
    return functools.reduce(np.maximum, window)


class CollisionDetector:
    """Fast residual, thresholds and the tool force they imply, one control period at a time."""

    # Over a wire: the unseen torque between two samples is bounded by the range of the last this many, ...
    TORQUE_WINDOW = 4
    # ... and this share of it, integrated over the time off the period, is the residual's own error.
    WIRE_ALLOWANCE = 1.0
    # A joint that has travelled this far since the residual was zeroed has moved (a held joint pushed by hand
    # yields far less): its friction may have stuck elsewhere in its band.
    MOVED_RAD = 0.05

    def __init__(self, model: LearnedModel, robot: RobotModel, dt: float, settings: DetectorSettings,
                 wrench_point: np.ndarray, over_wire: bool = False, exact_steps: bool | None = None,
                 model_step: ModelStep | None = None) -> None:
        n = robot.n
        if len(settings.floor_nm) != n:
            raise ValueError(f"collision.detector.floor_nm needs {n} values (one per joint), "
                             f"got {len(settings.floor_nm)}")
        if any(j > n for j in settings.combined_joints):
            raise ValueError(f"collision.detector.combined_joints names joints 1..{n}, got {settings.combined_joints}")
        self.settings = settings
        self.dt = dt
        self.n = n
        self._combined = np.asarray(settings.combined_joints, np.int64) - 1
        gain = min(settings.observer_gain, settings.wire_observer_gain) if over_wire else settings.observer_gain
        self.gain = gain
        self.over_wire = over_wire
        # Over a wire a late read spans several controller cycles and the momentum moved over all of
        # them: the observer integrates over the time between the samples as it is, never clipped.
        self.observer = MomentumObserver(model, dt, gain,
                                         max(1, int(round(settings.rebias_window_s / dt))), trapezoid=True,
                                         exact_steps=over_wire if exact_steps is None else exact_steps,
                                         step=model_step)
        self.coverage = model.coverage
        # The levels blended by coverage alone (the sticking regime has its own term below).
        self._levels = (dataclasses.replace(model.coverage, blend=True, stick_speed=0.0)
                        if model.coverage is not None else None)
        self.floor = np.asarray(settings.floor_nm, float)
        # Commanded slower than this a joint is held (rad/s): the speed over which the model's friction takes the
        # motion's direction (its smoothed sign's width), or a tenth of stick_speed.
        eps = float(getattr(model.physics.params, "sign_eps", 0.0) or 0.0) if model.physics is not None else 0.0
        self._held_speed = eps if eps > 0 else 0.1 * max(settings.stick_speed, 1e-3)
        self._beyond = _beyond_coverage(model.coverage, n)
        self.margin = settings.wire_margin if over_wire else 1.0
        # Over a wire a single repeated or skipped read can swing the residual for one period.
        self.confirm = max(settings.confirm_periods, 2) if over_wire else settings.confirm_periods
        self.wrench_map = JacobianMap(robot, np.asarray(wrench_point, float))
        # 1 kg at the tool's centre of mass: its gravity torques are what a payload error adds per kg.
        self._pm = robot.model.copy()
        tool = robot.tool
        com = tool.com if tool.com is not None else np.asarray(tool.tcp_offset, float) / 2
        flange = self._pm.frames[robot.flange_id]
        self._com_id = self._pm.addFrame(pin.Frame("payload_com", flange.parentJoint, robot.flange_id,
                                                   flange.placement * pin.SE3(np.eye(3), np.asarray(com, float)),
                                                   pin.FrameType.OP_FRAME))
        self._pd = self._pm.createData()
        self.reset()

    def reset(self) -> None:
        self.observer.reset()
        self._g_zero = np.zeros(self.n)
        self._zeroed = False
        self._over = np.zeros(self.n, np.int64)
        self._combined_over = 0
        self.together = False  # the last free check's detection was the combined joints' alone
        self._force_over = 0
        self._travel = np.zeros(self.n)  # |q'| integrated since the residual was last zeroed [rad]
        self.residual = np.zeros(self.n)
        self.threshold = np.full(self.n, np.inf)
        self.force = np.zeros(3)
        self._q = np.zeros(self.n)
        self._last: ArmState | None = None
        self._cmds: collections.deque[np.ndarray] = collections.deque(maxlen=3)
        self._cmd_inertial: collections.deque[np.ndarray] = collections.deque(
            maxlen=max(1, self.settings.command_window_periods))
        self._cmd_payload: collections.deque[np.ndarray] = collections.deque(
            maxlen=max(1, self.settings.command_window_periods))
        self._cmd_speed: collections.deque[np.ndarray] = collections.deque(  # |commanded joint speeds| [rad/s]
            maxlen=max(1, self.settings.command_window_periods))
        self._cmd_v = np.zeros(self.n)  # the latest commanded joint speeds [rad/s]
        self._meas_inertial: collections.deque[np.ndarray] = collections.deque(
            [np.zeros(self.n)], maxlen=max(1, self.settings.command_window_periods))
        # Over a wire: the residual's error from the time between samples not being one period, and the
        # measured inertial torque it scales with (held over the same window as the commanded one).
        self.jitter = np.zeros(self.n)
        self._step_inertial: collections.deque[np.ndarray] = collections.deque(
            maxlen=max(1, self.settings.command_window_periods))
        self._torques: collections.deque[np.ndarray] = collections.deque(maxlen=self.TORQUE_WINDOW)
        self.step = self.dt  # the time between the last two samples used [s]
        self.late = False  # the last sample came more than half a period late (a missed controller cycle)
        self.held = False  # the checks hold their counts on this sample (a repeat or a late one)
        self.repeats = 0
        self.late_samples = 0

    def rebias(self) -> None:
        """Zero the residual here (arm at rest, no contact): the payload term then counts from this pose."""
        self.observer.rebias()
        self._g_zero = self._payload_gravity(self._q)
        self._zeroed = True
        self._travel = np.zeros(self.n)

    def _payload_gravity(self, q: np.ndarray) -> np.ndarray:
        J = pin.computeFrameJacobian(self._pm, self._pd, q, self._com_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        return np.asarray(J[:3].T @ GRAVITY)

    def _payload_inertial(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Per kg at the tool's centre of mass: sum_i |J_ij| |a_i|, a its linear acceleration (q, q', q'')."""
        pin.forwardKinematics(self._pm, self._pd, q, v, a)
        pin.computeJointJacobians(self._pm, self._pd)  # on the placements just computed: one kinematics pass
        acc = pin.getFrameClassicalAcceleration(self._pm, self._pd, self._com_id,
                                                pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).linear
        J = pin.getFrameJacobian(self._pm, self._pd, self._com_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        return np.asarray(np.abs(J[:3]).T @ np.abs(acc))

    def thresholds(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        # (Array methods rather than numpy's dispatching functions, |q'| once: this runs every control period.)
        s = self.settings
        thr = self.floor.copy()
        speed = np.abs(dq)
        if self.coverage is not None and self._levels is not None:
            # Where the training data was sparse the hybrid's level does not hold: the physics part's does.
            w = self.coverage.weight_one(q, dq, ddq, min_count=s.coverage_min_count, stick=False)
            factor: float | np.ndarray = s.sigma_factor
            if s.rest_sigma_factor is not None and s.stick_speed > 0:
                # At rest the model's level is mostly the stuck friction's spread, which the zeroing at rest
                # removed and the static band term bounds: counted once there, not sigma_factor times.
                moving = np.minimum(1.0, speed / s.stick_speed)
                factor = s.rest_sigma_factor + (s.sigma_factor - s.rest_sigma_factor) * moving
            level = self._levels.sigma(dq, w)
            arm = self._levels.sigma_arm(dq, w)
            if arm is not None:
                # A slow joint of a fast arm errs as the arm's fastest joint makes it (coupling, velocity products).
                level = np.maximum(level, arm)
            thr += factor * level
        if self._beyond is not None:
            # Beyond the joint speeds the model was trained at its error is unknown: the physics part's
            # level at the trained edge, grown in proportion to the speed (a viscous-like error).
            # Any joint beyond its reach takes every joint out of the model's experience (the coupling and
            # velocity-product torques of a fast joint load the others), so the largest excess counts.
            v_max, edge = self._beyond
            thr += s.sigma_factor * edge * max(0.0, float((speed / v_max).max()) - 1.0)
        if s.stick_speed > 0 and self.coverage is not None:
            # A joint zeroed at rest held its friction somewhere in its band; one that has moved since may stick
            # anywhere in it again, as far as the other edge (a hard stop leaves it loaded there): twice the band.
            band = self.coverage.static_band * (1.0 + (self._travel > self.MOVED_RAD))
            held = np.maximum(0.0, 1.0 - speed / s.stick_speed)
            if self._cmd_speed:
                # A joint its command holds (still over the window: slower than the speed at which the model's
                # friction takes its direction) is held by its servo however the other joints' accelerations drag
                # it: it creeps (under stick_speed), its friction still anywhere in its band.  Only the command says
                # so: a joint an impact stops while its command moves on, however slowly, gains nothing; nor does a
                # held joint an impact jolts into sliding (from twice stick_speed on).
                by_cmd = (np.maximum(0.0, 1.0 - _window_max(self._cmd_speed) / self._held_speed)
                          * np.minimum(np.maximum(2.0 - speed / s.stick_speed, 0.0), 1.0))
                held = np.maximum(held, by_cmd)
                # The model's friction follows the sign of the creep speed (a full Coulomb level from a few mrad/s
                # on), which a held joint's friction need not follow: its error there is the band plus what the
                # model predicts beyond its friction at the commanded speed (none for a joint sliding as commanded).
                if by_cmd.any():  # (two loss evaluations: only when some joint is held)
                    thr += np.abs(self._creep_friction(q, dq, self._cmd_v)) * by_cmd
            thr += band * held
        if s.inertia_uncertainty > 0:
            # Without a command stream (a detector fed states only): the measured motion's, held over the same
            # window (the estimate swings through zero while a hard stop rings).
            inertial = _window_max(self._cmd_inertial if self._cmd_inertial else self._meas_inertial)
            thr += s.inertia_uncertainty * inertial
        if s.payload_uncertainty_kg > 0:
            g = self._payload_gravity(q)
            thr += s.payload_uncertainty_kg * np.abs(g - self._g_zero if self._zeroed else g)
            if self._cmd_payload:
                thr += s.payload_uncertainty_kg * _window_max(self._cmd_payload)
        return thr

    def _creep_friction(self, q: np.ndarray, dq: np.ndarray, v_ref: np.ndarray) -> np.ndarray:
        """The model's joint losses at speed `dq` beyond those at `v_ref` (N·m, both at rest acceleration)."""
        p2 = self.observer.p2
        zero = np.zeros(self.n)
        return np.asarray(p2.losses(q, dq, zero) - p2.losses(q, np.asarray(v_ref, float), zero))

    def update(self, state: ArmState) -> np.ndarray:
        """One period: the residual (N·m), its thresholds and the fast tool force; returns the residual."""
        q = np.asarray(state.q, float)
        if not (np.isfinite(q).all() and np.isfinite(state.dq).all() and np.isfinite(state.tau).all()):
            raise SafetyStopError("collision detector: non-finite joint state (q, q' or torque): cannot check "
                                  "for collisions")
        # Over a wire the host may read the controller's previous sample again (no new cycle yet): a
        # repeat carries no new momentum, and integrating its torque over another period would.  The
        # robot's counter says so even when a read tore between two cycles (joints from the newer one).
        last = self._last
        if last is not None and (
                ((q == last.q).all() and (np.asarray(state.tau) == last.tau).all())
                or (self.over_wire and (state.seq == last.seq != 0 or state.t <= last.t))):
            self.repeats += 1
            self.held = True  # the same sample checked again would count as another period over
            return self.residual
        self._last = state
        self._q = q
        self.residual = self.observer.update(state)
        self._travel += np.abs(np.asarray(state.dq, float)) * self.step
        self._meas_inertial.append(np.abs(self.observer.inertial))
        self.threshold = self.margin * self.thresholds(q, np.asarray(state.dq, float), self.observer.acceleration)
        r = self.residual
        if self.over_wire and last is not None:
            self._wire_allowance(state, last)
            self.threshold = self.threshold + self.jitter
            # The tool force from what the residual holds beyond the wire's own error: a late read's
            # aliasing must not read as a force.
            r = np.sign(r) * np.maximum(0.0, np.abs(r) - self.jitter)
        self.held = self.late
        self.force = self.wrench_map.map(q, r).wrench[:3]
        return self.residual

    def _wire_allowance(self, state: ArmState, last: ArmState) -> None:
        """Widen the thresholds by the residual's error from an irregular step (over a wire).

        The observer integrates the measured torque between two samples by the trapezoidal rule.  Over one
        controller period that is what the model's levels were measured with; over a longer step the
        torque changes unseen in between (stop-and-go while the host is late: the controller runs out of
        targets, then catches up), and over a shorter one the time stamp's own error weighs more.  The
        unseen torque is bounded by what the samples around it span: the measured torque's range over
        the last few samples, or the inertial torque the step's own speed change implies.  The integral
        of that bound over the time off the period enters the residual times the gain, then decays with it."""
        h = float(state.t - last.t)
        self.step = h
        self.late = h > 1.5 * self.dt
        self.late_samples += int(self.late)
        a = (np.asarray(state.dq, float) - np.asarray(last.dq, float)) / h
        self._torques.append(np.asarray(state.tau, float))
        taus = np.asarray(self._torques)
        # Each entry of M may carry the unseen change: sum_k |M_jk| |a_k|, as the commanded term.
        self._step_inertial.append(np.maximum(np.abs(self.observer.mass) @ np.abs(a), np.ptp(taus, axis=0)))
        unseen = np.max(np.asarray(self._step_inertial), axis=0)
        self.jitter = (self.jitter * float(np.exp(-self.gain * h))
                       + self.WIRE_ALLOWANCE * self.gain * abs(h - self.dt) * unseen)

    def commanded(self, q_cmd: np.ndarray) -> None:
        """The target just sent (rad): its second difference is the commanded acceleration."""
        if self.settings.command_window_periods == 0:
            return
        self._cmds.append(np.array(q_cmd, float))
        if len(self._cmds) >= 2:
            self._cmd_v = (self._cmds[-1] - self._cmds[-2]) / self.dt
            self._cmd_speed.append(np.abs(self._cmd_v))
        if len(self._cmds) == 3:
            a = (self._cmds[2] - 2.0 * self._cmds[1] + self._cmds[0]) / self.dt**2
            # Each entry of M may be off by its share: the bound is sum_k |M_jk| |a_k|, not |(M a)_j|
            # (a wrist joint barely commanded still carries the errors of the base joints' coupling).
            self._cmd_inertial.append(np.abs(self.observer.mass) @ np.abs(a))
            if self.settings.payload_uncertainty_kg > 0:
                self._cmd_payload.append(self._payload_inertial(self._cmds[2], (self._cmds[2] - self._cmds[1])
                                                                / self.dt, a))

    def check_free(self, ratios: np.ndarray | None = None) -> np.ndarray:
        """Joints (0-based) over their thresholds for `confirm_periods` periods in a row, or else the combined joints
        carrying a combined check over 1 as long (`together`); `ratios`: this period's `ratios()` where the caller
        has them.  A late sample or a repeated one (over a wire) holds the count: it neither confirms a collision
        nor clears one building up."""
        if self.held:
            return np.zeros(0, np.int64)
        r = self.ratios() if ratios is None else ratios
        self._over = np.where(r > 1.0, self._over + 1, 0)
        self._combined_over = self._combined_over + 1 if self.combined_ratio(r) > 1.0 else 0
        self._force_over = 0
        hit = np.flatnonzero(self._over >= self.confirm)
        self.together = hit.size == 0 and self._combined_over >= self.confirm
        if self.together:
            # The joints carrying the combined check: each at least the share it would hold were all equal.
            c = self._combined
            hit = np.sort(c[r[c] >= 1.0 / np.sqrt(c.size)])
        return hit

    def check_contact(self, limit_n: float) -> bool:
        """Whether the fast tool force has been over `limit_n` for `confirm_periods` periods in a row.  A
        late or repeated sample (over a wire) holds the count, as in free states."""
        if self.held:
            return False
        self._over[:] = 0
        self._force_over = self._force_over + 1 if float(np.linalg.norm(self.force)) > limit_n else 0
        return self._force_over >= self.confirm

    def ratios(self) -> np.ndarray:
        """Per joint: |r_j| / thr_j."""
        return np.abs(self.residual) / self.threshold

    def combined_ratio(self, ratios: np.ndarray | None = None) -> float:
        """The combined joints' root-sum-square of their ratios (0 with none)."""
        r = self.ratios() if ratios is None else ratios
        return float(np.sqrt(np.sum(r[self._combined] ** 2)))

    def ratio(self, ratios: np.ndarray | None = None) -> float:
        """How near the free check is to a detection (1 = detection): the largest joint ratio or the combined one."""
        r = self.ratios() if ratios is None else ratios
        return max(float(r.max()), self.combined_ratio(r))
