"""Shared, built-once artefacts for the virtual-sensor tests: a small causal H1 and its calibration on the sim.

Built at most once per test run, in the run's shared folder (tests/prepared_fixtures.py: the first
process that asks builds it under a lock, the other xdist workers read it), and loaded once per process (a
module-level cache, so every test module shares it): a small collection with the wiping tool, the causal H1
and a reduced calibration.  The tests read these artefacts; one that changes one works on its own copy.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import yaml

from cell.config import CalibrationConfig, CellConfig, load_config
from tests.prepared_fixtures import built_once

_CACHE: dict[str, Any] = {}


def small_config(root: Path) -> CellConfig:
    """The default cell with artefact paths under `root` and a reduced calibration (6 postures)."""
    cfg = load_config()
    cal = CalibrationConfig(
        postures=[[0.40, -0.25, 0.12, 0.0, 0.0], [0.50, 0.00, 0.12, 0.0, 0.0], [0.40, 0.00, 0.20, 8.0, 0.0],
                  [0.50, -0.25, 0.20, 0.0, -8.0], [0.45, -0.12, 0.09, 0.0, 0.0], [0.45, -0.05, 0.14, 4.0, 0.0]],
        holdout=[5], loads=6, load_s=1.2, settle_s=0.6,
    )
    vs = dataclasses.replace(cfg.virtual_sensor, data_dir=str(root / "data" / "{tool}"),
                             model_dir=str(root / "models" / "{tool}"),
                             calibration_dir=str(root / "calibration" / "{tool}"), calibration=cal)
    return dataclasses.replace(cfg, virtual_sensor=vs,
                               recording=dataclasses.replace(cfg.recording, directory=str(root / "runs")))


def artefacts() -> dict[str, Any]:
    """{"root", "cfg", "prepare" (its summary), "robot"}: built on first use."""
    if _CACHE:
        return _CACHE
    from app.tasks_registry import robot_for

    root = built_once("vs", _build)
    cfg = small_config(root)
    summary = json.loads((root / "prepare.json").read_text())
    _CACHE.update(root=root, cfg=cfg, prepare=summary, robot=robot_for(cfg, "wipe"))
    return _CACHE


def _build(root: Path) -> None:
    from app.cells import calibration_cells
    from app.tasks_registry import robot_for
    from tasks.lab.collect import collect
    from tasks.setup.prepare import prepare

    ex = root / "ex.yaml"
    ex.write_text(yaml.safe_dump({"max_configs": 4, "speeds": [0.7, 1.0],
                                  "fourier": {"harmonics": 3, "periods": 1, "base_hz": 0.25, "candidates": 3}}))
    cfg = small_config(root)
    robot = robot_for(cfg, "wipe")
    opener, hand = calibration_cells(cfg, "sim", "wipe", robot, None)

    # A small collection through the lab (its own excitation config keeps the planning short).
    data_dir = cfg.virtual_sensor.path("data", "wipe")
    collect(cfg, opener, data_dir, samples=12_000, test_trajectories=0, excitation=str(ex))
    summary = prepare(cfg, "wipe", robot, opener, opener, hand, samples=12_000)
    (root / "prepare.json").write_text(json.dumps(summary))
