"""Wiping a table at a constant normal force: approach, detect contact, regulate force along a path, retract."""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cell.config import WORKSPACE_REACH_M, check_task_motion
from cell.control.impedance import DiscreteImpedance, ImpedanceParams
from cell.control.loop import Command, Observation
from cell.control.trajectory import JointMove, PathProfile, tool_down_pose
from cell.model.robot import RobotModel
from drivers.configio import load_dataclass, require
from tasks.base import MachineTask, Trigger

log = logging.getLogger(__name__)


class WipeState(enum.Enum):
    MOVE_TO_START = "move_to_start"
    TARE = "tare"
    APPROACH = "approach"
    RAMP = "ramp"
    SETTLE = "settle"
    WIPE = "wipe"
    RETRACT = "retract"
    DONE = "done"
    FAILED = "failed"


@dataclass
class WipeConfig:
    force_setpoint_n: float = 60.0
    contact_threshold_n: float = 5.0
    approach_height_m: float = 0.03  # pre-contact TCP height above the table
    approach_speed_mps: float = 0.01
    max_approach_m: float = 0.06  # no contact after this much travel below the pre-contact pose: fail
    ramp_time_s: float = 1.0  # setpoint ramp from first contact to the full force
    settle_tolerance_n: float = 3.0
    settle_time_s: float = 0.5
    max_settle_s: float = 5.0
    path: list[list[float]] = field(
        default_factory=lambda: [[0.40, -0.25], [0.40, 0.0], [0.50, 0.0], [0.50, -0.25]]
    )  # (x, y) waypoints on the table [m], base frame
    speed_mps: float = 0.06
    accel_mps2: float = 0.15
    retract_height_m: float = 0.05
    retract_speed_mps: float = 0.05
    move_speed_fraction: float = 0.15  # of the joint speed limits, for the move to the start pose
    tare_time_s: float = 0.3
    max_force_n: float = 110.0  # task-level abort (the cell's safety limit is separate)
    lost_contact_s: float = 0.25
    max_duration_s: float = 90.0
    impedance: ImpedanceParams = field(default_factory=ImpedanceParams)

    def validate(self, where: str) -> None:
        require(0 < self.force_setpoint_n < self.max_force_n, f"{where}.force_setpoint_n",
                f"must lie in (0, max_force_n={self.max_force_n}) N, got {self.force_setpoint_n}")
        require(0 < self.contact_threshold_n < self.force_setpoint_n, f"{where}.contact_threshold_n",
                "must lie between 0 and the force setpoint")
        require(len(self.path) >= 2, f"{where}.path", "needs at least 2 (x, y) waypoints")
        for i, p in enumerate(self.path):
            require(len(p) == 2, f"{where}.path[{i}]", f"must be (x, y), got {p}")
        for name in ("approach_height_m", "approach_speed_mps", "max_approach_m", "ramp_time_s",
                     "settle_tolerance_n", "settle_time_s", "max_settle_s", "speed_mps", "accel_mps2",
                     "retract_height_m", "retract_speed_mps", "move_speed_fraction", "tare_time_s",
                     "lost_contact_s", "max_duration_s"):
            require(getattr(self, name) > 0, f"{where}.{name}", f"must be > 0, got {getattr(self, name)}")
        require(self.move_speed_fraction <= 1, f"{where}.move_speed_fraction", "must be <= 1")
        check_task_motion(self, where)
        for i, p in enumerate(self.path):
            require(all(abs(v) <= WORKSPACE_REACH_M for v in p), f"{where}.path[{i}]",
                    f"must lie within +-{WORKSPACE_REACH_M:g} m of the base, got {p}")


def load_wipe_config(raw: dict[str, Any] | None, where: str) -> WipeConfig:
    return load_dataclass(WipeConfig, raw or {}, where)


