"""The virtual force sensor: observer + wrench mapping behind the `ForceSource` seam, and its calibration artefact.

A calibration (`main.py calibrate`) belongs to one robot (URDF), one torque model artefact and one
tool; loading it anywhere else is refused with one line naming what differs.  Artefact folder:
`calibration.json` (metadata, measured noise, accuracy report) and `learned_<observer>_<axis>.ubj`
(the paper's learned Fz, Mx, My per observer kind).
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xgboost as xgb

from cell.config import VirtualSensorConfig
from cell.data.atomic import save_atomic, write_atomic
from cell.model.dynamics.artefact import load_model
from cell.model.dynamics.base import ModelMeta
from cell.model.dynamics.learned import LearnedModel
from cell.model.dynamics.rigid_body import urdf_sha256
from cell.model.robot import RobotModel
from cell.sensing.model_step import ModelStep
from cell.sensing.observer import TorqueObserver, make_observer
from cell.sensing.wrench_map import LEARNED_INPUTS, ContactMap, JacobianMap, LearnedMap
from drivers.configio import json_default, read_versioned_json
from drivers.errors import ConfigError, DataError
from drivers.interfaces import ArmState, Wrench

log = logging.getLogger(__name__)

FORMAT = "tmcell-virtual-sensor-calibration"
FORMAT_VERSION = 1
OBSERVERS = ("kalman", "momentum")


def model_identity(path: Path) -> str:
    """Content hash of a saved torque model (model.json and every booster file, in name order)."""
    path = Path(path)
    h = hashlib.sha256()
    for f in sorted(path.iterdir() if path.is_dir() else [path]):
        if f.is_file() and not f.name.startswith(".") and f.suffix in (".json", ".ubj"):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def tool_identity(robot: RobotModel, name: str) -> dict[str, Any]:
    t = robot.tool
    return {"name": name, "tcp": [round(float(v), 6) for v in t.tcp_offset], "mass": round(float(t.mass), 6)}


@dataclass
class Calibration:
    """What `calibrate` measured and trained; the artefact's content."""

    robot: str
    urdf_sha256: str
    joints: int
    tool: dict[str, Any]
    model: dict[str, Any]  # {"path", "kind", "sha256", "training_data_sha256"}
    measurement_var: list[float]  # R of the Kalman filter: model residual variance in free motion [N·m]^2
    wrench_point: list[float]
    version: int = FORMAT_VERSION
    created: str = ""
    report: dict[str, Any] = field(default_factory=dict)
    cell: dict[str, Any] = field(default_factory=dict)  # where it was calibrated (sim: plant profile and seed)
    boosters: dict[str, dict[str, xgb.Booster]] = field(default_factory=dict, repr=False)  # observer -> axis


def save_calibration(cal: Calibration, path: Path) -> Path:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    files: dict[str, dict[str, str]] = {}
    for obs, axes in cal.boosters.items():
        files[obs] = {}
        for axis, bst in axes.items():
            name = f"learned_{obs}_{axis}.ubj"
            save_atomic(path / name, bst.save_model)
            files[obs][axis] = name
    doc = {k: v for k, v in asdict(cal).items() if k != "boosters"}
    doc.update(format=FORMAT, format_version=FORMAT_VERSION, learned=files,
               created=cal.created or datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))
    write_atomic(path / "calibration.json", json.dumps(doc, indent=1, default=json_default))
    return path


def read_calibration_doc(path: Path) -> dict[str, Any]:
    return read_versioned_json(Path(path) / "calibration.json", FORMAT, FORMAT_VERSION, "calibration",
                               f"{path}: no calibration.json (not a virtual-sensor calibration; run main.py calibrate)")


def check_calibration(doc: dict[str, Any], where: str, robot: RobotModel, tool: str, model_path: Path,
                      model: LearnedModel) -> None:
    """Refuse a calibration made for another robot, model or tool: one line naming the difference."""
    fix = f"recalibrate with main.py calibrate --tool {tool}"
    want_robot = (robot.model.name, urdf_sha256(robot.urdf), robot.n)
    have_robot = (doc.get("robot"), doc.get("urdf_sha256"), doc.get("joints"))
    if have_robot != want_robot:
        raise DataError(f"{where}: calibration was made for robot '{have_robot[0]}' (URDF sha256 "
                        f"{str(have_robot[1])[:12]}, {have_robot[2]} joints), this cell's is '{want_robot[0]}' "
                        f"(sha256 {want_robot[1][:12]}, {want_robot[2]} joints); {fix}")
    t_have, t_want = doc.get("tool", {}), tool_identity(robot, tool)
    for key in ("name", "tcp", "mass"):
        a, b = t_have.get(key), t_want[key]
        same = np.allclose(a, b, atol=1e-6) if key != "name" and a is not None else a == b
        if not same:
            raise DataError(f"{where}: calibration was made for tool {key} {a}, this cell's tool has {b}; {fix}")
    m = doc.get("model", {})
    sha = model_identity(model_path)
    if m.get("sha256") != sha:
        raise DataError(f"{where}: calibration was made with torque model {m.get('kind')} sha256 "
                        f"{str(m.get('sha256'))[:12]} (data {str(m.get('training_data_sha256'))[:12]}), but "
                        f"{model_path} is {model.meta.kind} sha256 {sha[:12]} (data "
                        f"{model.meta.training_data_sha256[:12]}); {fix}")


