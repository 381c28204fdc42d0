"""Bad input and abuse: strict YAML, physical bounds on the safety limits, complete
cell configs, one validation of CLI arguments, and SIGTERM handled as Ctrl+C."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
import yaml

from cell.config import DEFAULT_CONFIG, load_config
from cell.control.signals import Terminated, interrupts_deferred, raise_if_interrupted, sigterm_as_interrupt
from drivers.configio import read_yaml
from drivers.errors import ConfigError
from main import main


def shipped() -> dict:
    return yaml.safe_load(DEFAULT_CONFIG.read_text())


def write(tmp_path: Path, data: dict, name: str = "cell.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def config_error(path: Path) -> str:
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    message = str(exc.value)
    assert "\n" not in message and str(path) in message
    return message


# ------------------------------------------------------------------------------------------- YAML
def test_duplicate_keys_aliases_and_non_utf8_are_refused_with_their_line(tmp_path):
    dup = tmp_path / "dup.yaml"
    dup.write_text("safety:\n  max_tool_force_n: 150\n  max_tool_force_n: 1000\n")
    with pytest.raises(ConfigError, match=r"line 3 .*duplicate key 'max_tool_force_n'"):
        read_yaml(dup)
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
                    "c: [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n")
    with pytest.raises(ConfigError, match="aliases"):
        read_yaml(bomb)
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"robot:\n  note: caf\xe9\n")
    with pytest.raises(ConfigError, match=r"line 2 is not UTF-8"):
        read_yaml(latin)
    big = tmp_path / "big.yaml"
    big.write_text("a: " + "x" * (2 << 20) + "\n")
    with pytest.raises(ConfigError, match="too large"):
        read_yaml(big)


def test_every_shipped_yaml_file_reads_strictly():
    root = Path(__file__).resolve().parents[1] / "config"
    files = sorted(root.rglob("*.yaml"))
    assert len(files) >= 5
    for f in files:
        read_yaml(f)  # no duplicate keys, no aliases, UTF-8


# ------------------------------------------------------------------------------------------- config
def test_an_empty_or_incomplete_config_is_refused_not_run_on_defaults(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert "empty" in config_error(empty)
    data = shipped()
    del data["virtual_sensor"]
    assert "missing section 'virtual_sensor'" in config_error(write(tmp_path, data))


@pytest.mark.parametrize("section, key", [
    (("collision", "detector"), "observer_gain"),
    (("virtual_sensor",), "momentum_gain"),
    (("virtual_sensor", "by_tool", "peg"), "touch_gain"),
])
def test_an_observer_gain_that_alternates_at_the_loops_period_is_refused(tmp_path, section, key):
    data = shipped()
    data["loop"]["period_s"] = 0.0156
    data["plant"] = str(Path(__file__).resolve().parents[1] / "config" / "plants" / "tm-ethernet.yaml")
    data["collision"]["detector"]["observer_gain"] = 50.0  # the others fit this period
    data["virtual_sensor"]["by_tool"]["peg"]["touch_gain"] = 50.0
    node = data
    for name in section:
        node = node[name]
    node[key] = 70.0  # 1.09 per period at 15.6 ms (fine at 8 ms: 0.56)
    message = config_error(write(tmp_path, data))
    assert f"{'.'.join(section)}.{key}" in message and "under 64.1 1/s" in message
    data["loop"]["period_s"] = 0.008
    data["collision"]["detector"]["observer_gain"] = 70.0
    data["virtual_sensor"]["by_tool"]["peg"]["touch_gain"] = 70.0
    load_config(write(tmp_path, data))


def test_a_typo_in_a_task_section_is_named(tmp_path):
    data = shipped()
    data["tasks"]["wpie"] = data["tasks"].pop("wipe")
    assert "unknown task 'wpie'" in config_error(write(tmp_path, data))


@pytest.mark.parametrize("key, value, words", [
    ("max_tool_force_n", 1e6, "(0, 200] N"),
    ("max_tool_force_n", 0.0, "(0, 200] N"),
    ("max_tool_torque_nm", 50.0, "(0, 10] N·m"),
    ("max_tcp_speed", 5.0, "(0, 1] m/s"),
    ("max_sensor_invalid_cycles", -1, "1..10"),
    ("max_sensor_invalid_cycles", 1_000_000_000, "1..10"),
    ("workspace_max", [0.8, 0.8, 50.0], "beyond the arm's reach"),
    ("workspace_min", [-9.0, -0.8, 0.0], "beyond the arm's reach"),
])
def test_safety_limits_have_physical_upper_bounds(tmp_path, key, value, words):
    data = shipped()
    data["safety"][key] = value
    message = config_error(write(tmp_path, data))
    assert f"safety.{key}" in message and words in message


def test_the_shipped_limits_are_within_the_bounds():
    cfg = load_config()
    assert 0 < cfg.safety.max_tool_force_n <= 200 and cfg.safety.max_tcp_speed <= 1.0


def test_a_task_force_limit_above_the_cells_is_refused(tmp_path, capsys):
    data = shipped()
    data["tasks"]["wipe"]["max_force_n"] = 180.0
    data["tasks"]["wipe"]["force_setpoint_n"] = 170.0
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--config", str(write(tmp_path, data))])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "tasks.wipe.max_force_n (180 N) must not exceed safety.max_tool_force_n (150 N)" in err[0]


def test_a_home_outside_the_joint_limits_is_refused(tmp_path, capsys):
    data = shipped()
    data["robot"]["home"][2] = 4.0
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--config", str(write(tmp_path, data))])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "robot.home[2] (4 rad) must lie within joint 3's limits" in err[0]


# ------------------------------------------------------------------------------------------- CLI args
@pytest.mark.parametrize("argv, words", [
    (["run", "wipe", "--seed", "-1"], "--seed: -1 must be in 0.."),
    (["bench", "peg-in-hole", "--max-offset-mm", "nan"], "--max-offset-mm: 'nan' must be a finite number"),
    (["bench", "peg-in-hole", "--max-tilt-deg", "inf"], "--max-tilt-deg: 'inf' must be a finite number"),
    (["bench", "peg-in-hole", "--peg-diameter-mm", "-5"], "--peg-diameter-mm: -5 must lie in"),
    (["bench", "drivers", "--n", "0"], "--n: 0 must be >= 1"),
    (["evaluate", "--data", "d.yaml", "--out", "o", "--curve", "a,b"], "--curve: 'a' is not an integer"),
    (["collect", "--out", "o", "--samples", "-1"], "--samples: -1 must be >= 1"),
    (["train", "--data", "d.yaml", "--out", "o", "--model", "H1", "--samples", "-5"], "--samples: -5 must be >= 100"),
    (["evaluate", "--data", "d.yaml", "--out", "o", "--train-samples", "0"], "--train-samples: 0 must be >= 100"),
    (["collect", "--out", "o", "--fourier-share", "1.5"], "--fourier-share: 1.5 must lie in (0, 1)"),
])
def test_bad_arguments_are_one_line_errors_with_exit_2(argv, words, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert words in err[-1] and "Traceback" not in "\n".join(err)


# ------------------------------------------------------------------------------------------- signals
def test_sigterm_is_raised_as_an_interrupt_inside_the_block_only():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), sigterm_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
    assert signal.getsignal(signal.SIGTERM) == before


def test_interrupts_wait_for_the_end_of_a_deferred_block():
    done = []
    with pytest.raises(Terminated), sigterm_as_interrupt(), interrupts_deferred():
        os.kill(os.getpid(), signal.SIGTERM)
        done.append("the summary was written")
    assert done == ["the summary was written"]


def test_an_interrupted_run_ends_the_whole_command():
    raise_if_interrupted("done")
    raise_if_interrupted("safety_stop")
    with pytest.raises(KeyboardInterrupt):
        raise_if_interrupted("interrupted")


@pytest.mark.slow
def test_sigterm_during_a_run_stops_the_arm_writes_the_summary_and_exits_143(capsys, monkeypatch):
    from tasks.wipe import WipeTask

    real_step = WipeTask.step
    calls = {"n": 0}

    def step(self, obs):
        calls["n"] += 1
        if calls["n"] == 300:  # mid-approach: the arm is moving
            os.kill(os.getpid(), signal.SIGTERM)
        return real_step(self, obs)

    monkeypatch.setattr(WipeTask, "step", step)
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--json"])
    assert code == 143
    runs = sorted(Path("runs").iterdir())
    summary = json.loads((runs[-1] / "summary.json").read_text())
    assert summary["outcome"] == "interrupted" and summary["reason"] == "terminated (SIGTERM)"
    assert 299 <= summary["cycles"] <= 302  # the 300th step (cycle 299) or within a couple of periods after
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL or callable(signal.getsignal(signal.SIGTERM))


# ------------------------------------------------------------------------------------------- devices
class _CountingArm:
    """A driver double on the real lifecycle (drivers.interfaces.Arm) that counts stops and writes;
    `q` and `status` are what its controller reports."""

    @staticmethod
    def make():
        import numpy as np

        from drivers.interfaces import Arm, ArmState, ArmStatus, JointLimits

        class Counting(Arm):
            def __init__(self) -> None:
                lim = JointLimits(lower=-np.ones(6), upper=np.ones(6), velocity=np.ones(6), effort=np.ones(6) * 10)
                super().__init__(lim, 0.008)
                self.stops = 0
                self.writes = 0
                self.q = np.zeros(6)
                self.status = ArmStatus()

            def _connect(self) -> None: ...
            def _disconnect(self) -> None: ...
            def _read_state(self) -> ArmState:
                return ArmState(t=0.0, q=self.q.copy(), dq=np.zeros(6), tau=np.zeros(6), status=self.status)
            def _write_target(self, q) -> None:
                self.writes += 1
            def _stop(self) -> None:
                self.stops += 1

        return Counting()


def test_a_session_that_never_armed_does_not_command_a_stop_on_disconnect():
    arm = _CountingArm.make()
    with arm:
        arm.read_state()
    assert arm.stops == 0  # `main.py status`: read-only, no hold latched on the robot side
    with arm:
        arm.arm()
    assert arm.stops == 1  # a session that could have moved the arm stops it on the way out
    with arm:
        arm.read_state()
    assert arm.stops == 1  # a new connection starts read-only again


def test_runs_starting_in_the_same_second_each_get_their_own_folder(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from cell.data.recorder import new_run_dir

    with ThreadPoolExecutor(8) as pool:
        dirs = list(pool.map(lambda _: new_run_dir(tmp_path / "runs", "wipe"), range(60)))
    assert len(set(dirs)) == 60 and all(d.is_dir() for d in dirs)


@pytest.mark.slow  # the cell opens before the run folder is made
def test_an_unwritable_recording_folder_is_a_one_line_error(tmp_path, capsys):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the runs folder should be")
    data = shipped()
    data["recording"] = {"directory": str(blocker / "runs")}
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--config", str(write(tmp_path, data))])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "cannot create a run folder" in err[0]


def test_a_recording_that_cannot_be_written_is_a_recording_error(tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    from cell.data.recorder import Recorder
    from drivers.errors import RecordingError

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    rec = Recorder(tmp_path / "run", chunk_rows=2)
    monkeypatch.setattr(pq, "write_table", full_disk)
    rec.append({"t": 0.0})
    rec.append({"t": 0.1})  # a whole part: handed to the writer, which fails
    with pytest.raises(RecordingError, match="No space left on device"):
        rec.flush()
    # The recording stays failed: the control loop's next row raises it too, and so does closing.
    with pytest.raises(RecordingError, match="No space left on device"):
        rec.append({"t": 0.2})
    with pytest.raises(RecordingError, match="No space left on device"):
        rec.close()
    assert rec.closed and not list((tmp_path / "run" / "log").glob("*.parquet"))


def test_a_column_of_mixed_kinds_fails_the_recording_not_the_writer(tmp_path):
    from cell.data.recorder import Recorder
    from drivers.errors import RecordingError

    rec = Recorder(tmp_path / "run", chunk_rows=2)
    rec.append({"t": 0.0, "state": "wipe"})
    rec.append({"t": 0.1, "state": 3.5})
    with pytest.raises(RecordingError, match="part-00000.parquet: cannot write the step log"):
        rec.close()
    assert rec.closed


def test_a_word_in_a_column_of_numbers_fails_the_recording_at_once(tmp_path):
    from cell.data.recorder import Recorder, read_log
    from drivers.errors import RecordingError

    rec = Recorder(tmp_path / "run", chunk_rows=2)
    rec.append({"t": 0.0, "fz": 1.5, "state": "wipe"})
    rec.append({"t": 0.1, "state": "wipe"})  # a missing number: NaN
    rec.append({"t": 0.2, "fz": 2, "state": "done"})  # an int among floats: a float
    with pytest.raises(RecordingError, match=r"part-00001\.parquet: cannot write the step log: column 'fz' holds a "
                                             r"str among numbers"):
        rec.append({"t": 0.3, "fz": "high", "state": "done"})
    with pytest.raises(RecordingError, match="column 'fz'"):
        rec.close()
    log = read_log(tmp_path / "run").to_pydict()  # the part before the failure stays readable (NaN != NaN)
    assert log["t"] == [0.0, 0.1] and log["state"] == ["wipe"] * 2
    assert log["fz"][0] == 1.5 and log["fz"][1] != log["fz"][1]


def test_no_part_after_one_that_failed_is_written(tmp_path, monkeypatch):
    """A log with a hole in it would read as a jump in time: after a failed part, later ones are refused."""
    import pyarrow.parquet as pq

    from cell.data.recorder import Recorder
    from drivers.errors import RecordingError

    written = pq.write_table
    calls = []

    def fails_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise OSError(5, "Input/output error")
        return written(*args, **kwargs)

    monkeypatch.setattr(pq, "write_table", fails_once)
    rec = Recorder(tmp_path / "run", chunk_rows=2)
    for i in range(8):
        try:
            rec.append({"t": float(i)})
        except RecordingError:
            break
    with pytest.raises(RecordingError, match="Input/output error"):
        rec.close()
    assert len(calls) == 2
    assert sorted(p.name for p in (tmp_path / "run" / "log").glob("*.parquet")) == ["part-00000.parquet"]


@pytest.mark.parametrize("reading", [1.2, 3e38, -1.06])
def test_a_position_reported_outside_the_joint_range_faults_and_refuses_arming(reading):
    import numpy as np

    from drivers.errors import DriverError, LifecycleError
    from drivers.interfaces import Lifecycle

    arm = _CountingArm.make()
    with arm:
        arm.arm()
        arm.q[2] = reading
        with pytest.raises(DriverError, match="joint 3 reported at .* outside its limits"):
            arm.read_state()
        assert arm.lifecycle is Lifecycle.FAULT and arm.stops >= 1
        with pytest.raises(LifecycleError):
            arm.send_target(np.zeros(6))
        with pytest.raises(DriverError):
            arm.arm()  # re-arming reads the state again: still refused
        assert arm.writes == 0
        arm.q[2] = 1.04  # within the overshoot tolerance of the 1 rad limit
        arm.arm()
        assert arm.lifecycle is Lifecycle.ARMED


@pytest.mark.parametrize("flag", ["error", "estop", "protective_stop"])
def test_the_driver_refuses_targets_itself_once_the_controller_reports_a_stop(flag):
    import dataclasses

    import numpy as np

    from drivers.errors import LifecycleError
    from drivers.interfaces import Lifecycle

    arm = _CountingArm.make()
    with arm:
        arm.arm()
        arm.send_target(np.zeros(6))
        assert arm.writes == 1
        arm.status = dataclasses.replace(arm.status, **{flag: True})
        arm.read_state()  # the state itself is valid data: returned, but the arm is faulted
        assert arm.lifecycle is Lifecycle.FAULT and arm.fault_reason == f"controller reports {flag}"
        with pytest.raises(LifecycleError):
            arm.send_target(np.zeros(6))
        assert arm.writes == 1


# ------------------------------------------------------------------------------------------- emulator
class _Recorder:
    """Stands in for the TM5 emulator: records the fault calls it gets."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def __getattr__(self, name):
        return lambda *args: self.calls.append((name, *args))


