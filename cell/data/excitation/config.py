"""Settings of the motion generators: joint ranges and steps, speeds, limits' fractions, Fourier excitation."""

from __future__ import annotations

from dataclasses import dataclass, field

from drivers.configio import join, load_dataclass, read_yaml, require


@dataclass
class FourierConfig:
    """Identification-grade excitation: finite Fourier series per joint (Swevers' parameterisation)."""

    harmonics: int = 5
    base_hz: float = 0.1  # fundamental: one period is 1 / base_hz seconds
    periods: int = 2
    ramp_s: float = 2.0  # smooth fade in/out so the trajectory starts and ends at rest
    candidates: int = 20  # random coefficient sets tried; the lowest condition number wins
    trajectories: int = 4  # independent excitation trajectories (each around its own centre)
    amplitude_fraction: float = 0.8  # of the room to the position limits around the centre
    centre_margin: float = 0.1  # centres are drawn in the joint ranges less this fraction at each end

    def validate(self, where: str) -> None:
        require(1 <= self.harmonics <= 20, join(where, "harmonics"), "must lie in 1..20")
        require(0 < self.base_hz <= 2, join(where, "base_hz"), "must lie in (0, 2] Hz")
        require(self.periods >= 1, join(where, "periods"), "must be >= 1")
        require(self.ramp_s > 0, join(where, "ramp_s"), "must be > 0")
        require(self.candidates >= 1, join(where, "candidates"), "must be >= 1")
        require(0 < self.amplitude_fraction <= 1, join(where, "amplitude_fraction"), "must lie in (0, 1]")
        require(0 <= self.centre_margin < 0.5, join(where, "centre_margin"), "must lie in [0, 0.5)")


@dataclass
class ExcitationConfig:
    """Joint ranges (a workspace restriction inside the hardware limits) and generator settings.

    The defaults keep the paper's workspace restrictions J2 +-80 deg and J3 +-150 deg (not the hardware
    limits, +-180 and +-155) and narrow J1 and J6 from the paper's +-270 to +-150 / +-180 deg: under the
    cell's commanded TCP speed limit, a 540 deg swing of J1 is a slow sweep during which every other
    joint crawls, which starves identification of acceleration.  J1-J3 get 4 steps (5 values each).
    """

    ranges_deg: list[list[float]] = field(default_factory=lambda: [
        [-150, 150], [-80, 80], [-150, 150], [-180, 180], [-180, 180], [-180, 180]])
    steps: list[int] = field(default_factory=lambda: [4, 4, 4, 2, 2, 2])  # N: N + 1 values per joint
    speeds: list[float] = field(default_factory=lambda: [0.4, 0.7, 1.0])  # V: fractions of the allowed speed
    max_configs: int = 0  # 0: every collision-free configuration; else this many drawn at random
    max_accel: list[float] = field(default_factory=lambda: [5.0, 5.0, 6.0, 8.0, 8.0, 8.0])  # rad/s^2
    joint_speed_fraction: float = 0.9  # of the safety monitor's joint speed limit
    tcp_speed_fraction: float = 0.85  # of the safety monitor's commanded TCP speed limit
    workspace_margin_m: float = 0.03  # TCP stays this far inside the safety workspace box
    clearance_m: float = 0.02  # minimum distance between bodies for a configuration to count as free
    path_step_rad: float = 0.04  # collision-check resolution along moves (largest joint step)
    tool_radius_m: float = 0.035  # tool envelope: a cylinder from the flange to the TCP
    # Pairs never checked: in the compact wrist the URDF's coarse boxes overlap where the real links
    # clear each other (geometry names from the URDF: <link>_0).
    ignore_pairs: list[list[str]] = field(default_factory=lambda: [["link_3_0", "link_5_0"], ["link_4_0", "link_6_0"]])
    floor: bool = True  # the mounting surface (z = 0) is a fixture
    rest_s: float = 0.25  # pause at each configuration (the arm settles; stiction is part of the data)
    test_ranges_deg: list[list[float]] = field(default_factory=lambda: [
        [-150, 150], [-80, 80], [-150, 150], [-150, 150], [-150, 150], [-180, 180]])
    seed: int = 0
    fourier: FourierConfig = field(default_factory=FourierConfig)

    def validate(self, where: str) -> None:
        for name in ("ranges_deg", "test_ranges_deg"):
            ranges = getattr(self, name)
            for i, r in enumerate(ranges):
                require(len(r) == 2 and r[0] < r[1], join(where, f"{name}[{i}]"),
                        f"must be [low, high] with low < high, got {r}")
        require(len(self.steps) == len(self.ranges_deg), join(where, "steps"), "needs one value per joint range")
        require(all(s >= 1 for s in self.steps), join(where, "steps"), "must all be >= 1")
        require(len(self.speeds) >= 1 and all(0 < v <= 1 for v in self.speeds), join(where, "speeds"),
                "must be fractions in (0, 1]")
        require(len(self.max_accel) == len(self.ranges_deg) and all(a > 0 for a in self.max_accel),
                join(where, "max_accel"), "needs one positive value per joint")
        require(0 < self.joint_speed_fraction <= 1, join(where, "joint_speed_fraction"), "must lie in (0, 1]")
        require(0 < self.tcp_speed_fraction <= 1, join(where, "tcp_speed_fraction"), "must lie in (0, 1]")
        require(self.clearance_m >= 0, join(where, "clearance_m"), "must be >= 0")
        require(self.path_step_rad > 0, join(where, "path_step_rad"), "must be > 0")
        require(self.max_configs >= 0, join(where, "max_configs"), "must be >= 0")
        for i, p in enumerate(self.ignore_pairs):
            require(len(p) == 2, join(where, f"ignore_pairs[{i}]"), f"must name two geometries, got {p}")


def load_excitation_config(raw: dict | None, where: str) -> ExcitationConfig:
    return load_dataclass(ExcitationConfig, raw or {}, where)


def read_excitation_config(path: str | None) -> ExcitationConfig:
    if path is None:
        return ExcitationConfig()
    return load_dataclass(ExcitationConfig, read_yaml(path), f"{path}:")  # type: ignore[arg-type]
