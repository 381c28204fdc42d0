"""Collision detection and reaction: thresholds from the model, quiet free motion, a push caught within
a few periods, each reaction's behaviour, the run summary and recording, the config and the bench."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np
import pytest

from cell.collision.config import CollisionConfig, DetectorSettings, TaskContactSafety
from cell.collision.guard import build_guard
from cell.config import CONFIG_DIR, VirtualSensorConfig
from cell.control.loop import Command, ControlLoop, Observation
from cell.control.safety import SafetyMonitor
from cell.data.recorder import Recorder, read_log
from drivers.configio import load_dataclass
from drivers.errors import ConfigError, SafetyStopError
from drivers.interfaces import ArmState
from tests.collision_fixtures import posture


def _guard(vs, model, reaction: str = "stop", contact_states: list[str] | None = None, limit: float = 150.0,
           **detector: Any):
    cfg = vs["cfg"]
    coll = dataclasses.replace(cfg.collision, reaction=reaction,
                               detector=dataclasses.replace(cfg.collision.detector, **detector),
                               tasks={"play": TaskContactSafety(contact_states=contact_states or [])})
    return build_guard(coll, model, vs["robot"], cfg.loop.period_s, "play", limit,
                       np.asarray(cfg.virtual_sensor.wrench_point, float))


class PushTask:
    """Moves the TCP along +y at `speed` and, from cycle `push_at`, a hand pushes the tool with `force`
    (world frame, on the tool).  Ends after `cycles`."""

    name = "play"

    def __init__(self, robot, plant, q0, speed: float, push_at: int | None, force, cycles: int, dt: float,
                 state: str = "move") -> None:
        self.robot, self.plant, self.q = robot, plant, np.array(q0, float)
        self.pose = robot.tcp_pose(self.q)
        self.speed, self.push_at, self.force, self.cycles, self.dt = speed, push_at, force, cycles, dt
        self.k = 0
        self.state_name = state
        self.aborted = ""
        self.pushed_at_t: float | None = None

    @property
    def done(self) -> bool:
        return self.k >= self.cycles or bool(self.aborted)

    def step(self, obs: Observation) -> Command:
        if self.push_at is not None and self.k == self.push_at:
            self.plant.external_wrench = np.concatenate([self.force, np.zeros(3)])
            self.pushed_at_t = obs.t
        self.k += 1
        ramp = min(1.0, self.k * self.dt / 0.25)  # a smooth start, as the cell's own moves have
        v = self.speed * 0.5 * (1.0 - np.cos(np.pi * ramp))
        self.pose.translation = self.pose.translation + np.array([0.0, v * self.dt, 0.0])
        self.q, _ = self.robot.ik(self.pose, self.q, iters=20)
        return Command(q=self.q.copy())

    def abort(self, reason: str) -> None:
        self.aborted = reason

    def summary(self) -> dict[str, Any]:
        return {"outcome": "failed" if self.aborted else "done", "reason": self.aborted}


def _run(vs, model, guard, speed=0.05, push_at=None, force=(0.0, 0.0, 0.0), cycles=150, record=None,
         state="move", on_row=None):
    from sim.cell import make_sim_cell

    cfg, robot = vs["cfg"], vs["robot"]
    holder = make_sim_cell(cfg, robot.limits, scene_kind="free", tool="wipe")
    q0 = posture(robot, np.asarray(cfg.robot.home, float), [0.45, -0.15, 0.25])
    holder.plant.reset(q0)
    cell = holder.open()
    try:
        for _ in range(25):  # settle, then zero the residual at rest
            cell.ticker.wait()
            guard.detector.update(holder.plant.measured_state())
        guard.rebias()
        task = PushTask(robot, holder.plant, q0, speed, push_at, np.asarray(force, float), cycles,
                        cfg.loop.period_s, state)
        rec = Recorder(record, 50) if record is not None else None
        loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s),
                           cell.ticker, rec, cfg.loop.period_s, 10.0, guard=guard, on_row=on_row)
        result = loop.run()
        tcp = robot.tcp_pose(holder.plant.measured_state().q).translation
    finally:
        holder.close()
    return result, task, tcp


# ----------------------------------------------------------------------------------------- detector
def test_thresholds_widen_with_speed_sticking_coverage_and_payload(vs, model):
    guard = _guard(vs, model)
    d = guard.detector
    robot = vs["robot"]
    q = posture(robot, np.asarray(vs["cfg"].robot.home, float), [0.45, -0.15, 0.25])
    moving = np.full(6, 0.5)
    base = d.thresholds(q, moving, np.zeros(6))
    no_stick = _guard(vs, model, stick_speed=0.0).detector
    band = model.coverage.static_band
    # At rest the static friction band is added in full (a sticking joint holds anything within it),
    # fading out toward stick_speed, and nothing of it once the joints move.
    rest = np.zeros(6)
    assert np.allclose(d.thresholds(q, rest, rest) - no_stick.thresholds(q, rest, rest), band)
    slow = np.full(6, d.settings.stick_speed / 2)
    assert np.allclose(d.thresholds(q, slow, rest) - no_stick.thresholds(q, slow, rest), band / 2)
    assert np.allclose(base, no_stick.thresholds(q, moving, rest))
    # Far outside the training data's (q, q', q'') the physics part's level applies: never tighter.
    far = d.thresholds(q + 2.5, moving * 4, np.full(6, 30.0))
    assert np.all(far >= d.thresholds(q + 2.5, moving * 4, np.zeros(6)) - 1e-9)
    assert np.all(d.thresholds(q, moving, np.full(6, 30.0)) >= base)  # accelerating: the inertia term
    # The payload term counts from where the residual was zeroed: nothing there, more elsewhere.
    d._q = q
    d.rebias()
    q_away = q + np.array([0.0, 0.4, -0.4, 0.0, 0.0, 0.0])
    d2 = _guard(vs, model, payload_uncertainty_kg=0.0).detector
    assert np.allclose(d.thresholds(q, moving, np.zeros(6)), d2.thresholds(q, moving, np.zeros(6)))
    assert d.thresholds(q_away, moving, np.zeros(6))[1] > d2.thresholds(q_away, moving, np.zeros(6))[1] + 0.5


def test_a_joint_that_moved_since_the_zeroing_gets_twice_its_friction_band_at_rest(vs, model):
    from drivers.interfaces import ArmStatus

    d = _guard(vs, model, payload_uncertainty_kg=0.0).detector
    robot, dt = vs["robot"], vs["cfg"].loop.period_s
    q = posture(robot, np.asarray(vs["cfg"].robot.home, float), [0.45, -0.15, 0.25])
    rest = np.zeros(6)
    tau = np.asarray(robot.rnea(q, rest, rest), float)
    d.update(ArmState(t=0.0, q=q, dq=rest, tau=tau, status=ArmStatus(), seq=1))
    d.rebias()
    still = d.thresholds(q, rest, rest)
    # Joint 2 travels 0.1 rad (well beyond a hand's push on a held joint), then stops: it may now stick
    # anywhere in its band, as far as the other edge from where it was zeroed.
    dq = np.array([0.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    for k in range(1, 26):
        d.update(ArmState(t=k * dt, q=q + dq * k * dt, dq=dq, tau=tau, status=ArmStatus(), seq=k + 1))
    band = model.coverage.static_band
    assert np.allclose(d.thresholds(q, rest, rest) - still, np.array([0, band[1], 0, 0, 0, 0]), atol=1e-3)
    d.rebias()  # zeroed again at rest: back to once
    assert np.allclose(d.thresholds(q, rest, rest), still, atol=1e-3)


def test_a_joint_its_command_holds_keeps_its_band_and_the_models_creep_friction_while_dragged(vs, model):
    d = _guard(vs, model, payload_uncertainty_kg=0.0).detector
    robot, dt = vs["robot"], vs["cfg"].loop.period_s
    q = posture(robot, np.asarray(vs["cfg"].robot.home, float), [0.45, -0.15, 0.25])
    no_stick = _guard(vs, model, payload_uncertainty_kg=0.0, stick_speed=0.0).detector
    band = model.coverage.static_band
    stick = d.settings.stick_speed
    # Joints 1-3 commanded at speed, the wrist commanded still; the base joints' accelerations drag joint 4
    # to a creep of 0.6 stick_speed (measured), while its servo holds it.
    v_cmd = np.array([0.5, -0.5, 0.5, 0.0, 0.0, 0.0])
    for k in range(d.settings.command_window_periods + 2):
        d.commanded(q + v_cmd * k * dt)
        no_stick.commanded(q + v_cmd * k * dt)
    dq = np.array([0.5, -0.5, 0.5, 0.6 * stick, 0.0, 0.0])
    extra = d.thresholds(q, dq, np.zeros(6)) - no_stick.thresholds(q, dq, np.zeros(6))
    creep = np.abs(d._creep_friction(q, dq, v_cmd))
    assert creep[3] > 0.5 * band[3]  # a creep of a few mrad/s already reads as most of the Coulomb level
    assert np.isclose(extra[3], band[3] + creep[3])  # held: the full band plus what the model claims there
    assert np.allclose(extra[:3], 0.0)  # commanded and moving: the model's friction applies
    # An impact that stops a joint its command moves: the band as the measured speed says, nothing more.
    stopped = dq.copy()
    stopped[0] = 0.0
    extra = d.thresholds(q, stopped, np.zeros(6)) - no_stick.thresholds(q, stopped, np.zeros(6))
    assert np.isclose(extra[0], band[0])
    # Without a command stream (a detector fed states only) the measured creep speed alone fades the band.
    plain = _guard(vs, model, payload_uncertainty_kg=0.0).detector
    plain_ns = _guard(vs, model, payload_uncertainty_kg=0.0, stick_speed=0.0).detector
    extra = plain.thresholds(q, dq, np.zeros(6)) - plain_ns.thresholds(q, dq, np.zeros(6))
    assert np.isclose(extra[3], 0.4 * band[3])


def test_beyond_the_trained_speeds_the_thresholds_grow_with_speed(vs, model):
    d = _guard(vs, model).detector
    robot = vs["robot"]
    q = posture(robot, np.asarray(vs["cfg"].robot.home, float), [0.45, -0.15, 0.25])
    v_max, edge = d._beyond
    assert np.all(np.isfinite(v_max)) and np.all(edge > 0)
    plain = _guard(vs, model).detector
    plain._beyond = None
    # Within the trained reach nothing is added; at twice it, one edge level (x sigma_factor) on every
    # joint: the model's own levels stop at its fastest bin, and beyond the reach its error is unknown.
    inside = 0.9 * v_max
    assert np.allclose(d.thresholds(q, inside, np.zeros(6)), plain.thresholds(q, inside, np.zeros(6)))
    # One joint at twice its reach takes every joint out of the model's experience.
    one_fast = inside.copy()
    one_fast[0] = 2.0 * v_max[0]
    extra = d.thresholds(q, one_fast, np.zeros(6)) - plain.thresholds(q, one_fast, np.zeros(6))
    assert np.allclose(extra, d.settings.sigma_factor * edge)


def test_commanded_acceleration_widens_the_inertial_term_and_a_cruise_adds_nothing(vs, model):
    d = _guard(vs, model).detector
    d.settings = dataclasses.replace(d.settings, payload_uncertainty_kg=0.0)  # its inertial part: the next test
    robot, dt = vs["robot"], vs["cfg"].loop.period_s
    q = posture(robot, np.asarray(vs["cfg"].robot.home, float), [0.45, -0.15, 0.25])
    moving = np.full(6, 0.5)
    d.update(ArmState(t=0.0, q=q, dq=np.zeros(6), tau=np.zeros(6)))
    base = d.thresholds(q, moving, np.zeros(6))
    v = np.array([0.0, 0.0, 0.3, 0.0, 0.5, 0.0])
    for k in range(3):  # constant commanded speed: no commanded acceleration
        d.commanded(q + k * v * dt)
    assert np.allclose(d.thresholds(q, moving, np.zeros(6)), base)
    a = np.array([0.0, 0.0, 0.0, 0.0, 40.0, 0.0])  # a move's start: joint 5 at 40 rad/s^2
    d.commanded(q + 3 * v * dt + a * dt**2)
    widened = d.thresholds(q, moving, np.zeros(6))
    expect = d.settings.inertia_uncertainty * np.abs(d.observer.mass @ a)
    assert widened[4] - base[4] == pytest.approx(expect[4], rel=1e-6)
    assert expect[4] > 1.0
    # ... for the servo's lag (command_window_periods), then the cruise again adds nothing.
    last = q + 3 * v * dt + a * dt**2
    for k in range(1, d.settings.command_window_periods + 2):
        d.commanded(last + k * (v * dt + a * dt**2))
    assert np.allclose(d.thresholds(q, moving, np.zeros(6)), base)


def test_a_time_optimal_plan_starting_at_full_acceleration_is_not_a_collision(vs, model):
    """`main.py plan`'s trajectory_3: toppra accelerates joints 3-5 from rest at 20-45 rad/s^2 within a
    few periods, while the measured acceleration's estimate still reads a fraction of it."""
    from cell.planning.constraints import toppra_terms
    from cell.planning.planner import ToppraPlanner
    from sim.cell import make_sim_cell
    from tasks.setup.plan import execute, load_plan_file

    cfg, robot = vs["cfg"], vs["robot"]
    plans = load_plan_file(CONFIG_DIR / "plans.yaml")
    cfg = dataclasses.replace(cfg, safety=dataclasses.replace(cfg.safety, max_tcp_speed=plans.max_tcp_speed))
    planner = ToppraPlanner(robot, model.predict, plans.planner, None, toppra_terms(model))
    traj = planner.plan(np.radians(np.asarray(plans.paths["trajectory_3"], float)), np.full(6, 0.8))
    assert np.max(np.abs(traj.ddq[:5])) > 20.0  # it does start hard

    def open_cell():
        holder = make_sim_cell(cfg, robot.limits, scene_kind="free", tool="wipe")
        cell = holder.open()
        return dataclasses.replace(cell, guard=lambda task, limit: _guard(vs, model)), holder

    result = execute(traj, cfg, robot, open_cell)
    assert result["outcome"] == "done", result.get("reason")
    assert result["collision"]["detections"] == []


