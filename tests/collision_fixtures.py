"""The collision tests' shared pieces (a pytest plugin, tests/conftest.py): `vs`, the small virtual-sensor artefacts,
`model`, their hybrid model (a test module may define its own of either), and `posture`, a tool-down pose by IK."""

from __future__ import annotations

import numpy as np
import pytest

from cell.sensing.virtual_sensor import load_observer_model
from tests.vsfixtures import artefacts


@pytest.fixture(scope="module")
def vs():
    return artefacts()


@pytest.fixture(scope="module")
def model(vs):
    return load_observer_model(vs["cfg"].virtual_sensor.path("model", "wipe"), vs["robot"])


def posture(robot, home, xyz):
    from cell.control.trajectory import tool_down_pose

    q, ok = robot.ik(tool_down_pose(np.asarray(xyz, float)), home)
    assert ok
    return q
