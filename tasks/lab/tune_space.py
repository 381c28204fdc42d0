"""Hyperparameter search spaces of `main.py tune`: a YAML file per learner, checked field by field."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cell.config import CONFIG_DIR
from cell.model.dynamics.learned import XGBParams
from cell.model.dynamics.nets import NetParams
from drivers.configio import read_yaml
from drivers.errors import ConfigError

SPACE_DIR = CONFIG_DIR / "tune"
# Settings that are not the learner's to tune (the run's threads and seed, the learner itself).
NOT_TUNED = {"nthread", "seed", "learner"}
KINDS = ("int", "float", "categorical")


@dataclass(frozen=True)
class Param:
    """One hyperparameter: a range (bayes) and the grid of values Algorithm 1 tries (grid)."""

    name: str
    kind: str
    low: float | None
    high: float | None
    log: bool
    grid: tuple[Any, ...]

    def contains(self, value: Any) -> bool:
        if self.kind == "categorical":
            return value in self.grid
        assert self.low is not None and self.high is not None
        return isinstance(value, int | float) and not isinstance(value, bool) and self.low <= value <= self.high


def default_space(learner: str) -> Path:
    return SPACE_DIR / f"{learner}.yaml"


def load_space(path: Path, learner: str) -> list[Param]:
    """The search space in `path`; a ConfigError naming the file and the field for anything wrong."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: search space file not found")
    doc = read_yaml(path)
    cls: type[Any] = XGBParams if learner == "xgboost" else NetParams
    fields = {f.name: f for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else {}
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(f"{path}: a search space maps hyperparameter names to {{type, low, high, grid}}")
    out: list[Param] = []
    for name, spec in doc.items():
        where = f"{path}: {name}"
        if name not in fields or name in NOT_TUNED:
            tunable = sorted(set(fields) - NOT_TUNED)
            raise ConfigError(f"{where}: not a {learner} hyperparameter (one of {', '.join(tunable)})")
        if not isinstance(spec, dict):
            raise ConfigError(f"{where}: expected a mapping with type, low, high, grid")
        unknown = set(spec) - {"type", "low", "high", "log", "grid", "choices"}
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} (type, low, high, log, grid)")
        kind = spec.get("type")
        if kind not in KINDS:
            raise ConfigError(f"{where}: type {kind!r} is not one of {', '.join(KINDS)}")
        log = bool(spec.get("log", False))
        if kind == "categorical":
            grid = spec.get("choices", spec.get("grid"))
            if not isinstance(grid, list) or not grid:
                raise ConfigError(f"{where}: a categorical needs a non-empty list of choices")
            out.append(Param(name, kind, None, None, False, tuple(grid)))
            continue
        low, high = spec.get("low"), spec.get("high")
        num = (int,) if kind == "int" else (int, float)
        if not isinstance(low, num) or not isinstance(high, num) or isinstance(low, bool) or isinstance(high, bool):
            raise ConfigError(f"{where}: low and high must be {kind} numbers, got {low!r} and {high!r}")
        if not low < high:
            raise ConfigError(f"{where}: low ({low}) must be below high ({high})")
        if log and low <= 0:
            raise ConfigError(f"{where}: a log range needs low > 0, got {low}")
        grid = spec.get("grid")
        if not isinstance(grid, list) or not grid:
            raise ConfigError(f"{where}: grid must be a non-empty list of values (Algorithm 1 searches it)")
        p = Param(name, kind, float(low), float(high), log, tuple(grid))
        bad = [g for g in grid if not p.contains(g) or (kind == "int" and not isinstance(g, int))]
        if bad:
            raise ConfigError(f"{where}: grid value(s) {bad} outside [{low}, {high}] or not {kind}")
        out.append(p)
    return out