def test_free_motion_is_quiet_and_a_push_is_caught_within_three_periods(vs, model):
    quiet, task, _ = _run(vs, model, _guard(vs, model, reaction="monitor"), speed=0.08, cycles=250)
    assert quiet.outcome == "done"
    assert quiet.collision["detections"] == [], quiet.collision
    assert quiet.collision["max_free_ratio"] < 0.8
    at = quiet.collision["max_free_at"]  # where the margin was thinnest: that joint's own residual over threshold
    assert 1 <= at["joint"] <= 6 and at["state"] == "move" and 0 < at["t"] <= 250 * vs["cfg"].loop.period_s
    own = abs(at["residual_nm"]) / at["threshold_nm"]
    if at["combined"]:  # joints 1-3 together were nearer a detection than any one joint
        assert own <= quiet.collision["max_free_ratio"] + 2e-3
    else:
        assert own == pytest.approx(quiet.collision["max_free_ratio"], abs=2e-3)
    assert at["arm_speed"] >= at["joint_speed"] >= 0

    result, task, _ = _run(vs, model, _guard(vs, model), speed=0.08, push_at=60, force=(0.0, -60.0, 0.0))
    assert result.outcome == "collision", result.reason
    assert "protective stop" in result.reason and "state move" in result.reason
    det = result.collision["detections"][0]
    latency = det["t"] - task.pushed_at_t
    assert 0 < latency <= 3 * vs["cfg"].loop.period_s + 1e-9, latency
    assert result.collision["reactions"] == ["stop"]


