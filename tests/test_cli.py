"""The real CLI (`main.main`): the wiping task end to end, its recording, and clear errors on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from app.commands_bench import BENCH_CONTEXT_KEYS
from cell.config import CONFIG_DIR
from cell.data.recorder import read_log
from main import main


def last_json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    return json.loads(out[-1])


@pytest.mark.slow
def test_wipe_on_the_default_plant_meets_the_force_targets(capsys):
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--json"])
    summary = last_json(capsys)
    assert code == 0, summary
    assert summary["outcome"] == "done" and not summary["safety_stop"]
    assert summary["force_tracking_mae_n"] <= 2.0
    assert summary["force_tracking_std_n"] <= 2.0
    assert summary["path_length_m"] >= 0.3 and summary["wipe_samples"] > 500
    run = Path(summary["run_dir"])
    assert (run / "summary.json").exists() and (run / "config.yaml").exists() and (run / "plot.png").exists()
    log = read_log(run)
    assert log.num_rows == summary["cycles"] + 1  # the last (finishing) step is logged too
    assert {"t", "state", "q1", "tau6", "q_cmd3", "fz", "fz_setpoint", "compute_ms"} <= set(log.column_names)
    assert set(log.column("state").to_pylist()) >= {"approach", "wipe", "retract"}
    saved = json.loads((run / "summary.json").read_text())
    assert saved["force_tracking_mae_n"] == summary["force_tracking_mae_n"]


@pytest.mark.slow
def test_missing_force_readings_are_not_scored_as_errors(capsys, monkeypatch):
    """A timed-out read (NaN) holds the reference for a period; the summary's figures skip it."""
    import numpy as np

    from drivers.interfaces import Wrench
    from sim.drivers import SimForceSensor

    real_read = SimForceSensor._read
    calls = {"n": 0}

    def dropping_read(self):
        calls["n"] += 1
        w = real_read(self)
        if calls["n"] % 40 == 0:
            return Wrench(t=w.t, force=np.full(3, np.nan), torque=np.full(3, np.nan))
        return w

    monkeypatch.setattr(SimForceSensor, "_read", dropping_read)
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--json", "--no-record"])
    summary = last_json(capsys)
    assert code == 0 and summary["outcome"] == "done", summary
    assert summary["missing_force_samples"] > 10
    assert np.isfinite(summary["force_tracking_mae_n"]) and summary["force_tracking_mae_n"] <= 2.0


def write_config(tmp_path: Path, mutate) -> Path:
    data = yaml.safe_load((CONFIG_DIR / "cell.yaml").read_text())
    data["robot"]["urdf"] = str(CONFIG_DIR / data["robot"]["urdf"])
    data["plant"] = str(CONFIG_DIR / data["plant"])
    mutate(data)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (lambda d: d["loop"].update(period_s="fast"), "loop.period_s must be a number"),
        (lambda d: d["safety"].update(max_tool_force_n=-1), "safety.max_tool_force_n must lie in (0, 200] N, got -1"),
        (lambda d: d["tasks"]["wipe"].update(force_setpoint_n=500), "tasks.wipe.force_setpoint_n must lie in"),
        (lambda d: d["tasks"]["wipe"].update(speeed_mps=1), "unknown key 'speeed_mps'"),
        (lambda d: d["robot"].update(home=[0, 1, 2]), "robot.home must have 6 values"),
        (lambda d: d.update(plant="/nonexistent/plant.yaml"), "/nonexistent/plant.yaml: cannot read"),
        (lambda d: d["loop"].update(period_s=0.004), "differs from the plant's sample_period_s"),
    ],
)
def test_bad_config_is_one_clear_line_and_exit_2(tmp_path, capsys, mutate, needle):
    path = write_config(tmp_path, mutate)
    code = main(["run", "wipe", "--config", str(path), "--no-record"])
    err = capsys.readouterr().err
    assert code == 2
    assert needle in err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1
    assert str(path) in lines[0] or "/nonexistent" in lines[0]


def test_malformed_plant_profile_names_the_field(tmp_path, capsys):
    profile = yaml.safe_load((CONFIG_DIR / "plants" / "default.yaml").read_text())
    profile["friction"]["coulomb"] = [1.0, 2.0]
    bad = tmp_path / "plant.yaml"
    bad.write_text(yaml.safe_dump(profile))
    code = main(["run", "wipe", "--plant", str(bad), "--no-record"])
    err = capsys.readouterr().err
    assert code == 2 and f"{bad}: friction.coulomb must have 6 values" in err and "Traceback" not in err


def test_invalid_yaml_names_the_line(tmp_path, capsys):
    bad = tmp_path / "cell.yaml"
    bad.write_text("loop:\n  period_s: [0.008\n")
    assert main(["status", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "invalid YAML" in err and str(bad) in err


def test_bad_arguments_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "mop-the-floor"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_virtual_force_source_without_artefacts_is_refused_on_the_real_cell(capsys):
    assert main(["run", "wipe", "--force-source", "virtual", "--cell", "real", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert "virtual force sensor" in err and "main.py prepare" in err


def test_status_prints_the_simulated_arm(capsys):
    assert main(["-q", "status", "--json"]) == 0
    out = last_json(capsys)
    assert out["cell"] == "sim" and len(out["q_deg"]) == 6 and len(out["wrench"]) == 6


@pytest.mark.slow
def test_bench_sim_reports_a_real_time_factor(capsys):
    assert main(["-q", "bench", "sim", "--json"]) == 0
    out = last_json(capsys)
    assert out["real_time_factor"] > 1.0 and out["outcomes"] == ["done", "done"]
    # The run's context beside it, as every bench reports it (its values are the machine's, not checked here).
    assert set(BENCH_CONTEXT_KEYS) <= out.keys()
    assert len(out["load_avg_before"]) == 3 and out["cpu_count"] >= 1
    assert out["cpu_model"] and 0 < out["machine_reference_ms"] < 1e4


@pytest.mark.slow
def test_bench_plant_reports_the_error_budget(capsys):
    assert main(["-q", "bench", "plant", "--json"]) == 0
    out = last_json(capsys)
    # The calibration the default profile promises (config/plants/README.md).
    assert 7.0 <= out["p1_rmse_j123_nm"] <= 13.0
    assert 2.0 <= out["ideal_p2_rmse_j123_nm"] <= 4.0
    assert out["noise_rmse_j123_nm"] < 0.5 * out["ideal_p2_rmse_j123_nm"]
