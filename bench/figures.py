"""The measured-figures page: the benchmarks' saved JSON summaries read through the figure table
(`bench/figures_table.py`) into one compact Markdown table, so the page is regenerated, never copied."""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cell.data.atomic import write_atomic
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
    return write_atomic(bench_dir / f"{name}.json", dumps_strict(out, indent=1) + "\n")


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
    except RecursionError:
        raise DataError(f"{path}: nested too deeply to be a saved summary") from None
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


NOT_MEASURED = "not measured"


def _measured_text(row: Sequence[Measured], fig: Figure) -> str:
    if not row:
        return f"{NOT_MEASURED} (run: `{fig.command}`)"
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


def _split_row(line: str) -> list[str]:
    r"""A Markdown table row's cells (a `\|` inside a cell is text)."""
    cells = re.split(r"(?<!\\)\|", line.strip())[1:-1]
    return [c.strip().replace("\\|", "|") for c in cells]


@dataclass(frozen=True)
class Committed:
    """A row of the page as it stands: what it measured and where that came from."""

    measured: str
    source: str


def read_page(path: Path) -> dict[str, Committed]:
    """The measured rows of an existing page by figure name (rows that say "not measured" are left out):
    what a regeneration keeps where no new summary holds the figure."""
    if not path.is_file():
        return {}
    rows: dict[str, Committed] = {}
    header: list[str] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("|") or line.startswith("|---"):
            continue
        cells = _split_row(line)
        if not header:
            header = cells
            continue
        if len(cells) != len(header) or "figure" not in header:
            continue
        row = dict(zip(header, cells, strict=True))
        measured = row.get("measured", "")
        if measured and not measured.startswith(NOT_MEASURED):
            rows[row["figure"]] = Committed(measured, row.get("from", "-"))
    return rows


# ---------------------------------------------------------------------------------------- targets
_NUMBER = r"[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?"


def _number(text: str) -> float | None:
    m = re.fullmatch(r"\s*(" + _NUMBER + r")\s*", text)
    return float(m.group(1).replace(",", "")) if m else None


def parse_values(measured: str) -> list[Any]:
    """The values of a measured cell as written (`14 (seed 1), 13.9 (seed 2)` -> [14.0, 13.9]): numbers,
    `true`/`false`, `none`, lists, or the text itself."""
    out: list[Any] = []
    for part in re.split(r",\s+(?![^\[]*\])", measured):
        text = re.sub(r"\s*\(seed \d+\)\s*$", "", part).strip()
        num = _number(text)
        if num is not None:
            out.append(num)
        elif text in ("true", "false"):
            out.append(text == "true")
        elif text == "none":
            out.append(None)
        elif text.startswith("["):
            try:
                out.append(json.loads(text))
            except json.JSONDecodeError:
                out.append(text)
        else:
            out.append(text)
    return out


def meets(value: Any, target: str) -> bool | None:
    """Whether one value meets a target as the table writes it (`<= 15`, `>= 0.95 (paper ...)`, `2-4`, `~10`,
    `0`, `none`, `done`, `all 23`); None when the target is no check (`reported`, `paper 24.7`, a formula)."""
    t = target.strip()
    if t in ("none", "0") and (value is None or value == [] or value == 0):
        return True
    if t == "none":
        return False
    if isinstance(value, bool) or value is None:
        return None if t not in ("true", "false") else value == (t == "true")
    if isinstance(value, str):
        return value == t if re.fullmatch(r"[a-z_]+", t) and t not in ("reported", "report", "minutes") else None
    if isinstance(value, list):
        return None
    m = re.match(r"(<=|>=|<|>)\s*(" + _NUMBER + r")(?:\s*(?:\(.*\))?)$", t)
    if m:
        bound = float(m.group(2).replace(",", ""))
        return {"<=": value <= bound, ">=": value >= bound, "<": value < bound, ">": value > bound}[m.group(1)]
    m = re.fullmatch(r"(" + _NUMBER + r")\s*-\s*(" + _NUMBER + r")", t)
    if m:
        return float(m.group(1)) <= value <= float(m.group(2))
    m = re.fullmatch(r"~\s*(" + _NUMBER + r")", t)
    if m:  # about: within a fifth
        return abs(value - float(m.group(1))) <= 0.2 * abs(float(m.group(1)))
    m = re.fullmatch(r"all\s+(\d+)", t)
    if m:
        return value == float(m.group(1))
    num = _number(t)
    return value == num if num is not None else None


def verdict(values: Sequence[Any], target: str) -> str:
    """`pass` when every value (seed) meets the target, `MISS` when one does not, `-` when there is nothing
    to check (no value, or a target that is no bound)."""
    checks = [meets(v, target) for v in values]
    if not values or any(c is None for c in checks):
        return "-"
    return "pass" if all(checks) else "MISS"


def render(figures: Sequence[Figure], rows: Sequence[Sequence[Measured]], bench_dir: Path = BENCH_DIR,
           committed: dict[str, Committed] | None = None) -> str:
    """The page: each figure's new values, or (no new summary holds it) the committed page's value and
    source as they stood, a pass/fail column against its target, and the misses listed first."""
    committed = committed or {}
    body, misses = [], []
    for fig, row in zip(figures, rows, strict=True):
        old = committed.get(fig.name)
        if row or old is None:
            measured, source = _measured_text(row, fig), _from_text(row, bench_dir)
            values = [m.value for m in row if m.found] if len(row) == sum(m.found for m in row) else []
        else:
            measured, source = old.measured, old.source
            values = parse_values(old.measured)
        mark = verdict(values, fig.target)
        if mark == "MISS":
            misses.append(f"- {fig.name}: {measured} (target {fig.target})")
        cells = [fig.name, measured, "**MISS**" if mark == "MISS" else mark, fig.target, f"`{fig.command}`", source]
        body.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    lines = [
        "# Measured figures",
        "",
        f"Generated by `main.py figures` from the JSON summaries in `{bench_dir}/` (every `main.py bench ...` and "
        "`main.py run ...` saves one there) and the lab's reports; do not edit by hand.  A figure no saved summary "
        "holds keeps the value and source this page had.  The rows are listed in `bench/figures_table.py`; what "
        "they mean and how they were measured: `docs/measurements.md`.  Several values in a cell are several "
        "seeds; `ok` compares every one with the target (`-`: no bound to check).",
        "",
        f"**{len(misses)} figures miss their targets**" + (":" if misses else "."),
        "",
        *misses,
        *([""] if misses else []),
        "| figure | measured | ok | target | command | from |",
        "|---|---|---|---|---|---|",
        *body,
    ]
    return "\n".join(lines) + "\n"


def write_page(text: str, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, text)


def figures_summary(figures: Sequence[Figure], rows: Sequence[Sequence[Measured]],
                    committed: dict[str, Committed] | None = None) -> dict[str, Any]:
    """The command's JSON: per figure its values by file and seed; `kept`: the figures no summary holds whose
    committed value stays; `not_measured`: neither."""
    committed = committed or {}
    return {
        "figures": len(figures),
        "measured": sum(1 for r in rows if r),
        "kept": [f.name for f, r in zip(figures, rows, strict=True) if not r and f.name in committed],
        "not_measured": [f.name for f, r in zip(figures, rows, strict=True) if not r and f.name not in committed],
        "rows": [{"figure": f.name, "target": f.target, "command": f.command,
                  "values": [{"file": str(m.file), "seed": m.seed, "value": m.value if m.found else None,
                              "found": m.found} for m in r]}
                 for f, r in zip(figures, rows, strict=True)],
    }