def _free_check(detector, ratios):
    """One free check on given residual / threshold ratios (thresholds of 10 N·m)."""
    detector.threshold = np.full(6, 10.0)
    detector.residual = 10.0 * np.asarray(ratios, float)
    return detector.check_free()


def test_joints_1_to_3_near_their_thresholds_together_are_a_collision(vs, model):
    d = _guard(vs, model).detector
    assert d.settings.combined_joints == [1, 2, 3]
    # Three joints at 0.7 of their thresholds: none alone, their root-sum-square (1.21) over 1 together.
    assert _free_check(d, [0.7, -0.7, 0.7, 0, 0, 0]).tolist() == [0, 1, 2] and d.together
    assert d.combined_ratio() == pytest.approx(np.sqrt(3 * 0.49)) and d.ratio() == pytest.approx(d.combined_ratio())
    # The joints named are those carrying at least an equal share (1 / sqrt(3) of the sphere's radius each).
    assert _free_check(d, [0.9, 0.5, 0.0, 0, 0, 0]).tolist() == [0] and d.together
    # Under the sphere: nothing, however near one joint is; the wrists never count together.
    assert _free_check(d, [0.99, 0.0, 0.0, 0, 0, 0]).size == 0 and not d.together
    assert _free_check(d, [0.6, 0.4, 0.4, 0.9, 0.9, 0.9]).size == 0 and d.ratio() == pytest.approx(0.9)
    # A joint over its own threshold is that joint's detection, as without the combined check.
    assert _free_check(d, [0.0, 0.0, 0.0, 1.1, 0.0, 0.0]).tolist() == [3] and not d.together
    # Off: only the joints' own thresholds.
    off = _guard(vs, model, combined_joints=[]).detector
    assert _free_check(off, [0.7, 0.7, 0.7, 0, 0, 0]).size == 0 and off.ratio() == pytest.approx(0.7)
    # Confirmed like the joints' own: two periods in a row where the settings ask for two.
    two = _guard(vs, model, confirm_periods=2).detector
    assert _free_check(two, [0.7, 0.7, 0.7, 0, 0, 0]).size == 0
    assert _free_check(two, [0.7, 0.7, 0.7, 0, 0, 0]).tolist() == [0, 1, 2] and two.together


