"""The plant profile: how the simulated 'true' arm differs from the nominal URDF (YAML in config/plants/)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from cell.config import read_layered_yaml
from drivers.configio import join, load_dataclass, require, require_len

LINKS = ("link_1", "link_2", "link_3", "link_4", "link_5", "link_6")


@dataclass
class InertialDeviation:
    """True inertial parameters relative to the URDF: absolute COMs, mass and inertia scale factors."""

    com: dict[str, list[float]] = field(default_factory=dict)  # link -> COM in the link frame [m]
    mass_scale: list[float] = field(default_factory=lambda: [1.0] * 6)
    inertia_scale: list[float] = field(default_factory=lambda: [1.0] * 6)

    def validate(self, where: str) -> None:
        for link, com in self.com.items():
            require(link in LINKS, f"{where}.com.{link}", f"is not a link of the arm ({', '.join(LINKS)})")
            require(len(com) == 3, f"{where}.com.{link}", f"must have 3 values (x, y, z), got {len(com)}")
        for name in ("mass_scale", "inertia_scale"):
            values = getattr(self, name)
            require_len(values, 6, f"{where}.{name}")
            for i, v in enumerate(values):
                require(0.2 <= v <= 5.0, f"{where}.{name}[{i}]", f"must lie in [0.2, 5], got {v}")


@dataclass
class FrictionProfile:
    """Joint losses of the true arm.  The friction torque magnitude each physics step is

        Fc * (1 + load * |tau_motor| / effort) + Fs * exp(-(v/vs)^2) + A * sin(cycles * q + phase)

    (Coulomb, load-dependent gear friction, Stribeck breakaway, position-dependent ripple) opposing
    the motion, plus `viscous * v`.  A textbook loss model (B_m, C_m, f_c sign) captures only the
    Coulomb and viscous parts; the rest is what a learned residual has to find.
    """

    viscous: list[float]  # N·m·s/rad
    coulomb: list[float]  # N·m
    stribeck: list[float]  # N·m extra at rest
    stribeck_velocity: list[float]  # rad/s
    ripple_amplitude: list[float]  # N·m
    ripple_cycles: list[float]  # ripple periods per joint revolution
    load: list[float]  # Coulomb increase per unit of |tau_motor| / effort limit

    def validate(self, where: str) -> None:
        for name in ("viscous", "coulomb", "stribeck", "stribeck_velocity", "ripple_amplitude",
                     "ripple_cycles", "load"):
            values = getattr(self, name)
            require_len(values, 6, f"{where}.{name}")
            for i, v in enumerate(values):
                require(v >= 0, f"{where}.{name}[{i}]", f"must be >= 0, got {v}")
        for i in range(6):
            require(self.stribeck_velocity[i] > 0, f"{where}.stribeck_velocity[{i}]", "must be > 0")
            require(self.ripple_amplitude[i] < self.coulomb[i] or self.ripple_amplitude[i] == 0,
                    f"{where}.ripple_amplitude[{i}]", "must be below the Coulomb level (friction cannot push)")


@dataclass
class TorqueSensing:
    """How the controller measures joint torque: white noise, quantisation and latency."""

    noise_std: list[float]  # N·m
    quantum: float = 0.001  # N·m (the controller reports mN·m)
    latency_periods: int = 0  # measured state is this many control periods old

    def validate(self, where: str) -> None:
        require_len(self.noise_std, 6, f"{where}.noise_std")
        require(all(v >= 0 for v in self.noise_std), f"{where}.noise_std", "must be >= 0")
        require(self.quantum >= 0, f"{where}.quantum", "must be >= 0")
        require(0 <= self.latency_periods <= 10, f"{where}.latency_periods", "must lie in 0..10")


@dataclass
class ServoProfile:
    """The arm controller's own joint servo: PID on the interpolated target plus its own model's bias."""

    kp: list[float]  # N·m/rad
    kd: list[float]  # N·m·s/rad
    ki: list[float]  # N·m/(rad·s)
    # Periods between a target's arrival and the servo's use of it, beyond the interpolation's own
    # period: the transport and buffering of a command channel (TM's Listen node queues scripts).
    command_latency_periods: int = 0

    def validate(self, where: str) -> None:
        for name in ("kp", "kd", "ki"):
            require_len(getattr(self, name), 6, f"{where}.{name}")
            require(all(v >= 0 for v in getattr(self, name)), f"{where}.{name}", "must be >= 0")
        require(0 <= self.command_latency_periods <= 5, f"{where}.command_latency_periods", "must lie in 0..5")


@dataclass
class FTSensorProfile:
    """The WACOH WEF-6A200 at the flange, as the plant produces its readings."""

    mass: float = 0.25  # kg
    length: float = 0.035  # m, flange to sensing face
    offset_force_n: float = 20.0  # unloaded offset drawn uniformly in +-this [N]
    offset_torque_nm: float = 0.4  # [N·m]
    noise_force_n: float = 0.05
    noise_torque_nm: float = 0.001
    quantum_force_n: float = 0.03
    quantum_torque_nm: float = 0.0006
    saturation_force_n: float = 200.0
    saturation_torque_nm: float = 4.0

    def validate(self, where: str) -> None:
        for name, value in vars(self).items():
            require(value >= 0, f"{where}.{name}", f"must be >= 0, got {value}")


@dataclass
class ToolProfile:
    """The true tool behind the sensor (its nominal twin is in the cell config)."""

    wipe_mass: float = 0.2  # kg, shaft (the sprung head adds sim.mjcf.PAD_MASS)
    wipe_length: float = 0.10  # m, sensor face to pad centre
    pad_radius: float = 0.02  # m
    pad_stiffness: float = 25000.0  # N/m, the compliant wiping pad
    pad_damping: float = 300.0  # N·s/m
    pad_friction: float = 0.3
    gripper_mass: float = 0.6  # kg
    gripper_length: float = 0.06  # m
    peg_diameter: float = 0.0214  # m
    peg_length: float = 0.048  # m
    peg_friction: float = 0.25

    def validate(self, where: str) -> None:
        for name, value in vars(self).items():
            require(value > 0, f"{where}.{name}", f"must be > 0, got {value}")


@dataclass
class PlantProfile:
    """Everything that makes the simulated arm 'real': seeded, and documented next to the YAML.

    `specimen_seed` draws what makes this arm this arm (friction-ripple phases, the F/T sensor's
    unloaded offset); `seed` draws what differs from run to run (torque and sensor noise).  A run's
    `--seed` replaces `seed` only, so every run of one profile is the same arm, as on a real cell;
    another specimen is another profile (or `specimen_seed`).  Default: the profile's own `seed`.
    """

    seed: int
    friction: FrictionProfile
    torque_sensing: TorqueSensing
    servo: ServoProfile
    rotor_inertia: list[float]  # kg·m², reflected to the joint (armature)
    inertial: InertialDeviation = field(default_factory=InertialDeviation)
    sample_period_s: float = 0.008
    physics_dt_s: float = 0.001
    sensor: FTSensorProfile = field(default_factory=FTSensorProfile)
    tool: ToolProfile = field(default_factory=ToolProfile)
    description: str = ""
    specimen_seed: int | None = None

    def validate(self, where: str) -> None:
        require_len(self.rotor_inertia, 6, join(where, "rotor_inertia"))
        require(all(v >= 0 for v in self.rotor_inertia), join(where, "rotor_inertia"), "must be >= 0")
        require(0.001 <= self.sample_period_s <= 0.1, join(where, "sample_period_s"), "must lie in [0.001, 0.1] s")
        require(0.0001 <= self.physics_dt_s <= 0.002, join(where, "physics_dt_s"), "must lie in [0.0001, 0.002] s")
        ratio = self.sample_period_s / self.physics_dt_s
        require(abs(ratio - round(ratio)) < 1e-6, join(where, "physics_dt_s"),
                "must divide sample_period_s into a whole number of steps")


def load_profile(path: Path) -> PlantProfile:
    profile = load_dataclass(PlantProfile, read_layered_yaml(path), f"{path}:")
    if profile.specimen_seed is None:
        profile.specimen_seed = profile.seed  # fixed now: a run seed set later does not change the arm
    return profile
