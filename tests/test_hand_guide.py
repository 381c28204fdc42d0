"""Hand guiding's admittance without a cell: the deadband, braking on release, the stop above the limit,
taught poses written as a task file that loads."""

from __future__ import annotations

import numpy as np
import yaml

from app.tasks_registry import robot_for
from cell.config import load_config
from cell.control.loop import Observation
from drivers.interfaces import ArmState, ArmStatus, Wrench
from tasks.hand_guide import HandGuideConfig, HandGuideTask, taught_task_file
from tasks.primitives.taskfile import load_task_file


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


def _task():
    cfg = load_config(None)
    robot = robot_for(cfg, "wipe")
    task = HandGuideTask(HandGuideConfig(), robot, 0.008, np.asarray(cfg.robot.home, float))
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


def test_taught_poses_make_a_task_file_that_loads(tmp_path):
    doc = taught_task_file([[0.40, -0.15, 0.25], [0.40, 0.0, 0.25]], [180.0, 0.0, 0.0], "wipe", "taught")
    f = tmp_path / "taught.yaml"
    f.write_text(yaml.safe_dump(doc, sort_keys=False))
    cfg = load_config(None)
    tf = load_task_file(f, cfg.collision.guarded, cfg.safety.max_tool_force_n)
    assert [s.kind for s in tf.steps] == ["move", "move"]