def test_a_detection_by_the_combined_joints_says_so(vs, model):
    from cell.collision.detector import Detection

    det = Detection(t=1.0, cycle=125, state="move", mode="free", joints=[2, 3], ratio=1.12, residual_nm=[0.0] * 6,
                    threshold_nm=[1.0] * 6, force_n=[0.0] * 3, together=True)
    assert "joints 2, 3 together near their thresholds (1.1x)" in det.describe()
    assert det.to_dict()["together"] is True


def test_combined_joints_must_name_the_arms_joints(vs, model):
    with pytest.raises(ValueError, match="combined_joints names joints 1..6"):
        _guard(vs, model, combined_joints=[1, 7])


def test_retract_moves_away_along_the_contact_direction_then_stops(vs, model):
    retract_m = 0.01
    guard = _guard(vs, model, reaction="retract")
    guard.cfg = dataclasses.replace(guard.cfg, retract_m=retract_m)
    result, task, tcp = _run(vs, model, guard, speed=0.0, push_at=40, force=(40.0, 0.0, 0.0))
    assert result.outcome == "collision", result.reason
    assert "retracted" in result.reason
    assert task.aborted  # the task was told why it ended
    start = vs["robot"].tcp_pose(task.q).translation  # unchanged: the task stopped commanding
    # The hand pushes the tool along +x: the tool presses -x on it, so the retract yields along +x.
    moved = tcp - start
    assert moved[0] > 0.6 * retract_m, moved


