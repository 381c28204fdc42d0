"""Calibration of the virtual sensor and `prepare`: the report, idempotence, refusing a mismatched
artefact, the operator prompt on the real cell, and the wiping task with the virtual sensor in the loop."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import yaml

from app.cells import calibration_cells
from app.tasks_registry import robot_for
from cell.config import CONFIG_DIR, load_config
from cell.data.recorder import read_log
from cell.sensing.artefacts import artefacts_missing
from cell.sensing.virtual_sensor import build_virtual_source
from drivers.errors import ConfigError, DataError
from main import main
from tasks.setup.calibrate import LoadApplier, OperatorLoads, calibrate, error_split
from tasks.setup.prepare import prepare
from tests.vsfixtures import artefacts


@pytest.fixture(scope="module")
def vs():
    return artefacts()


def no_applier(holder: object) -> LoadApplier:
    """For the runs that must stop before any load is applied."""
    raise AssertionError("a load applier was asked for")


def test_calibration_reports_every_route_on_held_out_postures(vs):
    steps = vs["prepare"]["steps"]
    assert steps["train"]["done"] and steps["calibrate"]["done"]
    doc = json.loads((vs["cfg"].virtual_sensor.path("calibration", "wipe") / "calibration.json").read_text())
    rep = doc["report"]
    routes = {f"{o}+{m}" for o in ("kalman", "momentum") for m in ("jacobian", "contact", "learned")}
    assert set(rep["routes"]) == routes
    assert rep["holdout_postures"] == [5] and rep["heldout_samples"] > 100 and rep["train_samples"] > 300
    # The loads really were 0-75 N presses, and the configured route reads them well on a posture
    # it never saw (a loose bound: this is a small model on a reduced calibration).
    assert rep["sensor_fz_range_n"][1] > 40
    cfg_vs = vs["cfg"].virtual_sensor
    wipe = cfg_vs.for_tool("wipe")
    assert rep["route"] == f"{wipe.observer}+{wipe.mapping}" and rep["fz_mae_n"] < 3.0
    for r in rep["routes"].values():
        assert {"fz_mae_n", "mx_mae_nm", "my_mae_nm"} <= set(r)
    # The configured route's error split by posture: the re-bias offset and the noise about it
    # (|e| <= |offset| + |e - offset|, so the parts bound the MAE).
    split = rep["error_split"]
    assert set(split) == {"fz_n", "mx_nm", "my_nm"}
    for key, total in (("fz_n", rep["fz_mae_n"]), ("mx_nm", rep["mx_mae_nm"]), ("my_nm", rep["my_mae_nm"])):
        part = split[key]
        assert part["posture_offset"] >= 0 and part["within_posture"] > 0
        assert total <= part["posture_offset"] + part["within_posture"] + 2e-4
    # The metadata names what the calibration belongs to.
    assert doc["robot"] == "tm5-700" and doc["tool"]["name"] == "wipe" and len(doc["model"]["sha256"]) == 64
    assert len(doc["measurement_var"]) == 6 and all(v > 0 for v in doc["measurement_var"])
    assert {"learned_kalman_fz.ubj", "learned_momentum_my.ubj"} <= {
        p.name for p in vs["cfg"].virtual_sensor.path("calibration", "wipe").iterdir()}


def test_prepare_skips_what_is_present_and_matching(vs):
    cfg, robot = vs["cfg"], vs["robot"]
    assert artefacts_missing(cfg, robot, "wipe") == ""

    def must_not_open():
        raise AssertionError("prepare opened a cell although everything was in place")

    out = prepare(cfg, "wipe", robot, must_not_open, must_not_open, no_applier)
    assert not any(step["done"] for step in out["steps"].values()), out["steps"]


def test_prepare_collects_again_a_dataset_without_the_working_posture_sweeps(vs):
    cfg, robot = vs["cfg"], vs["robot"]

    class Opened(Exception):
        pass

    def opener():
        raise Opened

    # The fixture's dataset was collected without a working posture: with one, prepare collects anew.
    with pytest.raises(Opened):
        prepare(cfg, "wipe", robot, opener, opener, no_applier, working_posture=np.asarray(cfg.robot.home))


def _copy_calibration(vs, tmp_path):
    src = vs["cfg"].virtual_sensor.path("calibration", "wipe")
    dst = tmp_path / "cal"
    shutil.copytree(src, dst)
    return dst


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda d: d["tool"].update(mass=0.85), "tool mass"),
        (lambda d: d["tool"].update(name="peg"), "tool name"),
        (lambda d: d.update(robot="ur5e"), "robot 'ur5e'"),
        (lambda d: d.update(urdf_sha256="0" * 64), "URDF sha256 000000000000"),
        (lambda d: d["model"].update(sha256="f" * 64), "torque model H1 sha256 ffffffffffff"),
    ],
)
def test_a_mismatched_calibration_is_refused_in_one_line(vs, tmp_path, mutate, needle):
    cfg = vs["cfg"]
    cal = _copy_calibration(vs, tmp_path)
    doc = json.loads((cal / "calibration.json").read_text())
    mutate(doc)
    (cal / "calibration.json").write_text(json.dumps(doc))
    with pytest.raises(DataError) as exc:
        build_virtual_source(cfg.virtual_sensor, vs["robot"], "wipe", cfg.loop.period_s, calibration_dir=cal)
    msg = str(exc.value)
    assert needle in msg and "main.py calibrate --tool wipe" in msg and "\n" not in msg


def test_the_peg_tool_does_not_take_the_wiping_calibration(vs):
    cfg = vs["cfg"]
    peg = robot_for(cfg, "peg")
    with pytest.raises(DataError, match="tool name wipe, this cell's tool has peg"):
        build_virtual_source(cfg.virtual_sensor, peg, "peg", cfg.loop.period_s,
                             model_dir=cfg.virtual_sensor.path("model", "wipe"),
                             calibration_dir=cfg.virtual_sensor.path("calibration", "wipe"))


def test_real_cell_without_artefacts_is_refused_naming_prepare(capsys):
    # The working directory is an empty temporary folder: no artefacts; nothing is built for a real cell.
    assert main(["run", "wipe", "--cell", "real", "--no-record"]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "main.py prepare --tool wipe --cell real" in lines[0] and "Traceback" not in err


def test_the_real_cell_asks_the_operator_on_the_cli():
    asked: list[str] = []

    def prompt(text: str) -> str:
        asked.append(text)
        return ""

    loads = OperatorLoads(prompt=prompt)
    loads.before_posture(2, 9, 20.0)
    assert len(asked) == 1 and "posture 3/9" in asked[0] and "20 s" in asked[0]
    # The operator pushes when the task says so (after the rest's re-zero), whatever settle_s is.
    assert "PUSH THE TOOL NOW" in asked[0]
    assert loads.update(3.0) == (-1, True) and not loads.scripted
    cfg, robot = artefacts()["cfg"], artefacts()["robot"]
    opener, applier = calibration_cells(cfg, "real", "wipe", robot, None)
    assert isinstance(applier(None), OperatorLoads)


@pytest.mark.slow
def test_wipe_runs_with_the_virtual_sensor_in_the_loop(vs, tmp_path, capsys):
    cfg = vs["cfg"]
    raw = yaml.safe_load((CONFIG_DIR / "cell.yaml").read_text())
    raw["robot"]["urdf"] = str(CONFIG_DIR / raw["robot"]["urdf"])
    raw["plant"] = str(CONFIG_DIR / raw["plant"])
    raw["virtual_sensor"].update(model_dir=cfg.virtual_sensor.model_dir,
                                 calibration_dir=cfg.virtual_sensor.calibration_dir)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["-q", "run", "wipe", "--config", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["force_source"] == "virtual"
    wipe = cfg.virtual_sensor.for_tool("wipe")
    assert s["virtual_sensor"] == f"{wipe.observer}+{wipe.mapping}"
    assert s["outcome"] == "done" and not s["safety_stop"]
    # Virtual against measured over the wiping samples (small model: loose bounds; the figures of the
    # shipped artefacts are in the README).
    assert s["virtual_vs_sensor_samples"] > 500
    assert s["virtual_vs_sensor_fz_mae_n"] < 5.0 and s["force_tracking_mae_n"] < 6.0
    # The cell's peak force is the F/T sensor's (pressing at 60 N it is well above 60); the task's own is kept
    assert 60.0 < s["peak_force_n"] < 150.0 and "virtual_peak_force_n" in s
    log = read_log(tmp_path / s["run_dir"]) if not s["run_dir"].startswith("/") else read_log(s["run_dir"])
    assert {"fz", "sensor_fz", "sensor_mx"} <= set(log.column_names)


def test_error_split_separates_posture_offsets_from_noise():
    err = np.array([0.3, 0.1, 0.2, -0.1, 0.1, 0.0])  # posture 0: mean 0.2, posture 1: mean 0.0
    group = np.array([0, 0, 0, 1, 1, 1])
    split = error_split(err, group)
    assert split["posture_offset"] == pytest.approx(0.1)  # (3 * 0.2 + 3 * 0.0) / 6
    assert split["within_posture"] == pytest.approx((0.1 + 0.1 + 0 + 0.1 + 0.1 + 0) / 6, abs=1e-4)


def test_a_rest_shorter_than_the_rebias_window_is_refused_before_the_cell_opens(vs):
    cfg = vs["cfg"]
    short = dataclasses.replace(cfg.virtual_sensor.calibration, settle_s=cfg.virtual_sensor.rebias_window_s)
    cfg = dataclasses.replace(cfg, virtual_sensor=dataclasses.replace(cfg.virtual_sensor, calibration=short))

    def must_not_open():
        raise AssertionError("calibrate opened a cell with an impossible rest")

    with pytest.raises(ConfigError, match=r"virtual_sensor.calibration.settle_s \(0.2 s\) must exceed rebias_window_s"):
        calibrate(cfg, "wipe", vs["robot"], must_not_open, no_applier)


def test_a_config_whose_rest_is_shorter_than_the_rebias_window_is_refused_at_load(tmp_path):
    raw = yaml.safe_load((CONFIG_DIR / "cell.yaml").read_text())
    raw["virtual_sensor"]["calibration"]["settle_s"] = 0.1
    raw["plant"] = str(CONFIG_DIR / raw["plant"])
    raw["robot"]["urdf"] = str(CONFIG_DIR / raw["robot"]["urdf"])
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"virtual_sensor.calibration.settle_s \(0.1 s\) must exceed"):
        load_config(path)


def test_the_default_rest_outlasts_the_rebias_window_and_the_creep():
    cfg = load_config()
    assert cfg.virtual_sensor.calibration.settle_s >= 1.2  # the joints creep ~1 s after a move
    assert cfg.virtual_sensor.calibration.settle_s > cfg.virtual_sensor.rebias_window_s