class WipeTask(MachineTask):
    """State machine (transitions) for force-controlled wiping; the force comes from the loop's source."""

    name = "wipe"
    # The force is regulated, and scored, while wiping; the table is first touched in the approach.
    working_states = (WipeState.WIPE.value,)
    touch_states = (WipeState.APPROACH.value,)
    arrived: Trigger
    tared: Trigger
    touched: Trigger
    ramped: Trigger
    settled: Trigger
    finished: Trigger
    retracted: Trigger

    def __init__(self, cfg: WipeConfig, robot: RobotModel, table_height: float, dt: float, q_home: np.ndarray) -> None:
        self.cfg = cfg
        self.robot = robot
        self.dt = dt
        self.table_height = table_height
        super().__init__(WipeState.MOVE_TO_START, [
            ("arrived", WipeState.MOVE_TO_START, WipeState.TARE),
            ("tared", WipeState.TARE, WipeState.APPROACH),
            ("touched", WipeState.APPROACH, WipeState.RAMP),
            ("ramped", WipeState.RAMP, WipeState.SETTLE),
            ("settled", WipeState.SETTLE, WipeState.WIPE),
            ("finished", WipeState.WIPE, WipeState.RETRACT),
            ("retracted", WipeState.RETRACT, WipeState.DONE),
        ])

        x0, y0 = cfg.path[0]
        self.pre_contact = tool_down_pose(np.array([x0, y0, table_height + cfg.approach_height_m]))
        q_start, ok = robot.ik(self.pre_contact, q_home)
        if not ok:
            raise ValueError(f"wipe start pose {self.pre_contact.translation.round(3).tolist()} is not reachable")
        self.q_start = q_start
        self.move: JointMove | None = None
        self.path = PathProfile(np.asarray(cfg.path, float), cfg.speed_mps, cfg.accel_mps2)
        self.law = DiscreteImpedance(cfg.impedance, dt)
        self.ref = self.pre_contact.copy()
        self._t_in_band = 0.0
        self._t_lost = 0.0
        self._contact_z = 0.0
        self._fz0 = 0.0
        self.errors: list[float] = []
        self.wipe_forces: list[float] = []
        self.missing_samples = 0  # wiping cycles with no valid force reading
        self.peak_force = 0.0

    def step(self, obs: Observation) -> Command:
        fz = float(obs.wrench.force[2])
        if np.isfinite(fz):
            self.peak_force = max(self.peak_force, fz)
        handler = getattr(self, f"_{self.state.value}")
        q, setpoint, rebias = handler(obs, fz)
        self.t_state += self.dt
        return Command(
            q=q,
            log={"fz_setpoint": setpoint, "ref_x": float(self.ref.translation[0]),
                 "ref_y": float(self.ref.translation[1]), "ref_z": float(self.ref.translation[2])},
            rebias_force=rebias,
        )

    # ------------------------------------------------------------------------- states
    def _move_to_start(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        if self.move is None:
            speed = self.robot.limits.velocity * self.cfg.move_speed_fraction
            self.move = JointMove(obs.q_cmd, self.q_start, speed)
        q = self.move.at(self.t_state)
        if self.t_state >= self.move.duration:
            self.arrived()
        return q, 0.0, False

    def _tare(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        # Hold still so the arm settles, then re-zero the force source in free space.
        if self.t_state + self.dt >= self.cfg.tare_time_s:
            self.tared()
            return self.q_start, 0.0, True
        return self.q_start, 0.0, False

    def _approach(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        if np.isfinite(fz) and fz > self.cfg.contact_threshold_n:
            self._contact_z = float(self.ref.translation[2])
            self._fz0 = fz
            self.law.reset()
            self.touched()
            return self._track(obs), self.cfg.contact_threshold_n, False
        self.ref.translation[2] -= self.cfg.approach_speed_mps * self.dt
        if self.pre_contact.translation[2] - self.ref.translation[2] > self.cfg.max_approach_m:
            self.fail_because(f"no contact within {self.cfg.max_approach_m * 1000:.0f} mm of approach")
        return self._track(obs), 0.0, False

    def _ramp(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        a = min(1.0, self.t_state / self.cfg.ramp_time_s)
        setpoint = self._fz0 + a * (self.cfg.force_setpoint_n - self._fz0)
        self._regulate(fz, setpoint)
        if a >= 1.0:
            self._t_in_band = 0.0
            self.ramped()
        return self._track(obs), setpoint, False

    def _settle(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        sp = self.cfg.force_setpoint_n
        self._regulate(fz, sp)
        if np.isfinite(fz):  # a missing reading neither settles nor unsettles the force
            self._t_in_band = self._t_in_band + self.dt if abs(fz - sp) < self.cfg.settle_tolerance_n else 0.0
        if self._t_in_band >= self.cfg.settle_time_s:
            self.settled()
        elif self.t_state > self.cfg.max_settle_s:
            self.fail_because(f"force did not settle within {self.cfg.max_settle_s:.1f} s (last {fz:.1f} N)")
        return self._track(obs), sp, False

    def _wipe(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        sp = self.cfg.force_setpoint_n
        if np.isfinite(fz):
            self.errors.append(fz - sp)
            self.wipe_forces.append(fz)
        else:  # a missing reading (the force source timed out) is no error sample
            self.missing_samples += 1
        xy, finished = self.path.at(self.t_state)
        self.ref.translation[0], self.ref.translation[1] = xy
        self._regulate(fz, sp)
        if finished:
            self._contact_z = float(self.ref.translation[2])
            self.finished()
        return self._track(obs), sp, False

    def _retract(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        self.ref.translation[2] += self.cfg.retract_speed_mps * self.dt
        if self.ref.translation[2] - self._contact_z >= self.cfg.retract_height_m:
            self.retracted()
        return self._track(obs), 0.0, False

    def _done(self, obs: Observation, fz: float) -> tuple[np.ndarray, float, bool]:
        return obs.q_cmd, 0.0, False

    _failed = _done

    # ------------------------------------------------------------------------- helpers
    def _regulate(self, fz: float, setpoint: float) -> None:
        """One step of the discretised impedance law along the table normal."""
        if not np.isfinite(fz):
            return  # hold the reference on a missing reading; the safety monitor counts them
        if fz > self.cfg.max_force_n:
            self.fail_because(f"normal force {fz:.1f} N exceeded the task limit {self.cfg.max_force_n:.1f} N")
            return
        if self.state in (WipeState.SETTLE, WipeState.WIPE):
            self._t_lost = self._t_lost + self.dt if fz < self.cfg.contact_threshold_n else 0.0
            if self._t_lost >= self.cfg.lost_contact_s:
                self.fail_because(f"lost contact with the table for {self._t_lost:.2f} s")
                return
        dz = float(self.law.update(setpoint - fz)[0])
        self.ref.translation[2] -= dz  # positive error: press further (the tool points down)

    def _track(self, obs: Observation) -> np.ndarray:
        """Joint target for the TCP reference: a few damped Newton steps from the last command."""
        q, _ = self.robot.ik(self.ref, obs.q_cmd, iters=3, tol=1e-7)
        return q

    # ------------------------------------------------------------------------- results
    def summary(self) -> dict[str, Any]:
        e = np.asarray(self.errors)
        out: dict[str, Any] = {
            "task": self.name,
            "outcome": self.outcome,
            "reason": self.reason,
            "final_state": self.state.value,
            "force_setpoint_n": self.cfg.force_setpoint_n,
            "peak_force_n": self.peak_force,
            "wipe_samples": int(e.size),
            "missing_force_samples": self.missing_samples,
            "path_length_m": self.path.length,
        }
        if e.size:
            # The force source's own view (with the virtual sensor in the loop the runner adds the F/T sensor's).
            out.update(
                force_tracking_mae_n=float(np.mean(np.abs(e))),
                force_tracking_std_n=float(np.std(e)),
                force_tracking_max_abs_error_n=float(np.max(np.abs(e))),
                force_mean_n=float(np.mean(self.wipe_forces)),
            )
        return out
