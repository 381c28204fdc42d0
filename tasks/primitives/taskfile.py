"""Task files: a YAML sequence of primitives with named poses, validated strictly (one-line errors that name
the file and the line), as the cell config is."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pinocchio as pin
import yaml

from cell.control.guarded import GuardedSettings, check_speeds
from drivers.configio import load_dataclass, read_yaml, require
from drivers.errors import ConfigError
from tasks.primitives.base import Common, Primitive, Reaction
from tasks.primitives.force import ForceMode, ForceModeParams, GuardedMove, GuardedMoveParams
from tasks.primitives.motion import (
    Hold,
    HoldParams,
    Move,
    MoveParams,
    Report,
    ReportParams,
    Tare,
    TareParams,
    Wait,
    WaitParams,
)
from tasks.primitives.search import SpiralSearch, SpiralSearchParams

log = logging.getLogger(__name__)

# primitive name -> (its parameters, its runtime class)
PRIMITIVES: dict[str, tuple[type[Common], type[Primitive]]] = {
    "move": (MoveParams, Move),
    "guarded_move": (GuardedMoveParams, GuardedMove),
    "force_mode": (ForceModeParams, ForceMode),
    "spiral_search": (SpiralSearchParams, SpiralSearch),
    "hold": (HoldParams, Hold),
    "wait": (WaitParams, Wait),
    "tare": (TareParams, Tare),
    "report": (ReportParams, Report),
}


@dataclass
class PoseSpec:
    """A named pose: `xyz` [m] and `rpy_deg` (base frame; the default points the tool down), or `joints_deg`."""

    xyz: list[float] | None = None
    rpy_deg: list[float] = field(default_factory=lambda: [180.0, 0.0, 0.0])
    joints_deg: list[float] | None = None

    def validate(self, where: str) -> None:
        require((self.xyz is None) != (self.joints_deg is None), where, "needs exactly one of `xyz` and `joints_deg`")
        require(self.xyz is None or len(self.xyz) == 3, f"{where}.xyz", "must be [x, y, z] in m")
        require(len(self.rpy_deg) == 3, f"{where}.rpy_deg", "must be [roll, pitch, yaw] in deg")
        require(self.joints_deg is None or len(self.joints_deg) == 6, f"{where}.joints_deg", "must have 6 values")


@dataclass
class TaskFileHeader:
    """A task file's top level (its `steps` are checked one by one after it)."""

    name: str
    steps: list[Any]
    tool: Literal["wipe", "peg"] = "wipe"
    scene: Literal["free", "table", "peg"] = "table"  # the simulated cell's fixture
    description: str = ""
    max_duration_s: float = 120.0
    max_force_n: float = 60.0  # every step's default task-level force limit
    collision: Reaction | None = None  # every step's default reaction (else the cell config's)
    poses: dict[str, PoseSpec] = field(default_factory=dict)

    def validate(self, where: str) -> None:
        require(re.fullmatch(r"[a-z0-9][a-z0-9_-]{0,40}", self.name) is not None, f"{where} name",
                f"must be lower-case letters, digits, '-' or '_' (it names the run), got {self.name!r}")
        require(0 < self.max_duration_s <= 3600, f"{where} max_duration_s", "must lie in (0, 3600] s")
        require(self.max_force_n > 0, f"{where} max_force_n", "must be > 0 N")
        require(len(self.steps) >= 1, f"{where} steps", "needs at least one step")


@dataclass
class Step:
    kind: str
    params: Any
    line: int
    index: int

    def build(self) -> Primitive:
        return PRIMITIVES[self.kind][1](self.params, self.line)

    @property
    def label(self) -> str:
        return self.params.name or f"{self.index + 1:02d}-{self.kind}"


@dataclass
class TaskFile:
    path: Path
    header: TaskFileHeader
    steps: list[Step]
    poses: dict[str, pin.SE3 | np.ndarray]  # Cartesian poses, or joint vectors [rad]
    pose_lines: dict[str, int] = field(default_factory=dict)

    def reaction(self, step: Step) -> Reaction | None:
        return step.params.collision or self.header.collision

    def max_force(self, step: Step) -> float:
        return float(step.params.max_force_n or self.header.max_force_n)


def _lines(text: str) -> dict[tuple[Any, ...], int]:
    """1-based line of every mapping key and sequence item, by its path (('steps', 2, 'force_mode', 'end'))."""
    out: dict[tuple[Any, ...], int] = {}

    def walk(node: Any, path: tuple[Any, ...]) -> None:
        out.setdefault(path, node.start_mark.line + 1)
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                key = (*path, k.value)
                out[key] = k.start_mark.line + 1
                walk(v, key)
                out[key] = k.start_mark.line + 1
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                walk(v, (*path, i))

    walk(yaml.compose(text, Loader=yaml.SafeLoader), ())
    return out


def _line_of(lines: dict[tuple[Any, ...], int], path: tuple[Any, ...], message: str, where: str) -> int:
    """The line of the deepest field the message names under `where` (e.g. 'steps[2].force_mode.end.time_s')."""
    rest = message[len(where):] if message.startswith(where) else ""
    for name in re.findall(r"\.([A-Za-z_][A-Za-z0-9_]*)|\[(\d+)\]", rest.split(" ")[0]):
        key: Any = name[0] if name[0] else int(name[1])
        if (*path, key) not in lines:
            break
        path = (*path, key)
    m = re.search(r"unknown key '([^']+)'", message)
    if m and (*path, m.group(1)) in lines:
        path = (*path, m.group(1))
    return lines.get(path, lines.get((), 1))