def test_a_moving_reaction_stops_the_arm_first_and_moves_once_at_rest(vs, model):
    guard = _guard(vs, model, reaction="retract")
    rows: list[dict[str, Any]] = []
    # Moving at 0.1 m/s when the push comes: the targets already sent lead on, the controller's stop does not.
    result, task, _ = _run(vs, model, guard, speed=0.1, push_at=60, force=(0.0, 0.0, 60.0), on_row=rows.append)
    assert result.outcome == "collision", result.reason
    assert "stopped (" in result.reason and "retracted" in result.reason
    braking = [r for r in rows if r.get("reaction") == "brake"]
    moving = [r for r in rows if r.get("reaction") == "retract"]
    assert len(braking) >= 2 and moving and braking[-1]["cycle"] < moving[0]["cycle"]
    # While braking nothing new was sent: the last target stays what it was at the detection.
    for j in range(6):
        assert len({r[f"q_cmd{j + 1}"] for r in braking}) == 1
    # At the first retract target the arm was at rest (the measured joints).
    assert max(abs(moving[0][f"dq{j + 1}"]) for j in range(6)) <= 0.02 + 1e-9


def test_comply_yields_to_the_push_and_monitor_only_records(vs, model):
    guard = _guard(vs, model, reaction="comply")
    result, task, tcp = _run(vs, model, guard, speed=0.0, push_at=40, force=(0.0, 0.0, 40.0))
    assert result.outcome == "collision" and "complied" in result.reason
    assert tcp[2] - vs["robot"].tcp_pose(task.q).translation[2] > 0.002

    result, task, _ = _run(vs, model, _guard(vs, model, reaction="monitor"), speed=0.0, push_at=40,
                           force=(0.0, 0.0, 40.0), cycles=120)
    assert result.outcome == "done" and not task.aborted
    assert len(result.collision["detections"]) == 1 and result.collision["reactions"] == ["monitor"]


def test_contact_states_hold_the_fast_force_to_the_contact_limit(vs, model):
    # A steady 40 N push in a state where contact is expected: under a 60 N limit nothing happens ...
    calm, _, _ = _run(vs, model, _guard(vs, model, contact_states=["move"], limit=60.0), speed=0.0, push_at=30,
                      force=(0.0, 0.0, 40.0), cycles=120)
    assert calm.outcome == "done", calm.reason
    assert 25.0 < calm.collision["max_fast_force_n"] < 60.0
    # ... under a 25 N limit it is a collision, reported as a force, not as joints.
    hit, _, _ = _run(vs, model, _guard(vs, model, contact_states=["move"], limit=25.0), speed=0.0, push_at=30,
                     force=(0.0, 0.0, 40.0), cycles=120)
    assert hit.outcome == "collision" and "fast tool force" in hit.reason
    assert hit.collision["detections"][0]["mode"] == "contact"


def test_the_recording_says_what_was_detected(vs, model, tmp_path):
    result, _, _ = _run(vs, model, _guard(vs, model), speed=0.05, push_at=50, force=(0.0, -60.0, 0.0),
                        record=tmp_path / "run")
    assert result.outcome == "collision"
    d = read_log(tmp_path / "run").to_pydict()
    assert {"coll_ratio", "fast_fx", "fast_fy", "fast_fz"} <= set(d)
    assert max(d["coll_ratio"]) >= 1.0  # the tripping sample is recorded
    assert max(d["coll_ratio"][:40]) < 1.0