@pytest.mark.parametrize("line, call", [
    ("drop_link 1.5", ("drop_link", 1.5)),
    ("delay 20", ("delay_replies", 20.0, None)),
    ("delay 20 1.0", ("delay_replies", 20.0, 1.0)),
    ("freeze", ("freeze", None)),
    ("clear", ("clear_faults",)),
])
def test_emulator_fault_commands_do_what_they_say(line, call):
    from sim.serve_cell import _apply
    from sim.wacoh_emulator import FaultConfig

    arm = _Recorder()
    _apply(line.split(), arm, FaultConfig())
    assert arm.calls == [call]


@pytest.mark.parametrize("line, words", [
    ("delay 20 -1.0", "must be a finite number >= 0"),
    ("delay 20 1.0 3", "takes 1 to 2 argument(s), got 3"),
    ("drop_link abc", "'abc' is not a number"),
    ("drop_link", "takes 1 argument(s), got 0"),
    ("freeze nan", "must be a finite number"),
    ("sensor garbage 1.5", "<= 1"),
    ("sensor garbage", "takes 1 argument(s)"),
    ("sensor melt 0.1", "sensor fault must be one of"),
    ("explode 1", "unknown command 'explode'"),
])
def test_malformed_emulator_fault_commands_are_refused_not_reinterpreted(line, words):
    from sim.serve_cell import _apply
    from sim.wacoh_emulator import FaultConfig

    arm, faults = _Recorder(), FaultConfig()
    with pytest.raises(ValueError, match=".*") as exc:
        _apply(line.split(), arm, faults)
    assert words in str(exc.value)
    assert arm.calls == [] and faults.garbage_prob == 0.0


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_bench_faults_detects_every_fault_in_its_budget(capsys):
    code = main(["-q", "bench", "faults", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(out["faults"]) == {"link_loss", "stale_robot_data", "late_replies", "modbus_exceptions",
                                  "sensor_silent", "sensor_garbage", "sensor_late_replies", "second_host"}
    # late sensor replies were seen and discarded as stale, never taken as new readings
    assert out["faults"]["sensor_late_replies"]["stale_records_discarded"] >= 1
    for name, row in out["faults"].items():
        assert row["detected"] and row["within_budget"] and row["arm_stopped"] and row["recording_ok"], (name, row)
    assert out["link_loss_detection_periods"] <= 2
    assert out["failures"] == 0 and code == 0


def test_the_sensor_delay_command_sets_the_emulators_reply_delay():
    from sim.serve_cell import _apply
    from sim.wacoh_emulator import FaultConfig

    faults = FaultConfig()
    _apply(["sensor", "delay", "12", "0.4"], _Recorder(), faults)
    assert faults.reply_delay_s == pytest.approx(0.012) and faults.reply_delay_prob == pytest.approx(0.4)
    _apply(["sensor", "clear"], _Recorder(), faults)
    assert faults.reply_delay_s == 0.0
    with pytest.raises(ValueError, match="<= 1"):
        _apply(["sensor", "delay", "12", "4"], _Recorder(), faults)
