"""`main.py figures`: docs/figures.md from the saved JSON summaries; every bench and run saves its summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.commands_bench import BENCHES
from app.commands_cell import run_tags
from bench.figures import BENCH_DIR, Figure, measure, read_summary, render, save_summary, summary_name
from bench.figures_table import COLLISION, FIGURES
from drivers.errors import DataError
from main import build_parser, main


def write(path: Path, doc: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))


def row_of(page: str, name: str) -> str:
    rows = [line for line in page.splitlines() if line.startswith(f"| {name} |")]
    assert len(rows) == 1, f"{name}: {len(rows)} rows"
    return rows[0]


def test_the_page_holds_measured_values_and_names_the_missing_ones(tmp_path, capsys):
    bench = tmp_path / "bench"
    write(bench / "faults.json", {"failures": 0, "faults": {"link_loss": {"detection_periods": 0},
                                                            "stale_robot_data": {"detection_periods": 13}}})
    write(bench / "peg-in-hole-seed1.json", {"success_rate": 0.98, "median_time_s": 13.714,
                                             "virtual_vs_sensor_my_mae_nm": 0.1081})
    write(bench / "peg-in-hole-seed3.json", {"success_rate": 1.0, "median_time_s": 13.6})
    write(bench / "peg-in-hole-sensor-seed1.json", {"success_rate": 0.5})  # a variant: not the default's row
    out = tmp_path / "docs" / "figures.md"
    assert main(["-q", "figures", "--bench-dir", str(bench), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    page = out.read_text()

    assert "| faults: failures | 0 | pass | 0 | `main.py bench faults --json` | `faults.json` |" in page
    assert "| 13 |" in row_of(page, "faults: stale robot data (periods)")
    rate = row_of(page, "peg-in-hole, virtual sensor: success rate")
    assert "0.98 (seed 1), 1 (seed 3)" in rate and "`peg-in-hole-seed1.json`, `peg-in-hole-seed3.json`" in rate
    assert "13.7 (seed 1), 13.6 (seed 3)" in row_of(page, "peg-in-hole, virtual sensor: median time (s)")
    my = row_of(page, "peg-in-hole, virtual vs F/T: My MAE (N m)")
    assert "0.108 (seed 1), no `virtual_vs_sensor_my_mae_nm` in the file (seed 3)" in my
    assert "| 0.5 (seed 1) |" in row_of(page, "peg-in-hole, F/T sensor: success rate")
    missing = row_of(page, "collision: false alarms (per 10 min of free motion)")
    assert f"not measured (run: `{COLLISION} --json`)" in missing
    assert summary["out"] == str(out) and summary["figures"] == len(FIGURES)
    assert "collision: false alarms (per 10 min of free motion)" in summary["not_measured"]
    assert summary["measured"] == len(FIGURES) - len(summary["not_measured"])


def test_an_empty_bench_folder_gives_a_page_of_not_measured_rows(tmp_path):
    out = tmp_path / "figures.md"
    (tmp_path / "none").mkdir()
    assert main(["-q", "figures", "--bench-dir", str(tmp_path / "none"), "--out", str(out)]) == 0
    rows = [line for line in out.read_text().splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert len(rows) == len(FIGURES)
    assert all("not measured (run: `" in r for r in rows)


@pytest.mark.parametrize("text", ['{"failures": 0', "[1, 2]", "\xff\xfe"])
def test_a_bad_summary_is_a_one_line_error_naming_the_file(tmp_path, capsys, text):
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "faults.json").write_bytes(text.encode("latin-1"))
    out = tmp_path / "figures.md"
    assert main(["-q", "figures", "--bench-dir", str(bench), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bench / "faults.json") in err
    assert not out.exists()


def test_values_are_formatted_compactly(tmp_path):
    figs = [Figure("a", "x", "v.0", "t", "c"), Figure("b", "x", "big", "t", "c"), Figure("c", "x", "ok", "t", "c"),
            Figure("d", "x", "none", "t", "c"), Figure("e", "x", "pipe", "t", "c")]
    write(tmp_path / "x.json", {"v": [0.123456], "big": 124321.7, "ok": True, "none": None, "pipe": "a|b"})
    page = render(figs, measure(figs, tmp_path), tmp_path)
    assert "| a | 0.123 |" in page and "| b | 124,322 |" in page and "| c | true |" in page
    assert "| d | none |" in page and "| e | a\\|b |" in page


def test_summaries_are_saved_atomically_under_their_names(tmp_path):
    assert summary_name("peg-in-hole", ["sensor", "d21.7mm"], 3) == "peg-in-hole-sensor-d21.7mm-seed3"
    assert summary_name("faults") == "faults"
    path = save_summary({"x": float("nan"), "y": 1}, "faults", tmp_path / "b")
    assert path == tmp_path / "b" / "faults.json"
    assert read_summary(path) == {"x": None, "y": 1}
    assert [p.name for p in (tmp_path / "b").iterdir()] == ["faults.json"]  # no temporary left behind
    with pytest.raises(DataError, match="missing.json"):
        read_summary(tmp_path / "missing.json")


def test_every_bench_saves_the_summary_it_prints(capsys):
    assert main(["-q", "bench", "drivers", "--n", "20", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert read_summary(BENCH_DIR / "drivers.json") == printed  # relative to the test's own folder


def saved_name(command: str) -> str:
    """The name (without its seed) that the figure's command saves its summary under."""
    argv = command.split()
    if argv[0] == "./run.sh":  # run.sh runs `main.py run peg-in-hole --cell sim` with its extra arguments
        argv = ["main.py", "run", "peg-in-hole", "--cell", "sim", *argv[1:]]
    assert argv[0] == "main.py", command
    args = build_parser().parse_args(argv[1:])
    if args.command == "bench":
        return summary_name(args.what, BENCHES[args.what].tags(args))
    if args.command == "run":
        return summary_name(f"run-{args.task}", run_tags(args.cell or "sim", args.force_source))
    return summary_name(args.command)


def test_every_figures_command_saves_the_summary_its_row_reads():
    for fig in FIGURES:
        if "/" in fig.source:  # another command's report
            continue
        assert saved_name(fig.command) == fig.source, fig.name


def test_bench_options_off_their_defaults_tag_the_name():
    args = build_parser().parse_args(["bench", "peg-in-hole", "--trials", "10", "--only", "3", "7"])
    assert BENCHES["peg-in-hole"].tags(args) == ["10trials", "only3_7"]
    args = build_parser().parse_args(["bench", "collision", "--reaction", "retract", "--free-s", "60"])
    assert BENCHES["collision"].tags(args) == ["retract", "free60s"]
