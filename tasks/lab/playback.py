"""Playback for data collection: move to the start, play a joint trajectory at the control rate, settle, finish."""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from cell.control.loop import Command, Observation
from cell.control.trajectory import JointMove
from cell.data.excitation.motion import Motion
from cell.model.robot import RobotModel
from tasks.base import MachineTask, Trigger

log = logging.getLogger(__name__)


class PlaybackState(enum.Enum):
    MOVE_TO_START = "move_to_start"
    PLAY = "play"
    SETTLE = "settle"
    DONE = "done"
    FAILED = "failed"


class PlaybackTask(MachineTask):
    """Plays a `Motion` sample by sample; every logged row carries the `traj` and `segment` it belongs to
    (-1 while moving to the start and settling), so the step log is a dataset as it is."""

    name = "collect"
    arrived: Trigger
    played_all: Trigger
    settled: Trigger
    state_log_level = logging.DEBUG

    def __init__(
        self,
        plan: Motion,
        robot: RobotModel,
        dt: float,
        move_speed_fraction: float = 0.2,
        settle_s: float = 0.3,
        progress: Callable[[int], None] | None = None,
    ) -> None:
        if abs(plan.dt - dt) > 1e-12:
            raise ValueError(f"plan sampled at {plan.dt} s but the loop runs at {dt} s")
        super().__init__(PlaybackState.MOVE_TO_START, [
            ("arrived", PlaybackState.MOVE_TO_START, PlaybackState.PLAY),
            ("played_all", PlaybackState.PLAY, PlaybackState.SETTLE),
            ("settled", PlaybackState.SETTLE, PlaybackState.DONE),
        ])
        self.plan = plan
        self.robot = robot
        self.dt = dt
        self.speed = robot.limits.velocity * move_speed_fraction
        self.settle_cycles = max(1, int(round(settle_s / dt)))
        self.progress = progress
        self.q = np.vstack([s.q for s in plan.segments])
        self.traj = np.concatenate([np.full(len(s.q), s.traj, float) for s in plan.segments])
        self.segment = np.concatenate([np.full(len(s.q), s.segment, float) for s in plan.segments])
        self.move: JointMove | None = None
        self.k = 0
        self.played = 0

    def abort(self, reason: str) -> None:
        if not self.done:
            log.warning("collect: %s after %d of %d samples", reason, self.played, len(self.q))
        super().abort(reason)

    def step(self, obs: Observation) -> Command:
        label = (-1.0, -1.0)
        if self.state is PlaybackState.MOVE_TO_START:
            if self.move is None:
                self.move = JointMove(obs.q_cmd, self.q[0], self.speed)
            q = self.move.at(self.t_state + self.dt)
            if self.t_state + self.dt >= self.move.duration:
                self.arrived()
            else:
                self.t_state += self.dt
        elif self.state is PlaybackState.PLAY:
            q = self.q[self.k]
            label = (float(self.traj[self.k]), float(self.segment[self.k]))
            self.k += 1
            self.played = self.k
            if self.progress is not None:
                self.progress(1)
            if self.k >= len(self.q):
                self.played_all()
        elif self.state is PlaybackState.SETTLE:
            q = self.q[-1]
            self.t_state += self.dt
            if self.t_state >= self.settle_cycles * self.dt:
                self.settled()
        else:
            q = obs.q_cmd
        return Command(q=np.asarray(q, float), log={"traj": label[0], "segment": label[1]})

    def summary(self) -> dict[str, Any]:
        return {
            "task": self.name, "outcome": self.outcome, "reason": self.reason, "final_state": self.state.value,
            "plan_samples": int(len(self.q)), "samples_played": int(self.played),
            "plan_duration_s": float(len(self.q) * self.dt),
        }
