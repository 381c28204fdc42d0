"""The cell configuration (config/cell.yaml): robot, scene, loop, safety limits, devices, recording."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

from cell.collision.config import CollisionConfig
from drivers.configio import join, load_dataclass, read_yaml, require, require_len
from drivers.errors import ConfigError

TOOLS = ("wipe", "peg")  # the tools a cell config knows (virtual_sensor.by_tool keys)

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "config"
DEFAULT_CONFIG = CONFIG_DIR / "cell.yaml"


def resolve(path: str, base: Path = CONFIG_DIR) -> Path:
    """Config paths are relative to config/ unless absolute."""
    p = Path(path)
    return p if p.is_absolute() else base / p


MAX_BASE_DEPTH = 4  # `base:` chains longer than this are a mistake (or a loop)


def read_layered_yaml(path: Path, _depth: int = 0) -> dict[str, Any]:
    """A YAML mapping that may name `base: OTHER.yaml` (relative to its own folder): the base is read
    first and this file's keys laid over it, mappings merged key by key, any other value replaced.
    So a variant (another arm protocol, another loop period) states only what differs."""
    data = read_yaml(path)
    if not isinstance(data, dict) or "base" not in data:
        return data
    base = data.pop("base")
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"{path}: base must name a YAML file, got {base!r}")
    if _depth >= MAX_BASE_DEPTH:
        raise ConfigError(f"{path}: base: more than {MAX_BASE_DEPTH} files chained (a loop?)")
    under = read_layered_yaml(resolve(base, Path(path).resolve().parent), _depth + 1)
    return _lay_over(under, data)


def _lay_over(under: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(under)
    for key, value in over.items():
        out[key] = _lay_over(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) \
            else value
    return out


@dataclass
class RobotConfig:
    """The controller's nominal model of the arm and its tool."""

    urdf: str = "robots/tm5-700/tm5-700.urdf"
    home: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.5708, 0.0, 1.5708, 0.0])  # rad
    # Nominal tool as configured on the pendant: sensor + tool mass, COM and TCP in the flange frame.
    tool_mass: float = 1.4
    tool_com: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.11])
    tcp_wipe: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.155])
    tcp_peg: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.143])

    def validate(self, where: str) -> None:
        require_len(self.home, 6, f"{where}.home")
        for name in ("tool_com", "tcp_wipe", "tcp_peg"):
            require(len(getattr(self, name)) == 3, f"{where}.{name}", "must have 3 values (x, y, z) in m")
        require(0 <= self.tool_mass <= 6.0, f"{where}.tool_mass", "must lie in [0, 6] kg (rated payload)")


# The simulated fixtures: none, the wiping table, the peg's hole fixture, the collision bench's plates.
SceneKind = Literal["free", "table", "peg", "obstacle"]


@dataclass
class SceneConfig:
    """Where the fixtures are, in the robot base frame [m].  The plant builds them; tasks aim at them."""

    kind: SceneKind = "table"  # obstacle: the collision bench's
    table_height: float = 0.05  # top surface z
    table_center: list[float] = field(default_factory=lambda: [0.45, -0.12])
    table_size: list[float] = field(default_factory=lambda: [0.6, 0.8])
    hole_center: list[float] = field(default_factory=lambda: [0.45, -0.12])
    hole_diameter: float = 0.0218
    hole_depth: float = 0.030

    def validate(self, where: str) -> None:
        require(len(self.table_center) == 2, f"{where}.table_center", "must have 2 values (x, y)")
        require(len(self.table_size) == 2, f"{where}.table_size", "must have 2 values (x, y)")
        require(len(self.hole_center) == 2, f"{where}.hole_center", "must have 2 values (x, y)")
        require(0.005 < self.hole_diameter < 0.1, f"{where}.hole_diameter", "must lie in (0.005, 0.1) m")
        require(0.005 < self.hole_depth < 0.2, f"{where}.hole_depth", "must lie in (0.005, 0.2) m")