def load_task_file(path: Path, guarded: GuardedSettings, cell_force_limit_n: float) -> TaskFile:
    """Read and check a task file against the cell's limits; every error is one ConfigError line
    '<file>: line N: <field> <problem>'."""
    data = read_yaml(path)  # YAML errors, duplicate keys, aliases: already one line with the line
    lines = _lines(Path(path).read_text(encoding="utf-8"))

    def fail(msg: str, at: tuple[Any, ...]) -> ConfigError:
        return ConfigError(f"{path}: line {lines.get(at, 1)}: {msg}")

    try:
        header = load_dataclass(TaskFileHeader, data, "")
    except ConfigError as exc:
        msg = str(exc).lstrip(": ").strip()
        m = re.match(r"(?:unknown key '([^']+)')|([a-z_]+)", msg)
        key = (m.group(1) or m.group(2)) if m else None
        sub = re.match(r"poses\.([A-Za-z0-9_-]+)", msg)
        at: tuple[Any, ...] = ("poses", sub.group(1)) if sub else ((key,) if key else ())
        raise fail(msg, at) from None
    if header.max_force_n > cell_force_limit_n:
        raise fail(f"max_force_n ({header.max_force_n:g} N) must not exceed the cell's safety.max_tool_force_n "
                   f"({cell_force_limit_n:g} N)", ("max_force_n",))
    poses: dict[str, pin.SE3 | np.ndarray] = {}
    for name, spec in header.poses.items():
        if spec.xyz is not None:
            R = pin.rpy.rpyToMatrix(*np.radians(spec.rpy_deg))
            poses[name] = pin.SE3(R, np.asarray(spec.xyz, float))
        else:
            assert spec.joints_deg is not None
            poses[name] = np.radians(np.asarray(spec.joints_deg, float))
    steps: list[Step] = []
    names: set[str] = set()
    for i, raw in enumerate(header.steps):
        at = ("steps", i)
        if not isinstance(raw, dict) or len(raw) != 1:
            raise fail(f"steps[{i}] must be one primitive: '- <primitive>: {{parameters}}' "
                       f"(known: {', '.join(PRIMITIVES)})", at)
        kind, body = next(iter(raw.items()))
        if kind not in PRIMITIVES:
            raise fail(f"steps[{i}]: unknown primitive '{kind}' (known: {', '.join(PRIMITIVES)})", (*at, kind))
        where = f"steps[{i}].{kind}"
        try:
            params = load_dataclass(PRIMITIVES[kind][0], body if body is not None else {}, where)
        except ConfigError as exc:
            raise ConfigError(f"{path}: line {_line_of(lines, (*at, kind), str(exc), where)}: {exc}") from None
        step = Step(kind, params, lines.get((*at, kind), lines.get(at, 1)), i)
        _check_step(step, header, poses, names, cell_force_limit_n, guarded, Path(path), lines, (*at, kind))
        if params.name is not None:
            names.add(params.name)
        steps.append(step)
    return TaskFile(Path(path), header, steps, poses, {k: lines.get(("poses", k), 1) for k in poses})


def _check_step(step: Step, header: TaskFileHeader, poses: dict[str, Any], names: set[str], cell_limit: float,
                guarded: GuardedSettings, path: Path, lines: dict[tuple[Any, ...], int], at: tuple[Any, ...]) -> None:
    """What a step's own dataclass cannot check: names that must exist, forces against the limits,
    head-on speeds against guarded motion."""
    p = step.params
    where = f"steps[{step.index}].{step.kind}"

    def fail_at(msg: str, key: str) -> ConfigError:
        return ConfigError(f"{path}: line {lines.get((*at, key), lines.get(at, 1))}: {msg}")

    if p.name is not None and p.name in names:
        raise fail_at(f"{where}.name '{p.name}' is used by an earlier step", "name")
    limit = float(p.max_force_n or header.max_force_n)
    if limit > cell_limit:
        raise fail_at(f"{where}.max_force_n ({limit:g} N) must not exceed the cell's safety.max_tool_force_n "
                      f"({cell_limit:g} N)", "max_force_n")
    if isinstance(p, MoveParams) and p.to is not None:
        if p.to not in poses:
            raise fail_at(f"{where}.to: unknown pose '{p.to}' (known: {', '.join(poses) or 'none'})", "to")
        if isinstance(poses[p.to], np.ndarray) and p.space != "joint":
            raise fail_at(f"{where}.to: pose '{p.to}' is given in joints: use space: joint", "to")
    if isinstance(p, GuardedMoveParams):
        if p.force_n >= limit:
            raise fail_at(f"{where}.force_n ({p.force_n:g} N) must be below the step's force limit ({limit:g} N)",
                          "force_n")
        try:
            check_speeds(guarded, {"speed_mps": p.speed_mps}, limit, where)
        except ConfigError as exc:
            raise fail_at(str(exc), "speed_mps") from None
    if isinstance(p, ForceModeParams | SpiralSearchParams):
        force = p.peak_force()
        if force >= limit:
            raise fail_at(f"{where}.wrench: a {force:g} N setpoint must be below the step's force limit "
                          f"({limit:g} N; the cell's is {cell_limit:g} N)", "wrench")
    if isinstance(p, ReportParams):
        for ref in p.references():
            if ref not in names:
                raise fail_at(f"{where}.point: no earlier step is named '{ref}'", "point")
