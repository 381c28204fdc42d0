"""Hand guiding: the admittance without a cell (the deadband, braking on release, the stop above the limit,
taught poses written as a task file that loads), and `--teach` end to end on the simulated cell."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from app.tasks_registry import robot_for
from cell.config import load_config
from cell.control.loop import Observation
from drivers.interfaces import ArmState, ArmStatus, Wrench
from tasks.hand_guide import HandGuideConfig, HandGuideTask, taught_task_file
from tasks.primitives.taskfile import load_task_file

ROOT = Path(__file__).resolve().parents[1]


def _drive(task, robot, forces, dt=0.008):
    """Step the task with an ideal arm (the measured joints are the last target) and the given hand forces
    (base frame, on the tool); returns the TCP positions."""
    q = np.asarray(task.q_start, float)
    out = []
    for f in forces:
        R = robot.tcp_pose(q).rotation
        w = Wrench(0.0, -(R.T @ np.asarray(f, float)), np.zeros(3))  # the tool exerts -F on the hand
        state = ArmState(t=0.0, q=q.copy(), dq=np.zeros(6), tau=np.zeros(6), status=ArmStatus(), seq=0)
        cmd = task.step(Observation(t=0.0, cycle=0, state=state, wrench=w, q_cmd=q))
        q = np.asarray(cmd.q, float)
        out.append(robot.tcp_pose(q).translation.copy())
        if task.done:
            break
    return np.array(out)


def _task(**settings):
    cfg = load_config(None)
    robot = robot_for(cfg, "wipe")
    task = HandGuideTask(HandGuideConfig(**settings), robot, 0.008, np.asarray(cfg.robot.home, float))
    task.move = None
    task.state = type(task.state)["TARE"]  # skip the move to the start: the ideal arm starts there
    return task, robot


def test_a_force_in_the_deadband_moves_nothing_and_a_push_moves_along_it():
    task, robot = _task()
    rest = _drive(task, robot, [[0.0, 0.0, 0.0]] * 70 + [[2.0, 0.0, 0.0]] * 250)
    assert np.linalg.norm(rest[-1] - rest[0]) < 1e-6
    moved = _drive(task, robot, [[0.0, 10.0, 0.0]] * 250)
    d = moved[-1] - moved[0]
    assert d[1] > 0.02 and abs(d[0]) < 1e-3 and abs(d[2]) < 1e-3


def test_release_brakes_to_rest_and_a_force_over_the_limit_stops():
    task, robot = _task()
    _drive(task, robot, [[0.0, 0.0, 0.0]] * 70 + [[0.0, 12.0, 0.0]] * 200)
    after = _drive(task, robot, [[0.0, 0.0, 0.0]] * 100)
    assert np.linalg.norm(after[-1] - after[-30]) < 1e-6  # at rest well within 100 periods
    _drive(task, robot, [[0.0, 0.0, -40.0]] * 5)
    assert task.outcome == "failed" and "above the limit" in task.reason


def test_the_kick_after_a_stop_neither_moves_nor_stops_the_tool_and_fades():
    """Just after the tool came to rest a reading along the last motion (the joints' stick) is held, and the
    force limit is raised by the same band; once the band and the rest hold have passed, a smaller force moves
    the tool and a force above the limit stops it."""
    task, robot = _task(inertia_readback=0.0)
    # 0.1 m/s, then braked to rest at 1 m/s^2 within 13 periods.
    _drive(task, robot, [[0.0, 0.0, 0.0]] * 70 + [[0.0, 12.0, 0.0]] * 200 + [[0.0, 0.0, 0.0]] * 14)
    assert not np.any(task.v)
    # (Each drive starts the ideal arm at the start posture: a few periods bring it back to the reference.)
    held = _drive(task, robot, [[0.0, 0.0, 0.0]] * 4 + [[0.0, 25.0, 0.0]] * 8)
    assert np.linalg.norm(held[-1] - held[3]) < 1e-6 and not task.done
    _drive(task, robot, [[0.0, 40.0, 0.0]] * 2)
    assert not task.done  # above the limit, within the kick's band above it
    _drive(task, robot, [[0.0, 0.0, 0.0]] * 160)  # to rest again, and past the hold
    moved = _drive(task, robot, [[0.0, 20.0, 0.0]] * 50)
    assert moved[-1][1] - moved[0][1] > 0.005
    _drive(task, robot, [[0.0, 0.0, -40.0]] * 5)
    assert task.outcome == "failed" and "above the limit" in task.reason


def test_from_rest_the_damping_is_lighter_until_the_tool_moves():
    """The start's damping (start_damping_scale) lets a steady push from rest drive the tool faster than the
    full damping would, as long as the tool stays below start_speed_mps."""
    speeds = {}
    for scale in (0.5, 1.0):
        task, robot = _task(inertia_readback=0.0, start_damping_scale=scale)
        _drive(task, robot, [[0.0, 0.0, 0.0]] * 70 + [[0.0, 6.0, 0.0]] * 300)
        speeds[scale] = float(np.linalg.norm(task.v))
    assert speeds[1.0] == pytest.approx(3.0 / 90.0, rel=0.05)  # (6 N - deadband) / damping
    assert speeds[0.5] == pytest.approx(3.0 / 45.0, rel=0.05)


def test_taught_poses_make_a_task_file_that_loads(tmp_path):
    doc = taught_task_file([[0.40, -0.15, 0.25], [0.40, 0.0, 0.25]], [180.0, 0.0, 0.0], "wipe", "taught")
    f = tmp_path / "taught.yaml"
    f.write_text(yaml.safe_dump(doc, sort_keys=False))
    cfg = load_config(None)
    tf = load_task_file(f, cfg.collision.guarded, cfg.safety.max_tool_force_n)
    assert [s.kind for s in tf.steps] == ["move", "move"]


@pytest.mark.usefixtures("prepared_wipe")  # the wipe tool's artefacts, prepared once per run
def test_teach_on_the_simulated_cell_writes_a_task_file_that_validates_and_replays(tmp_path, capsys):
    """`run hand-guide --teach` end to end: the scripted hand rests the tool at the demo path's three
    corners, the written file loads, and `run task` drives the arm through the taught poses."""
    from app.commands_hand_guide import DEMO_PATH
    from main import main

    taught = tmp_path / "taught.yaml"
    code = main(["-q", "run", "hand-guide", "--teach", str(taught), "--cell", "sim", "--json", "--no-record"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0, out.get("reason")
    cfg = load_config(None)
    start = np.asarray(HandGuideConfig().start_xyz, float)
    corners = start + np.asarray(DEMO_PATH[1:], float)
    poses = np.asarray(out["taught"], float)
    assert poses.shape == corners.shape
    assert np.max(np.linalg.norm(poses - corners, axis=1)) < 0.01  # where the hand rested the tool
    tf = load_task_file(taught, cfg.collision.guarded, cfg.safety.max_tool_force_n)
    assert [s.kind for s in tf.steps] == ["move"] * len(corners)
    code = main(["-q", "run", "task", str(taught), "--cell", "sim", "--json", "--no-record"])
    replay = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and replay["outcome"] == "done", replay.get("reason")
    assert replay["steps_done"] == len(corners)


def test_a_cell_config_sets_hand_guiding_and_a_bad_value_is_one_line(tmp_path):
    from drivers.errors import ConfigError
    from tasks.hand_guide import load_hand_guide_config

    path = tmp_path / "cell.yaml"
    path.write_text(f"base: {ROOT / 'config' / 'cell.yaml'}\ntasks:\n  hand_guide: {{deadband_n: 2.5}}\n",
                    encoding="utf-8")
    cfg = load_config(path)
    assert load_hand_guide_config(cfg.tasks["hand_guide"], "tasks.hand_guide").deadband_n == 2.5
    with pytest.raises(ConfigError, match=r"tasks\.hand_guide\.deadband_n"):
        load_hand_guide_config({"deadband_n": 40.0}, "tasks.hand_guide")
