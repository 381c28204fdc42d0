"""Typed loading of YAML into dataclasses, with one-line errors that name the file and the field."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from drivers.errors import ConfigError, DataError

T = TypeVar("T")


MAX_YAML_BYTES = 1 << 20  # a config or manifest is a few kB; anything this large is not one
MAX_YAML_DEPTH = 32  # the deepest shipped file nests 4 levels; deeper input would exhaust the parser's stack

# YAML 1.2's float (PyYAML resolves YAML 1.1, where `1.0e6` and `1e6` are strings: an exponent needs a sign
# there).  Checked after the 1.1 int and float forms, so what they read is unchanged.
_YAML12_FLOAT = re.compile(r"^[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?$")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys (YAML lets the last one win silently), aliases (a few
    nested aliases expand to billions of nodes in whatever walks the result) and nesting deeper than
    MAX_YAML_DEPTH, and reads numbers as YAML 1.2 does."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.constructor.ConstructorError(
                None, None, "aliases (*name) are not supported in this file", event.start_mark)
        self._depth = getattr(self, "_depth", 0) + 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise yaml.constructor.ConstructorError(
                    None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, typing.Hashable) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key '{key}' (the same key twice in one mapping)", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML12_FLOAT, list("-+.0123456789"))


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping; every failure is a ConfigError naming the file (and line when known):
    unreadable, not UTF-8, larger than MAX_YAML_BYTES, invalid YAML, duplicate keys, aliases."""
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(f"{path}: {len(raw)} bytes is too large for a YAML file here (at most {MAX_YAML_BYTES})")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}: line {line} is not UTF-8 text (byte 0x{raw[exc.start]:02x})") from None
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:  # the depth limit's backstop (the scanner nests too, for flow collections)
        raise ConfigError(f"{path}: nested too deeply to be a YAML file here") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}:{where} invalid YAML: {problem}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: invalid value {_describe(value)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where} must be one of {list(args)}, got {_describe(value)}")
        return value
    if dataclasses.is_dataclass(tp):
        return load_dataclass(tp, value, where)  # type: ignore[arg-type]
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where} must be a list, got {_describe(value)}")
        item_tp = args[0] if args else Any
        return [_convert(item_tp, v, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a mapping, got {_describe(value)}")
        val_tp = args[1] if len(args) == 2 else Any
        return {k: _convert(val_tp, v, join(where, str(k))) for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where} must be a number, got {_describe(value)}")
        if not math.isfinite(value):
            raise ConfigError(f"{where} must be finite, got {_describe(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {_describe(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {_describe(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {_describe(value)}")
        return value
    return value  # Any


def join(where: str, name: str) -> str:
    """'cell.yaml:' + 'loop' -> 'cell.yaml: loop'; 'cell.yaml: loop' + 'period_s' -> '... loop.period_s'."""
    if not where:
        return name
    return f"{where} {name}" if where.endswith(":") else f"{where}.{name}"


def load_dataclass(cls: type[T], data: Any, where: str) -> T:
    """Build dataclass `cls` from a mapping; unknown keys, missing required keys and wrong types
    raise ConfigError("<where>.<field> ...").  A dataclass may define `validate(self, where)`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a mapping, got {_describe(data)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        head = where if where.endswith(":") else f"{where}:"
        raise ConfigError(f"{head} unknown key '{unknown[0]}' (known: {', '.join(sorted(fields))})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        path = join(where, name)
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], path)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{path} is required")
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        validate(where)
    return obj


def to_plain(obj: Any) -> Any:
    """Dataclasses/numpy to plain YAML/JSON-able values (for the resolved-config record)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_plain(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def require(cond: bool, where: str, message: str) -> None:
    """Raise ConfigError('<where> <message>') unless `cond`."""
    if not cond:
        raise ConfigError(f"{where} {message}")


def require_len(values: list[Any], n: int, where: str) -> None:
    require(len(values) == n, where, f"must have {n} values (one per joint), got {len(values)}")


def json_default(obj: Any) -> Any:
    """`json.dumps(default=...)` for numpy scalars and arrays (anything else, e.g. a Path, as its string)."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def finite_json(obj: Any) -> Any:
    """`obj` with every NaN or infinite number replaced by None (JSON has no NaN: a report must parse
    with any strict reader); numpy values become plain ones."""
    if isinstance(obj, dict):
        return {str(k): finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_json(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps_strict(obj: Any, **kw: Any) -> str:
    """JSON text of `obj` with NaN/inf as null (`finite_json`), refusing anything else non-standard."""
    return json.dumps(finite_json(obj), default=json_default, allow_nan=False, **kw)


def read_versioned_json(doc_path: Path, fmt: str, version: int, what: str, missing: str) -> dict[str, Any]:
    """A saved artefact's JSON document: present, readable, of format `fmt` and not newer than `version`
    (one-line DataErrors naming the file otherwise; `missing` is the message when it does not exist)."""
    if not doc_path.exists():
        raise DataError(missing)
    try:
        doc = json.loads(doc_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"{doc_path}: unreadable {what} ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise DataError(f"{doc_path}: format is {found!r}, expected {fmt!r}")
    if int(doc.get("format_version", 0)) > version:
        raise DataError(f"{doc_path}: format_version {doc['format_version']} is newer than this build reads")
    return doc


# ------------------------------------------------------------------------------------ bounded values
# Validators for a `validate(self, where)`: each returns the value or raises a one-line ConfigError naming
# `where`.  bool is an int to Python: refused everywhere, so `true` never passes as 1.
def describe(value: Any) -> str:
    """`value` as an error message shows it (repr, at most 60 characters)."""
    return _describe(value)


def number_in(value: Any, where: str, low: float, high: float, unit: str = "") -> float:
    """A finite number within [low, high] (`unit` is shown after the bounds, e.g. " s")."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            math.isfinite(value) and low <= value <= high):
        raise ConfigError(f"{where} must be a number from {low:g} to {high:g}{unit}, got {_describe(value)}")
    return float(value)


def integer_in(value: Any, where: str, low: int, high: int) -> int:
    """An integer within [low, high]."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"{where} must be an integer from {low} to {high}, got {_describe(value)}")
    return value


def one_of(value: Any, where: str, options: tuple[Any, ...]) -> Any:
    """One of `options`."""
    if isinstance(value, bool) or value not in options:
        raise ConfigError(f"{where} must be one of {list(options)}, got {_describe(value)}")
    return value


def number_near(value: Any, where: str, reference: float, rel_tol: float) -> float:
    """A finite number within `rel_tol` (relative) of `reference`."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            math.isfinite(value) and abs(value - reference) <= rel_tol * abs(reference)):
        raise ConfigError(f"{where} must be within {rel_tol * 100:g}% of {reference:g}, got {_describe(value)}")
    return float(value)
