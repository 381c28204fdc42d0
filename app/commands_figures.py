"""The `figures` command: docs/figures.md regenerated from the benchmarks' saved JSON summaries."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.common import emit
from bench.figures import figures_summary, measure, render, write_page
from bench.figures_table import FIGURES


def cmd_figures(args: argparse.Namespace) -> int:
    bench_dir, out = Path(args.bench_dir), Path(args.out)
    rows = measure(FIGURES, bench_dir)
    write_page(render(FIGURES, rows, bench_dir), out)
    summary = figures_summary(FIGURES, rows)
    if args.json:
        emit({"out": str(out), **summary}, True)
    else:
        print(f"wrote {out}: {summary['measured']} of {summary['figures']} figures measured")
    return 0
