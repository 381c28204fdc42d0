"""Calibrating the virtual force sensor against the F/T sensor (`prepare` builds on it: tasks/setup/prepare.py).

`calibrate` (the user's "calibrate the virtual sensor with the real F/T sensor") moves the arm
through the configured postures (`virtual_sensor.calibration`); in each one it rests, re-zeroes the
F/T sensor in free space, then records joint torques and the sensor's wrench while loads are applied
by a `LoadApplier` (the simulated cell's scripted hand, or the operator prompted by the CLI).  The
moves between postures are free motion: the hybrid model's residual there is the Kalman filter's
measurement noise.  The recorded streams are then replayed through both observers exactly as the
controller runs them (causal, same re-bias instants), the paper's learned map is trained on the
training postures, and every route (observer x mapping) is scored on the held-out postures against
the sensor.  The artefact keeps the noise, the learned maps of both observers and the report.

"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pinocchio as pin
from tqdm import tqdm

from cell.config import CalibrationConfig, CellConfig
from cell.control.loop import Command, ControlLoop, Observation
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.control.trajectory import JointMove, tool_down_pose
from cell.data.recorder import Recorder, new_run_dir, read_log
from cell.model.dynamics.fastpredict import FastPredictor
from cell.model.dynamics.learned import LearnedModel
from cell.model.dynamics.rigid_body import urdf_sha256
from cell.model.robot import RobotModel
from cell.sensing.observer import make_observer
from cell.sensing.virtual_sensor import (
    OBSERVERS,
    Calibration,
    contact_map,
    load_observer_model,
    model_identity,
    save_calibration,
    tool_identity,
)
from cell.sensing.wrench_map import AXES, LEARNED_INPUTS, JacobianMap, LearnedMap, fit_learned_axes
from drivers.configio import to_plain
from drivers.errors import CellError, ConfigError, DataError
from drivers.interfaces import ArmState
from tasks.base import MachineTask, Trigger

log = logging.getLogger(__name__)

PHASES = {"move": 0, "settle": 1, "load": 2, "release": 3}
WARMUP_ROWS = 10  # the causal derivative filter's start-up is not model error


class LoadApplier(Protocol):
    """Who loads the tool in each posture: the sim's scripted hand, or the operator (real cell)."""

    scripted: bool

    def before_posture(self, index: int, total: int, duration_s: float) -> None: ...

    def update(self, t: float) -> tuple[int, bool]:
        """Called every period of the loading phase: (load index or -1, whether the load is steady)."""

    def release(self) -> None: ...


class OperatorLoads:
    """The real cell: the CLI prompts the operator (stdin) between postures; the loop never blocks."""

    scripted = False

    def __init__(self, prompt: Callable[[str], str] = input) -> None:
        self.prompt = prompt

    def before_posture(self, index: int, total: int, duration_s: float) -> None:
        self.prompt(
            f"posture {index + 1}/{total}: keep clear of the tool and press Enter; the arm moves there and rests "
            f"(it re-zeroes at the end of the rest: do not touch it before). When the log says PUSH THE TOOL NOW, "
            f"push the tool by hand (0-75 N, varying, incl. twisting) for {duration_s:.0f} s. "
        )

    def update(self, t: float) -> tuple[int, bool]:
        return -1, True

    def release(self) -> None:
        log.info("release the tool")


# ========================================================================================= the task
class Phase(enum.Enum):
    MOVE = "move"
    SETTLE = "settle"
    LOAD = "load"
    RELEASE = "release"
    DONE = "done"
    FAILED = "failed"


