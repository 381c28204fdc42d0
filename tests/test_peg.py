"""Peg-in-hole: contact states from staged wrenches, config checks, and short runs on the simulated cell."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivers.errors import ConfigError
from tasks.peg.config import PegConfig, load_peg_config
from tasks.peg.contact import Contact, classify
from tasks.peg.geometry import rim_points
from tasks.peg.scoring import wrench_errors
from tasks.peg.touch import GuardedDescent


@pytest.fixture
def pcfg() -> PegConfig:
    return PegConfig()


class TestContactStates:
    """Each of the paper's contact scenarios (Fig. 13) from a staged (Fz, Mx, My) and the kinematic depths
    of the lowest / highest point of the peg's bottom rim below the mouth."""

    def test_free_in_the_air(self, pcfg):
        assert classify(0.5, 0.02, -0.03, -0.005, -0.009, pcfg) == Contact.FREE

    def test_free_while_sliding_into_the_hole(self, pcfg):
        assert classify(1.0, 0.05, 0.0, 0.010, 0.010, pcfg) == Contact.FREE

    def test_stuck_outside_on_the_rim(self, pcfg):
        # The tilted peg's lowest point rests on the rim or plate: touching, nothing below the mouth.
        assert classify(15.0, 0.2, -0.1, -0.0005, -0.0045, pcfg) == Contact.STUCK_OUTSIDE

    def test_stuck_outside_by_moment_alone(self, pcfg):
        assert classify(1.0, 0.9, 0.0, 0.0, -0.004, pcfg) == Contact.STUCK_OUTSIDE

    def test_stuck_inside_lead_edge_in_face_on_the_far_rim(self, pcfg):
        # The tilted entry: the lead edge is below the mouth, the face rests on the far rim.
        assert classify(12.0, 0.0, 0.3, 0.0009, -0.0036, pcfg) == Contact.STUCK_INSIDE

    def test_stuck_inside_one_side_touching(self, pcfg):
        assert classify(12.0, 0.1, pcfg.side_moment_nm + 0.3, 0.011, 0.011, pcfg) == Contact.STUCK_INSIDE
        # ... but not on a moment inside the force source's error band
        assert classify(12.0, 0.1, pcfg.side_moment_nm - 0.3, 0.011, 0.011, pcfg) == Contact.ALIGNED

    def test_aligned_pushing_along_the_axis(self, pcfg):
        assert classify(20.0, 0.1, -0.1, 0.015, 0.015, pcfg) == Contact.ALIGNED

    def test_missing_reading_is_never_a_contact_outside(self, pcfg):
        assert classify(float("nan"), 0.0, 0.0, 0.0, -0.004, pcfg) == Contact.FREE
        assert classify(float("nan"), 0.0, 0.0, 0.02, 0.02, pcfg) == Contact.ALIGNED

    def test_rim_points_of_a_tilted_peg(self):
        # Peg tilted 10 deg: its rim's lowest and highest points are r sin(10 deg) below / above the centre.
        import pinocchio as pin

        from cell.control.trajectory import TOOL_DOWN

        pose = pin.SE3(pin.exp3(np.array([0.0, 1.0, 0.0]) * np.radians(10)) @ TOOL_DOWN, np.array([0.1, 0.2, 0.3]))
        low, high = rim_points(pose, 0.0107)
        assert low[2] == pytest.approx(0.3 - 0.0107 * np.sin(np.radians(10)), abs=1e-9)
        assert high[2] == pytest.approx(0.3 + 0.0107 * np.sin(np.radians(10)), abs=1e-9)
        assert np.linalg.norm(low - pose.translation) == pytest.approx(0.0107)


