"""Task files and force primitives: strict validation with the file's line, and the two shipped examples on
the simulated cell (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cell.config import load_config
from drivers.errors import ConfigError
from main import main
from tasks.primitives.taskfile import load_task_file

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "config" / "tasks"

GOOD = """\
name: t
tool: wipe
scene: table
poses:
  above: {xyz: [0.40, -0.20, 0.075]}
steps:
  - move: {to: above, space: joint}
  - guarded_move: {direction: [0, 0, -1], speed_mps: 0.005, force_n: 5.0, max_distance_m: 0.05}
  - force_mode:
      selection: [0, 0, 1, 0, 0, 0]
      wrench: [0, 0, -40, 0, 0, 0]
      end: {time_s: 1.0}
  - hold: {time_s: 1.0}
"""


def _load(tmp_path: Path, text: str):
    f = tmp_path / "t.yaml"
    f.write_text(text)
    cfg = load_config(None)
    return load_task_file(f, cfg.collision.guarded, cfg.safety.max_tool_force_n)


def test_a_good_file_loads_with_each_steps_line(tmp_path):
    tf = _load(tmp_path, GOOD)
    assert [s.kind for s in tf.steps] == ["move", "guarded_move", "force_mode", "hold"]
    assert [s.line for s in tf.steps] == [7, 8, 9, 13]


@pytest.mark.parametrize("edit, line, words", [
    (("  - hold: {time_s: 1.0}", "  - hlod: {time_s: 1.0}"), 13, "unknown primitive 'hlod'"),
    (("      end: {time_s: 1.0}\n", ""), 9, "end is required"),
    (("speed_mps: 0.005, force_n: 5.0, ", "force_n: 5.0, "), 8, "speed_mps is required"),
    (("wrench: [0, 0, -40, 0, 0, 0]", "wrench: [0, 0, -200, 0, 0, 0]"), 11, "200 N setpoint"),
    (("tool: wipe\n", "tool: wipe\nmax_force_n: 500\n"), 3, "safety.max_tool_force_n"),
    (("{to: above, space: joint}", "{to: abvoe, space: joint}"), 7, "unknown pose 'abvoe'"),
    (("speed_mps: 0.005,", "speed_mps: 0.03,"), 8, "faster than guarded motion allows"),
    (("      end: {time_s: 1.0}", "      end: {time_s: 1.0, bogus: 2}"), 12, "unknown key 'bogus'"),
])
def test_a_malformed_file_is_one_line_naming_its_line(tmp_path, edit, line, words):
    text = GOOD.replace(*edit)
    assert text != GOOD
    with pytest.raises(ConfigError) as exc:
        _load(tmp_path, text)
    msg = str(exc.value)
    assert "\n" not in msg and f"t.yaml: line {line}:" in msg and words in msg, msg


def test_the_cli_refuses_a_malformed_file_with_exit_2_and_no_traceback(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text(GOOD.replace("hold:", "hodl:"))
    proc = subprocess.run([sys.executable, str(ROOT / "main.py"), "run", "task", str(f)], capture_output=True,
                          text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"error: {f}: line 13:")


def test_the_shipped_examples_load():
    cfg = load_config(None)
    for name in ("edge-find.yaml", "press-slide.yaml"):
        load_task_file(EXAMPLES / name, cfg.collision.guarded, cfg.safety.max_tool_force_n)


def _run(name: str, capsys) -> dict:
    code = main(["-q", "run", "task", str(EXAMPLES / name), "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0, out.get("reason")
    return out


@pytest.mark.usefixtures("prepared_peg")  # the peg tool's artefacts, prepared once per run
def test_edge_find_reports_the_blocks_corner(capsys):
    out = _run("edge-find.yaml", capsys)
    assert out["truth_scores"]["corner"]["error_mm"] <= 0.3
    assert max(s["contact_force_max_n"] for s in out["step_scores"].values()) <= 30.0


@pytest.mark.usefixtures("prepared_wipe")  # the wipe tool's artefacts, prepared once per run
def test_press_slide_holds_and_slides_at_its_forces(capsys):
    out = _run("press-slide.yaml", capsys)
    assert out["force_source"] == "virtual"
    assert out["step_scores"]["hold"]["force_mae_n"] <= 1.0
    assert out["step_scores"]["slide"]["force_mae_n"] <= 1.5