@dataclass
class LoopConfig:
    period_s: float = 0.008
    clock: Literal["auto", "lockstep", "wall"] = "auto"  # auto: lockstep for sim, wall otherwise
    slow_cycle_fraction: float = 0.8  # a cycle whose compute takes more than this x period is 'slow'

    def validate(self, where: str) -> None:
        require(0.001 <= self.period_s <= 0.1, f"{where}.period_s", f"must lie in [0.001, 0.1] s, got {self.period_s}")
        require(0 < self.slow_cycle_fraction <= 1, f"{where}.slow_cycle_fraction", "must lie in (0, 1]")


# Physical upper bounds of the safety limits (SafetyConfig.validate).
MAX_TOOL_FORCE_N = 200.0  # the F/T sensor's rated range: a force it cannot measure it cannot score
MAX_TOOL_TORQUE_NM = 10.0  # the shipped limit; the sensor is rated 4 N·m, the tasks' moments stay far below
MAX_TCP_SPEED = 1.0  # m/s: collaborative operation (the tasks command under 0.1)
WORKSPACE_REACH_M = 1.0  # the TM5-700 reaches 0.7 m from its shoulder
MAX_INVALID_CYCLES = 10  # sensor readings missing in a row before a stop: 80 ms at 8 ms
# Sane ranges of a task's motion settings (check_task_motion): the tasks' paths accelerate at 0.15 m/s^2
# and move centimetres; a value past these is a typo, not a task.
MAX_TASK_ACCEL = 2.0  # m/s^2
MAX_TASK_DISTANCE_M = 0.5  # m: half the workspace box


def _within(value: float, lo: float, hi: float, where: str, unit: str) -> None:
    require(lo < value <= hi, where, f"must lie in ({lo:g}, {hi:g}] {unit}, got {value:g}")


@dataclass
class SafetyConfig:
    """Limits checked every control cycle; a breach stops the arm."""

    max_tool_force_n: float = 150.0
    max_tool_torque_nm: float = 10.0
    joint_torque_fraction: float = 0.9  # of the URDF effort limit
    joint_speed_fraction: float = 0.8  # of the URDF velocity limit
    workspace_min: list[float] = field(default_factory=lambda: [-0.8, -0.8, 0.0])
    workspace_max: list[float] = field(default_factory=lambda: [0.8, 0.8, 1.0])
    max_tcp_speed: float = 0.5  # m/s, commanded
    max_sensor_invalid_cycles: int = 3

    def validate(self, where: str) -> None:
        # Upper bounds are physical: a limit the cell cannot measure or the arm cannot reach protects
        # nothing, and a typo (1e6 for 150) must not switch a limit off.
        _within(self.max_tool_force_n, 0, MAX_TOOL_FORCE_N, f"{where}.max_tool_force_n", "N")
        _within(self.max_tool_torque_nm, 0, MAX_TOOL_TORQUE_NM, f"{where}.max_tool_torque_nm", "N·m")
        require(0 < self.joint_torque_fraction <= 1, f"{where}.joint_torque_fraction", "must lie in (0, 1]")
        require(0 < self.joint_speed_fraction <= 1, f"{where}.joint_speed_fraction", "must lie in (0, 1]")
        require(len(self.workspace_min) == 3, f"{where}.workspace_min", "must have 3 values")
        require(len(self.workspace_max) == 3, f"{where}.workspace_max", "must have 3 values")
        require(all(a < b for a, b in zip(self.workspace_min, self.workspace_max, strict=True)),
                f"{where}.workspace_min", "must be below workspace_max on every axis")
        for name in ("workspace_min", "workspace_max"):
            values = getattr(self, name)
            require(all(abs(v) <= WORKSPACE_REACH_M for v in values), f"{where}.{name}",
                    f"must lie within +-{WORKSPACE_REACH_M} m of the base (beyond the arm's reach), got {values}")
        _within(self.max_tcp_speed, 0, MAX_TCP_SPEED, f"{where}.max_tcp_speed", "m/s")
        require(1 <= self.max_sensor_invalid_cycles <= MAX_INVALID_CYCLES, f"{where}.max_sensor_invalid_cycles",
                f"must lie in 1..{MAX_INVALID_CYCLES} control periods, got {self.max_sensor_invalid_cycles}")


