"""Register codecs, poses and the user-area / driver configuration contract of the TM5 Modbus driver."""

from __future__ import annotations

import math
import struct
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.client import ModbusTcpClient

from drivers.errors import ConfigError
from drivers.tm5.config import TM5ModbusConfig
from drivers.tm5.contract import FIELD_WIDTH, UserAreaLayout
from drivers.tm5.registers import (
    counter_delta,
    float32_to_regs,
    floats_to_regs,
    int32_to_regs,
    matrix_to_rpy,
    pose_to_regs,
    regs_to_float32,
    regs_to_floats,
    regs_to_int32,
    regs_to_pose,
    regs_to_string,
    rpy_to_matrix,
    string_to_regs,
    wrap_int32,
)

WHERE = "config/cell.yaml: devices.arm.user_area"
FIELDS = [f.name for f in fields(UserAreaLayout)]
DOC = Path(__file__).resolve().parents[1] / "docs" / "robot-side-program.md"
F32 = ModbusTcpClient.DATATYPE.FLOAT32
I32 = ModbusTcpClient.DATATYPE.INT32

finite_f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
register = st.integers(0, 0xFFFF)


# ------------------------------------------------------------------------------------------------ FLOAT32
@pytest.mark.timeout(30)
@given(finite_f32)
def test_float32_round_trip_is_exact(x: float) -> None:
    regs = float32_to_regs(x)
    assert len(regs) == 2 and all(0 <= r <= 0xFFFF for r in regs)
    assert regs_to_float32(regs) == x
    # ABCD = big-endian bytes, high word first: what pymodbus' own decoder and struct say
    assert regs == list(struct.unpack(">HH", struct.pack(">f", x)))
    assert ModbusTcpClient.convert_from_registers(regs, F32) == x


@pytest.mark.timeout(30)
@given(st.lists(st.floats(min_value=-3.4e38, max_value=3.4e38, allow_nan=False), min_size=1, max_size=12))
def test_float64_values_round_to_nearest_float32(values: list[float]) -> None:
    decoded = regs_to_floats(floats_to_regs(values))
    np.testing.assert_array_equal(decoded, np.asarray(values, dtype=np.float32).astype(np.float64))


@pytest.mark.timeout(30)
@given(register, register)
def test_any_non_nan_register_pair_round_trips(hi: int, lo: int) -> None:
    x = regs_to_float32([hi, lo])
    if math.isnan(x):
        return
    assert float32_to_regs(x, allow_nonfinite=True) == [hi, lo]


@pytest.mark.timeout(30)
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nonfinite_floats_are_refused_unless_allowed(bad: float) -> None:
    with pytest.raises(ValueError, match="value 1 is not finite"):
        floats_to_regs([1.0, bad])
    regs = floats_to_regs([1.0, bad], allow_nonfinite=True)
    decoded = regs_to_floats(regs)
    assert decoded[0] == 1.0
    assert (math.isnan(decoded[1]) and math.isnan(bad)) or decoded[1] == bad


@pytest.mark.timeout(30)
def test_out_of_float32_range_is_refused_not_turned_into_inf() -> None:
    for allow in (False, True):
        with pytest.raises(ValueError, match="float32 range"):
            floats_to_regs([1e39], allow_nonfinite=allow)


@pytest.mark.timeout(30)
def test_bad_register_lists_are_refused() -> None:
    with pytest.raises(ValueError, match="even number"):
        regs_to_floats([1, 2, 3])
    with pytest.raises(ValueError, match="0..65535"):
        regs_to_floats([0x1_0000, 0])
    with pytest.raises(ValueError, match="expected 2 registers"):
        regs_to_float32([1])


# ------------------------------------------------------------------------------------------------ INT32
@pytest.mark.timeout(30)
@given(st.integers(-(2**31), 2**31 - 1))
def test_int32_round_trip(n: int) -> None:
    regs = int32_to_regs(n)
    assert regs_to_int32(regs) == n
    assert regs == ModbusTcpClient.convert_to_registers(n, I32)


@pytest.mark.timeout(30)
@given(st.one_of(st.integers(max_value=-(2**31) - 1), st.integers(min_value=2**31)))
def test_int32_out_of_range_is_refused(n: int) -> None:
    with pytest.raises(ValueError, match="does not fit INT32"):
        int32_to_regs(n)


