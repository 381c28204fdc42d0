"""The measured-figures page: the benchmarks' saved JSON summaries read through the figure table
(`bench/figures_table.py`) into one compact Markdown table, so the page is regenerated, never copied."""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.configio import dumps_strict
from drivers.errors import DataError

# Where `main.py bench ...` and `main.py run ...` save their summaries (relative to the working folder, as
# every artefact path is).
BENCH_DIR = Path("artifacts/bench")
FIGURES_PAGE = Path("docs/figures.md")


@dataclass(frozen=True)
class Figure:
    """One row of the page.  `source` is a saved summary's name in the bench folder (`faults`, or
    `peg-in-hole-sensor`, which also matches its `-seed<S>` variants), or a path with a `/` to another JSON
    document (relative to the working folder); `key` is a dotted path into it."""

    name: str
    source: str
    key: str
    target: str
    command: str


@dataclass(frozen=True)
class Measured:
    file: Path
    seed: int | None
    value: Any
    found: bool  # false: the file lacks the key


def summary_name(bench: str, tags: Sequence[str] = (), seed: int | None = None) -> str:
    """`<bench>[-<tag>...][-seed<S>]`: the file stem a run's summary is saved under; the tags name the
    options that change its figures (`sensor`, `d21.7mm`), so a variant never overwrites the default."""
    return "-".join([bench, *tags, *([f"seed{seed}"] if seed is not None else [])])


def save_summary(out: dict[str, Any], name: str, bench_dir: Path = BENCH_DIR) -> Path:
    """Write `out` as strict JSON to `<bench_dir>/<name>.json` atomically (a reader sees the old file or the
    new one, never half of one)."""
    bench_dir.mkdir(parents=True, exist_ok=True)
    path = bench_dir / f"{name}.json"
    fd, tmp = tempfile.mkstemp(dir=bench_dir, prefix=f".{name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(dumps_strict(out, indent=1) + "\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_summary(path: Path) -> dict[str, Any]:
    """A saved JSON object; anything else is a one-line DataError naming the file."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    if not isinstance(doc, dict):
        raise DataError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    return doc


def source_files(source: str, bench_dir: Path) -> list[tuple[Path, int | None]]:
    """The files a figure's source names, with their seeds (None: saved without --seed), by seed."""
    if "/" in source:
        path = Path(source)
        return [(path, None)] if path.is_file() else []
    if not bench_dir.is_dir():
        return []
    pattern = re.compile(re.escape(source) + r"(?:-seed(\d+))?\.json")
    found = []
    for path in bench_dir.iterdir():
        m = pattern.fullmatch(path.name)
        if m and path.is_file():
            found.append((path, int(m.group(1)) if m.group(1) else None))
    return sorted(found, key=lambda f: -1 if f[1] is None else f[1])


def lookup(doc: Any, key: str) -> tuple[bool, Any]:
    """(found, value) at the dotted `key` (a list index is a number)."""
    for part in key.split("."):
        if isinstance(doc, dict) and part in doc:
            doc = doc[part]
        elif isinstance(doc, list) and part.isdigit() and int(part) < len(doc):
            doc = doc[int(part)]
        else:
            return False, None
    return True, doc


def measure(figures: Sequence[Figure], bench_dir: Path = BENCH_DIR) -> list[list[Measured]]:
    """Per figure, its value in every file of its source (each file read once)."""
    docs: dict[Path, dict[str, Any]] = {}
    rows = []
    for fig in figures:
        row = []
        for path, seed in source_files(fig.source, bench_dir):
            if path not in docs:
                docs[path] = read_summary(path)
            found, value = lookup(docs[path], fig.key)
            row.append(Measured(path, seed, value, found))
        rows.append(row)
    return rows


def format_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"
    if v is None:
        return "none"
    if isinstance(v, list):
        return json.dumps(v) if len(v) <= 6 else f"{len(v)} items"
    if isinstance(v, dict):
        return f"{len(v)} entries"
    return str(v)


def _measured_text(row: Sequence[Measured], fig: Figure) -> str:
    if not row:
        return f"not measured (run: `{fig.command}`)"
    parts = []
    for m in row:
        text = format_value(m.value) if m.found else f"no `{fig.key}` in the file"
        parts.append(text if m.seed is None else f"{text} (seed {m.seed})")
    return ", ".join(parts)


def _from_text(row: Sequence[Measured], bench_dir: Path) -> str:
    names = [m.file.name if m.file.parent == bench_dir else str(m.file) for m in row]
    return ", ".join(f"`{n}`" for n in names) if names else "-"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render(figures: Sequence[Figure], rows: Sequence[Sequence[Measured]], bench_dir: Path = BENCH_DIR) -> str:
    lines = [
        "# Measured figures",
        "",
        f"Generated by `main.py figures` from the JSON summaries in `{bench_dir}/` (every `main.py bench ...` and "
        "`main.py run ...` saves one there) and the lab's reports; do not edit by hand.  The rows are listed in "
        "`bench/figures_table.py`; what they mean and how they were measured: `docs/measurements.md`.  Several "
        "values in a cell are several seeds.",
        "",
        "| figure | measured | target | command | from |",
        "|---|---|---|---|---|",
    ]
    for fig, row in zip(figures, rows, strict=True):
        cells = [fig.name, _measured_text(row, fig), fig.target, f"`{fig.command}`", _from_text(row, bench_dir)]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def write_page(text: str, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def figures_summary(figures: Sequence[Figure], rows: Sequence[Sequence[Measured]]) -> dict[str, Any]:
    """The command's JSON: per figure its values by file and seed."""
    return {
        "figures": len(figures),
        "measured": sum(1 for r in rows if r),
        "not_measured": [f.name for f, r in zip(figures, rows, strict=True) if not r],
        "rows": [{"figure": f.name, "target": f.target, "command": f.command,
                  "values": [{"file": str(m.file), "seed": m.seed, "value": m.value if m.found else None,
                              "found": m.found} for m in r]}
                 for f, r in zip(figures, rows, strict=True)],
    }
