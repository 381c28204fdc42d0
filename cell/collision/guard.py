"""The control loop's contact safety: runs the collision detector every period and reacts as the task's
state says (protective stop, retract along the contact direction, comply, or only record).

A reaction that moves (retract, comply) first stops the arm (the controller's own stop brakes at once, where a
streamed target reaches the servo a period later, while the targets already sent still lead into the contact),
then, at rest, re-arms and moves from the measured pose, not from the last target: a position servo pressed
against an obstacle has wound up a lag toward it, and resuming from the target would push that lag into the
contact.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from cell.collision.config import CollisionConfig
from cell.collision.detector import CollisionDetector, Detection
from cell.model.robot import RobotModel
from cell.sensing.model_step import ModelStep
from drivers.errors import SafetyStopError
from drivers.interfaces import ArmState

log = logging.getLogger(__name__)


class CollisionStop(SafetyStopError):
    """A collision whose reaction is a protective stop."""

    def __init__(self, detection: Detection) -> None:
        super().__init__(f"{detection.describe()}: protective stop")
        self.detection = detection


class Reaction:
    """A brake, then a short motion away from a contact, then a stop: one joint target per period.

    With `stop_first` the loop stops the arm at the detection and asks `braking` every period; once the
    measured joints are at rest (or after MAX_BRAKE_PERIODS) the reaction starts from the measured pose and
    the loop re-arms.  The direction is fixed at the detection (away from where the tool pushed).  Retract
    runs along it at a set speed for a set distance; comply runs along it as fast as the contact still pushes
    that way (the fast force low-passed, times an admittance), for a set time.  The speed changes at a
    bounded acceleration: a position servo fed jagged targets answers with large feedforward torques."""

    ACCEL = 1.0  # m/s^2
    FORCE_TIME_CONSTANT = 0.05  # s: the comply's force filter
    REST_SPEED = 0.02  # rad/s: every measured joint slower than this is at rest after the brake
    MAX_BRAKE_PERIODS = 12  # the brake is over after this many periods whatever the measured speeds

    def __init__(self, kind: str, robot: RobotModel, state: ArmState, direction: np.ndarray, speed: float,
                 distance: float | None, duration: float | None, dt: float, force_gain: float = 0.0,
                 stop_first: bool = False) -> None:
        self.kind = kind
        self.stop_first = stop_first
        self.braked = 0  # periods spent braking (stop_first)
        self.brake_done = not stop_first
        self.robot = robot
        self.dt = dt
        self.speed = speed
        self.distance = distance
        self.duration = duration
        self.force_gain = force_gain
        self.direction = np.asarray(direction, float)
        self.q = np.array(state.q, float)
        self.ref: pin.SE3 = robot.tcp_pose(self.q)
        self.travelled = 0.0
        self.t = 0.0
        self.v = 0.0
        self.push = 0.0  # filtered force along the yield direction [N]
        self.done = False

    def braking(self, state: ArmState) -> bool:
        """Whether the arm is still braking after the stop (nothing is sent then); when the brake ends, the
        motion starts from this measured pose."""
        if self.brake_done:
            return False
        self.braked += 1
        if self.braked < 2 or (np.max(np.abs(state.dq)) > self.REST_SPEED and self.braked < self.MAX_BRAKE_PERIODS):
            return True  # the first measured state after the stop still predates it (one period old)
        self.brake_done = True
        self.q = np.array(state.q, float)
        self.ref = self.robot.tcp_pose(self.q)
        return False

    def step(self, state: ArmState, force: np.ndarray) -> np.ndarray:
        """The next joint target (`force`: the fast tool force, cell convention)."""
        if self.kind == "comply":
            # The environment pushes the tool with -force: its component along the yield direction.
            along = max(0.0, float(-np.asarray(force, float) @ self.direction))
            a = self.dt / (self.FORCE_TIME_CONSTANT + self.dt)
            self.push += a * (along - self.push)
            want = min(self.speed, self.force_gain * self.push)
        else:
            want = self.speed
        if self.distance is not None:  # brake to arrive at the distance
            left = max(0.0, self.distance - self.travelled)
            want = min(want, float(np.sqrt(2.0 * self.ACCEL * left)))
        dv = self.ACCEL * self.dt
        self.v = float(np.clip(want, self.v - dv, self.v + dv))
        step = self.v * self.dt
        if self.distance is not None:
            step = min(step, max(0.0, self.distance - self.travelled))
        self.ref.translation = self.ref.translation + self.direction * step
        self.travelled += step
        self.t += self.dt
        q, _ = self.robot.ik(self.ref, self.q, iters=20, tol=1e-7)
        self.q = q
        if (self.distance is not None and self.travelled >= self.distance - 1e-6) or \
                (self.duration is not None and self.t >= self.duration):
            self.done = True
        return q

    def describe(self) -> str:
        brake = f"stopped ({self.braked * self.dt * 1e3:.0f} ms), " if self.stop_first else ""
        if self.kind == "retract":
            return (f"{brake}retracted {self.travelled * 1e3:.1f} mm along {np.round(self.direction, 2).tolist()}, "
                    "then stopped")
        return f"{brake}complied for {self.t:.2f} s ({self.travelled * 1e3:.1f} mm), then stopped"


@dataclass
class GuardSummary:
    enabled: bool
    detections: list[dict[str, Any]] = field(default_factory=list)
    reactions: list[str] = field(default_factory=list)
    max_free_ratio: float = 0.0  # largest residual / threshold seen in free states (1 = detection)
    max_free_at: dict[str, Any] = field(default_factory=dict)  # where it was: time, joint, speeds, residual
    max_fast_force_n: float = 0.0


class ContactGuard:
    """Detector + the task's reaction table; the loop asks it every period (see cell/control/loop.py)."""

    RELEASE = 0.5  # a recorded collision ends once the residual falls under this share of its threshold

    def __init__(self, detector: CollisionDetector, cfg: CollisionConfig, task: str, robot: RobotModel, dt: float,
                 contact_limit_n: float) -> None:
        self.detector = detector
        self.cfg = cfg
        self.task_cfg = cfg.for_task(task)
        self.contact_states = set(self.task_cfg.contact_states)
        self.contact_limit_n = (self.task_cfg.contact_limit_n if self.task_cfg.contact_limit_n is not None
                                else contact_limit_n)
        self.robot = robot
        self.dt = dt
        self.stats = GuardSummary(enabled=True)
        self.last: Detection | None = None
        self._latched = False  # a monitored collision is counted once, until the residual falls back

    def reaction_for(self, state: str) -> str:
        return self.task_cfg.reactions.get(state, self.cfg.reaction)

    def rebias(self) -> None:
        self.detector.rebias()

    def commanded(self, q_cmd: np.ndarray) -> None:
        """The target the loop just sent (the detector widens its inertial term by its acceleration)."""
        self.detector.commanded(q_cmd)

    def observe(self, state: ArmState, t: float, cycle: int, task_state: str) -> Detection | None:
        """Update the detector on this period's state; a new collision, or None."""
        d = self.detector
        d.update(state)
        fast = float(np.linalg.norm(d.force))
        if not d.held:  # the figures of what was checked (a late or repeated sample over a wire is not)
            self.stats.max_fast_force_n = max(self.stats.max_fast_force_n, fast)
        if task_state in self.contact_states:
            hit = d.check_contact(self.contact_limit_n)
            joints: list[int] = []
            ratio = fast / self.contact_limit_n
            mode = "contact"
        else:
            ratios = d.ratios()  # once a period: the checks and the figures below share them
            over = d.check_free(ratios)
            hit = over.size > 0
            ratio = d.ratio(ratios)
            if not d.held and ratio > self.stats.max_free_ratio:
                self.stats.max_free_ratio = ratio
                j = int(ratios.argmax())
                dq = np.abs(np.asarray(state.dq, float))
                # Where the margin is thinnest says which term of the threshold to look at (docs/collision.md);
                # `joint` is the largest single ratio's also when the combined check is the nearer.
                self.stats.max_free_at = {"t": round(t, 3), "state": task_state, "joint": j + 1,
                                          "joint_speed": round(float(dq[j]), 3), "arm_speed": round(float(dq.max()), 3),
                                          "residual_nm": round(float(d.residual[j]), 2),
                                          "threshold_nm": round(float(d.threshold[j]), 2),
                                          "combined": ratio > float(ratios.max())}
            joints = [int(j) + 1 for j in over]
            mode = "free"
        if not hit:
            if ratio < self.RELEASE:  # hysteresis: a residual hovering at its threshold is one collision
                self._latched = False
            return None
        if self._latched:
            return None
        self._latched = True
        det = Detection(t=t, cycle=cycle, state=task_state, mode=mode, joints=joints, ratio=ratio,
                        residual_nm=d.residual.tolist(), threshold_nm=d.threshold.tolist(), force_n=d.force.tolist(),
                        together=mode == "free" and d.together)
        self.last = det
        self.stats.detections.append(det.to_dict())
        return det

    def react(self, det: Detection, state: ArmState) -> Reaction | None:
        """The configured reaction to `det`: raises CollisionStop for a stop, a moving Reaction, or None
        (monitor: recorded and logged only)."""
        kind = self.reaction_for(det.state)
        self.stats.reactions.append(kind)
        if kind == "monitor":
            log.warning("%s (monitored, no reaction)", det.describe())
            return None
        if kind == "stop":
            raise CollisionStop(det)
        log.error("%s: %s", det.describe(), kind)
        f = self._world(state, np.asarray(det.force_n, float))
        norm = float(np.linalg.norm(f))
        if norm > 1e-6:
            direction = -f / norm  # away from where the tool pushes
        else:  # no readable tool force (a contact on a link): back along the motion
            v = self.robot.tcp_jacobian(np.asarray(state.q, float))[:3] @ np.asarray(state.dq, float)
            vn = float(np.linalg.norm(v))
            direction = -v / vn if vn > 1e-9 else np.array([0.0, 0.0, 1.0])
        c = self.cfg
        if kind == "retract":
            return Reaction("retract", self.robot, state, direction, c.retract_speed_mps, c.retract_m, None, self.dt,
                            stop_first=True)
        return Reaction("comply", self.robot, state, direction, c.retract_speed_mps, None, c.comply_time_s, self.dt,
                        force_gain=c.comply_admittance, stop_first=True)

    def _world(self, state: ArmState, force_tool: np.ndarray) -> np.ndarray:
        """A tool-frame force (the detector's, as the F/T sensor reports) in the base frame."""
        return np.asarray(self.robot.tcp_pose(np.asarray(state.q, float)).rotation @ force_tool)

    def reaction_force(self, state: ArmState) -> np.ndarray:
        """The fast tool force now, base frame (what a moving reaction yields to)."""
        return self._world(state, self.detector.force)

    def log_columns(self) -> dict[str, float]:
        d = self.detector
        return {"coll_ratio": d.ratio(), "fast_fx": float(d.force[0]), "fast_fy": float(d.force[1]),
                "fast_fz": float(d.force[2])}

    def summary(self) -> dict[str, Any]:
        s = self.stats
        d = self.detector
        out: dict[str, Any] = {"enabled": True, "detections": s.detections, "reactions": s.reactions,
                               "max_free_ratio": round(s.max_free_ratio, 3), "max_free_at": s.max_free_at,
                               "max_fast_force_n": round(s.max_fast_force_n, 1)}
        if d.over_wire:
            # How often the wire's timing held the checks (a late sample) or gave no new sample at all.
            out.update(late_samples=d.late_samples, repeated_samples=d.repeats)
        return out


def build_guard(cfg: CollisionConfig, model: Any, robot: RobotModel, dt: float, task: str, contact_limit_n: float,
                wrench_point: np.ndarray, over_wire: bool = False,
                model_step: ModelStep | None = None) -> ContactGuard | None:
    """The guard for `task` on the hybrid `model` (cell/sensing/virtual_sensor.py load_observer_model), or None
    when collision detection is switched off; `model_step`: the model evaluation it shares with the virtual
    sensor's observers (cell/sensing/model_step.py), on the same model."""
    if not cfg.enabled:
        return None
    detector = CollisionDetector(model, robot, dt, cfg.detector, wrench_point, over_wire, model_step=model_step)
    return ContactGuard(detector, cfg, task, robot, dt, contact_limit_n)