@pytest.mark.timeout(30)
@given(st.integers(-(2**31), 2**31 - 1), st.integers(0, 2**20))
def test_wrapping_counter_delta(start: int, steps: int) -> None:
    end = wrap_int32(start + steps)
    assert -(2**31) <= end < 2**31
    assert counter_delta(end, start) == steps


@pytest.mark.timeout(30)
def test_int32_refuses_non_integers() -> None:
    for bad in (1.5, True, "3"):
        with pytest.raises(ValueError):
            int32_to_regs(bad)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------ strings
@pytest.mark.timeout(30)
@given(st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=127), max_size=20))
def test_ascii_string_round_trip(text: str) -> None:
    regs = string_to_regs(text, 10)
    assert len(regs) == 10
    assert regs_to_string(regs) == text


@pytest.mark.timeout(30)
def test_string_layout_and_errors() -> None:
    assert string_to_regs("TM5", 2) == [0x544D, 0x3500]  # high byte first, NUL-terminated
    assert regs_to_string([0x544D, 0x3500, 0x4142]) == "TM5"  # stops at the NUL
    with pytest.raises(ValueError, match="not ASCII"):
        string_to_regs("µ", 2)
    with pytest.raises(ValueError, match="only 4 available"):
        string_to_regs("TM5-700", 2)


# ------------------------------------------------------------------------------------------------ poses
angle = st.floats(-math.pi + 1e-3, math.pi - 1e-3)


@pytest.mark.timeout(30)
@given(angle, st.floats(-1.5, 1.5), angle)
def test_rpy_round_trip_and_fixed_axis_convention(rx: float, ry: float, rz: float) -> None:
    rot = rpy_to_matrix(rx, ry, rz)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    expected = (np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
                @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]))
    np.testing.assert_allclose(rot, expected, atol=1e-12)
    np.testing.assert_allclose(matrix_to_rpy(rot), (rx, ry, rz), atol=1e-9)


@pytest.mark.timeout(30)
def test_pose_registers_are_mm_and_degrees() -> None:
    pos = np.array([0.4, -0.12, 0.3])
    rot = rpy_to_matrix(math.radians(180.0), 0.0, math.radians(90.0))
    regs = pose_to_regs(pos, rot)
    values = ModbusTcpClient.convert_from_registers(regs, F32)
    assert isinstance(values, list)
    np.testing.assert_allclose(values[:3], [400.0, -120.0, 300.0], atol=1e-4)
    np.testing.assert_allclose(np.abs(values[3]), 180.0, atol=1e-4)
    np.testing.assert_allclose(values[4:], [0.0, 90.0], atol=1e-4)
    back_pos, back_rot = regs_to_pose(regs)
    np.testing.assert_allclose(back_pos, pos, atol=1e-7)
    np.testing.assert_allclose(back_rot, rot, atol=1e-6)


# ------------------------------------------------------------------------------------------------ layout
@pytest.mark.timeout(30)
def test_default_layout_is_valid_and_compact() -> None:
    layout = UserAreaLayout()
    layout.validate(WHERE)
    assert layout.robot_block == (9000, 32)
    assert layout.host_block == (9100, 17)
    assert UserAreaLayout.from_dict({}, WHERE) == layout
    assert UserAreaLayout.from_dict(None, WHERE) == layout


@pytest.mark.timeout(30)
def test_layout_out_of_range_names_the_field() -> None:
    with pytest.raises(ConfigError) as exc:
        UserAreaLayout.from_dict({"torque": 8000}, WHERE)
    assert str(exc.value) == f"{WHERE}.torque must lie in 9000-9999, got 8000"


@pytest.mark.timeout(30)
@given(st.sampled_from(FIELDS), st.one_of(st.integers(0, 8999), st.integers(10_000, 70_000)))
def test_any_field_outside_the_user_area_is_named(name: str, address: int) -> None:
    with pytest.raises(ConfigError, match=rf"^{WHERE}\.{name} must lie in 9000-9999, got {address}"):
        UserAreaLayout.from_dict({name: address}, WHERE)


@pytest.mark.timeout(30)
def test_multi_register_field_must_fit_entirely() -> None:
    with pytest.raises(ConfigError, match=r"\.targets must lie in 9000-9999, got 9990 \(it needs 12 registers"):
        UserAreaLayout.from_dict({"targets": 9990}, WHERE)


@pytest.mark.timeout(30)
def test_overlapping_fields_are_named() -> None:
    with pytest.raises(ConfigError, match=r"user_area\.speed \(9010-9021\) overlaps .*user_area\.torque"):
        UserAreaLayout.from_dict({"speed": 9010}, WHERE)


