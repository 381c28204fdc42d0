"""The `figures` command: docs/figures.md regenerated from the benchmarks' saved JSON summaries."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.common import emit
from bench.figures import BENCH_DIR, figures_summary, measure, read_page, render, write_page
from bench.figures_table import FIGURES
from cell.data.outputs import check_out_file
from drivers.errors import ConfigError


def cmd_figures(args: argparse.Namespace) -> int:
    bench_dir, out = Path(args.bench_dir), Path(args.out)
    if not bench_dir.is_dir():  # a typo must not regenerate the page as all "not measured"
        raise ConfigError(f"--bench-dir {bench_dir}: no such folder (the benchmarks save their summaries in "
                          f"{BENCH_DIR})")
    check_out_file(out)
    rows = measure(FIGURES, bench_dir)
    committed = read_page(out)  # a figure no summary holds keeps its value on the page
    summary = figures_summary(FIGURES, rows, committed)
    if summary["measured"] == 0 and not committed and out.exists():
        raise ConfigError(f"--bench-dir {bench_dir}: no saved summary holds any figure; {out} is left as it was")
    write_page(render(FIGURES, rows, bench_dir, committed), out)
    if args.json:
        emit({"out": str(out), **summary}, True)
    else:
        print(f"wrote {out}: {summary['measured']} of {summary['figures']} figures measured, {len(summary['kept'])} "
              f"kept from the page, {len(summary['not_measured'])} not measured")
    return 0
