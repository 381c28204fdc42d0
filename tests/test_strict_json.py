"""Strict JSON reports (drivers/configio.py finite_json, dumps_strict): no NaN or Infinity in the text, ever."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.configio import dumps_strict, finite_json


def strict_loads(text: str):
    """json.loads that refuses the non-standard constants Python's json writes for NaN and infinities."""

    def refuse(name: str):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


REPORT = {
    "rmse": float("nan"),
    "ratio": float("inf"),
    "floor": -float("inf"),
    "fine": 0.25,
    "count": 3,
    "flag": True,
    "none": None,
    "name": "H1",
    "np_nan": np.float64("nan"),
    "np_f32": np.float32(1.5),
    "np_int": np.int64(7),
    "np_bool": np.bool_(False),
    "per_joint": [1.0, float("nan"), 2.0, np.nan, np.inf],
    "tuple": (np.nan, 4.0),
    "array": np.array([[1.0, np.nan], [-np.inf, 2.5]]),
    "array_f32": np.array([np.nan, 3.0], np.float32),
    "scalar_array": np.array(np.nan),
    "nested": {"models": {"P2": {"j123": {"mean": np.nan, "std": [np.inf, 0.5]}}, "H1": [{"x": np.nan}]}},
    7: "int key",
}


def test_the_plain_dumps_would_not_be_strict_json():
    """The premise: Python's json writes NaN / Infinity, which strict readers refuse."""
    text = json.dumps({"a": float("nan"), "b": [float("inf")]})
    with pytest.raises(ValueError, match="NaN"):
        strict_loads(text)


def test_finite_json_replaces_every_non_finite_number_by_none():
    out = finite_json(REPORT)
    assert out["rmse"] is None and out["ratio"] is None and out["floor"] is None and out["np_nan"] is None
    assert out["per_joint"] == [1.0, None, 2.0, None, None]
    assert out["tuple"] == [None, 4.0]
    assert out["array"] == [[1.0, None], [None, 2.5]]
    assert out["array_f32"] == [None, 3.0]
    assert out["scalar_array"] is None
    assert out["nested"] == {"models": {"P2": {"j123": {"mean": None, "std": [None, 0.5]}}, "H1": [{"x": None}]}}
    # Finite values and the rest of the structure are kept, numpy values as plain Python ones.
    assert out["fine"] == 0.25 and out["count"] == 3 and out["flag"] is True and out["none"] is None
    assert out["name"] == "H1" and out["7"] == "int key"
    assert out["np_f32"] == 1.5 and type(out["np_f32"]) is float
    assert out["np_int"] == 7 and type(out["np_int"]) is int
    assert out["np_bool"] is False
    # The input is not modified.
    rmse, array = REPORT["rmse"], REPORT["array"]
    assert isinstance(rmse, float) and math.isnan(rmse)
    assert isinstance(array, np.ndarray) and np.isnan(array[0, 1])


def walk(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from walk(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from walk(v)
    else:
        yield obj


def test_dumps_strict_parses_with_a_strict_reader():
    text = dumps_strict({**REPORT, "path": Path("/tmp/x"), 7: "int key"}, indent=2)
    assert "NaN" not in text and "Infinity" not in text
    back = strict_loads(text)
    assert all(v is None or not isinstance(v, float) or math.isfinite(v) for v in walk(back))
    assert back == json.loads(json.dumps(finite_json({**REPORT, "path": "/tmp/x"})))
    assert back["path"] == "/tmp/x"  # other objects as their string, as json_default does
    assert back["nested"]["models"]["P2"]["j123"]["std"] == [None, 0.5]
    assert "\n  " in text  # keyword arguments reach json.dumps


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf"), np.float32("nan"), np.float64("-inf")])
def test_a_bare_non_finite_number(value):
    assert finite_json(value) is None
    assert dumps_strict(value) == "null"
    assert dumps_strict([value, {"v": value}]) == '[null, {"v": null}]'


def test_random_nested_reports_are_always_strict():
    rng = np.random.default_rng(0)
    specials = [np.nan, np.inf, -np.inf, 1.0, -2.5, 0.0]

    def build(depth: int):
        kind = rng.integers(0, 5) if depth < 4 else 4
        if kind == 0:
            return {f"k{i}": build(depth + 1) for i in range(rng.integers(0, 4))}
        if kind == 1:
            return [build(depth + 1) for _ in range(rng.integers(0, 4))]
        if kind == 2:
            return tuple(build(depth + 1) for _ in range(rng.integers(0, 3)))
        if kind == 3:
            return rng.choice(specials, size=tuple(rng.integers(1, 3, size=rng.integers(1, 3))))
        value = rng.choice(specials)
        return float(value) if rng.random() < 0.5 else np.float64(value)

    for _ in range(200):
        report = {"r": build(0)}
        back = strict_loads(dumps_strict(report))
        assert all(v is None or not isinstance(v, float) or math.isfinite(v) for v in walk(back))
