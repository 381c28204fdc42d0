"""Fast moves (cell/data/excitation/fast.py): time-optimal rest-to-rest moves between random poses at the
speeds `plan` runs at, added to the training plan, collected under the planner's TCP speed stop, and the rule
by which `prepare` collects a dataset again when it lacks a part."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cell.config import CONFIG_DIR, CellConfig, load_config
from cell.data.excitation.config import ExcitationConfig, FourierConfig
from cell.data.excitation.fast import FastConfig, fast_moves
from cell.data.excitation.limits import Workspace, excitation_checker
from cell.data.excitation.motion import Motion
from cell.model.dynamics.physics import P1Model
from cell.model.robot import RobotModel
from cell.model.specs import robot_by_name
from cell.planning.config import PlannerConfig
from drivers.errors import ConfigError
from tasks.setup.plan import load_plan_file

DT = 0.008
SAMPLES = 1500
TRAJ_BASE, SEGMENT_BASE = 900, 40
SMALL = ExcitationConfig(steps=[2, 2, 2, 2, 2, 2], speeds=[0.5, 1.0], max_configs=5,
                         fourier=FourierConfig(harmonics=3, periods=1, base_hz=0.25, candidates=4, trajectories=1))


@dataclasses.dataclass
class Fast:
    cfg: CellConfig
    robot: RobotModel
    planner: PlannerConfig
    start: np.ndarray
    motion: Motion

    @property
    def q(self) -> np.ndarray:
        return np.vstack([s.q for s in self.motion.segments])

    @property
    def moves(self) -> list[Any]:
        """The timed moves (after the way in from the start)."""
        return self.motion.segments[-self.motion.info["moves"]:]


@pytest.fixture(scope="module")
def fast() -> Fast:
    cfg = load_config()
    robot = robot_by_name(cfg)  # the model `collect` plans the training motion on
    planner = load_plan_file(CONFIG_DIR / "plans.yaml").planner
    start = np.asarray(cfg.robot.home, float) + np.array([0.05, -0.05, 0.05, 0.0, 0.05, 0.0])
    motion = fast_moves(robot, cfg, read_default_excitation(), DT, SAMPLES, planner, start=start,
                        traj_base=TRAJ_BASE, segment_base=SEGMENT_BASE)
    return Fast(cfg, robot, planner, start, motion)


def read_default_excitation() -> ExcitationConfig:
    from cell.data.excitation.config import read_excitation_config

    return read_excitation_config(None)


# ------------------------------------------------------------------------------------------ the motion
def test_fast_moves_fill_the_samples_in_one_continuous_motion_from_the_start(fast):
    m = fast.motion
    q = fast.q
    # Moves are kept until their samples are filled, not far beyond; the way in from the start is a transfer
    # (traj -1), outside the count.
    assert SAMPLES <= m.labelled_samples < SAMPLES + 600
    way_in = [s for s in m.segments if s.traj < 0]
    assert way_in and all(s.kind == "transfer" for s in way_in)
    assert m.info["moves"] >= 3 and all(s.kind == "fast" for s in m.segments if s.traj >= 0)
    np.testing.assert_allclose(q[0], fast.start, atol=1e-3)  # the way in leaves from the given start
    # Continuous: no step between consecutive samples (across moves too) outruns the planner's speed limit.
    vmax = fast.robot.limits.velocity * fast.planner.velocity_fraction
    steps = np.abs(np.diff(np.vstack([fast.start, q]), axis=0))
    assert np.all(steps <= vmax * DT * (1 + 1e-3))
    # Ids: trajectories from traj_base, each move a trajectory of its own; segments numbered on from
    # segment_base, one per segment.
    assert [s.segment for s in m.segments] == list(range(SEGMENT_BASE, SEGMENT_BASE + len(m.segments)))
    assert min(s.traj for s in m.segments if s.traj >= 0) == TRAJ_BASE
    assert [s.traj for s in fast.moves] == list(range(TRAJ_BASE, TRAJ_BASE + m.info["moves"]))


def test_every_move_ends_at_rest_at_a_free_pose_inside_the_workspace(fast):
    cc = excitation_checker(fast.robot, fast.cfg, read_default_excitation())
    ws = Workspace(fast.robot, fast.cfg, read_default_excitation())
    rest = int(round(FastConfig().rest_s / DT))
    begin = fast.motion.segments[-len(fast.moves) - 1].q[-1]
    for seg in fast.moves:
        end = seg.q[-1]
        assert len(seg.q) > rest
        np.testing.assert_array_equal(seg.q[-rest:], np.repeat(end[None, :], rest, axis=0))
        # It arrives at rest: the last planned steps before the hold are tiny.
        assert np.abs(seg.q[-rest] - seg.q[-rest - 1]).max() < 1e-3
        assert cc.free(end) and ws.inside(end)
        assert np.abs(end - begin).max() > 0.1  # a real move, not a hold
        begin = end


def test_fast_moves_reach_working_speeds_within_the_planners_speed_limits(fast):
    dq = np.diff(fast.q, axis=0) / DT
    peak = np.abs(dq).max(axis=0)
    assert peak.max() > 1.5  # the point of them: well above the other families' 0.5-0.8 rad/s
    assert np.all(peak <= fast.robot.limits.velocity * fast.planner.velocity_fraction * (1 + 1e-3))
    # The reported peaks are the planned ones.
    np.testing.assert_allclose(fast.motion.info["peak_speed_rad_s"], peak, atol=0.05)


def test_fast_moves_keep_the_commanded_tcp_under_the_planners_stop_and_inside_the_safety_box(fast):
    tcp = np.array([fast.robot.tcp_pose(x).translation for x in fast.q])
    speed = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / DT
    assert speed.max() <= fast.planner.tcp_speed_limit
    assert speed.max() > fast.cfg.safety.max_tcp_speed  # beyond the cell's own stop: why the run raises it
    assert fast.motion.info["tcp_speed_limit"] == fast.planner.tcp_speed_limit  # the stop it reports is the one kept
    s = fast.cfg.safety
    assert np.all(tcp >= np.asarray(s.workspace_min)) and np.all(tcp <= np.asarray(s.workspace_max))


def test_nominal_torque_plus_the_rotor_bound_stays_under_the_scaled_planning_limit(fast):
    fc = FastConfig()
    q = fast.q
    dq = (q[2:] - q[:-2]) / (2 * DT)
    ddq = (q[2:] - 2 * q[1:-1] + q[:-2]) / DT**2
    tau = P1Model(fast.robot).predict(q[1:-1], dq, ddq) + np.asarray(fc.rotor_inertia_bound) * ddq
    limit = fast.robot.limits.effort * (1.0 - fast.planner.torque_margin) * fc.torque_scale
    ratio = np.abs(tau).max(axis=0) / limit
    assert np.all(ratio <= 1.05), ratio  # (finite differences of the sampled motion: a few % of slack)
    # The torque bound, not only the speed limits, shapes the timing: some joint uses most of it.
    assert ratio.max() > 0.6, ratio
    assert np.all(np.abs(ddq).max(axis=0) <= np.asarray(fc.acceleration_limits) * 1.1)


def test_no_timeable_move_is_a_value_error(fast, caplog):
    # A torque bound too low to hold the arm against gravity: no move can be timed, and an empty motion is
    # refused rather than returned.
    with caplog.at_level("WARNING", logger="cell.data.excitation.fast"), pytest.raises(ValueError, match="no move"):
        fast_moves(fast.robot, fast.cfg, SMALL, DT, 3000, fast.planner, fc=FastConfig(torque_scale=1e-3))
    assert "infeasible move" in caplog.text


# ------------------------------------------------------------------------------------------ training plan
def test_training_plan_needs_planner_settings_with_a_tcp_stop(fast):
    from tasks.lab.collect import training_plan

    cfg, robot = fast.cfg, fast.robot
    with pytest.raises(ConfigError, match="TCP speed limit"):
        training_plan(robot, cfg, SMALL, DT, 2000, "fourier", fast_share=0.25)
    with pytest.raises(ConfigError, match="TCP speed limit"):
        training_plan(robot, cfg, SMALL, DT, 2000, "fourier", fast_share=0.25,
                      fast_planner=dataclasses.replace(fast.planner, tcp_speed_limit=0.0))
    with pytest.raises(ConfigError, match="fast_share"):
        training_plan(robot, cfg, SMALL, DT, 2000, "fourier", fast_share=1.0, fast_planner=fast.planner)


def test_training_plan_appends_fast_moves_after_the_other_parts(fast):
    from tasks.lab.collect import training_plan

    cfg, robot = fast.cfg, fast.robot
    base = training_plan(robot, cfg, SMALL, DT, 4000, "fourier", slow_share=0.2)
    plan = training_plan(robot, cfg, SMALL, DT, 4000, "fourier", slow_share=0.2, fast_share=0.5,
                         fast_planner=fast.planner)
    assert "fast" in plan.info and plan.info["fast"]["moves"] >= 1 and plan.info["fast_share"] == 0.5
    assert "slow" in plan.info  # the other parts stay
    fast_segs = [s for s in plan.segments if s.kind == "fast"]
    assert sum(len(s.q) for s in fast_segs) >= int(4000 * 0.5)
    assert all(s.traj >= 900 for s in fast_segs)
    # Appended last: after the other parts, a transfer to the first pose (traj -1), then the moves.
    added = plan.segments[len(base.segments):]
    way_in = added[:len(added) - len(fast_segs)]
    assert way_in and all(s.kind == "transfer" and s.traj == -1 for s in way_in)
    assert all(s.kind == "fast" for s in added[len(way_in):])
    assert max(s.traj for s in plan.segments if s.kind != "fast") < 900
    segs = [s.segment for s in plan.segments]
    assert len(set(segs)) == len(segs)  # segment ids stay unique
    assert plan.labelled_samples == base.labelled_samples + sum(len(s.q) for s in fast_segs)
    q = np.vstack([s.q for s in plan.segments])
    vmax = robot.limits.velocity * fast.planner.velocity_fraction
    assert np.all(np.abs(np.diff(q, axis=0)) <= vmax * DT * (1 + 1e-3))  # the fast part follows on
    assert np.abs(np.diff(q, axis=0)).max() / DT > 1.5


# ------------------------------------------------------------------------------------------ collect
class _Stop(Exception):
    """Raised by the stand-in player once it has what the test needs."""


class _Arm:
    def __init__(self, q: np.ndarray) -> None:
        self.q = q

    def read_state(self) -> Any:
        return dataclasses.make_dataclass("State", ["q"])(self.q)


class _Holder:
    """What `collect` opens: a cell whose arm is at home; nothing is ever played on it."""

    def __init__(self, home: np.ndarray) -> None:
        self.closed = False
        self.home = home

    def open(self) -> Any:
        return type("Cell", (), {"arm": _Arm(self.home)})()

    def close(self) -> None:
        self.closed = True


def _captured_train_cfg(monkeypatch, tmp_path: Path, fast: Fast, fast_share: float) -> tuple[CellConfig, Motion]:
    import tasks.lab.collect as lab

    seen: dict[str, Any] = {}

    def play(plan: Motion, split: str, cell: Any, cfg: CellConfig, robot: RobotModel) -> dict[str, Any]:
        seen.update(plan=plan, split=split, cfg=cfg)
        raise _Stop

    monkeypatch.setattr(lab, "_play", play)
    ex_file = tmp_path / "excitation.yaml"
    ex_file.write_text(json.dumps(dataclasses.asdict(SMALL)))
    holder = _Holder(np.asarray(fast.cfg.robot.home, float))
    with pytest.raises(_Stop):
        lab.collect(fast.cfg, lambda: holder, tmp_path / f"ds-{fast_share}", samples=4000, family="fourier",
                    test_trajectories=0, excitation=str(ex_file), fast_share=fast_share,
                    fast_planner=fast.planner if fast_share > 0 else None)
    assert holder.closed and seen["split"] == "train"
    return seen["cfg"], seen["plan"]


def test_collect_runs_the_train_split_under_the_planners_tcp_stop(monkeypatch, tmp_path, fast):
    # (A large share: the way from the end of the Fourier part to the first pose counts against it.)
    cfg, plan = _captured_train_cfg(monkeypatch, tmp_path, fast, 0.9)
    assert cfg.safety.max_tcp_speed == max(fast.cfg.safety.max_tcp_speed, fast.planner.tcp_speed_limit)
    assert cfg.safety.max_tcp_speed > fast.cfg.safety.max_tcp_speed
    # Only the TCP stop is raised: the other stops stay the cell's.
    assert dataclasses.replace(cfg.safety, max_tcp_speed=fast.cfg.safety.max_tcp_speed) == fast.cfg.safety
    assert any(s.kind == "fast" for s in plan.segments)
    # Without fast moves the train split keeps the cell's own stop.
    plain, plain_plan = _captured_train_cfg(monkeypatch, tmp_path, fast, 0.0)
    assert plain.safety == fast.cfg.safety
    assert not any(s.kind == "fast" for s in plain_plan.segments)


# ------------------------------------------------------------------------------------------ prepare's rule
def _write_collect_json(folder: Path, train: Any) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "collect.json").write_text(json.dumps({"plans": {"train": train}}))
    return folder


@pytest.mark.parametrize("train, sweep, fast_part", [
    ({"trajectories": 3, "sweep": {"blocks": 2}, "fast": {"moves": 5}}, True, True),
    ({"trajectories": 3, "sweep": {"blocks": 2}}, True, False),
    ({"trajectories": 3, "fast": {"moves": 5}}, False, True),
    ({"trajectories": 3}, False, False),
    (["sweep", "fast"], False, False),  # not a plan's info
])
def test_has_part_reads_the_train_plans_parts_from_collect_json(tmp_path, train, sweep, fast_part):
    from tasks.setup.prepare import _has_part

    folder = _write_collect_json(tmp_path / "data", train)
    assert _has_part(folder, "sweep") is sweep
    assert _has_part(folder, "fast") is fast_part


def test_has_part_is_false_without_a_readable_collect_json(tmp_path):
    from tasks.setup.prepare import _has_part

    assert _has_part(tmp_path / "missing", "fast") is False
    garbled = tmp_path / "garbled"
    garbled.mkdir()
    (garbled / "collect.json").write_text('{"plans": {"train": {"fast": ')
    assert _has_part(garbled, "fast") is False
    no_plans = tmp_path / "no-plans"
    no_plans.mkdir()
    (no_plans / "collect.json").write_text(json.dumps({"train_samples": 10, "fast": {}}))
    assert _has_part(no_plans, "fast") is False
    not_a_dict = tmp_path / "list"
    not_a_dict.mkdir()
    (not_a_dict / "collect.json").write_text(json.dumps(["plans"]))
    assert _has_part(not_a_dict, "fast") is False


def test_a_model_fitted_with_other_robot_settings_is_trained_again():
    """`train` records the robot.yaml settings it fitted with; `prepare` keeps a model only when they are today's
    (a regime moved, an identification changed)."""
    import dataclasses
    from types import SimpleNamespace

    from tasks.lab.train import fit_settings, lab_settings
    from tasks.setup.prepare import fitted_with_current_settings

    settings = lab_settings()
    cc = settings["coverage"]
    assert cc.fit_max_speed > 0 and cc.fit_max_accel > 0  # the TM5-700 fits its residual in a regime

    def model(recorded: Any) -> Any:
        extra = {} if recorded is None else {"fit_settings": recorded}
        return SimpleNamespace(meta=SimpleNamespace(extra=extra))

    assert fitted_with_current_settings(model(fit_settings(settings)))
    assert not fitted_with_current_settings(model(None))  # made before the record: its settings are unknown
    moved = {**settings, "coverage": dataclasses.replace(cc, fit_max_speed=2 * cc.fit_max_speed)}
    assert not fitted_with_current_settings(model(fit_settings(moved)))
    other_id = dataclasses.replace(settings["identification"], consistency="log_cholesky", loss_terms=("load",))
    assert not fitted_with_current_settings(model(fit_settings({**settings, "identification": other_id})))