def load_calibration(path: Path, robot: RobotModel, tool: str, model_path: Path, model: LearnedModel) -> Calibration:
    path = Path(path)
    doc = read_calibration_doc(path)
    where = str(path / "calibration.json")
    check_calibration(doc, where, robot, tool, model_path, model)
    boosters: dict[str, dict[str, xgb.Booster]] = {}
    for obs, axes in doc.get("learned", {}).items():
        boosters[obs] = {}
        for axis, name in axes.items():
            file = path / name
            if not file.exists():
                raise DataError(f"{where}: learned map file {file} is missing")
            bst = xgb.Booster()
            bst.load_model(str(file))
            bst.set_param({"nthread": 1})
            boosters[obs][axis] = bst
    var = doc.get("measurement_var")
    if not isinstance(var, list) or len(var) != robot.n or not all(np.isfinite(var)) or min(var) <= 0:
        raise DataError(f"{where}: measurement_var must be {robot.n} positive numbers")
    return Calibration(robot=doc["robot"], urdf_sha256=doc["urdf_sha256"], joints=doc["joints"], tool=doc["tool"],
                       model=doc["model"], measurement_var=[float(v) for v in var],
                       wrench_point=list(doc.get("wrench_point", [])), version=int(doc.get("version", 1)),
                       created=str(doc.get("created", "")), report=dict(doc.get("report", {})),
                       cell=dict(doc.get("cell", {})), boosters=boosters)


# ========================================================================================= runtime
class VirtualForceSource:
    """`ForceSource` from joint torques: observer -> mapping, every control period.

    Ill-conditioned poses are counted and logged (once per episode), the wrench stays bounded by the
    damping; `summary()` reports them with the step timing."""

    name = "virtual"

    def __init__(self, observer: TorqueObserver, mapping: JacobianMap | LearnedMap, label: str = "",
                 zero_at_tare: bool = True, touch: TorqueObserver | None = None, touch_band_n: float = 0.0,
                 model_step: ModelStep | None = None, model_dir: Path | None = None) -> None:
        self.observer = observer
        # The model evaluation its observers share, for a collision detector on the same model to join.
        self.model_step = model_step
        self.model_dir = model_dir  # where its model was loaded from (resolved)
        # The fast channel for touches (VirtualSensorConfig.touch_gain), used while `contact_expected()`
        # (set by whoever knows the task's state: the runner, replay) says a touch may come.
        self.touch = touch
        self.touch_band_n = touch_band_n
        self.contact_expected: Callable[[], bool] | None = None
        self.mapping = mapping
        self.zero_at_tare = zero_at_tare  # False: a task's tare leaves the model's own zero (see VirtualSensorConfig)
        self.label = label or f"{observer.kind}+{mapping.kind}"
        self.ill_conditioned_cycles = 0
        self.cycles = 0
        self.last: Wrench | None = None
        self.last_tau_ext = np.zeros(6)
        self.ill_conditioned = False

    def read(self, state: ArmState) -> Wrench:
        tau_ext = self.observer.update(state)
        m = self.mapping.map(state.q, tau_ext)
        self.cycles += 1
        if m.ill_conditioned:
            self.ill_conditioned_cycles += 1
            if not self.ill_conditioned:  # warn once per singular stretch
                log.warning("virtual sensor: the arm is near a singularity (smallest Jacobian singular value "
                            "%.4f); the wrench is damped and less reliable", m.sigma_min)
        self.ill_conditioned = m.ill_conditioned
        self.last_tau_ext = tau_ext
        force = m.wrench[:3].copy()
        if self.touch is not None:
            fast = self.touch.update(state)  # every period: warm when a touch comes
            if self.contact_expected is not None and self.contact_expected():
                # The fast force's departure from the steady one beyond the band: the touch's ringing
                # passes, the fast observer's noise in steady contact does not.
                d = self.mapping.map(state.q, fast).wrench[:3] - force
                force += np.sign(d) * np.maximum(0.0, np.abs(d) - self.touch_band_n)
        w = Wrench(t=state.t, force=force, torque=m.wrench[3:].copy())
        self.last = w
        return w

    def rebias(self) -> None:
        if self.zero_at_tare:
            self.observer.rebias()
            if self.touch is not None:
                self.touch.rebias()

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"virtual_sensor": self.label, "ill_conditioned_cycles": self.ill_conditioned_cycles}
        if self.touch is not None:
            out["virtual_sensor_touch_gain"] = float(getattr(self.touch, "K", np.zeros(1))[0])
        return out


# A model's sample period may differ from the loop's by this share (a logged period's median jitters).
PERIOD_TOLERANCE = 0.02


