"""The shipped spiral search (config/tasks/spiral-find-hole.yaml) on the simulated cell: it finds the peg
fixture's hole from an offset start, scored against where the plant has it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cell.config import load_config
from main import main
from tasks.primitives.taskfile import load_task_file

ROOT = Path(__file__).resolve().parents[1]
FILE = ROOT / "config" / "tasks" / "spiral-find-hole.yaml"


def test_the_example_loads_with_its_spiral_step():
    cfg = load_config(None)
    tf = load_task_file(FILE, cfg.collision.guarded, cfg.safety.max_tool_force_n)
    assert "spiral_search" in [s.kind for s in tf.steps]


@pytest.mark.usefixtures("prepared_peg")  # the peg tool's artefacts, prepared once per run
def test_spiral_search_finds_the_hole_from_an_offset_start(capsys):
    code = main(["-q", "run", "task", str(FILE), "--cell", "sim", "--json", "--no-record"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0, out.get("reason")
    found = next(s["result"] for s in out["steps"] if s["step"] == "hole")
    start = next(s["result"] for s in out["steps"] if s["step"] == "face")["contact_point_m"]
    assert found["found"] and found["sunk_m"] >= 0.0005  # the depth condition, not a force drop
    assert found["radius_m"] > 0.001  # it had to spiral out to the hole (the start is 1.4 mm off)
    score = out["truth_scores"]["found"]
    assert score["truth"] == "hole_center_xy" and score["error_mm"] <= 0.5
    # It sank where the hole is, not where it started.
    assert abs(found["point_m"][0] - start[0]) + abs(found["point_m"][1] - start[1]) > 0.001