class TestConfig:
    def test_defaults_are_valid(self):
        from app.tasks_registry import peg_head_on_speeds
        from cell.control.guarded import GuardedSettings, check_speeds

        cfg = load_peg_config(None, "tasks.peg")
        assert cfg == PegConfig()  # nothing configured: the dataclass's defaults, and they validate
        # The thresholds stack as the task's state machine reads them: a touch before a contact before
        # the probe's hold before the task's own force limit.
        assert cfg.touch_force_n <= cfg.contact_force_n < cfg.probe_force_n < cfg.max_force_n
        assert cfg.contact_force_n < cfg.insert_force_n < cfg.max_force_n
        assert cfg.comply_deadband_nm < cfg.side_moment_nm < cfg.max_moment_nm
        # Every head-on speed stays under guarded motion's bound for the task's force limit.
        bound = check_speeds(GuardedSettings(), peg_head_on_speeds(cfg), cfg.max_force_n, "tasks.peg")
        assert cfg.approach_speed_mps <= bound
        # The feed slows where a peg can wedge, and more at a tighter fit.
        assert cfg.feed_speed(0.0, cfg.free_insert_speed_mps) == cfg.wedge_speed_mps < cfg.free_insert_speed_mps
        assert cfg.tight_feed_speed(0.000025) < cfg.tight_feed_speed(0.00005) <= cfg.tight_insert_speed_mps

    def test_bad_threshold_names_the_field(self):
        with pytest.raises(ConfigError, match="tasks.peg.probe_force_n"):
            load_peg_config({"probe_force_n": 200.0}, "tasks.peg")

    def test_entry_tilt_must_be_below_the_tilt_limit(self):
        with pytest.raises(ConfigError, match="tasks.peg.entry_tilt_deg"):
            load_peg_config({"entry_tilt_deg": 20.0}, "tasks.peg")

    def test_unknown_key(self):
        with pytest.raises(ConfigError, match="unknown key 'depth'"):
            load_peg_config({"depth": 0.03}, "tasks.peg")

    def test_overrides_apply_to_their_force_source_only(self):
        raw = {"comply_deadband_nm": 1.5, "by_force_source": {"sensor": {"comply_deadband_nm": 0.3}}}
        assert load_peg_config(raw, "tasks.peg", "sensor").comply_deadband_nm == 0.3
        assert load_peg_config(raw, "tasks.peg", "virtual").comply_deadband_nm == 1.5

    def test_the_shipped_config_complies_early_only_on_the_ft_sensor(self, cfg):
        raw = cfg.tasks["peg"]
        sensor, virtual = load_peg_config(raw, "tasks.peg", "sensor"), load_peg_config(raw, "tasks.peg", "virtual")
        assert sensor.comply_deadband_nm < 0.5 < 1.0 < virtual.comply_deadband_nm

    def test_bad_overrides_are_named(self):
        with pytest.raises(ConfigError, match="unknown force source 'ft'"):
            load_peg_config({"by_force_source": {"ft": {}}}, "tasks.peg")
        with pytest.raises(ConfigError, match=r"tasks.peg.side_moment_nm.*by_force_source.sensor overrides"):
            load_peg_config({"by_force_source": {"sensor": {"side_moment_nm": 9.0}}}, "tasks.peg", "sensor")


def test_wrench_errors_only_over_the_insertion():
    log = {
        "state": ["tare", "approach", "insert", "retract"],
        "mx": [9.0, 0.1, 0.2, 9.0], "sensor_mx": [0.0, 0.0, 0.0, 0.0],
        "my": [0.0, 0.0, 0.0, 0.0], "sensor_my": [0.0, 0.1, 0.3, 0.0],
        "fz": [0.0, 1.0, 20.0, 0.0], "sensor_fz": [0.0, 2.0, 18.0, 0.0],
    }
    out = wrench_errors(log)
    assert out["virtual_vs_sensor_samples"] == 2
    assert out["virtual_vs_sensor_mx_mae_nm"] == pytest.approx(0.15)
    assert out["virtual_vs_sensor_my_mae_nm"] == pytest.approx(0.2)
    assert out["virtual_vs_sensor_fz_mae_n"] == pytest.approx(1.5)


# --------------------------------------------------------------------------------------- on the sim
def _trial(cfg, offset=(0.0, 0.0), tilt=(0.0, 0.0), **overrides):
    from app.tasks_registry import robot_for
    from bench.peg import run_trial

    robot = robot_for(cfg, "peg")
    pcfg = replace(PegConfig(), **overrides)
    return run_trial(cfg, robot, pcfg, np.asarray(offset), np.radians(tilt), 3, None, None)


@pytest.mark.slow
def test_aligned_peg_is_inserted_and_retracted(cfg):
    tr = _trial(cfg, offset=(0.0015, -0.001))
    assert tr.outcome == "done", tr.reason
    assert tr.success and tr.true_depth_m >= 0.026
    assert tr.peak_force_n < 80


