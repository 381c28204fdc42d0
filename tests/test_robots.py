"""Robots by name (`config/robots/<name>/robot.yaml`, `cell.model.specs`) and the lab's `--robot`."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.model.specs import ROBOTS_DIR, available_robots, load_robot_spec, robot_by_name, robot_model
from drivers.errors import ConfigError
from main import main
from tasks.lab.collect import collect


def test_both_robots_load_from_their_folders():
    assert available_robots() == ["tm5-700", "ur10e"]
    tm5 = load_robot_spec("tm5-700")
    assert tm5.urdf == ROBOTS_DIR / "tm5-700" / "tm5-700.urdf" and tm5.urdf.is_file()
    assert tm5.joints == 6 and tm5.flange_frame == "flange"
    assert tm5.torque_source == "torque" and tm5.torque_constants is None
    ur = load_robot_spec("ur10e")
    assert ur.folder == ROBOTS_DIR / "ur10e" and ur.urdf.name == "ur10e.urdf"
    assert ur.torque_source == "current"
    assert ur.torque_constants == (10.0, 10.6956, 8.4566, 9.0029, 9.48, 10.1232)
    assert "Universal Robots" in ur.description
    model = robot_model(ur)
    assert model.model.name == "ur10e" and model.n == 6 and model.tool.mass == 0.0
    q = np.array([0.0, -1.5, 1.0, -1.0, 0.5, 0.2])
    np.testing.assert_allclose(model.tcp_pose(q).translation, model.frame_pose(q, "flange").translation)
    assert np.all(model.limits.upper[:2] == pytest.approx(6.2832))  # limits come from the URDF


def test_unknown_robot_names_the_available_ones():
    with pytest.raises(ConfigError) as exc:
        load_robot_spec("ur5")
    assert str(exc.value) == "unknown robot 'ur5' (available: tm5-700, ur10e)"


def _copy_robot(tmp_path: Path, name: str = "ur10e") -> tuple[Path, dict]:
    robots = tmp_path / "robots"
    shutil.copytree(ROBOTS_DIR / name, robots / name)
    doc = yaml.safe_load((robots / name / "robot.yaml").read_text())
    return robots, doc


def _write(robots: Path, doc: dict, name: str = "ur10e") -> None:
    (robots / name / "robot.yaml").write_text(yaml.safe_dump(doc))


def test_unknown_and_missing_keys_name_the_file_and_key(tmp_path):
    robots, doc = _copy_robot(tmp_path)
    _write(robots, {**doc, "colour": "blue"})
    with pytest.raises(ConfigError) as exc:
        load_robot_spec("ur10e", robots)
    msg = str(exc.value)
    assert "\n" not in msg and "robot.yaml" in msg and "unknown key 'colour'" in msg
    del doc["flange_frame"]
    _write(robots, doc)
    with pytest.raises(ConfigError, match=r"robot\.yaml: flange_frame is required"):
        load_robot_spec("ur10e", robots)


def test_drive_keys_are_checked(tmp_path):
    robots, doc = _copy_robot(tmp_path)
    _write(robots, {**doc, "drive": {**doc["drive"], "gear_ratio": 100}})
    with pytest.raises(ConfigError, match=r"robot\.yaml: drive: unknown key 'gear_ratio'|drive.*gear_ratio"):
        load_robot_spec("ur10e", robots)
    _write(robots, {**doc, "drive": {"torque_source": "current"}})
    with pytest.raises(ConfigError, match="torque_constants_nm_per_a is required"):
        load_robot_spec("ur10e", robots)
    _write(robots, {**doc, "drive": {**doc["drive"], "torque_constants_nm_per_a": [10.0] * 5}})
    with pytest.raises(ConfigError, match="must have 6 values"):
        load_robot_spec("ur10e", robots)


def test_joint_count_is_checked_against_the_urdf(tmp_path):
    robots, doc = _copy_robot(tmp_path, "tm5-700")
    _write(robots, {**doc, "joints": 7}, "tm5-700")
    with pytest.raises(ConfigError) as exc:
        load_robot_spec("tm5-700", robots)
    assert "robot.yaml: joints is 7 but tm5-700.urdf has 6 joints" in str(exc.value)


def test_robot_by_name_keeps_the_cell_model_for_the_tm5_and_takes_others_by_name(cfg, robot):
    tm5 = robot_by_name(cfg)
    assert tm5.urdf == robot.urdf and tm5.tool.mass == cfg.robot.tool_mass  # today's model, nominal tool
    q = np.array([0.1, -0.4, 1.2, 0.3, 1.0, 0.0])
    np.testing.assert_allclose(robot_by_name(cfg, "tm5-700").gravity(q), robot.gravity(q))
    ur = robot_by_name(cfg, "ur10e")
    assert ur.model.name == "ur10e" and ur.tool.mass == 0.0
    with pytest.raises(ConfigError, match="unknown robot 'ur3'"):
        robot_by_name(cfg, "ur3")


def test_collect_refuses_another_robot(cfg, tmp_path, capsys):
    def never() -> None:
        raise AssertionError("no cell may be opened")

    with pytest.raises(ConfigError, match="the simulated plant is a tm5-700"):
        collect(cfg, never, tmp_path / "data", robot="ur10e")
    assert main(["-q", "collect", "--robot", "ur10e", "--out", str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "collect --robot ur10e" in err[0]
    assert not (tmp_path / "data").exists()