@dataclass
class DeviceConfig:
    """One device: `sim` (in-process plant), `emulated` (real driver against a local emulator) or `real`."""

    kind: Literal["sim", "emulated", "real"] = "sim"
    settings: dict[str, Any] = field(default_factory=dict)  # driver-specific; validated by the driver


@dataclass
class DevicesConfig:
    arm: DeviceConfig = field(default_factory=DeviceConfig)
    sensor: DeviceConfig = field(default_factory=DeviceConfig)


@dataclass
class RecordingConfig:
    directory: str = "runs"  # relative to the working directory
    chunk_rows: int = 250

    def validate(self, where: str) -> None:
        require(self.chunk_rows >= 1, f"{where}.chunk_rows", "must be >= 1")


@dataclass
class CalibrationConfig:
    """The guided calibration of the virtual sensor against the F/T sensor (`main.py calibrate`).

    Postures are tool-down TCP poses [x, y, z (m), tilt about x, tilt about y (deg)] in the base
    frame, around where the tasks work; `holdout` lists the (0-based) postures kept out of training
    and used only to score the result."""

    postures: list[list[float]] = field(default_factory=lambda: [
        [0.40, -0.25, 0.12, 0.0, 0.0], [0.50, 0.00, 0.12, 0.0, 0.0], [0.40, 0.00, 0.20, 8.0, 0.0],
        [0.50, -0.25, 0.20, 0.0, -8.0], [0.45, -0.12, 0.09, 0.0, 0.0], [0.35, -0.12, 0.15, -8.0, 0.0],
        [0.55, -0.12, 0.15, 0.0, 8.0], [0.45, -0.05, 0.14, 4.0, 0.0], [0.43, -0.20, 0.10, 0.0, -4.0],
    ])
    holdout: list[int] = field(default_factory=lambda: [7, 8])
    # At rest, no load, before the free-space re-bias.  Why this long: after a move the joints creep
    # (tenths of a mrad/s) for about a second while the servo's integral settles, and the hybrid model
    # reads Coulomb friction from that velocity's sign; a zero taken while they still creep is off by
    # ~0.1 N·m in My once they have stopped (held-out My MAE 0.20 -> 0.12 N·m going from 0.8 s to
    # 1.2-2 s, docs/virtual-sensor-settings.md).  Must exceed virtual_sensor.rebias_window_s.
    settle_s: float = 1.5
    loads: int = 10  # load changes per posture
    load_s: float = 1.5  # each load: ramped in (0.25 s), then held; scored over its last 40 %
    max_force_n: float = 75.0  # |F| of a load (the paper's hand-applied 0-75 N)
    max_lateral_n: float = 15.0  # tool x, y force components (keeps the sensor's moments in range)
    max_moment_nm: float = 1.0  # tool x, y moments at the TCP (z: half of it)
    move_speed_fraction: float = 0.2  # of the joint speed limits, between postures
    operator_load_s: float = 20.0  # real cell: how long the operator pushes in each posture

    def validate(self, where: str) -> None:
        require(len(self.postures) >= 5, f"{where}.postures", "needs at least five postures")
        for i, p in enumerate(self.postures):
            require(len(p) == 5, f"{where}.postures[{i}]", "must be [x, y, z, tilt_x_deg, tilt_y_deg]")
        require(len(self.holdout) >= 1, f"{where}.holdout", "must name at least one held-out posture")
        require(all(0 <= i < len(self.postures) for i in self.holdout), f"{where}.holdout",
                "must index the postures list")
        require(len(set(self.holdout)) < len(self.postures) - 2, f"{where}.holdout",
                "must leave at least three postures for training")
        for name in ("settle_s", "load_s", "max_force_n", "move_speed_fraction", "operator_load_s"):
            require(getattr(self, name) > 0, f"{where}.{name}", "must be > 0")
        require(self.loads >= 2, f"{where}.loads", "must be >= 2")
        require(self.max_lateral_n >= 0 and self.max_moment_nm >= 0, f"{where}.max_lateral_n",
                "and max_moment_nm must be >= 0")


