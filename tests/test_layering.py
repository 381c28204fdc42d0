"""The source tree's shape: each package imports only the layers below it, and no module grows past 500 lines."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# What each top-level package may import from the project (itself included).  main.py dispatches to app/,
# the composition layer, which assembles tasks, benches and cells; the simulator is a backend beside the
# real drivers, so it knows nothing of the tasks that run on it.  bench/ and app/ stand at one level, app/
# dispatching to the benches: bench/ never imports app/, so the two cannot import each other.
ALLOWED: dict[str, set[str]] = {
    "main": {"app", "bench", "tasks", "sim", "cell", "drivers"},
    "app": {"app", "bench", "tasks", "sim", "cell", "drivers"},
    "bench": {"bench", "tasks", "sim", "cell", "drivers"},
    "tasks": {"tasks", "cell", "drivers"},
    "sim": {"sim", "cell", "drivers"},
    "cell": {"cell", "drivers"},
    "drivers": {"drivers"},
}
PROJECT = set(ALLOWED)

MAX_LINES = 500
MAX_MAIN_LINES = 250  # main.py parses arguments and dispatches, nothing more


def source_files() -> list[Path]:
    files = [ROOT / "main.py"]
    for package in sorted(PROJECT - {"main"}):
        files += sorted((ROOT / package).rglob("*.py"))
    return files


def layer_of(path: Path) -> str:
    rel = path.relative_to(ROOT)
    return "main" if rel == Path("main.py") else rel.parts[0]


def module_name(path: Path) -> list[str]:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return parts[:-1] if parts[-1] == "__init__" else parts


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every import in the module, those inside functions and classes included."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                found.append((node.lineno, node.module or ""))
                continue
            # A relative import: resolved from this module's package.
            package = module_name(path) if is_package else module_name(path)[:-1]
            base = package[: len(package) - (node.level - 1)]
            found.append((node.lineno, ".".join([*base, *([node.module] if node.module else [])])))
    return found


def test_every_top_level_package_has_a_layer():
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert packages <= PROJECT, f"place {sorted(packages - PROJECT)} in ALLOWED"


def test_imports_point_only_down():
    wrong = []
    for path in source_files():
        layer = layer_of(path)
        wrong += [f"{path.relative_to(ROOT)}:{line}: {name} ({layer} may import only {sorted(ALLOWED[layer])})"
                  for line, name in imported_modules(path)
                  if name.split(".")[0] in PROJECT and name.split(".")[0] not in ALLOWED[layer]]
    assert not wrong, "imports pointing up or sideways:\n" + "\n".join(wrong)


def test_no_module_is_over_the_line_limit():
    over = {}
    for path in source_files():
        rel = path.relative_to(ROOT).as_posix()
        lines = len(path.read_text(encoding="utf-8").splitlines())
        if lines > MAX_LINES:
            over[rel] = lines
    assert not over, f"modules over {MAX_LINES} lines (split them along their concepts): {over}"


def test_main_only_parses_and_dispatches():
    lines = len((ROOT / "main.py").read_text(encoding="utf-8").splitlines())
    assert lines < MAX_MAIN_LINES, f"main.py has {lines} lines; command bodies belong in app/"


# Below the composition layer nothing starts the command line: a child process is a module of its own
# layer (`python -m sim.serve_cell`), so the import rules above see every arrow.
NO_MAIN_LAYERS = ("cell", "drivers", "sim", "tasks", "bench")
_MAIN_PATH = re.compile(r"^(?:.*[/\\])?main\.py$")


def names_main(path: Path) -> list[int]:
    """Lines where a module names main.py as a file (a path ending in main.py) or runs it as `-m main`."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and _MAIN_PATH.match(node.value.strip()):
            lines.append(node.lineno)
        elif isinstance(node, ast.List | ast.Tuple):
            words = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
            if any(a == "-m" and b == "main" for a, b in zip(words, words[1:], strict=False)):
                lines.append(node.lineno)
    return sorted(lines)


def test_no_lower_layer_runs_main():
    wrong = [f"{path.relative_to(ROOT)}:{line}" for path in source_files() if layer_of(path) in NO_MAIN_LAYERS
             for line in names_main(path)]
    assert not wrong, "modules below app/ that name main.py (start a sim/ module instead):\n" + "\n".join(wrong)


def test_the_main_checker_sees_paths_and_module_runs(tmp_path: Path):
    module = tmp_path / "child.py"
    module.write_text('MAIN = ROOT / "main.py"\ncmd = [exe, "-m", "main", "emulate"]\nhelp = "run main.py prepare"\n',
                      encoding="utf-8")
    assert names_main(module) == [1, 2]


def test_the_checker_sees_imports_inside_functions(tmp_path: Path):
    # The rules are only as good as the parse: a lazy import in a function body must be caught too.
    module = tmp_path / "lazy.py"
    module.write_text("def f():\n    from sim.cell import make_sim_cell\n    import tasks.peg\n", encoding="utf-8")
    assert [name for _, name in imported_modules(module)] == ["sim.cell", "tasks.peg"]