class PostureTask(MachineTask):
    """One posture: move there, rest (free space; re-zero the sensor at the end), loads, release."""

    name = "calibrate"
    moved: Trigger
    settled: Trigger
    unloaded: Trigger
    released: Trigger
    state_log_level = logging.DEBUG  # nine postures of four states each: the progress bar says enough

    def __init__(self, q_target: np.ndarray, index: int, robot: RobotModel, dt: float, cal: CalibrationConfig,
                 applier: LoadApplier, load_s: float) -> None:
        super().__init__(Phase.MOVE, [
            ("moved", Phase.MOVE, Phase.SETTLE),
            ("settled", Phase.SETTLE, Phase.LOAD),
            ("unloaded", Phase.LOAD, Phase.RELEASE),
            ("released", Phase.RELEASE, Phase.DONE),
        ])
        self.q_target = q_target
        self.index = index
        self.dt = dt
        self.cal = cal
        self.applier = applier
        self.load_s = load_s
        self.speed = robot.limits.velocity * cal.move_speed_fraction
        self.move: JointMove | None = None

    def abort(self, reason: str) -> None:
        if not self.done:
            self.applier.release()
        super().abort(reason)

    def step(self, obs: Observation) -> Command:
        load, steady, rebias = -1, 0.0, False
        phase_code = PHASES.get(self.state.value, -1)
        q = self.q_target
        if self.state is Phase.MOVE:
            if self.move is None:
                self.move = JointMove(obs.q_cmd, self.q_target, self.speed)
            q = self.move.at(self.t_state + self.dt)
            if self.t_state + self.dt >= self.move.duration:
                self.moved()
            else:
                self.t_state += self.dt
        elif self.state is Phase.SETTLE:
            self.t_state += self.dt
            if self.t_state >= self.cal.settle_s:
                rebias = True  # free space, at rest: zero the F/T sensor (and, in replay, the observers)
                self.settled()
                if not self.applier.scripted:
                    log.warning("posture %d: PUSH THE TOOL NOW, varying, for %.0f s", self.index + 1, self.load_s)
        elif self.state is Phase.LOAD:
            load, is_steady = self.applier.update(self.t_state)
            steady = float(is_steady)
            self.t_state += self.dt
            if self.t_state >= self.load_s:
                self.applier.release()
                self.unloaded()
                if not self.applier.scripted:
                    log.warning("posture %d: let go of the tool", self.index + 1)
        elif self.state is Phase.RELEASE:
            self.t_state += self.dt
            if self.t_state >= 0.4:
                self.released()
        return Command(q=np.asarray(q, float), rebias_force=rebias,
                       log={"phase": float(phase_code), "posture": float(self.index), "load": float(load),
                            "steady": steady, "rebias": float(rebias)})

    def summary(self) -> dict[str, Any]:
        return {"task": self.name, "outcome": self.outcome, "reason": self.reason, "posture": self.index}


def posture_targets(robot: RobotModel, cal: CalibrationConfig, q_home: np.ndarray) -> list[np.ndarray]:
    """Joint targets of the configured tool-down postures (IK chained from home)."""
    out = []
    seed = np.asarray(q_home, float)
    for i, (x, y, z, tx, ty) in enumerate(cal.postures):
        down = tool_down_pose(np.array([x, y, z]))
        R = pin.rpy.rpyToMatrix(np.radians(tx), np.radians(ty), 0.0) @ down.rotation
        q, ok = robot.ik(pin.SE3(R, down.translation), seed)
        if not ok:
            raise ConfigError(f"virtual_sensor.calibration.postures[{i}] {[x, y, z, tx, ty]} is not reachable")
        out.append(q)
        seed = q
    return out


# ========================================================================================= replay
def _columns(table: Any, prefix: str, n: int) -> np.ndarray:
    return np.column_stack([np.asarray(table.column(f"{prefix}{i + 1}").to_numpy(), float) for i in range(n)])


def _stream(run_dir: Path, n: int) -> dict[str, np.ndarray]:
    t = read_log(run_dir)
    out = {"t": np.asarray(t.column("t").to_numpy(), float), "q": _columns(t, "q", n), "dq": _columns(t, "dq", n),
           "tau": _columns(t, "tau", n),
           "sensor": np.column_stack([np.asarray(t.column(a).to_numpy(), float) for a in AXES])}
    for c in ("phase", "posture", "load", "steady", "rebias"):
        out[c] = np.asarray(t.column(c).to_numpy(), float)
    return out


def free_motion_variance(model: LearnedModel, streams: list[dict[str, np.ndarray]], dt: float) -> np.ndarray:
    """Variance of tau - tau_free while the arm moves without contact: the Kalman measurement noise."""
    res = []
    for s in streams:
        fast = FastPredictor(model, dt)
        r = np.array([s["tau"][k] - fast.step(s["q"][k], s["dq"][k]) for k in range(len(s["t"]))])
        moving = (s["phase"] == PHASES["move"]) & (np.arange(len(r)) >= WARMUP_ROWS)
        res.append(r[moving])
    r = np.concatenate(res)
    if len(r) < 50:
        raise DataError(f"calibration: only {len(r)} free-motion samples to measure the model's residual noise")
    # Variance about the mean: a constant model bias is what the free-space re-bias removes.
    return np.maximum(np.var(r, axis=0), 1e-4)


def replay(observer: Any, s: dict[str, np.ndarray], reset: bool = True) -> np.ndarray:
    """The observer over a recorded stream as the loop ran it: read, then re-bias where commanded
    (`reset=False` continues from the previous stream, as the controller runs across postures)."""
    if reset:
        observer.reset()
    out = np.empty_like(s["tau"])
    for k in range(len(s["t"])):
        state = ArmState(t=float(s["t"][k]), q=s["q"][k], dq=s["dq"][k], tau=s["tau"][k])
        out[k] = observer.update(state)
        if s["rebias"][k] > 0:
            observer.rebias()
    return out