def test_a_non_finite_state_stops_instead_of_passing_silently(vs, model):
    guard = _guard(vs, model)
    guard.detector.update(ArmState(t=0.0, q=np.zeros(6), dq=np.zeros(6), tau=np.zeros(6)))
    bad = ArmState(t=0.0, q=np.zeros(6), dq=np.zeros(6), tau=np.array([0, np.nan, 0, 0, 0, 0.0]))
    with pytest.raises(SafetyStopError, match="non-finite"):
        guard.detector.update(bad)


# ------------------------------------------------------------------------------------------- config
@pytest.mark.parametrize("raw, words", [
    ({"reaction": "explode"}, "reaction"),
    ({"tasks": {"dance": {}}}, "unknown task 'dance'"),
    ({"tasks": {"wipe": {"reactions": {"wipe": "flee"}}}}, "unknown reaction 'flee'"),
    ({"detector": {"observer_gain": 0}}, "observer_gain"),
    ({"detector": {"floor_nm": [1, 1, 0, 1, 1, 1]}}, "floor_nm"),
    ({"detector": {"combined_joints": [0, 1]}}, "combined_joints"),
    ({"detector": {"combined_joints": [2, 2]}}, "combined_joints"),
    ({"retract_m": 0.5}, "retract_m"),
])
def test_bad_collision_settings_are_one_line_errors(raw, words):
    with pytest.raises(ConfigError) as err:
        load_dataclass(CollisionConfig, raw, "cell.yaml: collision")
    msg = str(err.value)
    assert words in msg and "\n" not in msg


def test_floor_count_must_match_the_joints(vs, model):
    with pytest.raises(ValueError, match="floor_nm needs 6"):
        _guard(vs, model, floor_nm=[1.0, 1.0])


def test_detector_settings_defaults_are_valid():
    d = load_dataclass(DetectorSettings, {}, "collision.detector")
    assert d == DetectorSettings()  # nothing configured: the defaults, and they validate
    assert len(d.floor_nm) == 6 and all(v > 0 for v in d.floor_nm)  # one floor per TM5 joint
    # Over a wire the detector is no more sensitive than in lock-step: a slower residual, wider thresholds.
    assert d.wire_observer_gain <= d.observer_gain and d.wire_margin >= 1
    # Faster than the virtual sensor's observer, whose bandwidth filters impacts away.
    assert d.observer_gain > VirtualSensorConfig().momentum_gain


# -------------------------------------------------------------------------------------------- bench
@pytest.mark.slow
def test_bench_collision_measures_impacts_and_free_motion(vs, model):
    from bench.collision import bench_collision

    out = bench_collision(vs["cfg"], vs["robot"], model, impacts=2, seed=3, free_s=4.0, tool="wipe")
    assert out["impacts"] == 2 and out["free_motion_s"] == pytest.approx(4.0, abs=0.1)
    for key in ("detection_latency_ms_p95", "peak_force_n_p95", "peak_force_n_max", "false_alarms",
                "virtual_peak_ratio", "rigid_impact_n_per_mps_p95", "guarded_speed_mps_150n",
                "force_at_detection_n_median_soft", "force_at_first_decision_n_p95_soft",
                "peak_over_detection_p95_soft", "spring_peak_n_p95_soft", "free_motion_max_ratio_by_kind"):
        assert key in out
    for t in out["per_impact"]:
        if t["contact"]:
            assert t["peak_force_n"] > 0 and t["ft_peak_n"] > 0
            assert t["detected"], t
            assert 0.0 <= t["force_at_detection_n"] <= t["peak_force_n"], t
            # No detector on this loop decides before the first period whose state postdates the contact.
            assert t["force_at_first_decision_n"] is not None
            if not t["rigid"]:
                assert 0.0 < t["spring_force_at_detection_n"] <= t["spring_peak_n"] + 1e-6, t


