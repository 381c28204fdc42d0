"""The nominal URDF against the fact sheet's documented checks."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from cell.config import CONFIG_DIR

URDF = CONFIG_DIR / "robots" / "tm5-700" / "tm5-700.urdf"


@pytest.fixture(scope="module")
def bare():
    model = pin.buildModelFromUrdf(str(URDF))
    return model, model.createData(), model.getFrameId("flange")


def flange(bare, q):
    model, data, fid = bare
    pin.framesForwardKinematics(model, data, np.asarray(q, float))
    return data.oMf[fid]


def test_flange_pose_at_zero_points_up_with_z_along_minus_y(bare):
    pose = flange(bare, np.zeros(6))
    np.testing.assert_allclose(pose.translation, [0.0, -0.23545, 0.8917], atol=1e-6)
    np.testing.assert_allclose(pose.rotation[:, 2], [0.0, -1.0, 0.0], atol=1e-9)


def test_flange_pose_with_arm_horizontal(bare):
    pose = flange(bare, [0, np.pi / 2, 0, 0, 0, 0])
    np.testing.assert_allclose(pose.translation, [0.7465, -0.2354, 0.1452], atol=1e-4)


def test_nominal_gravity_torques_arm_horizontal(bare):
    model, data, _ = bare
    g = pin.computeGeneralizedGravity(model, data, np.array([0, np.pi / 2, 0, 0, 0, 0]))
    np.testing.assert_allclose(g, [0, -33.5, -13.9, -2.3, -0.7, 0], atol=0.06)


def test_limits_follow_the_fact_sheet(bare):
    model, _, _ = bare
    np.testing.assert_allclose(np.degrees(model.upperPositionLimit), [270, 180, 155, 180, 180, 270], atol=1e-3)
    np.testing.assert_allclose(np.degrees(model.velocityLimit), [180, 180, 180, 225, 225, 225], atol=1e-3)
    np.testing.assert_allclose(model.effortLimit, [157, 157, 157, 43, 43, 43])


def test_j2_j3_j4_axes_are_parallel(bare):
    model, data, _ = bare
    q = np.random.default_rng(0).uniform(-1, 1, 6)
    pin.forwardKinematics(model, data, q)
    axes = [data.oMi[j].rotation[:, 2] for j in (2, 3, 4)]
    for a in axes[1:]:
        assert abs(abs(a @ axes[0]) - 1.0) < 1e-9


def test_ik_reaches_a_tool_down_pose(robot, home):
    from cell.control.trajectory import tool_down_pose

    target = tool_down_pose(np.array([0.45, -0.1, 0.12]))
    q, ok = robot.ik(target, home)
    assert ok
    np.testing.assert_allclose(robot.tcp_pose(q).translation, target.translation, atol=1e-6)
