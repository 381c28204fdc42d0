"""What an operator reads is true: virtual-vs-F/T scores only after the tare in the task's working states, the
touch figure, the regulated force's own name, limits and contact state on the plot, the .rrd's blueprint and
series, the figures page keeping what it measured, and servers on 127.0.0.1 unless told otherwise."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from bench.figures import Committed, Figure, meets, read_page, render, verdict
from bench.figures_table import FIGURES
from main import build_parser, main
from tasks.peg.states import PegState
from tasks.peg.task import PegInHoleTask
from tasks.runner import TOUCH_RATIO_BAND, touch_figures, virtual_vs_sensor
from tasks.setup.play import PlayTask
from tasks.wipe import WipeState, WipeTask

ROOT = Path(__file__).resolve().parents[1]


def wrenches(fz: list[float]) -> np.ndarray:
    w = np.zeros((len(fz), 6))
    w[:, 2] = fz
    return w


# ------------------------------------------------------------------------------------------------ scores
def test_virtual_vs_sensor_scores_only_the_working_states_after_the_tare():
    # Before the tare the F/T sensor carries its 5 N offset: a big "error" that must not be scored.
    states = ["move_to_start", "tare", "approach", "insert", "insert", "retract"]
    meas = wrenches([5.0, 5.0, 0.0, 10.0, 12.0, 0.0])
    est = wrenches([0.0, 0.0, 1.0, 11.0, 11.0, 3.0])
    tared = [False, False, True, True, True, True]
    out = virtual_vs_sensor(states, meas, est, ("approach", "insert"), {}, tared)
    assert out["virtual_vs_sensor_samples"] == 3
    assert out["virtual_vs_sensor_fz_mae_n"] == pytest.approx(1.0)
    # A working state before the tare is still no sample.
    out = virtual_vs_sensor(["insert", "insert"], wrenches([5.0, 1.0]), wrenches([0.0, 1.5]), ("insert",), {},
                            [False, True])
    assert out["virtual_vs_sensor_samples"] == 1 and out["virtual_vs_sensor_fz_mae_n"] == pytest.approx(0.5)


def test_the_tracking_error_and_the_estimate_error_have_their_own_names():
    states = ["wipe"] * 4
    meas, est = wrenches([59.0, 61.0, 58.0, 62.0]), wrenches([60.0, 60.0, 60.0, 60.0])
    task = {"force_setpoint_n": 60.0, "force_tracking_mae_n": 0.0}
    out = virtual_vs_sensor(states, meas, est, ("wipe",), task)
    assert out["force_tracking_mae_n"] == pytest.approx(1.5)  # the F/T sensor against the setpoint
    assert out["force_tracking_virtual_mae_n"] == 0.0  # what the task saw through the virtual sensor
    assert out["virtual_vs_sensor_fz_mae_n"] == pytest.approx(1.5)
    assert not [k for k in out if k.startswith("mae_") or k == "force_mae_n"]


def test_every_task_declares_its_working_and_touch_states():
    for task, states in ((WipeTask, WipeState), (PegInHoleTask, PegState)):
        values = {s.value for s in states}
        assert task.working_states and set(task.working_states) <= values - {"move_to_start", "tare"}, task
        assert set(task.touch_states) <= values, task
    assert "survey" in PegInHoleTask.touch_states and "move_to_start" not in PegInHoleTask.working_states
    assert PlayTask.working_states == ()  # free motion only: nothing to compare


def test_the_touch_figure_compares_the_peaks_and_warns_outside_its_band():
    states = ["survey"] * 20
    meas = wrenches([0.0] * 5 + [30.0, 20.0] + [0.0] * 13)
    seen = wrenches([0.0] * 6 + [24.0, 10.0] + [0.0] * 12)  # a period late, as the joint torques come
    out = touch_figures(np.array(states), meas, seen, ("survey",), np.ones(20, bool))
    assert out["touches"] == 1 and out["touch_peak_ratio"] == pytest.approx(0.8) and "warnings" not in out
    missed = wrenches([0.0] * 6 + [5.0] + [0.0] * 13)
    out = touch_figures(np.array(states), meas, missed, ("survey",), np.ones(20, bool))
    assert out["touch_peak_ratio"] < TOUCH_RATIO_BAND[0] and "saw 0.17 of the touches' peak" in out["warnings"][0]
    # Not a touch state, or before the tare: no touch.
    assert touch_figures(np.array(["slide"] * 20), meas, seen, ("survey",), np.ones(20, bool)) == {"touches": 0}
    assert touch_figures(np.array(states), meas, seen, ("survey",), np.zeros(20, bool)) == {"touches": 0}


def test_the_fast_touch_channel_adds_only_what_exceeds_its_band(robot):
    from cell.sensing.virtual_sensor import VirtualForceSource
    from drivers.interfaces import ArmState

    class Fixed:
        kind = "fixed"

        def __init__(self, tau: np.ndarray) -> None:
            self.tau = tau

        def update(self, state):
            return self.tau

        def rebias(self):
            pass

    class Identity:
        kind = "identity"

        def map(self, q, tau_ext):
            from types import SimpleNamespace

            return SimpleNamespace(wrench=np.asarray(tau_ext, float), ill_conditioned=False, sigma_min=1.0)

    slow, fast = np.array([0.0, 0.0, 2.0, 0, 0, 0]), np.array([0.0, 0.0, 12.0, 0, 0, 0.5])
    src = VirtualForceSource(Fixed(slow), Identity(), touch=Fixed(fast), touch_band_n=3.0)  # type: ignore[arg-type]
    state = ArmState(t=0.0, q=np.zeros(6), dq=np.zeros(6), tau=np.zeros(6))
    assert src.read(state).force[2] == pytest.approx(2.0)  # nobody said a touch is expected
    src.contact_expected = lambda: True
    w = src.read(state)
    assert w.force[2] == pytest.approx(12.0 - 3.0) and w.torque[2] == 0.0  # force only, beyond the band


def test_the_peg_tool_reads_touches_fast_and_the_wipe_tool_does_not(cfg):
    assert cfg.virtual_sensor.for_tool("peg").touch_gain > 0
    assert cfg.virtual_sensor.for_tool("wipe").touch_gain == 0


# ------------------------------------------------------------------------------------- plot and .rrd
def peg_log(robot):
    import pyarrow as pa

    n = 40
    rows = {"t": list(np.arange(n) * 0.008), "state": ["tare"] * 5 + ["survey"] * 15 + ["slide"] * 20,
            "contact": ["free"] * n, "contact_state": ["free"] * 20 + ["stuck_inside"] * 20,
            "depth": [0.001] * n, "fz_setpoint": [0.0] * n, "coll_ratio": [0.2] * n}
    rows["state_read"] = rows["state"]
    for i in range(robot.n):
        rows[f"q{i + 1}"] = [0.1 * i] * n
        rows[f"tau{i + 1}"] = [float(i)] * n
    for a in ("fx", "fy", "fz", "mx", "my", "mz"):
        rows[a] = [0.0] * n
        rows[f"sensor_{a}"] = [0.0] * n
    rows["sensor_fz"] = [5.0] * 5 + [0.0] * 5 + [33.0] + [0.0] * 29
    rows["fz"] = [0.0] * 11 + [20.0] + [0.0] * 28
    return pa.table(rows)


LIMITS = {"fz": [("task limit", 70.0), ("cell limit", 150.0)], "mx": [("task limit", 5.0), ("cell limit", 10.0)],
          "my": [("task limit", 5.0), ("cell limit", 10.0)]}


def test_the_peg_plot_draws_limits_marks_the_peak_and_the_classified_contact(tmp_path, robot, monkeypatch):
    import matplotlib.axes

    from cell.view.report import plot_peg_run

    texts: list[str] = []
    real = matplotlib.axes.Axes.annotate

    def spy(self, text, *args, **kwargs):
        texts.append(str(text))
        return real(self, text, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "annotate", spy)
    steps: list[list[float]] = []
    real_step = matplotlib.axes.Axes.step
    def spy_step(self, x, y, *args, **kwargs):
        steps.append(list(y))
        return real_step(self, x, y, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "step", spy_step)
    path = plot_peg_run(peg_log(robot), tmp_path / "plot.png", "test", LIMITS)
    assert path.exists() and path.stat().st_size > 10_000
    # The F/T peak after the tare (33 N, not the 5 N offset before it) and the virtual one, with their sizes.
    assert any("F/T Fz peak 33.0 N" in t for t in texts) and any("virtual Fz peak 20.0 N" in t for t in texts)
    assert steps and 2 in steps[-1]  # the contact panel shows the task's stuck_inside, not the free per-cycle one


def test_the_rrd_holds_torques_ratio_contact_depth_limits_and_a_blueprint(tmp_path, robot):
    from rerun.chunk import RrdReader

    from cell.view.rerun_view import write_rrd

    path = write_rrd(tmp_path, peg_log(robot), robot, {"force_source": "virtual", "outcome": "done"}, LIMITS)
    entities = {c.entity_path for c in RrdReader(path).stream().collect().stream()}
    assert {"/joints/torque/1", "/joints/torque/6", "/collision/ratio", "/contact/depth_mm", "/contact/state",
            "/wrench/virtual/fz", "/wrench/sensor/fz", "/wrench/limit/fz/task_limit",
            "/wrench/limit/my/cell_limit_neg"} <= entities
    # The blueprint travels with the recording: one chart per wrench axis, the arm, torques, states.
    reader = RrdReader(path)
    (store,) = reader.blueprints()
    names: set[str] = set()
    for chunk in reader.stream(store=store).collect().stream():
        batch = chunk.to_record_batch()
        for col in (n for n in batch.schema.names if n.endswith("display_name")):
            names.update(str(v[0]) for v in batch.column(col).to_pylist() if v)
    assert {"Fx", "Fz", "Mz", "arm", "joint torques (N·m)", "states and events"} <= names


# ------------------------------------------------------------------------------------------ figures page
def data_rows(page: str) -> dict[str, list[str]]:
    rows = {}
    for line in page.splitlines():
        if line.startswith("| ") and not line.startswith("| figure |"):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
            rows[cells[0]] = cells
    return rows


def test_regenerating_with_an_empty_bench_folder_keeps_every_committed_row(tmp_path):
    page = tmp_path / "figures.md"
    shutil.copy(ROOT / "docs" / "figures.md", page)
    before = read_page(page)
    assert len(before) > 40
    (tmp_path / "empty").mkdir()
    assert main(["-q", "figures", "--bench-dir", str(tmp_path / "empty"), "--out", str(page)]) == 0
    after = read_page(page)
    for name, row in before.items():
        if any(f.name == name for f in FIGURES):
            assert after.get(name) == row, name
    # Regenerating again changes nothing.
    text = page.read_text()
    assert main(["-q", "figures", "--bench-dir", str(tmp_path / "empty"), "--out", str(page)]) == 0
    assert page.read_text() == text


def test_new_summaries_replace_their_rows_and_misses_are_listed_first(tmp_path):
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "sim.json").write_text(json.dumps({"real_time_factor": 12.5}))
    (bench / "faults.json").write_text(json.dumps({"failures": 2}))
    figs = [Figure("sim rtf", "sim", "real_time_factor", ">= 10", "c"),
            Figure("faults", "faults", "failures", "0", "c"), Figure("kept", "nowhere", "x", "<= 1", "c"),
            Figure("info", "sim", "real_time_factor", "reported", "c")]
    from bench.figures import measure

    text = render(figs, measure(figs, bench), bench, {"kept": Committed("3 (seed 1), 0.5 (seed 2)", "`old.json`"),
                                                      "sim rtf": Committed("9", "`sim.json`")})
    rows = data_rows(text)
    assert rows["sim rtf"][1:3] == ["12.5", "pass"]
    assert rows["faults"][1:3] == ["2", "**MISS**"]
    assert rows["kept"][1:3] == ["3 (seed 1), 0.5 (seed 2)", "**MISS**"] and rows["kept"][5] == "`old.json`"
    assert rows["info"][2] == "-"
    head = text.split("| figure |")[0]
    assert "**2 figures miss their targets**" in head and "- faults: 2 (target 0)" in head
    assert "- kept: 3 (seed 1), 0.5 (seed 2) (target <= 1)" in head


@pytest.mark.parametrize(("value", "target", "ok"), [
    (14.0, "<= 15", True), (16.0, "<= 15", False), (0.98, ">= 0.95", True), (30.3, "<= 16 (two periods)", False),
    (115907.0, ">= 100,000", True), (2.39, "2-4", True), (10.4, "~10", True), (0.0, "0", True), ([], "none", True),
    ([1], "none", False), ("done", "done", True), ("failed", "done", False), (23.0, "all 23", True),
    (1.0, "reported", None), (1.0, "paper 24.7", None), (13.0, "<= stale_after_s / period + 3", None),
    (0.5, "< half of P2", None),
])
def test_targets_are_checked_as_the_table_writes_them(value, target, ok):
    assert meets(value, target) is ok


def test_every_committed_miss_is_marked():
    rows = data_rows((ROOT / "docs" / "figures.md").read_text())
    for f in FIGURES:
        row = rows.get(f.name)
        if row and len(row) == 6 and not row[1].startswith("not measured"):
            from bench.figures import parse_values

            assert row[2] == {"MISS": "**MISS**"}.get(verdict(parse_values(row[1]), f.target),
                                                      verdict(parse_values(row[1]), f.target)), f.name


# ------------------------------------------------------------------------------------------------ servers
@pytest.mark.parametrize("argv", [["run", "wipe"], ["replay", "runs/x"], ["bench", "peg-in-hole"],
                                  ["emulate", "arm"]])
def test_every_server_binds_the_loopback_unless_told(argv):
    parser = build_parser()
    assert parser.parse_args(argv).bind == "127.0.0.1"
    assert parser.parse_args([*argv, "--bind", "0.0.0.0"]).bind == "0.0.0.0"


def test_the_served_view_starts_the_viewer_on_the_bind_address(monkeypatch):
    from cell.view import rerun_view

    started: list[list[str]] = []

    class FakeProc:
        def __init__(self, cmd, **kwargs):
            started.append(cmd)

        def poll(self):
            return None

        def terminate(self):
            pass

        def wait(self, timeout=None):
            return 0

    monkeypatch.setattr(rerun_view.subprocess, "Popen", FakeProc)
    calls = iter([True])
    monkeypatch.setattr(rerun_view, "_listening", lambda host, port: next(calls, True))
    grpc, page = rerun_view.serve_viewer()
    cmd = started[-1]
    assert cmd[cmd.index("--bind") + 1] == "127.0.0.1" and "--serve-web" in cmd
    assert grpc.startswith("rerun+http://127.0.0.1:") and page.startswith("http://127.0.0.1:")
    rerun_view.serve_viewer("0.0.0.0")
    assert started[-1][started[-1].index("--bind") + 1] == "0.0.0.0"
    rerun_view.stop_servers()


def test_the_arm_emulator_listens_on_the_loopback_by_default(cfg):
    from sim.kinematic_plant import KinematicPlant
    from sim.serve_cell import arm_emulator

    emu = arm_emulator(cfg, KinematicPlant())
    assert emu.host == "127.0.0.1"
    assert arm_emulator(cfg, KinematicPlant(), bind="0.0.0.0").host == "0.0.0.0"