def test_contact_figures_say_whether_the_reaction_cut_the_force():
    from bench.collision import contact_figures

    dt = 0.008
    t = np.arange(0.0, 0.06, 0.001)
    # Rising at 10 N/ms until 20 ms, the decision at 15 ms: held flat from 20 ms, it was cut within a period ...
    flat = [(x, 10e3 * min(x, 0.020)) for x in t]
    c = contact_figures(flat, 0.015, dt)
    assert c["at"] == pytest.approx(150.0) and c["reached"] == pytest.approx(150.0)
    assert c["peak_after"] == pytest.approx(200.0) and not c["rising"]
    # ... still rising 30 ms after it: not cut.
    late = [(x, 10e3 * min(x, 0.045)) for x in t]
    assert contact_figures(late, 0.015, dt)["rising"]
    # A step without contact at the decision (the plate bounced): what the contact had reached counts.
    bounce = [(x, 0.0 if abs(x - 0.015) < 1e-6 else 100.0) for x in t]
    b = contact_figures(bounce, 0.015, dt)
    assert b["at"] == 0.0 and b["reached"] == pytest.approx(100.0)


def test_a_model_trained_again_on_the_same_data_is_another_model_to_planning(vs, tmp_path):
    import shutil

    from app.planning_model import model_name
    from cell.model.dynamics.artefact import load_model

    folder = tmp_path / "wipe"
    shutil.copytree(vs["cfg"].virtual_sensor.path("model", "wipe"), folder)
    model = load_model(folder, vs["robot"])
    before = model_name(model, str(folder))
    assert before.startswith(f"H1 ({folder}, model ")
    assert model_name(model, str(folder)) == before  # the same files: the same name
    doc = json.loads((folder / "model.json").read_text())
    doc["coverage"]["sigma_hybrid"][0][0] += 0.1  # trained again with other settings: its levels moved
    (folder / "model.json").write_text(json.dumps(doc))
    assert model.meta.training_data_sha256 and model_name(model, str(folder)) != before


def test_bench_collision_takes_the_planning_settings_made_for_the_model_plan_uses(vs, model, tmp_path, monkeypatch):
    import bench.collision_plans as cp

    (tmp_path / "model_trust.json").write_text(json.dumps({"key": {"model": "H1 (a, data 1)"}, "fraction": 0.77}))
    (tmp_path / "ppo").mkdir()
    (tmp_path / "ppo" / "policy.json").write_text("{}")
    stored = {"model": "H1 (a, data 1)", "ppo": {"updates": 300}}
    monkeypatch.setattr(cp, "load_policy", lambda *a: ("stored", stored))
    monkeypatch.setattr(cp, "load_or_train", lambda *a, **k: ("small", {"training_s": 1.0}))
    monkeypatch.setattr(cp, "PpoPlanner", lambda robot, fn, pcfg, policy, *a: policy)
    same = cp.bench_planners(vs["robot"], vs["cfg"], model, tmp_path, "H1 (a, data 1)")
    assert "0.770 (bench planning)" in same.sources["model"] and same.planners["model"][1][0] == 0.77
    assert same.sources["ppo"].startswith("bench planning's policy") and same.planners["ppo"][0] == "stored"
    # The model was trained again (other data): neither the trust nor the policy is its own.
    other = cp.bench_planners(vs["robot"], vs["cfg"], model, tmp_path, "H1 (a, data 2)")
    assert other.sources["model"] == f"first-run scale {cp.TORQUE_SCALE}"
    assert other.planners["model"][1][0] == cp.TORQUE_SCALE
    assert other.sources["ppo"].startswith("small policy trained here") and other.planners["ppo"][0] == "small"


@pytest.mark.slow
def test_bench_collision_free_motion_plays_the_planning_benchs_plans(vs, model, tmp_path):
    from bench.collision import bench_collision
    from bench.collision_plans import FAST_PPO_UPDATES, bench_planners

    # No stored `bench planning` artefacts here: the configured guards, the first-run scale, a small PPO policy.
    planners = bench_planners(vs["robot"], vs["cfg"], model, tmp_path)
    assert set(planners.planners) == {"model", "kinematic", "ppo"}
    assert str(FAST_PPO_UPDATES) in planners.sources["ppo"] and "guards" in planners.sources["kinematic"]
    out = bench_collision(vs["cfg"], vs["robot"], model, impacts=0, seed=4, free_s=8.0, tool="wipe",
                          planners=planners)
    kinds = out["free_motion_max_ratio_by_kind"]
    assert {"random", "time_optimal", "plan_model", "plan_kinematic", "plan_ppo"} <= set(kinds), kinds
    assert out["false_alarm_events"] == [] and 0.0 < out["free_motion_max_ratio"] < 1.0
    assert out["free_motion_planners"] == planners.sources