@pytest.mark.slow
def test_a_jam_that_cannot_be_cleared_fails_by_name_with_the_arm_stopped(cfg, monkeypatch):
    # A hole only 12 mm deep can never reach the 27 mm target: the peg bottoms out and stalls.
    cfg.scene = replace(cfg.scene, hole_depth=0.012)
    import bench.peg as bench

    holders = []
    real = bench.SimCell

    def keep(*a, **k):
        h = real(*a, **k)
        holders.append(h)
        return h

    monkeypatch.setattr(bench, "SimCell", keep)
    tr = _trial(cfg, max_realigns=2, free_insert_speed_mps=0.002)  # a gentle feed: the jam, not the impact
    assert tr.outcome == "failed"
    assert "jammed at depth 12" in tr.reason and "2 realignments" in tr.reason
    assert holders[0].plant.holding  # the loop stopped the arm
    assert tr.task_time_s < 30  # bounded, not a hang


@pytest.mark.slow
def test_a_tilted_hole_is_surveyed_and_inserted(cfg):
    # The fixture tilted 2 deg about x and -1.5 deg about y, offset 1 mm: the survey of its face gives
    # the hole's axis (to ~0.1 deg), the insertion then follows it.
    tr = _trial(cfg, offset=(0.001, -0.001), tilt=(2.0, -1.5))
    assert tr.outcome == "done", tr.reason
    assert tr.axis_error_deg is not None and tr.axis_error_deg < 0.2
    assert tr.success and tr.peak_force_n < 80


def test_the_surveyed_face_defines_the_hole_frame(cfg):
    # Three touch points on a face tilted 2 deg about x through the nominal mouth centre: the fitted frame
    # makes the face level at the nominal height, and a point on the face reads depth 0 in it.
    import pinocchio as pin

    from app.tasks_registry import robot_for
    from tasks.peg.task import PegInHoleTask

    robot = robot_for(cfg, "peg")
    centre = np.array([*cfg.scene.hole_center, cfg.scene.table_height])
    task = PegInHoleTask(PegConfig(), robot, centre[:2], centre[2], cfg.loop.period_s,
                         np.asarray(cfg.robot.home, float))
    R = pin.exp3(np.array([np.radians(2.0), 0.0, 0.0]))
    task.survey.points = [centre + R @ np.array([r * np.cos(a), r * np.sin(a), 0.0])
                           for r, a in ((0.0145, np.pi / 2), (0.0145, -np.pi / 2), (0.0145, np.pi))]
    assert task._fit_face()
    assert task.hole_tilt_deg == pytest.approx(2.0, abs=1e-6)
    assert np.allclose(task.world_from_hole.rotation[:, 2], R[:, 2], atol=1e-9)
    on_face = centre + R @ np.array([0.005, 0.012, 0.0])
    assert (task.hole_from_world.act(on_face))[2] == pytest.approx(centre[2], abs=1e-9)


def test_a_face_tilted_beyond_the_limit_fails_by_name(cfg):
    from app.tasks_registry import robot_for
    from tasks.peg.task import PegInHoleTask

    robot = robot_for(cfg, "peg")
    centre = np.array([*cfg.scene.hole_center, cfg.scene.table_height])
    task = PegInHoleTask(PegConfig(max_hole_tilt_deg=3.0), robot, centre[:2], centre[2], cfg.loop.period_s,
                         np.asarray(cfg.robot.home, float))
    s = np.tan(np.radians(6.0))
    task.survey.points = [centre + np.array([x, y, s * x]) for x, y in ((0.0, 0.0145), (0.0, -0.0145), (-0.0145, 0.0))]
    assert not task._fit_face()
    assert task.outcome == "failed" and "fixture face tilted 6.0 deg" in task.reason


def _bare_task(cfg, pc: PegConfig | None = None):
    """A peg task on the default cell, driven by hand (no loop): for its single steps."""
    from app.tasks_registry import robot_for
    from tasks.peg.task import PegInHoleTask

    return PegInHoleTask(pc or PegConfig(), robot_for(cfg, "peg"), np.asarray(cfg.scene.hole_center),
                         cfg.scene.table_height, cfg.loop.period_s, np.asarray(cfg.robot.home, float))