@dataclass
class ToolSensorSettings:
    """One tool's values of the virtual sensor's settings (observer and mapping); unset ones are
    `virtual_sensor`'s."""

    observer: Literal["kalman", "momentum"] | None = None
    process_noise_nm: list[float] | None = None
    innovation_gate: float | None = None
    momentum_gain: float | None = None
    zero_at_tare: bool | None = None
    mapping: Literal["jacobian", "learned", "contact"] | None = None
    free_moment_nm: float | None = None
    measurement_noise: Literal["calibrated", "model"] | None = None
    touch_gain: float | None = None
    touch_band_n: float | None = None


@dataclass
class VirtualSensorConfig:
    """The virtual force sensor (paper section 4): external-torque observer + wrench mapping.

    Artefact paths may contain `{tool}` ("wipe", "peg") and are relative to the working directory
    (as `recording.directory` is): the model lab's H1 for that tool and its calibration."""

    observer: Literal["kalman", "momentum"] = "kalman"
    # Per tool (wipe | peg): settings its tasks (and its calibration's reported route) use where they
    # differ from the ones here; `for_tool` merges them.
    by_tool: dict[str, ToolSensorSettings] = field(default_factory=dict)
    # jacobian: (J^T)^+ tau_ext | learned: the paper's XGBoost Fz, Mx, My | contact: (J^T)^+ with the
    # prior that the tool is touched at its TCP (cell/sensing/wrench_map.py ContactMap)
    mapping: Literal["jacobian", "learned", "contact"] = "jacobian"
    data_dir: str = "artifacts/data/{tool}"
    model_dir: str = "artifacts/models/{tool}"
    calibration_dir: str = "artifacts/calibration/{tool}"
    # Kalman random-walk process noise, std per control period per joint [N·m]; the measurement
    # noise comes from the model's residual statistics (measured by the calibration).
    # Half of this (0.05 on joints 1-3) lags the wiping force loop into a ~1 Hz oscillation at 60 N.
    process_noise_nm: list[float] = field(default_factory=lambda: [0.1, 0.1, 0.1, 0.02, 0.02, 0.02])
    # Innovation gate [standard deviations, 0: off]: a joint breaking away from stiction swings the
    # raw residual by +-10 N·m for a few periods, which an ungated filter reads as a 5 N contact.
    innovation_gate: float = 3.0
    # The Kalman filter's measurement noise: "calibrated", the calibration's free-motion residual
    # variance per joint (constant); "model", that variance raised each period to the hybrid model's
    # own uncertainty there (cell/model/dynamics/uncertainty.py: wider at speeds it fits worse, outside its
    # training coverage and, where it models a sticking regime, within the static friction band).
    measurement_noise: Literal["calibrated", "model"] = "calibrated"
    # 1/s, bandwidth of the momentum observer's first-order response (it has no gate: at 25/s a joint
    # breaking away from stiction at the start of the approach reads as a contact).
    momentum_gain: float = 10.0
    rebias_window_s: float = 0.2  # free-space re-bias averages the raw estimate over this much
    # Whether a task's tare (`ForceSource.rebias`) re-zeroes the estimate.  At rest every joint's static
    # friction holds some unknown torque within its break-away band, which a zero taken there carries
    # into the motion that follows (see config/cell.yaml for the tool that goes without).
    zero_at_tare: bool = True
    # While the task expects a touch (its `touch_states`), a momentum observer of this bandwidth [1/s] runs
    # beside the configured one, and its force's departure from the configured reading beyond touch_band_n
    # [N] is added to it: a stiff touch rings for a few periods, which the steady observer filters away
    # (it read 5 N of a 38 N touch).  0: off.
    touch_gain: float = 0.0
    touch_band_n: float = 4.0
    # The contact map's prior standard deviation of the moment a force at the TCP does not explain [N·m].
    free_moment_nm: float = 0.3
    wrench_point: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.035])  # flange frame: the F/T face
    singular_sigma: float = 0.03  # smallest Jacobian singular value below which the map is damped, flagged
    max_damping: float = 0.05  # damping at an exact singularity
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def validate(self, where: str) -> None:
        require_len(self.process_noise_nm, 6, f"{where}.process_noise_nm")
        require(all(v > 0 for v in self.process_noise_nm), f"{where}.process_noise_nm", "must be > 0")
        require(self.momentum_gain > 0, f"{where}.momentum_gain", "must be > 0 (1/s)")
        require(0 <= self.touch_gain <= 1000, f"{where}.touch_gain", "must lie in [0, 1000] 1/s (0: off)")
        require(self.touch_band_n >= 0, f"{where}.touch_band_n", "must be >= 0 (N)")
        require(self.innovation_gate >= 0, f"{where}.innovation_gate", "must be >= 0 (0: off)")
        require(self.rebias_window_s > 0, f"{where}.rebias_window_s", "must be > 0")
        require(self.free_moment_nm > 0, f"{where}.free_moment_nm", f"must be > 0 (N·m), got {self.free_moment_nm}")
        require(self.calibration.settle_s > self.rebias_window_s, f"{where}.calibration.settle_s",
                f"({self.calibration.settle_s} s) must exceed rebias_window_s ({self.rebias_window_s} s): "
                "the re-bias would average the move")
        for tool in self.by_tool:
            require(tool in TOOLS, f"{where}.by_tool", f"unknown tool '{tool}' ({', '.join(TOOLS)})")
            self.for_tool(tool).validate(join(where, f"by_tool.{tool}"))
        require(len(self.wrench_point) == 3, f"{where}.wrench_point", "must have 3 values (x, y, z) in m")
        require(self.singular_sigma > 0 and self.max_damping > 0, f"{where}.singular_sigma",
                "and max_damping must be > 0")

    def for_tool(self, tool: str) -> VirtualSensorConfig:
        """These settings with `tool`'s own values (`by_tool`) in place of the shared ones."""
        own = self.by_tool.get(tool)
        if own is None:
            return replace(self, by_tool={})
        return replace(self, by_tool={}, **{k: v for k, v in asdict(own).items() if v is not None})

    def path(self, which: str, tool: str) -> Path:
        return Path(str(getattr(self, f"{which}_dir")).replace("{tool}", tool))


