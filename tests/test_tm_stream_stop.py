"""What velocity mode does when the host falls silent, measured through the real driver: doctor's stream_stop."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.errors import LifecycleError
from drivers.interfaces import JointLimits, Lifecycle
from drivers.tm5.ethernet import TMEthernetArm
from drivers.tm5.stream_stop import stream_stop
from sim.kinematic_plant import KinematicPlant
from sim.tm_ethernet_emulator import TMEthernetEmulator
from tasks.setup.doctor import Doctor, DoctorSettings
from tests.tm_ethernet_fixtures import DT, LIMITS, connected, make_arm, start, wait_for

SPEED = 0.05  # rad/s


@pytest.fixture(params=[None, 0.1], ids=["no-timeout", "timeout-100ms"])
def emulator(request: pytest.FixtureRequest) -> Iterator[TMEthernetEmulator]:
    emu = start(KinematicPlant(dt=DT), vjog_timeout_s=request.param)
    yield emu
    emu.stop()


@pytest.fixture
def arm(emulator: TMEthernetEmulator) -> Iterator[TMEthernetArm]:
    yield from connected(emulator)


def test_the_result_is_read_off_the_tables_after_the_last_speed() -> None:
    moving = [(0.01 * k, 0.001 * k, SPEED) for k in range(50)]
    still = stream_stop(5, SPEED, 0.3, 0.5, SPEED, moving)
    assert still.stopped_after_s is None and still.travelled_rad == pytest.approx(0.049)
    assert "still moving 0.5 s after" in still.summary()
    stops = moving[:12] + [(0.12, 0.0115, 0.3 * SPEED), (0.13, 0.0117, 0.1 * SPEED), (0.14, 0.0117, 0.0)]
    out = stream_stop(5, -SPEED, 0.3, 0.5, SPEED, stops)
    assert out.stopped_after_s == pytest.approx(0.13) and out.travelled_rad == pytest.approx(0.0117)
    assert out.moved and "stopped by itself 130 ms after" in out.summary()
    assert not stream_stop(5, SPEED, 0.3, 0.5, 0.2 * SPEED, stops).moved


def test_the_probe_measures_the_node_and_leaves_the_arm_stopped(arm: TMEthernetArm,
                                                                emulator: TMEthernetEmulator) -> None:
    timeout = emulator.node.vjog_timeout_s
    q0 = arm.read_state().q
    probe = arm.stream_stop_probe(speed_rad_s=SPEED, stream_s=0.2, watch_s=0.5)
    assert probe.moved and probe.joint == 5
    if timeout is None:
        assert probe.stopped_after_s is None
        assert probe.travelled_rad == pytest.approx(SPEED * 0.5, rel=0.35)
    else:
        # The node's timeout plus the emulated joint's lag (a 50 ms time constant) and the broadcast's period;
        # well inside the watch, on a busy machine too.
        assert probe.stopped_after_s is not None and timeout <= probe.stopped_after_s <= 0.45
    assert arm.lifecycle is not Lifecycle.ARMED and not emulator.node.vmode.active
    seq = arm.read_state().seq
    wait_for(lambda: arm.read_state().seq > seq + 2, what="tables after the stop")
    q1 = arm.read_state().q
    assert np.allclose(np.delete(q1 - q0, 5), 0.0, atol=1e-6)  # only the probed joint moved
    assert 0 < abs(q1[5] - q0[5]) <= SPEED * 0.7 + 0.01


def test_doctor_runs_it_only_when_asked_and_fails_a_node_that_keeps_moving(emulator: TMEthernetEmulator) -> None:
    def run(asked: bool) -> dict[str, object]:
        arm = make_arm(emulator)
        try:
            settings = DoctorSettings(period_s=0.0156, timing_steps=5, tail_periods=3.0, stream_stop=asked)
            return {c.name: c for c in Doctor(arm, None, LIMITS, settings).run()}
        finally:
            arm.disconnect()

    skipped = run(False)["stream_stop"]
    assert skipped.status == "skipped" and "doctor --stream-stop" in skipped.detail  # type: ignore[attr-defined]
    check = run(True)["stream_stop"]
    if emulator.node.vjog_timeout_s is None:
        assert check.status == "fail" and "still moving" in check.detail  # type: ignore[attr-defined]
        assert "route A" in check.fix and "E-stop" in check.fix  # type: ignore[attr-defined]
    else:
        assert check.status == "pass" and "stopped by itself" in check.detail  # type: ignore[attr-defined]


def test_the_probe_refuses_an_armed_arm_and_a_joint_without_room() -> None:
    emulator = start(KinematicPlant(dt=DT))  # the node's stop behaviour does not matter here: one emulator
    try:
        _refuses(emulator)
    finally:
        emulator.stop()


def _refuses(emulator: TMEthernetEmulator) -> None:
    arm = make_arm(emulator)
    arm.connect()
    try:
        arm.arm()
        with pytest.raises(LifecycleError, match="stop first"):
            arm.stream_stop_probe()
        arm.stop()
    finally:
        arm.disconnect()
    q6 = KinematicPlant.HOME[5]
    narrow = JointLimits(lower=LIMITS.lower.copy(), upper=LIMITS.upper.copy(), velocity=LIMITS.velocity,
                         effort=LIMITS.effort)
    narrow.lower[5], narrow.upper[5] = q6 - math.radians(2), q6 + math.radians(2)
    tight = TMEthernetArm(make_arm(emulator).config, narrow, DT)
    tight.connect()
    try:
        with pytest.raises(LifecycleError, match="joint 6 has under .* of room"):
            tight.stream_stop_probe()
        assert tight.lifecycle is not Lifecycle.ARMED and not emulator.node.vmode.active
    finally:
        tight.disconnect()


def test_the_emulated_cells_vjog_timeout_command_sets_what_the_probe_measures() -> None:
    from sim.serve_cell import _apply

    emu = start(KinematicPlant(dt=DT))
    try:
        _apply(["vjog_timeout", "100"], emu, None)
        wait_for(lambda: emu.node.vjog_timeout_s == 0.1, what="the command applied")
        arm = make_arm(emu)
        arm.connect()
        try:
            probe = arm.stream_stop_probe(speed_rad_s=SPEED, stream_s=0.2, watch_s=0.5)
        finally:
            arm.disconnect()
        assert probe.stopped_after_s is not None
        _apply(["vjog_timeout", "0"], emu, None)  # 0: the last speed is kept again
        wait_for(lambda: emu.node.vjog_timeout_s is None, what="the command applied")
        with pytest.raises(ValueError, match="vjog_timeout takes 1 argument"):
            _apply(["vjog_timeout"], emu, None)
    finally:
        emu.stop()