class _Descent:
    """A guarded descent at the survey speed, the measured tip scripted by the test."""

    def __init__(self, cfg) -> None:
        import pinocchio as pin

        self.pin = pin
        self.pc = PegConfig()
        self.dt = cfg.loop.period_s
        self.guard = GuardedDescent(self.pc, self.dt)
        self.t = 0.0
        self.v = self.pc.survey_speed_mps
        self.z0 = 0.06
        self.ref = pin.SE3(np.eye(3), np.array([0.45, -0.12, self.z0]))

    def cycle(self, tip_z: float) -> float:
        """One control cycle with the tip at `tip_z`: how far the reference then leads the tip."""
        self.t += self.dt
        self.guard.descend(self.v, self.t, self.ref, self.pin.SE3(np.eye(3), np.array([0.45, -0.12, tip_z])))
        return tip_z - float(self.ref.translation[2])

    def onto_face(self) -> tuple[list[float], float]:
        """Descend freely at the commanded speed for 12 cycles: the leads, and where the tip is then."""
        leads = [self.cycle(self.z0 - self.v * self.dt * k) for k in range(12)]
        return leads, self.z0 - self.v * self.dt * 11


def test_a_guarded_descent_that_stalls_on_a_face_cuts_its_lead(cfg):
    # The tip descends at the commanded speed, then stops dead (a stiff face): the reference may lead it
    # by only touch_lead_m from then on (the force on the face stays bounded while the wrench confirms
    # the touch); once the tip moves on again, the full lead is back.
    d = _Descent(cfg)
    pc = d.pc
    leads, z_face = d.onto_face()
    assert max(leads) <= pc.max_lead_m + 1e-12 and not d.guard.pressing
    leads = [d.cycle(z_face) for _ in range(10)]  # stopped dead on the face
    assert d.guard.pressing
    assert leads[-1] <= pc.touch_lead_m + 1e-12
    assert leads[-1] < pc.max_lead_m / 2
    for k in range(1, 8):  # it was a stick, not a face: it moves on
        d.cycle(z_face - d.v * d.dt * k)
    assert not d.guard.pressing


def test_a_tip_bouncing_on_the_face_keeps_the_lead_cut(cfg):
    # A stiff face throws the tip back up after the first touch (the arm's own spring), and it falls back
    # onto the face faster than the descent.  That fall is not a stick breaking free: the lead stays cut
    # to touch_lead_m all the way down (with the full lead back, a bench trial's next impact reached
    # 174 N); only moving on below where it stalled gives the lead back.
    d = _Descent(cfg)
    _, z_face = d.onto_face()
    for _ in range(5):
        d.cycle(z_face)
    assert d.guard.pressing
    leads, pressing = [], []
    for h in (3e-5, 6e-5, 8e-5, 6e-5, 3e-5, 1e-5, 0.0, 0.0, 0.0):
        leads.append(d.cycle(z_face + h))
        pressing.append(d.guard.pressing)
    assert all(pressing), pressing
    assert max(leads) <= d.pc.touch_lead_m + 1e-12
    for k in range(1, 10):  # through the face: it moves on
        d.cycle(z_face - d.v * d.dt * k)
    assert not d.guard.pressing


def test_a_descent_starting_from_rest_keeps_its_full_lead(cfg):
    # A tip that has not moved yet (the arm sticks at the start of a move) has not decelerated onto
    # anything: the lead stays max_lead_m so the servo can break it free.
    d = _Descent(cfg)
    leads = [d.cycle(d.z0) for _ in range(15)]
    assert not d.guard.pressing
    assert leads[-1] == pytest.approx(d.pc.max_lead_m)



def test_the_touch_test_on_a_two_reading_mean_ignores_a_ringing_force_but_not_a_touch():
    # A force source that rings at the control period (signs alternating, here +-20 N in free air) is not a
    # touch on the mean of two readings, while a touch that bounces on and off the face (0 / 40 N) is, as
    # on single readings.
    import pinocchio as pin

    def run(pc: PegConfig, fz: list[float]) -> list[str]:
        guard = GuardedDescent(pc, 0.0156)
        pose = pin.SE3(np.eye(3), np.array([0.45, -0.12, 0.06]))
        return [guard.touch(f, pc.survey_cycles, pose.copy(), pose) for f in fz]

    ringing = [(-1.0) ** k * 20.0 for k in range(12)]
    bouncing = [0.0, 0.0, 40.0, 0.0, 40.0, 0.0, 40.0]
    single, mean2 = PegConfig(), PegConfig(touch_mean_cycles=2)
    assert "touch" in run(single, ringing)
    assert "touch" not in run(mean2, ringing)
    assert "touch" in run(single, bouncing) and "touch" in run(mean2, bouncing)
    with pytest.raises(ConfigError):
        replace(mean2, touch_mean_cycles=0).validate("tasks.peg")