def _mae(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a - b))) if len(a) else float("nan")


def error_split(err: np.ndarray, group: np.ndarray) -> dict[str, float]:
    """An axis' error over the held-out samples split by posture: `posture_offset` is the mean |mean
    error| of each posture (sample-weighted; what its free-space re-bias and the model's static error
    leave), `within_posture` the MAE about those means (the observer's noise and its per-load error)."""
    offset = np.zeros_like(err)
    for g in np.unique(group):
        offset[group == g] = err[group == g].mean()
    return {"posture_offset": round(float(np.mean(np.abs(offset))), 4),
            "within_posture": round(float(np.mean(np.abs(err - offset))), 4)}


# ========================================================================================= calibrate
def calibrate(
    cfg: CellConfig,
    tool: str,
    robot: RobotModel,
    open_cell_fn: Callable[[], Any],
    applier_fn: Callable[[Any], LoadApplier],
    model_dir: Path | None = None,
    out_dir: Path | None = None,
    cell_info: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run the guided calibration on a cell and save the artefact; returns the accuracy report.

    open_cell_fn() -> holder with .open() -> OpenCell (free scene, `tool` mounted, F/T sensor as its
    force source) and .close(); applier_fn(holder) -> the LoadApplier for that cell.

    CLI: main.py calibrate [--tool wipe|peg] [--cell sim|real] [--seed N] [--model DIR] [--out DIR] [--json]
    """
    t_start = time.perf_counter()
    cfg.virtual_sensor.validate(f"{cfg.source}: virtual_sensor")  # a config built in code has not been loaded
    vs = cfg.virtual_sensor.for_tool(tool)  # the tool's observer settings: its route is the one reported
    cal = vs.calibration
    dt = cfg.loop.period_s
    model_dir = Path(model_dir) if model_dir is not None else vs.path("model", tool)
    out_dir = Path(out_dir) if out_dir is not None else vs.path("calibration", tool)
    model = load_observer_model(model_dir, robot, cfg.loop.period_s)
    targets = posture_targets(robot, cal, np.asarray(cfg.robot.home, float))
    base = Path(cfg.recording.directory)
    holder = open_cell_fn()
    run_dirs: list[Path] = []
    try:
        cell = holder.open()
        applier = applier_fn(holder)
        load_s = cal.loads * cal.load_s if applier.scripted else cal.operator_load_s
        for i, q in enumerate(tqdm(targets, desc=f"calibrate {tool}", unit="posture")):
            applier.before_posture(i, len(targets), load_s)
            run_dir = new_run_dir(base, f"calibrate-{tool}-p{i + 1}")
            rec = Recorder(run_dir, max(cfg.recording.chunk_rows, 1000))
            rec.write_config(to_plain(cfg))
            task = PostureTask(q, i, robot, dt, cal, applier, load_s)
            loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(cfg.safety, robot, dt), cell.ticker, rec,
                               dt, 120.0 + load_s, cfg.loop.slow_cycle_fraction)
            res = loop.run()
            applier.release()
            raise_if_interrupted(res.outcome)
            if res.outcome != "done":
                raise CellError(f"calibrate: posture {i + 1} ended '{res.outcome}' ({res.reason}); "
                                f"recording kept in {run_dir}")
            run_dirs.append(run_dir)
    finally:
        holder.close()
    t_collect = time.perf_counter() - t_start

    streams = [_stream(d, robot.n) for d in run_dirs]
    R = free_motion_variance(model, streams, dt)
    jac = JacobianMap(robot, np.asarray(vs.wrench_point, float), vs.singular_sigma, vs.max_damping)
    tip = contact_map(vs, robot, R)
    holdout = set(cal.holdout)
    sel = [(s["phase"] == PHASES["load"]) & (s["steady"] > 0) for s in streams]
    is_test = np.concatenate([np.full(int(m.sum()), i in holdout) for i, m in enumerate(sel)])
    posture_of = np.concatenate([np.full(int(m.sum()), i) for i, m in enumerate(sel)])
    q_rows = np.concatenate([s["q"][m] for s, m in zip(streams, sel, strict=True)])
    sensor = np.concatenate([s["sensor"][m] for s, m in zip(streams, sel, strict=True)])
    if is_test.sum() == 0 or (~is_test).sum() == 0:
        raise DataError("calibration: no loaded samples in the training or the held-out postures")
    # Free motion scored on the moves after the first posture: sensor and observers zeroed there.
    free_sel = [(s["phase"] == PHASES["move"]) & (i > 0) for i, s in enumerate(streams)]

    routes: dict[str, dict[str, Any]] = {}
    boosters: dict[str, dict[str, Any]] = {}
    chosen = f"{vs.observer}+{vs.mapping}"
    split: dict[str, dict[str, float]] = {}
    for kind in tqdm(OBSERVERS, desc="observers", unit="observer"):
        obs = make_observer(kind, model, dt, R, np.asarray(vs.process_noise_nm), vs.momentum_gain, vs.rebias_window_s,
                            vs.innovation_gate)
        taus = [replay(obs, s, reset=i == 0) for i, s in enumerate(streams)]
        tau_rows = np.concatenate([t[m] for t, m in zip(taus, sel, strict=True)])
        w_jac = np.array([jac.map(q, t).wrench for q, t in zip(q_rows, tau_rows, strict=True)])
        bst = fit_learned_axes(q_rows[~is_test], tau_rows[~is_test], sensor[~is_test])
        boosters[kind] = bst
        w_contact = np.array([tip.map(q, t).wrench for q, t in zip(q_rows[is_test], tau_rows[is_test], strict=True)])
        learned = LearnedMap(bst, jac, robot.n).predict_batch(q_rows[is_test], tau_rows[is_test])
        w_learned = w_jac[is_test].copy()
        w_learned[:, [LEARNED_INPUTS[a][0] for a in LEARNED_INPUTS]] = learned
        # Free motion (moves between postures, no contact): how far the estimate strays from zero.
        free_w = np.array([jac.map(q, t).wrench for s, tt, m in zip(streams, taus, free_sel, strict=True)
                           for q, t in zip(s["q"][m], tt[m], strict=True)]).reshape(-1, 6)
        free_s = np.concatenate([s["sensor"][m] for s, m in zip(streams, free_sel, strict=True)])
        # The learned map on the postures it was trained on: what it does where it has seen data.
        fitted = LearnedMap(bst, jac, robot.n).predict_batch(q_rows[~is_test], tau_rows[~is_test])
        in_sample = {f"training_postures_{a}_mae": round(_mae(fitted[:, k], sensor[~is_test, LEARNED_INPUTS[a][0]]), 4)
                     for k, a in enumerate(LEARNED_INPUTS)}
        for mapping, w in (("jacobian", w_jac[is_test]), ("contact", w_contact), ("learned", w_learned)):
            ref = sensor[is_test]
            r = {f"{a}_mae": round(_mae(w[:, i], ref[:, i]), 4) for i, a in enumerate(AXES)}
            r.update(fz_mae_n=r["fz_mae"], mx_mae_nm=r["mx_mae"], my_mae_nm=r["my_mae"])
            if mapping == "jacobian":
                r["free_motion_fz_mae_n"] = round(_mae(free_w[:, 2], free_s[:, 2]), 4)
            elif mapping == "learned":
                r.update(in_sample)
            routes[f"{kind}+{mapping}"] = r
            if f"{kind}+{mapping}" == chosen:
                split = {f"{a}_{unit}": error_split(w[:, AXES.index(a)] - ref[:, AXES.index(a)], posture_of[is_test])
                         for a, unit in (("fz", "n"), ("mx", "nm"), ("my", "nm"))}
    report = {
        "tool": tool, "route": chosen,
        "fz_mae_n": routes[chosen]["fz_mae_n"], "mx_mae_nm": routes[chosen]["mx_mae_nm"],
        "my_mae_nm": routes[chosen]["my_mae_nm"], "error_split": split, "routes": routes,
        "postures": len(targets), "holdout_postures": sorted(holdout),
        "train_samples": int((~is_test).sum()), "heldout_samples": int(is_test.sum()),
        "free_motion_samples": int(sum(int(m.sum()) for m in free_sel)),
        "measurement_std_nm": np.sqrt(R).round(4).tolist(),
        "process_noise_nm": list(vs.process_noise_nm), "scripted_loads": bool(applier.scripted),
        "sensor_fz_range_n": [round(float(sensor[:, 2].min()), 2), round(float(sensor[:, 2].max()), 2)],
    }
    calib = Calibration(
        robot=robot.model.name, urdf_sha256=urdf_sha256(robot.urdf), joints=robot.n, tool=tool_identity(robot, tool),
        model={"path": str(model_dir), "kind": model.meta.kind, "sha256": model_identity(model_dir),
               "training_data_sha256": model.meta.training_data_sha256},
        measurement_var=R.tolist(), wrench_point=list(vs.wrench_point), report=report, boosters=boosters,
        cell=dict(cell_info or {}),
    )
    save_calibration(calib, out_dir)
    report.update(out=str(out_dir), runs=[str(d) for d in run_dirs], collect_s=round(t_collect, 1),
                  wall_s=round(time.perf_counter() - t_start, 1))
    return report
