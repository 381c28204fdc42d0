"""First use on a fresh clone: calibrate and plan without prepared artefacts prepare them (sim) or say how."""

from __future__ import annotations

import json

import pytest

from app.planning_model import PLANS
from cell.config import load_config
from drivers.errors import ConfigError
from main import main
from tasks.setup.plan import load_plan_file


def test_calibrate_without_a_model_on_the_real_cell_says_to_prepare(capsys):
    assert main(["calibrate", "--tool", "peg", "--cell", "real"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no torque model" in err[0] and "main.py prepare --tool peg --cell real" in err[0]


def test_calibrate_with_a_missing_model_folder_says_to_prepare(tmp_path, capsys):
    assert main(["calibrate", "--model", str(tmp_path / "none")]) == 2
    assert "main.py prepare --tool wipe --cell sim" in capsys.readouterr().err


def test_calibrate_without_a_model_on_the_simulated_cell_prepares_it(monkeypatch, capsys):
    calls = []

    def fake_prepare(cfg, tool, kind, seed, samples, force):
        calls.append((tool, kind, force))
        return {"tool": tool, "prepared": True}

    monkeypatch.setattr("app.commands_lab.run_prepare", fake_prepare)
    assert main(["-q", "calibrate", "--tool", "wipe", "--json"]) == 0
    assert calls == [("wipe", "sim", False)]
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == {"tool": "wipe", "prepared": True}


def test_plan_without_a_prepared_model_on_the_real_cell_says_how(capsys):
    assert main(["plan", "--cell", "real"]) == 2
    err = capsys.readouterr().err
    assert "main.py prepare --tool wipe --cell real" in err and "--model nominal" in err


@pytest.mark.parametrize("argv", [["plan", "--cell", "sim"], ["bench", "planning"]])
def test_plan_without_a_prepared_model_on_the_simulated_cell_prepares_it(monkeypatch, capsys, argv):
    """Prepared as `run` prepares it: on the cell's own limits, not the plans' TCP limit (the collection keeps to
    the TCP speed limit, so a raised one would collect another dataset, and the model would depend on which
    command ran first)."""
    calls = []

    def fake_prepare(cfg, tool, kind, seed, samples, force):
        calls.append((tool, kind, cfg.safety.max_tcp_speed))
        raise ConfigError("stop here: the test only checks that prepare is asked for")

    monkeypatch.setattr("app.planning_model.run_prepare", fake_prepare)
    assert main(argv) == 2
    assert calls == [("wipe", "sim", load_config().safety.max_tcp_speed)]
    assert load_plan_file(PLANS).max_tcp_speed != load_config().safety.max_tcp_speed  # what the check tells apart
    assert "stop here" in capsys.readouterr().err


@pytest.mark.parametrize("cell", ["sim", "real"])
def test_plan_on_the_nominal_model_needs_nothing_prepared(monkeypatch, cell):
    """--model nominal: the old behaviour, asked for by name (the plans themselves are not run here)."""
    seen = {}

    def fake_run_plans(cfg, robot, predictor, model_name, *rest, **kw):
        seen["model"] = model_name
        return {"plans": 0, "paths": {}, "mean_improvement_vs_uniform_pct": None}

    monkeypatch.setattr("tasks.setup.plan.run_plans", fake_run_plans)
    monkeypatch.setattr("app.planning_model.run_prepare", lambda *a, **k: pytest.fail("prepare was asked for"))
    assert main(["-q", "plan", "--model", "nominal", "--cell", cell]) == 0
    assert seen["model"].startswith("P1")
