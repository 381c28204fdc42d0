"""Sensorless hand guiding: admittance on the virtual wrench.  The operator's force on the tool (the force
source's wrench, turned around and into the base frame) drives a virtual mass-damper per axis,
M dv/dt + D v = F - deadband, whose velocity moves the TCP reference (orientation held).  Speed and a
workspace box bound it; on release (the force back within the deadband) the reference brakes to rest; a
force above `max_force_n` stops the arm (the task fails, the loop stops it).  Taught poses: each place the
tool comes to rest after it was moved at least `teach_min_move_m` (for `--teach`)."""

from __future__ import annotations

import collections
import enum
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from cell.config import ToolSensorSettings, VirtualSensorConfig
from cell.control.loop import Command, Observation
from cell.control.trajectory import JointMove, tool_down_pose
from cell.model.robot import RobotModel
from drivers.configio import load_dataclass, require
from tasks.base import MachineTask, Trigger

log = logging.getLogger(__name__)


class GuideState(enum.Enum):
    MOVE_TO_START = "move_to_start"
    TARE = "tare"
    GUIDE = "guide"
    DONE = "done"
    FAILED = "failed"


@dataclass
class HandGuideConfig:
    """`tasks.hand_guide` in the cell config (every field has this default)."""

    mass_kg: list[float] = field(default_factory=lambda: [4.0, 4.0, 4.0])  # virtual mass per base axis
    # Virtual damping: the virtual sensor reads about 0.1 s late (its observer's bandwidth), which a hand of
    # stiffness K feels as a negative damping of about 0.1 * K (80 N s/m at 800 N/m); 90 keeps the loop
    # damped at a steady 9 N of the hand's force per 0.1 m/s.
    damping_ns_per_m: list[float] = field(default_factory=lambda: [90.0, 90.0, 90.0])
    deadband_n: float = 3.0  # |F| under this moves nothing: above the virtual sensor's error at rest
    max_speed_mps: float = 0.15
    # Coming to rest, the joints stick holding the kinetic friction they had, which the model (no friction at
    # zero speed) reads as the hand still pushing along the last motion for a few tenths of a second: for
    # `rest_hold_s` after the tool stopped, only a force above `restart_n` moves it again (0: off).  The bias
    # lasts about a second, and a restart within it starts with the joints' break-away, which the observer reads
    # as a push along the motion: a hand holding a few newtons at rest would creep the tool on in jolts.
    rest_hold_s: float = 1.0
    restart_n: float = 10.0
    # The tool coming to rest kicks the reading: as its joints stick, the reading jumps along the last motion
    # within a few periods and then decays at the observer's bandwidth (14 N with the arm stopped by the F/T
    # sensor's admittance, up to about 25 N in the virtual sensor's own loop, at the observer's default gain).
    # After the tool stopped, the force must exceed deadband_n + `rest_kick_n` for `rest_kick_hold_s`, a band
    # that then decays at `rest_kick_decay_per_s` (the observer's bandwidth: momentum_gain); the force limit
    # is raised by the same amount, so the kick neither moves nor stops the arm; the collision guard still
    # watches (0: off).
    rest_kick_n: float = 25.0
    rest_kick_hold_s: float = 0.1
    rest_kick_decay_per_s: float = 10.0
    # From rest the reading lags the hand the most (the joints' static friction first holds part of the push,
    # then the observer's lag): until the tool first moves faster than `start_speed_mps`, the damping is
    # `start_damping_scale` of damping_ns_per_m (1: off), so the arm catches up with the hand.  It applies at
    # the start and again once the tool has rested `start_after_rest_s`.
    start_damping_scale: float = 0.5
    start_speed_mps: float = 0.08
    start_after_rest_s: float = 0.5
    brake_mps2: float = 1.0  # deceleration to rest on release
    # The admittance's acceleration cap: the virtual sensor reads a fast arm's inertial torques as force
    # (its model's error grows with acceleration), which a light virtual mass would then chase.
    max_accel_mps2: float = 5.0
    max_force_n: float = 30.0  # a guiding force above this stops the arm
    # The arm's own acceleration read back as a hand force: when the arm accelerates the virtual sensor's
    # momentum observer reads about `inertia_readback` of the arm's inertial force (Cartesian inertia of the
    # controller's model, rotor inertia included, times the commanded acceleration) against the motion,
    # `inertia_readback_periods` control periods after the command, then relaxes at the observer's bandwidth
    # (`inertia_readback_decay_per_s`).  The task commands that acceleration, so it adds the predicted reading
    # back before using the force (0: off).  Uncompensated it closes a loop of gain
    # inertia_readback * inertia / mass_kg with a two-period delay, which rings at the control rate for a light
    # virtual mass and makes every stop ring.  Identified on free motion with random accelerations, the
    # coefficient is about momentum_gain * period (0.075 at 10/s and 8 ms), with the decay at momentum_gain:
    # both move with the guiding observer's gain.  The inertia must include the rotors' (3-4 times the links'
    # alone here): the callers pass the hybrid model's (`model_inertia`).
    inertia_readback: float = 0.075
    inertia_readback_periods: int = 2
    inertia_readback_decay_per_s: float = 10.0
    workspace_min: list[float] = field(default_factory=lambda: [0.2, -0.45, 0.1])
    workspace_max: list[float] = field(default_factory=lambda: [0.65, 0.35, 0.5])
    start_xyz: list[float] = field(default_factory=lambda: [0.40, -0.15, 0.25])  # tool down here first
    move_speed_fraction: float = 0.15  # of the joint speed limits, for the move to the start
    tare_time_s: float = 0.5  # rest, then zero the force source: nobody touches the tool then
    duration_s: float = 600.0  # guiding ends (done) after this
    teach_rest_s: float = 0.8  # a taught pose: at rest this long ...
    teach_rest_speed_mps: float = 0.003  # ... (slower than this) ...
    teach_min_move_m: float = 0.03  # ... and this far from the last taught pose
    # The virtual sensor's settings while guiding, over the tool's own (`virtual_sensor.by_tool`); unset: theirs.
    virtual_sensor: ToolSensorSettings = field(default_factory=ToolSensorSettings)

    def validate(self, where: str) -> None:
        for name in ("mass_kg", "damping_ns_per_m", "workspace_min", "workspace_max"):
            require(len(getattr(self, name)) == 3, f"{where}.{name}", "must have 3 values (x, y, z)")
        require(len(self.start_xyz) == 3, f"{where}.start_xyz", "must be [x, y, z] in m")
        require(0 < self.move_speed_fraction <= 0.5, f"{where}.move_speed_fraction", "must lie in (0, 0.5]")
        require(all(m > 0 for m in self.mass_kg), f"{where}.mass_kg", "must be > 0 kg")
        require(all(d > 0 for d in self.damping_ns_per_m), f"{where}.damping_ns_per_m", "must be > 0 N s/m")
        require(0 < self.deadband_n < self.max_force_n, f"{where}.deadband_n", "must lie in (0, max_force_n)")
        require(self.rest_hold_s >= 0, f"{where}.rest_hold_s", "must be >= 0 s")
        require(self.deadband_n <= self.restart_n < self.max_force_n, f"{where}.restart_n",
                "must lie in [deadband_n, max_force_n)")
        require(0 < self.max_speed_mps <= 0.25, f"{where}.max_speed_mps", "must lie in (0, 0.25] m/s")
        require(self.brake_mps2 > 0 and self.max_accel_mps2 > 0, f"{where}.brake_mps2",
                "and max_accel_mps2 must be > 0 m/s^2")
        require(all(lo < hi for lo, hi in zip(self.workspace_min, self.workspace_max, strict=True)),
                f"{where}.workspace_min", "must be below workspace_max on every axis")
        for name in ("tare_time_s", "duration_s", "teach_rest_s", "teach_rest_speed_mps", "teach_min_move_m"):
            require(getattr(self, name) > 0, f"{where}.{name}", "must be > 0")
        require(0 <= self.inertia_readback <= 1, f"{where}.inertia_readback", "must lie in [0, 1] (0: off)")
        require(1 <= self.inertia_readback_periods <= 10, f"{where}.inertia_readback_periods", "must lie in 1..10")
        require(self.rest_kick_n >= 0 and self.rest_kick_hold_s >= 0 and self.rest_kick_decay_per_s >= 0,
                f"{where}.rest_kick_n", "rest_kick_hold_s and rest_kick_decay_per_s must be >= 0")
        require(0 < self.start_damping_scale <= 1, f"{where}.start_damping_scale", "must lie in (0, 1] (1: off)")
        require(self.start_speed_mps >= 0 and self.start_after_rest_s >= 0, f"{where}.start_speed_mps",
                "and start_after_rest_s must be >= 0")
        require(self.inertia_readback_decay_per_s >= 0, f"{where}.inertia_readback_decay_per_s", "must be >= 0 (1/s)")


