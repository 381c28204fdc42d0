"""Bad input and abuse, second part: the publisher's I/O off the loop, task speeds within the cell's limits,
checksummed recordings, outputs checked before the work, one-line errors for damaged files, and the CLI's
edge cases (interrupted --json, headless --view, YAML 1.2 numbers)."""

from __future__ import annotations

import ipaddress
import json
import socket
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import yaml

from cell.config import DEFAULT_CONFIG, load_config
from drivers.configio import read_yaml, to_plain
from drivers.errors import ConfigError, DataError
from main import main


def shipped() -> dict:
    return yaml.safe_load(DEFAULT_CONFIG.read_text())


def write(tmp_path: Path, data: dict, name: str = "cell.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 1, err
    return lines[0]


# ------------------------------------------------------------------------------------------- publish
def test_the_publisher_resolves_once_before_the_loop_and_never_blocks_in_it(monkeypatch):
    import cell.view.publish as publish

    resolved: list[tuple] = []
    real_getaddrinfo = socket.getaddrinfo

    def counting_getaddrinfo(*args, **kwargs):
        resolved.append(args)
        return real_getaddrinfo(*args, **kwargs)

    sends: list[tuple] = []

    class RecordingSocket(socket.socket):
        def sendto(self, data, address):  # type: ignore[override]
            # what the loop hands the kernel: a numeric address (no lookup) on a non-blocking socket
            sends.append((address, self.gettimeout(), len(resolved)))
            return super().sendto(data, address)

    monkeypatch.setattr(socket, "getaddrinfo", counting_getaddrinfo)
    monkeypatch.setattr(publish.socket, "socket", RecordingSocket)
    pub = publish.WrenchPublisher(("localhost", 9), joints=1)
    assert len(resolved) == 1
    for k in range(20):  # the loop's per-step path
        pub.row({"t": k * 0.008, "cycle": k, "q1": 0.0, "fx": 0, "fy": 0, "fz": 0, "mx": 0, "my": 0, "mz": 0})
    pub.event("outcome: done")
    pub.close()
    assert len(sends) == 21 and len(resolved) == 1
    for address, timeout, lookups in sends:
        ipaddress.ip_address(address[0])  # raises on a host name: sendto would resolve it again
        assert timeout == 0.0 and lookups == 1


def test_an_unresolvable_publish_host_is_refused_before_the_cell_opens(monkeypatch, capsys):
    import app.commands_cell

    def unresolvable(*args, **kwargs):
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    def no_cell(*args, **kwargs):
        raise AssertionError("the cell was opened")

    monkeypatch.setattr(socket, "getaddrinfo", unresolvable)
    monkeypatch.setattr(app.commands_cell, "open_cell", no_cell)
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--no-record", "--publish", "nohost.invalid:5005"])
    assert code == 2 and "cannot resolve 'nohost.invalid'" in one_error_line(capsys)


# ------------------------------------------------------------------------------------------- task speeds
@pytest.mark.parametrize("task, key, value, words", [
    ("wipe", "speed_mps", 50.0, "tasks.wipe.speed_mps (50 m/s) must not exceed"),
    ("wipe", "speed_mps", 0.8, "tasks.wipe.speed_mps (0.8 m/s) must not exceed safety.max_tcp_speed (0.5 m/s)"),
    ("wipe", "accel_mps2", 15.0, "tasks.wipe.accel_mps2 must lie in (0, 2] m/s^2"),
    ("wipe", "retract_height_m", 5.0, "tasks.wipe.retract_height_m must lie in [0, 0.5] m"),
    ("peg", "free_insert_speed_mps", 0.9, "tasks.peg.free_insert_speed_mps (0.9 m/s) must not exceed"),
    ("peg", "survey_move_speed_mps", 0.7, "tasks.peg.survey_move_speed_mps (0.7 m/s) must not exceed"),
    ("peg", "target_depth_m", 27.0, "tasks.peg.target_depth_m must lie in [0, 0.5] m"),
])
def test_task_speeds_are_bounded_by_the_cells_tcp_speed(tmp_path, capsys, task, key, value, words):
    data = shipped()
    data["tasks"][task][key] = value
    name = {"wipe": "wipe", "peg": "peg-in-hole"}[task]
    code = main(["-q", "run", name, "--force-source", "sensor", "--no-record", "--config", str(write(tmp_path, data))])
    assert code == 2 and words in one_error_line(capsys)


def test_a_cell_speed_limit_below_a_shipped_task_speed_is_named(tmp_path, capsys):
    data = shipped()
    data["safety"]["max_tcp_speed"] = 0.05  # the wipe's path runs at 0.06 m/s
    config = str(write(tmp_path, data))
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--no-record", "--config", config])
    assert code == 2 and "speed_mps (0.06 m/s) must not exceed safety.max_tcp_speed (0.05 m/s)" in \
        one_error_line(capsys)


# ------------------------------------------------------------------------------------------- recordings
def recorded_run(tmp_path: Path, rows: int = 30, tau3: float | None = None) -> Path:
    """A run folder as `main.py run` writes it (config, summary, chunked log with its manifest)."""
    from cell.data.recorder import Recorder, new_run_dir

    run = new_run_dir(tmp_path / "runs", "wipe")
    rec = Recorder(run, chunk_rows=10)
    rec.write_config(to_plain(load_config()))
    for k in range(rows):
        row = {"t": k * 0.008, "cycle": k, "state": "wipe", "state_read": "wipe", "force_rebias": False}
        for name, value in (("q", 0.5), ("dq", 0.01), ("tau", 2.0)):
            row.update({f"{name}{i + 1}": value for i in range(6)})
        if tau3 is not None and k == 15:
            row["tau3"] = tau3
        for prefix in ("", "sensor_"):
            row.update({f"{prefix}{a}": 1.0 for a in ("fx", "fy", "fz", "mx", "my", "mz")})
        rec.append(row)
    rec.close()
    rec.write_summary({"task": "wipe", "cell": "sim", "force_source": "virtual", "outcome": "done"})
    return run


def test_each_closed_part_is_listed_with_its_checksum(tmp_path):
    from cell.data.recorder import MANIFEST, read_log, verify_log

    run = recorded_run(tmp_path, rows=25)
    doc = json.loads((run / "log" / MANIFEST).read_text())
    assert sorted(doc["parts"]) == ["part-00000.parquet", "part-00001.parquet", "part-00002.parquet"]
    assert [p["rows"] for p in doc["parts"].values()] == [10, 10, 5]
    assert verify_log(run) and read_log(run).num_rows == 25  # the manifest stays out of the table


def flip_bits(path: Path, offsets: list[int]) -> None:
    raw = bytearray(path.read_bytes())
    for pos in offsets:
        raw[pos % len(raw)] ^= 0x10
    path.write_bytes(bytes(raw))


def test_a_bit_flipped_part_is_refused_by_replay_in_one_line(tmp_path, capsys):
    run = recorded_run(tmp_path)
    part = run / "log" / "part-00001.parquet"
    flip_bits(part, [200, 201, 333])
    code = main(["-q", "replay", str(run)])
    line = one_error_line(capsys)
    assert code == 2 and str(part) in line and "checksum mismatch" in line


def test_a_part_added_after_the_run_is_refused(tmp_path):
    from cell.data.recorder import verify_log

    run = recorded_run(tmp_path)
    (run / "log" / "part-00009.parquet").write_bytes((run / "log" / "part-00000.parquet").read_bytes())
    with pytest.raises(DataError, match="part-00009.parquet: a step-log part the manifest does not list"):
        verify_log(run)


def test_physically_impossible_values_are_refused_by_replay(tmp_path, capsys):
    run = recorded_run(tmp_path, tau3=-8.3e10)  # checksummed as written: only the range check can tell
    code = main(["-q", "replay", str(run)])
    line = one_error_line(capsys)
    assert code == 2 and "column tau3 row 15" in line and "physically impossible" in line


def test_a_typod_bench_folder_never_overwrites_the_figures_page(tmp_path, capsys):
    page = tmp_path / "figures.md"
    page.write_text("the good page\n")
    assert main(["-q", "figures", "--bench-dir", str(tmp_path / "artifacts/bnech"), "--out", str(page)]) == 2
    assert "no such folder" in one_error_line(capsys)
    (tmp_path / "empty").mkdir()
    assert main(["-q", "figures", "--bench-dir", str(tmp_path / "empty"), "--out", str(page)]) == 2
    assert "left as it was" in one_error_line(capsys)
    assert page.read_text() == "the good page\n"


# ------------------------------------------------------------------------------------------- outputs
@pytest.mark.parametrize("argv", [
    ["train", "--data", "missing/dataset.yaml", "--model", "P1"],
    ["collect", "--samples", "100"],
])
def test_an_occupied_out_is_refused_before_the_work(tmp_path, capsys, monkeypatch, argv):
    import app.commands_lab

    monkeypatch.setattr(app.commands_lab, "open_cell", lambda *a, **k: pytest.fail("the cell was opened"))
    blocker = tmp_path / "occupied"
    blocker.write_text("a file where the output folder goes")
    for out in (blocker, blocker / "sub"):
        assert main(["-q", *argv, "--out", str(out)]) == 2
        line = one_error_line(capsys)
        assert line.startswith(f"error: --out {out}: not a folder")


def test_a_folder_as_the_figures_page_is_refused(tmp_path, capsys):
    (tmp_path / "bench").mkdir()
    assert main(["-q", "figures", "--bench-dir", str(tmp_path / "bench"), "--out", str(tmp_path)]) == 2
    assert "a folder, not a file" in one_error_line(capsys)


def test_a_database_storage_without_its_driver_is_one_line(tmp_path, capsys):
    code = main(["-q", "tune", "--data", str(tmp_path / "d.yaml"), "--out", str(tmp_path / "o"),
                 "--storage", "mysql://x"])
    assert code == 2 and "--storage mysql://x" in one_error_line(capsys)


# ------------------------------------------------------------------------------------------- model files
@pytest.fixture(scope="module")
def saved_model(tmp_path_factory) -> Path:
    return make_model(tmp_path_factory.mktemp("model") / "m")


def make_model(out: Path) -> Path:
    """A small H1 artefact (three trees a joint) saved at `out`."""
    from cell.model.dynamics.artefact import save_model
    from cell.model.dynamics.features import FeatureSpec
    from cell.model.dynamics.learned import XGBParams, fit_learned
    from cell.model.dynamics.rigid_body import nominal_p2
    from cell.model.specs import cell_robot
    from tests.test_dynamics_learned import motion

    robot = cell_robot(load_config())
    s = motion(600, 0)
    s.tau = nominal_p2(robot).predict(s.q, s.dq, s.ddq)
    model = fit_learned("H1", robot, s, FeatureSpec(window=1, grouping="own"), XGBParams(n_estimators=3),
                        p2=nominal_p2(robot))
    save_model(model, out)
    return out


def truncated_copy(model: Path, name: str, dest: Path) -> Path:
    import shutil

    shutil.copytree(model, dest)
    raw = (dest / name).read_bytes()
    (dest / name).write_bytes(raw[: len(raw) // 2])
    return dest


@pytest.mark.parametrize("name", ["booster_j3.ubj", "model.json"])
def test_a_truncated_model_file_is_one_line_naming_it(tmp_path, saved_model, robot, name):
    from cell.model.dynamics.artefact import load_model

    model = truncated_copy(saved_model, name, tmp_path / "m")
    with pytest.raises(DataError) as exc:
        load_model(model, robot)
    assert str(model / name) in str(exc.value) and "\n" not in str(exc.value)


def test_a_model_file_missing_its_entries_is_one_line(tmp_path, saved_model, robot):
    import shutil

    from cell.model.dynamics.artefact import load_model

    shutil.copytree(saved_model, tmp_path / "m")
    doc = json.loads((tmp_path / "m" / "model.json").read_text())
    del doc["features"]
    (tmp_path / "m" / "model.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match="model.json: damaged model file"):
        load_model(tmp_path / "m", robot)


@pytest.mark.parametrize("argv", [["plan", "--cell", "sim", "--model"], ["calibrate", "--cell", "sim", "--model"]])
def test_commands_refuse_a_truncated_model_in_one_line(tmp_path, saved_model, capsys, argv):
    model = truncated_copy(saved_model, "booster_j2.ubj", tmp_path / "m")
    assert main(["-q", *argv, str(model)]) == 2
    assert "booster_j2.ubj: not a readable XGBoost booster" in one_error_line(capsys)


# ------------------------------------------------------------------------------------------- YAML
def test_a_deeply_nested_yaml_file_is_one_line(tmp_path):
    path = tmp_path / "deep.yaml"
    path.write_text("robot: " + "[" * 400 + "]" * 400 + "\n")
    with pytest.raises(ConfigError, match="nested deeper than 32 levels") as exc:
        read_yaml(path)
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)


def test_yaml_reads_exponent_numbers_as_yaml_1_2(tmp_path):
    path = tmp_path / "n.yaml"
    path.write_text("a: 1.0e6\nb: 1e-3\nc: 2E+5\nd: 12\ne: 1_000\nf: 0x10\ng: 1e\nh: v1.0e6\n")
    assert read_yaml(path) == {"a": 1e6, "b": 1e-3, "c": 2e5, "d": 12, "e": 1000, "f": 16, "g": "1e", "h": "v1.0e6"}
    data = shipped()
    text = yaml.safe_dump(data, sort_keys=False).replace("max_tool_force_n: 150.0", "max_tool_force_n: 1.5e2")
    assert "1.5e2" in text
    (tmp_path / "cell.yaml").write_text(text)
    assert load_config(tmp_path / "cell.yaml").safety.max_tool_force_n == 150.0


# ------------------------------------------------------------------------------------------- CLI edges
def test_an_interrupt_that_ends_the_command_still_prints_the_json_line(monkeypatch, capsys):
    import app.commands_cell

    def interrupted(*args, **kwargs):  # a repeated Ctrl+C escaping the run before its summary
        raise KeyboardInterrupt

    monkeypatch.setattr(app.commands_cell, "open_cell", interrupted)
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--no-record", "--json"])
    out = capsys.readouterr().out.strip().splitlines()
    assert code == 130 and json.loads(out[-1])["outcome"] == "interrupted"


def test_view_on_a_headless_machine_spawns_nothing_and_says_so(monkeypatch, caplog, robot):
    import sys

    import cell.view.rerun_view
    from app.view import live_view

    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(cell.view.rerun_view, "open_viewer", lambda *a: pytest.fail("a viewer was spawned"))
    with caplog.at_level("WARNING"):
        assert live_view(robot, "run-wipe", serve=False, virtual_in_loop=True) is None
    assert [r.getMessage() for r in caplog.records if "no display" in r.getMessage()]


def test_ranges_accept_a_normal_recording(tmp_path, robot):
    from tasks.setup.replay import check_ranges, joint_columns, read_run

    run = recorded_run(tmp_path)
    _, table = read_run(run)
    check_ranges(run, table, joint_columns(table, 6), robot)
    assert np.isfinite(joint_columns(table, 6)["tau"]).all() and isinstance(table, pa.Table)