@pytest.mark.timeout(30)
@settings(max_examples=200)
@given(st.dictionaries(st.sampled_from(FIELDS), st.integers(9000, 9999 - 11), min_size=1, max_size=len(FIELDS)))
def test_random_layouts_are_valid_or_name_a_field(d: dict[str, int]) -> None:
    try:
        layout = UserAreaLayout.from_dict(d, WHERE)
    except ConfigError as exc:
        assert any(f"{WHERE}.{name}" in str(exc) for name in FIELDS) or str(exc).startswith(f"{WHERE}:")
        return
    extents = sorted(layout.extent(n) for n in FIELDS)
    assert all(a[1] < b[0] for a, b in zip(extents, extents[1:], strict=False))  # valid means disjoint
    assert all(a >= 9000 and b <= 9999 for a, b in extents)


@pytest.mark.timeout(30)
def test_host_field_inside_robot_block_is_refused() -> None:
    # command alone fits in the gap between torque and speed... but that gap is inside the robot block
    with pytest.raises(ConfigError, match=r"\.command \(9020-9020\) lies inside the robot->host block"):
        UserAreaLayout.from_dict({"speed": 9021, "robot_status": 9033, "host_seq_echo": 9034, "lease_holder": 9036,
                                  "lease_age_ms": 9038, "command": 9020}, WHERE)


@pytest.mark.timeout(30)
def test_layout_rejects_unknown_keys_and_non_integers() -> None:
    with pytest.raises(ConfigError, match=rf"^{WHERE}: unknown key 'torqe'"):
        UserAreaLayout.from_dict({"torqe": 9002}, WHERE)
    with pytest.raises(ConfigError, match=rf"^{WHERE}\.speed must be an integer, got '9014'"):
        UserAreaLayout.from_dict({"speed": "9014"}, WHERE)
    with pytest.raises(ConfigError, match=rf"^{WHERE}\.speed must be an integer, got True"):
        UserAreaLayout.from_dict({"speed": True}, WHERE)
    with pytest.raises(ConfigError, match="must be a mapping"):
        UserAreaLayout.from_dict([9000], WHERE)


@pytest.mark.timeout(30)
def test_doc_register_table_matches_layout_defaults() -> None:
    """docs/robot-side-program.md and UserAreaLayout() must describe the same contract."""
    text = DOC.read_text()
    assert "UNTESTED ON HARDWARE" in text.split("\n\n")[0] + text.split("\n\n")[1]
    for name, first, last, direction in UserAreaLayout().as_table():
        cells = f"| {first}-{last} |" if last > first else f"| {first} |"
        rows = [line for line in text.splitlines() if line.startswith(cells)]
        assert rows, f"no table row starting {cells} for {name}"
        assert f"`{name}`" in rows[0] and direction in rows[0], rows[0]
        assert FIELD_WIDTH[name] == last - first + 1


# ------------------------------------------------------------------------------------------------ config
@pytest.mark.timeout(30)
def test_config_defaults_and_nested_layout() -> None:
    cfg = TM5ModbusConfig.from_dict({"host": "192.168.50.49", "user_area": {"command": 9200}}, "cell.yaml:")
    assert (cfg.port, cfg.unit_id, cfg.timeout_s, cfg.stale_after_s, cfg.stop_coil) == (502, 1, 0.01, 0.05, False)
    assert cfg.user_area.command == 9200 and cfg.user_area.targets == 9102