def load_hand_guide_config(raw: dict[str, Any] | None, where: str) -> HandGuideConfig:
    return load_dataclass(HandGuideConfig, raw or {}, where)


def guiding_sensor(vs: VirtualSensorConfig, tool: str, own: ToolSensorSettings, where: str) -> VirtualSensorConfig:
    """The virtual sensor's settings for hand guiding: `tool`'s, with the guiding's own values (`own`) on top;
    checked as the cell's are (ConfigError naming the field)."""
    base = vs.for_tool(tool)
    merged = replace(base, **{k: v for k, v in asdict(own).items() if v is not None})
    merged.validate(where)
    return merged


class CartesianInertia:
    """The arm's translational inertia at the TCP with orientation held: the 3x3 block of J^-T M(q) J^-1
    (base frame), M from a Pinocchio model plus the rotor inertia (the controller's hybrid model's, or the
    nominal URDF's without rotors)."""

    def __init__(self, robot: RobotModel, model: Any | None = None, rotor: np.ndarray | None = None) -> None:
        self.robot = robot
        self.model = model if model is not None else robot.model
        self.data = self.model.createData()
        self.rotor = np.zeros(robot.n) if rotor is None else np.asarray(rotor, float)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        import pinocchio as pin

        M = pin.crba(self.model, self.data, q)
        M = np.triu(M) + np.triu(M, 1).T + np.diag(self.rotor)
        Ji = np.linalg.inv(self.robot.tcp_jacobian(q))
        return (Ji.T @ M @ Ji)[:3, :3]


