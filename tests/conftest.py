"""Shared fixtures: the default config, the nominal robot model and fresh simulated plants."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cell.config import CellConfig, load_config, resolve
from cell.model.robot import RobotModel, load_robot

ROOT = Path(__file__).resolve().parents[1]

# The drivers' fixtures (emulator, connected device), shared by each driver's test modules.
pytest_plugins = ["tests.tm5_fixtures", "tests.wacoh_fixtures"]


@pytest.fixture(autouse=True)
def _isolated_runs(tmp_path, monkeypatch):
    """Every test writes its runs/ below its own temporary folder."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture
def cfg() -> CellConfig:
    return load_config()


@pytest.fixture
def robot(cfg: CellConfig) -> RobotModel:
    return load_robot(resolve(cfg.robot.urdf), cfg.robot.tcp_wipe, cfg.robot.tool_mass, cfg.robot.tool_com)


@pytest.fixture
def home(cfg: CellConfig) -> np.ndarray:
    return np.asarray(cfg.robot.home, float)
