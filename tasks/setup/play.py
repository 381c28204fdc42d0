"""Plays a timed joint trajectory on the cell and measures it: elapsed time to arrival and peak joint torques."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.control.loop import Command, Observation
from cell.control.trajectory import JointMove
from cell.planning.planner import TimedTrajectory
from tasks.base import MachineTask, Trigger


class PlayPhase(enum.Enum):
    MOVE_TO_START = "move_to_start"
    SETTLE = "settle"
    PLAY = "play"
    ARRIVE = "arrive"
    DONE = "done"
    FAILED = "failed"


@dataclass
class PlayConfig:
    move_speed_fraction: float = 0.3
    settle_s: float = 0.4
    arrive_tolerance_rad: float = np.radians(0.2)
    arrive_speed_rad_s: float = np.radians(2.0)
    max_arrive_s: float = 2.0


class PlayTask(MachineTask):
    """Move to the trajectory's start, settle, play it at the control rate, wait for arrival.

    Elapsed time runs from the first played sample to arrival (every joint within tolerance of the
    end and nearly at rest); peak torques are the measured joint torques over that interval.
    """

    name = "play"
    arrived_at_start: Trigger
    settled: Trigger
    played: Trigger
    arrived: Trigger

    def __init__(self, traj: TimedTrajectory, dt: float, speed_limits: np.ndarray, cfg: PlayConfig | None = None):
        self.traj = traj
        self.dt = dt
        self.cfg = cfg or PlayConfig()
        self.speed = speed_limits * self.cfg.move_speed_fraction
        super().__init__(PlayPhase.MOVE_TO_START, [
            ("arrived_at_start", PlayPhase.MOVE_TO_START, PlayPhase.SETTLE),
            ("settled", PlayPhase.SETTLE, PlayPhase.PLAY),
            ("played", PlayPhase.PLAY, PlayPhase.ARRIVE),
            ("arrived", PlayPhase.ARRIVE, PlayPhase.DONE),
        ])
        self._move: JointMove | None = None
        self._t_play = 0.0
        self.elapsed_s: float | None = None
        self.peak_tau: np.ndarray | None = None

    def step(self, obs: Observation) -> Command:
        q = getattr(self, f"_{self.state.value}")(obs)
        self.t_state += self.dt
        return Command(q=q, log={"plan_t": self._t_play})

    def _move_to_start(self, obs: Observation) -> np.ndarray:
        if self._move is None:
            self._move = JointMove(obs.q_cmd, self.traj.q[0], self.speed)
        q = self._move.at(self.t_state)  # before any transition: entering a state resets the clock
        if self.t_state >= self._move.duration:
            self.arrived_at_start()
        return q

    def _settle(self, obs: Observation) -> np.ndarray:
        if self.t_state >= self.cfg.settle_s:
            self.settled()
            self.peak_tau = np.abs(obs.state.tau)
        return self.traj.q[0]

    def _play(self, obs: Observation) -> np.ndarray:
        self._track_peak(obs)
        self._t_play += self.dt
        if self._t_play >= self.traj.duration:
            self.played()
        return self.traj.at(self._t_play)

    def _arrive(self, obs: Observation) -> np.ndarray:
        self._track_peak(obs)
        end = self.traj.q[-1]
        s = obs.state
        at_rest = np.max(np.abs(s.dq)) < self.cfg.arrive_speed_rad_s
        if np.max(np.abs(s.q - end)) < self.cfg.arrive_tolerance_rad and at_rest:
            # The measured state is one sample old at most; count arrival at this cycle.
            self.elapsed_s = self._t_play + self.t_state
            self.arrived()
        elif self.t_state > self.cfg.max_arrive_s:
            self.fail_because(f"did not arrive within {self.cfg.max_arrive_s:.1f} s of the trajectory's end")
        return end

    def _done(self, obs: Observation) -> np.ndarray:
        return obs.q_cmd

    _failed = _done

    def _track_peak(self, obs: Observation) -> None:
        assert self.peak_tau is not None
        np.maximum(self.peak_tau, np.abs(obs.state.tau), out=self.peak_tau)

    def summary(self) -> dict[str, Any]:
        return {
            "task": self.name,
            "outcome": self.outcome,
            "reason": self.reason,
            "planner": self.traj.planner,
            "planned_duration_s": self.traj.duration,
            "elapsed_s": self.elapsed_s,
            "peak_tau_nm": None if self.peak_tau is None else self.peak_tau.tolist(),
        }