@pytest.mark.timeout(30)
@pytest.mark.parametrize(("settings_", "message"), [
    ({}, "config/cell.yaml: devices.arm.host is required"),
    ({"host": ""}, "config/cell.yaml: devices.arm.host must be the controller's address"),
    ({"host": "h", "port": 70000}, "config/cell.yaml: devices.arm.port must lie in 1-65535, got 70000"),
    ({"host": "h", "port": "502"}, "config/cell.yaml: devices.arm.port must be an integer"),
    ({"host": "h", "unit_id": 256}, "config/cell.yaml: devices.arm.unit_id must lie in 0-255, got 256"),
    ({"host": "h", "timeout_s": 0}, "config/cell.yaml: devices.arm.timeout_s must lie in 0.001-1 s"),
    ({"host": "h", "timeout_s": 5}, "config/cell.yaml: devices.arm.timeout_s must lie in 0.001-1 s"),
    ({"host": "h", "stale_after_s": "x"}, "config/cell.yaml: devices.arm.stale_after_s must be a number"),
    ({"host": "h", "stale_after_s": 100}, "config/cell.yaml: devices.arm.stale_after_s must lie in 0.001-1 s"),
    ({"host": "h", "stale_after_s": float("nan")}, "config/cell.yaml: devices.arm.stale_after_s must be finite"),
    ({"host": "h", "reconnect_initial_s": -1}, "config/cell.yaml: devices.arm.reconnect_initial_s must lie in"),
    ({"host": "h", "reconnect_max_s": 60}, "config/cell.yaml: devices.arm.reconnect_max_s must lie in 0.001-10 s"),
    ({"host": "h", "reconnect_initial_s": 1.0, "reconnect_max_s": 0.5},
     "config/cell.yaml: devices.arm.reconnect_max_s must be >= reconnect_initial_s"),
    ({"host": "h", "arm_timeout_s": 0.001}, "config/cell.yaml: devices.arm.arm_timeout_s must lie in 0.01-10 s"),
    ({"host": "h", "arm_timeout_s": 3600}, "config/cell.yaml: devices.arm.arm_timeout_s must lie in 0.01-10 s"),
    ({"host": "h", "stop_coil": "yes"}, "config/cell.yaml: devices.arm.stop_coil must be true or false"),
    ({"host": "h", "unit": 1}, "config/cell.yaml: devices.arm: unknown key 'unit'"),
    ({"host": "h", "user_area": [9000]}, "config/cell.yaml: devices.arm.user_area must be a mapping"),
    ({"host": "h", "user_area": {"command": 8000}},
     "config/cell.yaml: devices.arm.user_area.command must lie in 9000-9999, got 8000"),
])
def test_config_errors_name_the_field(settings_: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        TM5ModbusConfig.from_dict(settings_, "config/cell.yaml: devices.arm")
    assert str(exc.value).startswith(message), str(exc.value)


@pytest.mark.timeout(30)
def test_stale_limit_is_a_few_control_periods_at_least() -> None:
    cfg = TM5ModbusConfig.from_dict({"host": "h", "stale_after_s": 0.02}, "cell.yaml: devices.arm")
    cfg.check_period(0.004, "cell.yaml: devices.arm")  # 5 periods: fine
    with pytest.raises(ConfigError, match=r"^cell.yaml: devices.arm.stale_after_s must be >= 3 control periods "
                                          r"\(0.024 s at 0.008 s\), got 0.02$"):
        cfg.check_period(0.008, "cell.yaml: devices.arm")


@pytest.mark.timeout(30)
def test_config_errors_are_one_line() -> None:
    for settings_ in ({"host": "h", "timeout_s": "1\n2"}, {"host": "h", "unit\n": 1}, {"host": ["a\nb"]}):
        with pytest.raises(ConfigError) as exc:
            TM5ModbusConfig.from_dict(settings_, "cell.yaml: devices.arm")
        assert "\n" not in str(exc.value)


@pytest.mark.timeout(30)
def test_open_drivers_lays_fixed_settings_over_the_config_and_floors_the_timeouts() -> None:
    from drivers.real_cell import open_drivers
    from tests.tm5_fixtures import LIMITS

    where = "cell.yaml: devices"
    drivers = open_drivers({"timeout_s": 0.01, "stale_after_s": 0.2}, {"timeout_s": 0.005}, LIMITS, 0.008, where,
                           arm_fixed={"host": "127.0.0.1", "port": 1502}, sensor_fixed={"port": "/dev/null"},
                           min_timeout_s=0.05, min_stale_s=0.1)
    arm = drivers.arm.config
    assert isinstance(arm, TM5ModbusConfig)
    assert (arm.host, arm.port, arm.timeout_s, arm.stale_after_s) == ("127.0.0.1", 1502, 0.05, 0.2)
    assert drivers.sensor_cfg is not None and drivers.sensor_cfg.timeout_s == 0.05
    assert open_drivers({"host": "h"}, None, LIMITS, 0.008, where).sensor is None
    with pytest.raises(ConfigError, match=r"^cell.yaml: devices.arm.settings.stale_after_s must be a number"):
        open_drivers({"host": "h", "stale_after_s": "x"}, None, LIMITS, 0.008, where, min_stale_s=0.1)
    with pytest.raises(ConfigError, match=r"^cell.yaml: devices.arm.settings.stale_after_s must be >= 3 control"):
        open_drivers({"host": "h", "stale_after_s": 0.02}, None, LIMITS, 0.008, where)