def period_mismatch(model_dir: Path, meta: ModelMeta, period_s: float) -> str:
    """'' when the model was made at the control period `period_s` (or its period is unknown); else why not.

    Such a model is refused, not re-derived: its causal derivative filters and time windows are defined
    in samples, and its learned residual holds the arm's servo behaviour at the period it was recorded
    at, so at another period its features mean something else."""
    made = meta.features.get("sample_period_s")
    if made is None or abs(float(made) - period_s) <= PERIOD_TOLERANCE * period_s:
        return ""
    return (f"{model_dir}: the model was made from samples every {float(made) * 1e3:.1f} ms and this cell runs every "
            f"{period_s * 1e3:.1f} ms (loop.period_s): prepare the tool at this period (`main.py prepare`, with its "
            "own virtual_sensor.model_dir)")


def load_observer_model(model_dir: Path, robot: RobotModel, period_s: float | None = None) -> LearnedModel:
    """The hybrid model an observer runs on: an H1-style model (physics + learned) with causal derivatives,
    made at the control period `period_s` when given (ConfigError otherwise)."""
    model = load_model(model_dir, robot)
    why = period_mismatch(model_dir, model.meta, period_s) if period_s is not None else ""
    if why:
        raise ConfigError(why)
    if not isinstance(model, LearnedModel) or model.physics is None:
        raise DataError(f"{model_dir}: the virtual sensor needs a hybrid model (H1), got {model.meta.kind}")
    if model.meta.features.get("derivatives") != "causal":
        raise DataError(f"{model_dir}: the model was trained with {model.meta.features.get('derivatives')} "
                        "derivatives; the controller needs causal ones (main.py train --derivatives causal)")
    return model


def build_virtual_source(cfg: VirtualSensorConfig, robot: RobotModel, tool: str, dt: float,
                         observer: str | None = None, mapping: str | None = None,
                         model_dir: Path | None = None, calibration_dir: Path | None = None) -> VirtualForceSource:
    """The configured virtual sensor for `tool` from its model and calibration artefacts (checked)."""
    model_dir = Path(model_dir) if model_dir is not None else cfg.path("model", tool)
    calibration_dir = Path(calibration_dir) if calibration_dir is not None else cfg.path("calibration", tool)
    model = load_observer_model(model_dir, robot, dt)
    cal = load_calibration(calibration_dir, robot, tool, model_dir, model)
    own = cfg.for_tool(tool)
    return source_from(own, robot, dt, model, cal, observer or own.observer, mapping or own.mapping,
                       str(calibration_dir), model_dir=model_dir.resolve())


def source_from(cfg: VirtualSensorConfig, robot: RobotModel, dt: float, model: LearnedModel, cal: Calibration,
                observer: str, mapping: str, where: str = "calibration",
                model_dir: Path | None = None) -> VirtualForceSource:
    # One model evaluation per period for the observer, its touch channel and (app/sensing.py with_guard) the
    # collision detector: the main observer leads it; the touch channel reads a touch's friction from its own
    # fast estimate (the slow one lags the very touch the channel is there to catch).
    step = ModelStep(model, dt)
    obs = make_observer(observer, model, dt, np.asarray(cal.measurement_var), np.asarray(cfg.process_noise_nm),
                        cfg.momentum_gain, cfg.rebias_window_s, cfg.innovation_gate,
                        model_noise=cfg.measurement_noise == "model", step=step)
    wmap: JacobianMap | LearnedMap
    if mapping == "contact":
        wmap = contact_map(cfg, robot, np.asarray(cal.measurement_var))
    elif mapping in ("jacobian", "learned"):
        wmap = JacobianMap(robot, np.asarray(cfg.wrench_point, float), cfg.singular_sigma, cfg.max_damping)
        if mapping == "learned":
            boosters = cal.boosters.get(observer)
            if not boosters or any(a not in boosters for a in LEARNED_INPUTS):
                raise DataError(f"{where}: no learned map for the {observer} observer; recalibrate")
            wmap = LearnedMap(boosters, wmap, robot.n)
    else:
        raise DataError(f"unknown wrench mapping {mapping!r} (jacobian, learned or contact)")
    touch = (make_observer("momentum", model, dt, np.asarray(cal.measurement_var), np.asarray(cfg.process_noise_nm),
                           cfg.touch_gain, cfg.rebias_window_s, step=step, own_load=True)
             if cfg.touch_gain > 0 else None)
    return VirtualForceSource(obs, wmap, zero_at_tare=cfg.zero_at_tare, touch=touch, touch_band_n=cfg.touch_band_n,
                              model_step=step, model_dir=model_dir)


def contact_map(cfg: VirtualSensorConfig, robot: RobotModel, joint_var: np.ndarray) -> ContactMap:
    """The contact-prior map for the mounted tool: touched at its TCP, the residual variances as weights."""
    return ContactMap(robot, np.asarray(cfg.wrench_point, float), robot.tool.tcp_offset, cfg.free_moment_nm,
                      joint_var, cfg.singular_sigma, cfg.max_damping)