def model_inertia(robot: RobotModel, model: Any) -> CartesianInertia:
    """The Cartesian inertia of a hybrid model's identified rigid body with its rotors (what the observer's
    read-back of the commanded acceleration scales with)."""
    return CartesianInertia(robot, model.physics.model, np.asarray(model.physics.params.B_m, float))


class HandGuideTask(MachineTask):
    name = "hand-guide"
    regulated_states = ("guide",)
    arrived: Trigger
    tared: Trigger
    finished: Trigger

    def __init__(self, cfg: HandGuideConfig, robot: RobotModel, dt: float, q_home: np.ndarray,
                 inertia: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        self.cfg = cfg
        self.inertia = inertia if inertia is not None else CartesianInertia(robot)
        # The commanded inertial forces of the last `inertia_readback_periods` periods (newest last) and the
        # low-pass, at the decay rate, of the ones before.
        self._inertial: collections.deque[np.ndarray] = collections.deque(
            [np.zeros(3)] * cfg.inertia_readback_periods, maxlen=cfg.inertia_readback_periods)
        self._inertial_lp = np.zeros(3)
        self.readback = np.zeros(3)
        self.robot = robot
        self.dt = dt
        super().__init__(GuideState.MOVE_TO_START, [
            ("arrived", GuideState.MOVE_TO_START, GuideState.TARE),
            ("tared", GuideState.TARE, GuideState.GUIDE),
            ("finished", GuideState.GUIDE, GuideState.DONE),
        ])
        self.mass = np.asarray(cfg.mass_kg, float)
        self.damping = np.asarray(cfg.damping_ns_per_m, float)
        self.lo, self.hi = np.asarray(cfg.workspace_min, float), np.asarray(cfg.workspace_max, float)
        self.ref: Any = None
        self.v = np.zeros(3)
        self.peak_force = 0.0
        self.taught: list[list[float]] = []  # taught TCP positions [m]
        self._rest_t = 0.0
        self._hold_t = 0.0  # time left of the rest hold (rest_hold_s)
        self._since_rest = np.inf  # time since the tool last came to rest (braked to zero)
        self._still_s = np.inf  # how long the admittance's velocity has been zero
        self._starting = True  # from rest: the start's damping (start_damping_scale)
        self._moved_since_taught = False
        self.stop_force_n: float | None = None
        start = tool_down_pose(np.asarray(cfg.start_xyz, float))
        q_start, ok = robot.ik(start, q_home)
        if not ok:
            raise ValueError(f"hand-guide start {cfg.start_xyz} is not reachable")
        self.q_start = q_start
        self.move: JointMove | None = None

    def step(self, obs: Observation) -> Command:
        rebias = False
        f_hand = np.full(3, np.nan)
        if self.state == GuideState.MOVE_TO_START:
            if self.move is None:
                speed = self.robot.limits.velocity * self.cfg.move_speed_fraction
                self.move = JointMove(obs.q_cmd, self.q_start, speed)
            q = self.move.at(self.t_state)
            if self.t_state >= self.move.duration:
                self.arrived()
            self.t_state += self.dt
            t = self.robot.tcp_pose(q).translation
            return Command(q=q, log=self._row(t, f_hand))
        if self.ref is None:
            self.ref = self.robot.tcp_pose(self.q_start)
            self._last_taught = self.ref.translation.copy()
        if self.state == GuideState.TARE:
            if self.t_state + self.dt >= self.cfg.tare_time_s:
                self.tared()
                rebias = True
        elif self.state == GuideState.GUIDE:
            f_hand = self._guide(obs)
            if self.t_state >= self.cfg.duration_s:
                self.finished()
        self.t_state += self.dt
        q, _ = self.robot.ik(self.ref, obs.q_cmd, iters=3, tol=1e-7)
        return Command(q=q, rebias_force=rebias, log=self._row(self.ref.translation, f_hand))

    def _row(self, t: np.ndarray, f_hand: np.ndarray) -> dict[str, float | str]:
        return {"ref_x": float(t[0]), "ref_y": float(t[1]), "ref_z": float(t[2]), "fz_setpoint": 0.0,
                "hand_fx": float(f_hand[0]), "hand_fy": float(f_hand[1]), "hand_fz": float(f_hand[2]),
                "v_x": float(self.v[0]), "v_y": float(self.v[1]), "v_z": float(self.v[2])}

    def _guide(self, obs: Observation) -> np.ndarray:
        c = self.cfg
        R = self.robot.tcp_pose(np.asarray(obs.state.q, float)).rotation
        # The tool exerts w on the hand (cell convention): the hand pushes the tool with -w.
        f = -(R @ np.asarray(obs.wrench.force, float))
        if not np.all(np.isfinite(f)):
            f = np.zeros(3)  # a missing reading: brake as on release (the safety monitor counts them)
        elif c.inertia_readback > 0:
            f = f + self.readback
        norm = float(np.linalg.norm(f))
        self.peak_force = max(self.peak_force, norm)
        # The rest kick (`rest_kick_n`) as it stands now: it raises the band that moves the tool and the limit.
        self._since_rest += self.dt
        kick = 0.0
        if c.rest_kick_n > 0 and np.isfinite(self._since_rest):
            kick = c.rest_kick_n * float(np.exp(-c.rest_kick_decay_per_s
                                                * max(0.0, self._since_rest - c.rest_kick_hold_s)))
        if norm > c.max_force_n + kick:
            self.stop_force_n = norm
            self.fail_because(f"guiding force {norm:.1f} N above the limit {c.max_force_n + kick:.3g} N: arm stopped")
            self.v[:] = 0.0
            return f
        v_before = self.v.copy()
        # The deadband on the force's magnitude keeps its direction (an axis-wise band would bend it).
        f_eff = f * max(0.0, 1.0 - c.deadband_n / norm) if norm > 0 else f
        self._hold_t = max(0.0, self._hold_t - self.dt)
        band = c.restart_n if self._hold_t > 0 else c.deadband_n
        band = max(band, c.deadband_n + kick)
        if self._still_s >= c.start_after_rest_s:
            self._starting = True
        if norm <= band:
            # Released: brake to rest, whatever the virtual mass would coast.
            speed = float(np.linalg.norm(self.v))
            if speed > 0:
                self.v *= max(0.0, speed - c.brake_mps2 * self.dt) / speed
                if not np.any(self.v):
                    self._hold_t = c.rest_hold_s
                    self._since_rest = 0.0
        else:
            if float(np.linalg.norm(self.v)) > c.start_speed_mps:
                self._starting = False
            damping = self.damping * c.start_damping_scale if self._starting else self.damping
            a = (f_eff - damping * self.v) / self.mass
            na = float(np.linalg.norm(a))
            if na > c.max_accel_mps2:
                a *= c.max_accel_mps2 / na
            self.v += self.dt * a
        speed = float(np.linalg.norm(self.v))
        if speed > c.max_speed_mps:
            self.v *= c.max_speed_mps / speed
        p = self.ref.translation + self.v * self.dt
        clipped = np.clip(p, self.lo, self.hi)
        self.v[clipped != p] = 0.0  # at the workspace's wall: stop along that axis
        self.ref.translation = clipped
        self._still_s = 0.0 if np.any(self.v) else self._still_s + self.dt
        self._predict_readback(obs, (self.v - v_before) / self.dt)
        self._teach(obs)
        return f

    def _predict_readback(self, obs: Observation, a_cmd: np.ndarray) -> None:
        """The part of the next reading that is the arm's own commanded acceleration (see `inertia_readback`):
        the inertial force of `inertia_readback_periods` ago, less its low-pass at the observer's bandwidth."""
        c = self.cfg
        if c.inertia_readback <= 0:
            return
        self._inertial.append(self.inertia(np.asarray(obs.state.q, float)) @ a_cmd)
        x = self._inertial[0]
        self.readback = c.inertia_readback * (x - self._inertial_lp)
        self._inertial_lp += min(1.0, c.inertia_readback_decay_per_s * self.dt) * (x - self._inertial_lp)

    def _teach(self, obs: Observation) -> None:
        c = self.cfg
        tcp = self.robot.tcp_pose(np.asarray(obs.state.q, float)).translation
        if float(np.linalg.norm(tcp - self._last_taught)) > c.teach_min_move_m:
            self._moved_since_taught = True
        if float(np.linalg.norm(self.v)) < c.teach_rest_speed_mps:
            self._rest_t += self.dt
        else:
            self._rest_t = 0.0
        if self._moved_since_taught and self._rest_t >= c.teach_rest_s:
            self.taught.append([round(float(v), 5) for v in tcp])
            self._last_taught = tcp.copy()
            self._moved_since_taught = False
            log.info("taught pose %d at %s m", len(self.taught), self.taught[-1])

    def summary(self) -> dict[str, Any]:
        return {"task": self.name, "outcome": self.outcome, "reason": self.reason, "final_state": self.state.value,
                "peak_force_n": self.peak_force, "taught_poses": len(self.taught),
                "stop_force_n": self.stop_force_n}


def taught_task_file(poses: list[list[float]], rpy_deg: list[float], tool: str, name: str) -> dict[str, Any]:
    """A task file (docs/task-files.md) that visits the taught poses in order: what `--teach` writes."""
    names = [f"taught_{i + 1}" for i in range(len(poses))]
    return {
        "name": name,
        "description": "poses taught by hand guiding (main.py run hand-guide --teach)",
        "tool": tool,
        "scene": "free",
        # Fresh lists per pose: yaml.safe_dump writes a shared one as an alias, which task files refuse.
        "poses": {n: {"xyz": list(p), "rpy_deg": list(rpy_deg)} for n, p in zip(names, poses, strict=True)},
        "steps": ([{"move": {"to": names[0], "space": "joint", "speed_fraction": 0.15}}] if names else [])
                 + [{"move": {"to": n, "speed_mps": 0.05}} for n in names[1:]] or [{"wait": {"time_s": 0.1}}],
    }
