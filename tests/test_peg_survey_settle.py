"""The peg survey's settle (PegConfig.survey_settle_s): arrived above a touch point, the reference holds
still and the force reading is not tested until the settle is over; after it, the descent and the touch test
run as before."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import pinocchio as pin
import pytest

from drivers.errors import ConfigError
from tasks.peg.config import PegConfig, load_peg_config
from tasks.peg.geometry import rim_points
from tasks.peg.survey import Survey
from tasks.peg.touch import GuardedDescent

DT = 0.008
HOLE_XY = np.array([0.45, -0.12])
HOLE_TOP = 0.05  # the fixture's face: level, at the nominal mouth height
FACE_FZ = 40.0  # what the force source reads with the peg's rim on the face


@dataclass
class Bench:
    """A survey driven cycle by cycle: the measured tip follows the reference but its lowest rim point
    cannot go below the face; Fz is FACE_FZ on the face, 0 in the air, unless the test overrides it."""

    pc: PegConfig
    survey: Survey = field(init=False)
    guard: GuardedDescent = field(init=False)
    ref: pin.SE3 = field(init=False)
    k: int = 0
    log: list[tuple[float, str, float, int]] = field(default_factory=list)  # (t, status, ref z, points)

    def __post_init__(self) -> None:
        lead = np.array([math.cos(math.radians(self.pc.lead_direction_deg)),
                         math.sin(math.radians(self.pc.lead_direction_deg)), 0.0])
        self.survey = Survey(self.pc, DT, HOLE_XY, HOLE_TOP, lead)
        self.guard = GuardedDescent(self.pc, DT)
        self.ref = self.survey.poses[0].copy()

    @property
    def t(self) -> float:
        return self.k * DT

    def tip(self) -> pin.SE3:
        tip = self.ref.copy()
        low = rim_points(tip, self.pc.peg_diameter_m / 2)[0]
        tip.translation[2] += max(0.0, HOLE_TOP - float(low[2]))
        return tip

    def on_face(self, tip: pin.SE3) -> bool:
        return float(rim_points(tip, self.pc.peg_diameter_m / 2)[0][2]) <= HOLE_TOP + 1e-9

    def cycle(self, fz: float | None = None) -> str:
        self.k += 1
        tip = self.tip()
        reading = (FACE_FZ if self.on_face(tip) else 0.0) if fz is None else fz
        self.ref, status = self.survey.step(reading, self.ref, tip, self.guard, self.t)
        self.log.append((self.t, status, float(self.ref.translation[2]), len(self.survey.points)))
        return status

    def until(self, wanted: str, limit: int = 2000) -> None:
        for _ in range(limit):
            status = self.cycle()
            assert status != "failed", self.survey.reason
            if status == wanted:
                return
        pytest.fail(f"no '{wanted}' within {limit} cycles")


def arrived_at_second_point(pc: PegConfig) -> Bench:
    """The first point touched on the face, lifted off and moved on: the cycle that arrives above the
    second touch point has just run."""
    b = Bench(pc)
    for _ in range(2000):
        b.cycle()
        if b.survey.points:
            break
    assert len(b.survey.points) == 1
    b.until("at_point")
    return b


def test_a_force_spike_while_settling_is_no_touch_and_the_reference_holds():
    pc = PegConfig()
    assert pc.survey_settle_s > 2 * DT and pc.survey_cycles >= 1
    b = arrived_at_second_point(pc)
    t_arrived, z_arrived = b.t, float(b.ref.translation[2])
    assert not b.on_face(b.tip())  # above the face: any force now is the stop's kick, not a touch
    # The force reading kicks well above the touch threshold for the whole settle.
    while b.t + DT < t_arrived + pc.survey_settle_s - 1e-9:
        assert b.cycle(fz=5 * pc.contact_force_n) == "moving"
        assert len(b.survey.points) == 1 and b.guard.touching == 0
        assert float(b.ref.translation[2]) == z_arrived  # no descent while settling
    assert b.t >= t_arrived + pc.survey_settle_s - DT - 1e-9  # (the spike did cover the settle)


def test_after_the_settle_a_force_over_the_threshold_is_a_touch_again():
    pc = PegConfig()
    b = arrived_at_second_point(pc)
    t_arrived = b.t
    settle_end = t_arrived + pc.survey_settle_s
    while b.t + DT < settle_end - 1e-9:
        b.cycle(fz=5 * pc.contact_force_n)
    assert len(b.survey.points) == 1
    # The reading stays over the threshold: once the settle is over it is tested, and it is a touch.
    first_crossing = None
    for _ in range(pc.survey_cycles + 3):
        b.cycle(fz=5 * pc.contact_force_n)
        if first_crossing is None and b.guard.touching:
            first_crossing = b.t
        if len(b.survey.points) == 2:
            break
    assert len(b.survey.points) == 2
    assert first_crossing is not None or pc.survey_cycles == 1
    if first_crossing is not None:
        assert settle_end - 1e-9 <= first_crossing <= settle_end + DT + 1e-9


def test_after_the_settle_the_descent_finds_the_face():
    # No kick: the settle only delays the descent, which then touches the face as before.
    pc = PegConfig()
    b = arrived_at_second_point(pc)
    t_arrived, z_arrived = b.t, float(b.ref.translation[2])
    for _ in range(2000):
        b.cycle()
        if len(b.survey.points) == 2:
            break
    assert len(b.survey.points) == 2
    first_down = next(t for t, _, z, _ in b.log if t > t_arrived and z < z_arrived)
    assert first_down >= t_arrived + pc.survey_settle_s - 1e-9
    assert b.survey.points[1][2] == pytest.approx(HOLE_TOP, abs=1e-4)  # on the face


def test_without_a_settle_the_same_spike_is_taken_for_a_touch():
    # The contrast: with survey_settle_s = 0 the stop's kick right after arrival reads as a touch above
    # the face -- the point the settle keeps out of the face fit.
    pc = replace(PegConfig(), survey_settle_s=0.0)
    b = arrived_at_second_point(pc)
    for _ in range(pc.survey_cycles + 1):
        b.cycle(fz=5 * pc.contact_force_n)
    assert len(b.survey.points) == 2
    assert b.survey.points[1][2] > HOLE_TOP + 1e-4  # recorded in the air


def test_the_settle_must_not_be_negative():
    replace(PegConfig(), survey_settle_s=0.0).validate("tasks.peg")  # none at all is allowed
    with pytest.raises(ConfigError, match=r"tasks\.peg\.survey_settle_s"):
        replace(PegConfig(), survey_settle_s=-0.01).validate("tasks.peg")
    with pytest.raises(ConfigError, match=r"tasks\.peg\.survey_settle_s.*>= 0"):
        load_peg_config({"survey_settle_s": -0.5}, "tasks.peg")
    assert load_peg_config({"survey_settle_s": 0.2}, "tasks.peg").survey_settle_s == 0.2