@pytest.mark.slow
def test_bench_runs_one_trial_again_and_records_it(capsys):
    # `--only` re-runs trial 1 of a 3-trial bench (the same draws), `--record` logs it; the peak force is
    # the F/T sensor's, with the state it was measured in.
    import json
    from pathlib import Path

    from cell.data.recorder import read_log
    from main import main

    code = main(["-q", "bench", "peg-in-hole", "--trials", "3", "--only", "1", "--seed", "2", "--record",
                 "--force-source", "sensor", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0
    assert out["trials"] == 1 and [t["trial"] for t in out["per_trial"]] == [1]
    assert out["per_trial"][0]["success"], out["failures"]
    (bench_dir,) = Path("runs").glob("*-bench-peg")
    log = read_log(bench_dir / "trial_001")
    states = log.column("state").to_pylist()
    assert {"approach", "insert", "retract"} <= set(states)
    # The reported peak is the F/T sensor's (here the force source: fx..fz) largest |F| in the recording
    # once the task is past its setup, named by the state it was read in: a row's `state` is the one after
    # its step, so a reading's is the row before's.
    f = np.linalg.norm(np.stack([log.column(f"f{a}").to_numpy() for a in "xyz"], axis=1), axis=1)
    read_in = np.asarray(["move_to_start"] + states[:-1])
    k = int(np.argmax(np.where(np.isin(read_in, ["move_to_start", "tare"]), -1.0, f)))
    assert out["peak_force_n"] == pytest.approx(f[k], abs=1e-6)
    assert out["peak_force_state"] == read_in[k]
    assert not (bench_dir / "trial_000").exists()


def test_bench_refuses_a_trial_number_outside_the_bench(capsys):
    from main import main

    assert main(["bench", "peg-in-hole", "--trials", "3", "--only", "3", "--force-source", "sensor"]) == 2
    assert "--only [3]: trial numbers must lie in 0..2" in capsys.readouterr().err


@pytest.mark.slow
def test_run_peg_in_hole_records_states_wrench_depth_and_a_plot(capsys):
    # The main job's command on the simulated cell (here with the F/T sensor in the loop, which needs no
    # prepared artefacts): done, and the recording holds what the paper's Fig. 16 shows.
    import json
    from pathlib import Path

    from cell.data.recorder import read_log
    from main import main

    code = main(["-q", "run", "peg-in-hole", "--force-source", "sensor", "--json"])
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and s["outcome"] == "done", s
    assert s["inserted"] and s["max_depth_m"] >= 0.027 and s["peak_force_n"] < 80
    run = Path(s["run_dir"])
    assert (run / "plot.png").exists()
    log = read_log(run)
    assert {"contact", "depth", "fz", "mx", "my", "tip_x", "tilt_x"} <= set(log.column_names)
    assert {"survey", "approach", "slide", "rotate", "insert", "release", "retract"} <= \
        set(log.column("state").to_pylist())


def test_upright_on_the_wall_the_peg_steps_onto_the_axis_gradually_before_feeding(cfg):
    # A step of the radial clearance in one period jerked the arm into the rim (90-100 N): the reference
    # moves off the wall at centre_speed_mps, and the feed along the axis starts only after it.
    import pinocchio as pin

    pc = PegConfig()
    dt = cfg.loop.period_s
    task = _bare_task(cfg, pc)
    task.ref = pin.SE3(pin.rpy.rpyToMatrix(np.pi, 0.0, 0.0), np.array([0.45, -0.12, 0.049]))
    task._tip = task.ref.copy()
    task.lead = np.array([-1.0, 0.0, 0.0])
    task._centre_left = (pc.hole_diameter_m - pc.peg_diameter_m) / 2
    task.depth = 0.001
    start = task.ref.translation.copy()
    deltas = []
    for _ in range(200):
        before = task.ref.translation.copy()
        task._insert(None, 0.0, 0.0, 0.0)
        deltas.append(task.ref.translation - before)
        if task._centre_left <= 0:
            break
    steps = np.array(deltas)
    assert np.all(np.abs(steps[:, 0]) <= pc.centre_speed_mps * dt + 1e-12)
    assert np.allclose(steps[:, 1:], 0.0)  # no feed while stepping off the wall
    assert task.ref.translation[0] - start[0] == pytest.approx(0.0002)  # off the lead wall by the clearance
    task._insert(None, 0.0, 0.0, 0.0)  # then the feed along the peg's axis
    assert task.ref.translation[2] < start[2]


@pytest.mark.parametrize("climb_m, ends", [(0.0002, True), (0.0001, False)])
def test_a_search_move_carried_up_the_mouths_edge_has_met_the_wall(pcfg, climb_m, ends):
    # The wall can stop a search move by lifting the peg rather than holding it back (the tilted peg's
    # lead edge rides up the mouth's edge): past slide_climb_m above its reference, the move has met it.
    import pinocchio as pin

    from tasks.peg.search import WallSearch

    dt = 0.008
    search = WallSearch(pcfg, dt)
    ref, tip = pin.SE3.Identity(), pin.SE3.Identity()
    search.begin(ref, tip)
    lead = np.array([1.0, 0.0, 0.0])
    status = "searching"
    for _ in range(int(0.5 / dt) + int(pcfg.max_slide_m / (pcfg.slide_slow_speed_mps * dt))):
        tip = ref.copy()  # the tip follows its reference exactly ...
        if search.slid > pcfg.slide_fast_m:
            tip.translation[2] += climb_m  # ... until the lead edge meets the edge and climbs
        status = search.step(ref, tip, lead, 0.0, 0.0)
        if search.phase > 0 or status != "searching":
            break
    if ends:
        assert search.phase == 1 and status == "searching"
        assert search.slid == 0.0  # the next phase (back off along the lead) has begun
    else:
        assert status == "lost" and search.phase == 0


def test_a_search_starts_by_moving_its_reference_to_the_tip_gradually(pcfg):
    # A contact can push the tip 0.7 mm off the reference the probe held; jumping the reference there in one
    # period swung joint 1 past its torque limit.  It travels at the lift's speed instead.
    import pinocchio as pin

    from tasks.peg.search import WallSearch

    dt = 0.008
    search = WallSearch(pcfg, dt)
    ref, tip = pin.SE3.Identity(), pin.SE3.Identity()
    tip.translation[:] = [0.0003, -0.0007, -0.0002]
    search.begin(ref, tip)
    path = [ref.translation.copy()]
    for _ in range(40):
        search.step(ref, tip, np.array([1.0, 0.0, 0.0]), 0.0, 0.0)
        path.append(ref.translation.copy())
        if np.allclose(ref.translation[:2], tip.translation[:2]) and ref.translation[2] > tip.translation[2]:
            break
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    assert steps.max() <= pcfg.backoff_speed_mps * dt + 1e-12
    assert np.allclose(path[-1][:2], tip.translation[:2])  # there, and then lifting off as before
    assert len(path) > 0.00079 / (pcfg.backoff_speed_mps * dt)


def test_after_a_climb_the_reference_is_not_dropped_on_the_edge(pcfg):
    # A move that ended on a climb left the tip above its reference; the next move takes the peg off the
    # mouth's edge, and a reference left below would drop it by the whole climb within a period (a 99 N hit).
    import pinocchio as pin

    from tasks.peg.search import WallSearch

    dt, climb = 0.008, 0.0002
    search = WallSearch(pcfg, dt)
    ref, tip = pin.SE3.Identity(), pin.SE3.Identity()
    search.begin(ref, tip)
    lead = np.array([1.0, 0.0, 0.0])
    while search.phase == 0:
        tip = ref.copy()
        if search.slid > pcfg.slide_fast_m:
            tip.translation[2] += climb
        z_before = ref.translation[2]
        search.step(ref, tip, lead, 0.0, 0.0)
    assert ref.translation[2] == pytest.approx(tip.translation[2])  # the reference starts from the climbed tip
    heights = []
    for _ in range(100):
        search.step(ref, ref.copy(), lead, 0.0, 0.0)
        heights.append(ref.translation[2])
    steps = np.diff([tip.translation[2], *heights])
    assert np.all(steps <= 1e-15) and np.all(steps >= -pcfg.climb_return_speed_mps * dt - 1e-12)
    assert heights[-1] == pytest.approx(z_before)  # then back at the slide's height