# ----------------------------------------------------------------------------------------- guarded motion
def test_guarded_speed_bound_and_the_tasks_head_on_speeds(vs):
    from app.tasks_registry import build_task
    from cell.control.guarded import GuardedSettings, check_speeds

    g = GuardedSettings(impact_n_per_mps=10_000.0)
    assert g.speed_bound(80.0) == pytest.approx(0.008)
    assert check_speeds(g, {"approach_speed_mps": 0.008}, 80.0, "x") == pytest.approx(0.008)
    with pytest.raises(ConfigError, match=r"x\.approach_speed_mps: 9\.0 mm/s is faster than guarded motion allows "
                                          r"\(8\.0 mm/s\).*80 N"):
        check_speeds(g, {"approach_speed_mps": 0.009}, 80.0, "x")
    check_speeds(dataclasses.replace(g, enabled=False), {"approach_speed_mps": 1.0}, 80.0, "x")
    # The wipe's approach is held to it when the task is built: a stiffer measured impact refuses it.
    cfg = vs["cfg"]
    stiff = dataclasses.replace(cfg, collision=dataclasses.replace(
        cfg.collision, guarded=GuardedSettings(impact_n_per_mps=50_000.0)))
    build_task("wipe", cfg, vs["robot"])
    with pytest.raises(ConfigError, match="tasks.wipe.approach_speed_mps"):
        build_task("wipe", stiff, vs["robot"])


def test_bad_guarded_settings_are_one_line_errors():
    with pytest.raises(ConfigError, match="guarded.impact_n_per_mps"):
        load_dataclass(CollisionConfig, {"guarded": {"impact_n_per_mps": 5}}, "collision")


def test_the_pegs_head_on_speeds_and_its_feed_while_it_can_wedge(vs):
    from app.tasks_registry import build_task, peg_head_on_speeds
    from cell.control.guarded import GuardedSettings
    from tasks.peg.config import PegConfig

    cfg = vs["cfg"]
    peg = PegConfig()
    bound = cfg.collision.guarded.speed_bound(peg.max_force_n)
    assert all(v <= bound for v in peg_head_on_speeds(peg).values())  # the defaults keep guarded motion
    stiff = dataclasses.replace(cfg, collision=dataclasses.replace(
        cfg.collision, guarded=GuardedSettings(impact_n_per_mps=20_000.0)))
    with pytest.raises(ConfigError, match="tasks.peg.approach_speed_mps"):
        build_task("peg-in-hole", stiff, vs["robot"])
    # The free feed is held to the wedge speed while the peg is shallower than mu x D, then runs free.
    wedge = peg.wedge_friction * peg.peg_diameter_m
    assert peg.feed_speed(0.5 * wedge, peg.free_insert_speed_mps) == peg.wedge_speed_mps
    assert peg.feed_speed(1.01 * wedge, peg.free_insert_speed_mps) == peg.free_insert_speed_mps


def test_a_payload_error_widens_the_thresholds_by_its_inertial_load_at_the_commanded_acceleration(vs, model):
    # +0.45 kg braking a fast wrist move read 1.06x on joint 5: the payload term carries the error's
    # inertial load as well as its weight: payload_kg * sum_i |J_ij| |a_i| at the tool's centre of mass.
    import pinocchio as pin

    d = _guard(vs, model).detector
    robot, dt = vs["robot"], vs["cfg"].loop.period_s
    q = posture(robot, np.asarray(vs["cfg"].robot.home, float), [0.45, -0.15, 0.25])
    moving = np.full(6, 0.5)
    d.update(ArmState(t=0.0, q=q, dq=np.zeros(6), tau=np.zeros(6)))
    base = d.thresholds(q, moving, np.zeros(6))
    a = np.array([0.0, 0.0, 0.0, 0.0, -40.0, 0.0])  # braking joint 5 from rest's speed 0: pure q''
    for k in range(3):
        d.commanded(q + 0.5 * a * (k * dt) ** 2)
    widened = d.thresholds(q, moving, np.zeros(6))
    # The same load computed apart: the centre of mass's acceleration by finite differences of its position.
    pm, pd, fid = d._pm, d._pm.createData(), d._com_id
    qs = [q + 0.5 * a * (k * dt) ** 2 for k in range(3)]
    pos = []
    for qk in qs:
        pin.framesForwardKinematics(pm, pd, qk)
        pos.append(pd.oMf[fid].translation.copy())
    acc = (pos[2] - 2 * pos[1] + pos[0]) / dt**2
    J = pin.computeFrameJacobian(pm, pd, qs[2], fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3]
    payload = d.settings.payload_uncertainty_kg * (np.abs(J).T @ np.abs(acc))
    inertial = d.settings.inertia_uncertainty * (np.abs(d.observer.mass) @ np.abs(a))
    assert np.allclose(widened - base, inertial + payload, rtol=0.05, atol=1e-3)
    assert payload[4] > 0.01