@dataclass
class CellConfig:
    robot: RobotConfig = field(default_factory=RobotConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    devices: DevicesConfig = field(default_factory=DevicesConfig)
    plant: str = "plants/default.yaml"
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    tasks: dict[str, dict[str, Any]] = field(default_factory=dict)  # validated by each task
    virtual_sensor: VirtualSensorConfig = field(default_factory=VirtualSensorConfig)
    collision: CollisionConfig = field(default_factory=CollisionConfig)

    source: str = ""  # file this was loaded from (not a config key)

    def validate(self, where: str) -> None:
        for task in self.tasks:
            require(task in TASK_SECTIONS, join(where, "tasks"),
                    f"unknown task '{task}' (known: {', '.join(TASK_SECTIONS)})")
        self._check_observer_gains(where)

    def _check_observer_gains(self, where: str) -> None:
        """Every first-order observer's gain times the control period under 1: a discrete observer
        r_k = (1 - K dt) r_(k-1) + K dt x_k turns its estimate's sign each period from K dt = 1 on (a
        touch channel at 110/s rang to +-30 N in free air at 15.6 ms)."""
        dt = self.loop.period_s
        vs, det = self.virtual_sensor, self.collision.detector
        gains: list[tuple[str, float | None]] = [
            ("collision.detector.observer_gain", det.observer_gain),
            ("collision.detector.wire_observer_gain", det.wire_observer_gain),
            ("virtual_sensor.momentum_gain", vs.momentum_gain), ("virtual_sensor.touch_gain", vs.touch_gain)]
        for tool, own in vs.by_tool.items():
            gains += [(f"virtual_sensor.by_tool.{tool}.momentum_gain", own.momentum_gain),
                      (f"virtual_sensor.by_tool.{tool}.touch_gain", own.touch_gain)]
        for name, k in gains:
            if k is not None:
                require(k * dt < 1.0, join(where, name),
                        f"({k:g} 1/s) times loop.period_s ({dt:g} s) is {k * dt:.2f}: the observer's estimate "
                        f"alternates sign every period from 1 on; at this period it must be under {1 / dt:.1f} 1/s")


TASK_SECTIONS = ("wipe", "peg", "hand_guide")  # config sections under `tasks` (each validated by its task)
# A cell config names every section: a missing one would silently run built-in defaults that differ
# from the shipped file (config/cell.yaml is the documented starting point).
REQUIRED_SECTIONS = ("robot", "scene", "loop", "safety", "devices", "plant", "virtual_sensor", "collision")


def load_config(path: Path | None = None) -> CellConfig:
    path = Path(path) if path is not None else DEFAULT_CONFIG
    data = read_layered_yaml(path)
    if not data:
        raise ConfigError(f"{path}: the file is empty: a cell config needs its sections (start from {DEFAULT_CONFIG})")
    missing = [k for k in REQUIRED_SECTIONS if k not in data]
    if missing:
        raise ConfigError(f"{path}: missing section '{missing[0]}' (a cell config names "
                          f"{', '.join(REQUIRED_SECTIONS)}; start from {DEFAULT_CONFIG})")
    data.pop("source", None)
    cfg = load_dataclass(CellConfig, data, f"{path}:")
    cfg.source = str(path)
    return cfg


def check_home(cfg: CellConfig, robot: Any) -> None:
    """`robot.home` within the arm's joint limits (`robot`: a cell.robot.RobotModel): a home outside
    them is a posture the arm cannot take, or one in collision."""
    lim = robot.limits
    for j, (q, lo, hi) in enumerate(zip(cfg.robot.home, lim.lower, lim.upper, strict=True)):
        require(lo <= q <= hi, f"{cfg.source}: robot.home[{j}]",
                f"({q:g} rad) must lie within joint {j + 1}'s limits [{lo:.4g}, {hi:.4g}] rad")


def check_task_motion(settings: Any, where: str, max_speed: float = MAX_TCP_SPEED,
                      limit: str = "the highest TCP speed a cell allows") -> None:
    """A task's settings dataclass: every speed (`*_mps`) at most `max_speed` (`limit` names it), every
    acceleration (`*_mps2`) in (0, MAX_TASK_ACCEL] and every distance (`*_m`) in [0, MAX_TASK_DISTANCE_M]."""
    for f in fields(settings):
        value = getattr(settings, f.name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            continue
        name = f"{where}.{f.name}"
        if f.name.endswith("_mps"):
            require(value <= max_speed, name, f"({value:g} m/s) must not exceed {limit} ({max_speed:g} m/s)")
        elif f.name.endswith("_mps2"):
            require(0 < value <= MAX_TASK_ACCEL, name, f"must lie in (0, {MAX_TASK_ACCEL:g}] m/s^2, got {value:g}")
        elif f.name.endswith("_m"):
            require(0 <= value <= MAX_TASK_DISTANCE_M, name,
                    f"must lie in [0, {MAX_TASK_DISTANCE_M:g}] m, got {value:g}")


def check_task_speeds(cfg: CellConfig, task: str, settings: Any) -> None:
    """A task's speeds within the cell's TCP speed limit: the task must never command what safety stops."""
    check_task_motion(settings, f"{cfg.source}: tasks.{task}", cfg.safety.max_tcp_speed, "safety.max_tcp_speed")


def check_task_force(cfg: CellConfig, task: str, max_force_n: float) -> None:
    """A task's own force limit within the cell's: the task aborts first, the safety stop is the backstop."""
    require(max_force_n <= cfg.safety.max_tool_force_n, f"{cfg.source}: tasks.{task}.max_force_n",
            f"({max_force_n:g} N) must not exceed safety.max_tool_force_n ({cfg.safety.max_tool_force_n:g} N)")
