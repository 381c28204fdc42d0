"""The cell's observers share one model evaluation per period: the virtual sensor's main observer leads it,
its touch channel and the collision detector follow (app/sensing.py, cell/sensing/model_step.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.cells import open_cell
from app.sensing import make_force_source, with_guard
from app.tasks_registry import robot_for
from cell.config import load_config
from cell.sensing.virtual_sensor import VirtualForceSource


@pytest.mark.slow
@pytest.mark.usefixtures("prepared_peg")  # the peg tool's artefacts, prepared once per run
def test_the_collision_detector_follows_the_virtual_sensors_model_step():
    cfg = load_config()
    robot = robot_for(cfg, "peg")
    holder = open_cell(cfg, "sim", robot, None, None)
    try:
        cell = with_guard(cfg, "peg", make_force_source(cfg, "virtual", "peg", holder.open(), robot), robot)
        force = cell.force
        assert isinstance(force, VirtualForceSource) and force.model_step is not None
        assert cell.guard is not None
        guard = cell.guard("peg-in-hole", 60.0)
        assert guard is not None
        step = force.model_step
        assert guard.detector.observer.step is step
        assert step.lead is force.observer
        assert force.touch is None or getattr(force.touch, "step", None) is step
        state = cell.arm.read_state()
        for k in range(5):
            s = dataclasses.replace(state, t=state.t + k * cfg.loop.period_s)
            force.read(s)
            guard.observe(s, s.t, k, "approach")
        assert step.evaluations == 5
        assert np.all(np.isfinite(guard.detector.residual))
    finally:
        holder.close()


@pytest.mark.slow
@pytest.mark.usefixtures("prepared_peg")
def test_a_sensor_in_the_loop_leaves_the_detector_its_own_step():
    cfg = load_config()
    robot = robot_for(cfg, "peg")
    holder = open_cell(cfg, "sim", robot, None, None)
    try:
        cell = with_guard(cfg, "peg", make_force_source(cfg, "sensor", "peg", holder.open(), robot), robot)
        assert cell.guard is not None
        guard = cell.guard("peg-in-hole", 60.0)
        assert guard is not None
        assert guard.detector.observer.step.lead is guard.detector.observer
    finally:
        holder.close()
