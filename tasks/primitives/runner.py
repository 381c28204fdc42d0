"""Runs a task file as a task: its primitives one after another on the control loop, under the cell's safety
limits and collision guard, with the same recording, plot and summary as the built-in tasks
(tasks/runner.py runs it)."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pyarrow as pa

from cell.collision.config import TaskContactSafety
from cell.control.loop import Command, Observation
from cell.model.robot import RobotModel
from tasks.primitives.base import Context, Primitive
from tasks.primitives.taskfile import Step, TaskFile

log = logging.getLogger(__name__)

# Every row carries every column (the recorder takes its columns from the first row).
LOG_KEYS = ("f_setpoint", "f_estimate", "f_axis_tx", "f_axis_ty", "f_axis_tz", "f_axis_moment", "f_along")
CONTACT_KINDS = ("guarded_move", "force_mode", "spiral_search")


class TaskFileTask:
    """A task file's steps as one task (the loop's Task protocol).  Its states are the steps' labels (a
    step's `name`, else '<number>-<primitive>')."""

    def __init__(self, tf: TaskFile, robot: RobotModel, dt: float) -> None:
        self.tf = tf
        self.name = f"task-{tf.header.name}"
        self.robot = robot
        self.dt = dt
        self.steps: list[Step] = tf.steps
        self.prims: list[Primitive] = [s.build() for s in tf.steps]
        poses = {k: v for k, v in tf.poses.items() if not isinstance(v, np.ndarray)}
        self.ctx = Context(robot=robot, dt=dt, poses=poses)
        self.index = 0
        self.t_step = 0.0
        self.started = False
        self._initialised = False
        self._outcome = "running"
        self.reason = ""
        self.durations: list[float] = []
        self.peak_force = 0.0
        self.contact_states, self.regulated_states = self._classify()

    # ------------------------------------------------------------------ what the guard and the scores need
    def _classify(self) -> tuple[list[str], list[str]]:
        """Steps that expect contact (the guard reads the residual as a tool force there), and steps that
        regulate a force (scored).  A hold after a force_mode keeps its regulation; a step right after one in
        contact starts in contact (leaving a surface must not read as a collision)."""
        contact: list[str] = []
        regulated: list[str] = []
        regulating = in_contact = False
        for s in self.steps:
            if s.kind in ("force_mode", "spiral_search"):
                regulating = s.kind == "force_mode" and s.params.keep
                regulated.append(s.label)
            elif s.kind == "hold" and regulating:
                regulated.append(s.label)
            else:
                regulating = False
            if s.kind in CONTACT_KINDS or in_contact or s.label in regulated:
                contact.append(s.label)
            in_contact = s.kind in CONTACT_KINDS or s.label in regulated
        return contact, regulated

    def collision_settings(self) -> TaskContactSafety:
        """The guard's table for this file: its contact steps and each step's reaction where the file sets one.
        In contact the guard holds the fast residual force to the cell's limit, as for the built-in tasks: it
        reads impacts' transients the task's filtered force does not, which the step limits are not meant for."""
        reactions: dict[str, str] = {s.label: r for s in self.steps if (r := self.tf.reaction(s)) is not None}
        return TaskContactSafety(contact_states=list(self.contact_states), reactions=reactions)

    # ------------------------------------------------------------------------------------ Task protocol
    @property
    def done(self) -> bool:
        return self._outcome != "running"

    @property
    def state_name(self) -> str:
        if self._outcome != "running":
            return self._outcome if self._outcome == "done" else "failed"
        return self.steps[self.index].label

    def abort(self, reason: str) -> None:
        if not self.done:
            self._fail(reason)

    def _fail(self, reason: str) -> None:
        step = self.steps[min(self.index, len(self.steps) - 1)]
        self.reason = f"{step.label} (line {step.line}): {reason}"
        self._outcome = "failed"
        log.error("%s: %s", self.name, self.reason)

    def step(self, obs: Observation) -> Command:
        if not self._initialised:
            self.ctx.ref = self.robot.tcp_pose(np.asarray(obs.q_cmd, float))
            self._initialised = True
        prim, step = self.prims[self.index], self.steps[self.index]
        if not self.started:
            log.info("%s: %s (line %d)", self.name, step.label, step.line)
            try:
                prim.start(self.ctx, obs)
            except ValueError as exc:
                self._fail(str(exc))
                return Command(q=obs.q_cmd, log=self._row({}))
            self.started = True
            self.t_step = 0.0
        out = prim.step(self.ctx, obs, self.t_step)
        self.t_step += self.dt
        f = float(np.linalg.norm(np.asarray(obs.wrench.force, float)))
        if np.isfinite(f) and step.label in self.contact_states:
            self.peak_force = max(self.peak_force, f)
        limit = self.tf.max_force(step)
        if np.isfinite(f) and f > limit:
            self._fail(f"tool force {f:.1f} N exceeded the step's limit {limit:g} N")
        elif out.failed:
            self._fail(out.failed)
        elif out.finished:
            self.durations.append(self.t_step)
            if step.params.name:
                self.ctx.results[step.params.name] = prim.result
            self.index += 1
            self.started = False
            if self.index >= len(self.steps):
                self._outcome = "done"
                self.index = len(self.steps) - 1
        return Command(q=out.q, log=self._row(out.log), rebias_force=out.rebias)

    def _row(self, extra: dict[str, float | str]) -> dict[str, float | str]:
        row: dict[str, float | str] = {"step": float(self.index), "fz_setpoint": 0.0,
                                       "ref_x": float(self.ctx.ref.translation[0]),
                                       "ref_y": float(self.ctx.ref.translation[1]),
                                       "ref_z": float(self.ctx.ref.translation[2])}
        row.update({k: float("nan") for k in LOG_KEYS})
        row.update(extra)
        return row

    # ------------------------------------------------------------------------------------------ results
    @property
    def outcome(self) -> str:
        return self._outcome

    def summary(self) -> dict[str, Any]:
        steps = []
        for i, (s, p) in enumerate(zip(self.steps, self.prims, strict=True)):
            entry: dict[str, Any] = {"step": s.label, "primitive": s.kind, "line": s.line}
            if i < len(self.durations):
                entry["duration_s"] = round(self.durations[i], 4)
            if p.result:
                entry["result"] = p.result
            steps.append(entry)
        reports = {s.params.name: p.result for s, p in zip(self.steps, self.prims, strict=True)
                   if s.kind == "report" and p.result}
        return {"task": self.name, "task_file": str(self.tf.path), "outcome": self.outcome, "reason": self.reason,
                "final_state": self.state_name, "steps_done": len(self.durations), "steps": steps,
                "reports": reports, "peak_force_n": self.peak_force}

    def log_summary(self, table: pa.Table) -> dict[str, Any]:
        """Per force-regulating step: the force error against its setpoint along the regulated axis, as the
        controller saw it (virtual sensor) and as the F/T sensor measured it; per guarded move its peak contact
        force on the F/T sensor."""
        d = table.to_pydict()
        states = np.asarray(d["state"]).astype(str)
        out: dict[str, Any] = {}
        has_truth = "sensor_fx" in d
        for s in self.steps:
            rows = states == s.label
            if not rows.any():
                continue
            if s.label in self.regulated_states:
                sp = np.asarray(d["f_setpoint"], float)[rows]
                est = np.asarray(d["f_estimate"], float)[rows]
                ok = np.isfinite(sp) & np.isfinite(est) & (np.asarray(d["f_axis_moment"], float)[rows] == 0)
                if not ok.any():
                    continue
                entry: dict[str, Any] = {"samples": int(ok.sum()), "setpoint_n": float(sp[ok][-1]),
                                         "virtual_force_mae_n": float(np.mean(np.abs(est[ok] - sp[ok])))}
                if has_truth:
                    axis = np.column_stack([np.asarray(d[f"f_axis_t{a}"], float)[rows] for a in "xyz"])
                    meas_t = np.column_stack([np.asarray(d[f"sensor_f{a}"], float)[rows] for a in "xyz"])
                    meas = np.sum(axis * meas_t, axis=1)
                    ok &= np.isfinite(meas)
                    err = meas[ok] - sp[ok]
                    entry.update(force_mae_n=float(np.mean(np.abs(err))),
                                 force_max_abs_error_n=float(np.max(np.abs(err))),
                                 force_mean_n=float(np.mean(meas[ok])))
                out[s.label] = entry
            elif s.kind == "guarded_move" and has_truth:
                f = np.linalg.norm(np.column_stack([np.asarray(d[f"sensor_f{a}"], float)[rows] for a in "xyz"]), axis=1)
                f = f[np.isfinite(f)]
                if f.size:
                    out[s.label] = {"contact_force_max_n": float(np.max(f))}
        return {"step_scores": out}
