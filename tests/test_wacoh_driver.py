"""The real `WacohSensor` against the WACOH emulator: its settings, the emulator's command set, connect, `p`."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import ConfigError, ProtocolError
from drivers.wacoh.codec import (
    SENSITIVITY_TOLERANCE,
    SHEET_TOLERANCE,
    Sensitivities,
    decode_counts,
    parse_sensitivities,
)
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor
from drivers.wacoh.sensitivity import P_ATTEMPTS
from sim.wacoh_emulator import REAL_UNIT_SENSITIVITIES, FaultConfig, draw_bit_flips, flip_bits
from tests.test_wacoh_codec import REAL_LINE, corruptions
from tests.wacoh_fixtures import FALLBACK, NOMINAL, SLACK_TIMEOUT_S, EmulatorFactory, Source, connect

pytestmark = pytest.mark.timeout(25)


# ------------------------------------------------------------------------------------ config
def test_config_defaults() -> None:
    cfg = WacohConfig.from_dict({"port": "/dev/ttyUSB0"}, "config/cell.yaml: devices.sensor")
    assert (cfg.baudrate, cfg.timeout_s, cfg.tare, cfg.tare_samples, cfg.filter, cfg.mode) == (
        921600, 0.05, "software", 50, None, "poll"
    )
    assert cfg.sensitivities is None  # no calibration sheet: `p` is checked against the band only ...
    assert cfg.fallback_sensitivities.values == (32.8, 32.8, 32.8, 1638.0, 1638.0, 1638.0)  # ... else nominal
    assert WacohConfig.from_dict({"port": "p", "sensitivities": None}, "x").sensitivities is None


def test_config_accepts_every_field() -> None:
    cfg = WacohConfig.from_dict(
        {"port": "/dev/ttyUSB1", "baudrate": 115200, "timeout_s": 0.1, "tare": "sensor", "tare_samples": 10,
         "filter": 4, "mode": "stream", "sensitivities": [32.8, 32.815, 32.835, 1653.801, 1634.816, 1636.136],
         "max_consecutive_failures": 3},
        "x",
    )
    assert cfg.filter == 4 and cfg.mode == "stream" and cfg.sensitivities == REAL_UNIT_SENSITIVITIES
    assert cfg.fallback_sensitivities == REAL_UNIT_SENSITIVITIES  # the sheet


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"baudrate": "fast"}, "config/cell.yaml: devices.sensor.baudrate must be an integer, got 'fast'"),
        ({"baudrate": 0}, "devices.sensor.baudrate must be an integer from 9600 to 3000000, got 0"),
        ({"timeout_s": -1}, "devices.sensor.timeout_s must be a number from 0.001 to 1 s, got -1"),
        ({"timeout_s": True}, "devices.sensor.timeout_s must be a number, got True"),
        ({"filter": 3}, "devices.sensor.filter must be one of [1, 2, 4, 8], got 3"),
        ({"filter": True}, "devices.sensor.filter must be an integer, got True"),
        ({"mode": "push"}, "devices.sensor.mode must be one of ['poll', 'stream'], got 'push'"),
        ({"tare": "hardware"}, "devices.sensor.tare must be one of ['sensor', 'software'], got 'hardware'"),
        ({"tare_samples": 2.5}, "devices.sensor.tare_samples must be an integer, got 2.5"),
        ({"sensitivities": [32.8] * 5}, "devices.sensor.sensitivities must be a list of 6 numbers"),
        ({"sensitivities": [32.8] * 3 + [1638.0] * 2 + [0.0]}, "devices.sensor.sensitivities[5] (Mz, against "
                                                             "nominal_sensitivities) must be within 1.5% of 1638"),
        ({"sensitivities": "32.8"}, "devices.sensor.sensitivities must be a list of 6 numbers"),
        ({"port": ""}, "devices.sensor.port must be a non-empty string"),
        ({"sensitivity_tolerance": 1.5}, "devices.sensor.sensitivity_tolerance must be a number from 0.001 to 0.05"),
        ({"nominal_sensitivities": [32.8] * 3}, "devices.sensor.nominal_sensitivities must be a list of 6"),
        ({"bauds": 9600}, "config/cell.yaml: devices.sensor: unknown key 'bauds'"),
    ],
)
def test_config_errors_name_the_field(settings: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        WacohConfig.from_dict({"port": "/dev/ttyUSB0", **settings}, "config/cell.yaml: devices.sensor")
    assert message in str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"timeout_s": 1e9}, "timeout_s must be a number from 0.001 to 1 s, got 1000000000.0"),
        ({"timeout_s": 0.0005}, "timeout_s must be a number from 0.001 to 1 s, got 0.0005"),
        ({"timeout_s": float("nan")}, "timeout_s must be finite, got nan"),
        ({"sensitivities": [1e9] * 6}, "sensitivities[0] (Fx, against nominal_sensitivities) must be within 1.5% "
                                       "of 32.8, got 1000000000.0"),
        ({"sensitivities": [32.8, 32.8, 32.8, 1638.0, 1638.0, 1700.0]}, "sensitivities[5] (Mz, against"),
        ({"sensitivity_tolerance": 0.99}, "sensitivity_tolerance must be a number from 0.001 to 0.05, got 0.99"),
        ({"sensitivity_tolerance": 0.0}, "sensitivity_tolerance must be a number from 0.001 to 0.05, got 0.0"),
        ({"max_consecutive_failures": 10**9}, "max_consecutive_failures must be an integer from 1 to 100"),
        ({"max_consecutive_failures": 1e9}, "max_consecutive_failures must be an integer, got 1000000000.0"),
        ({"max_consecutive_failures": 0}, "max_consecutive_failures must be an integer from 1 to 100, got 0"),
        ({"baudrate": 10**9}, "baudrate must be an integer from 9600 to 3000000"),
        ({"tare_samples": 10**9}, "tare_samples must be an integer from 1 to 10000"),
        ({"nominal_sensitivities": [40.0, 32.8, 32.8, 1638.0, 1638.0, 1638.0]},
         "nominal_sensitivities[0] (Fx, against the model's nominal) must be within 10% of 32.8, got 40.0"),
    ],
)
def test_every_setting_is_bounded(settings: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        WacohConfig.from_dict({"port": "/dev/ttyUSB0", **settings}, "cell.yaml: devices.sensor")
    assert str(err.value).startswith("cell.yaml: devices.sensor.") and message in str(err.value)
    assert "\n" not in str(err.value)


def test_bounds_hold_for_a_config_built_in_code() -> None:
    with pytest.raises(ConfigError, match=r"^WacohConfig.timeout_s must be a number from 0.001 to 1 s"):
        WacohSensor(WacohConfig(port="/dev/ttyUSB0", timeout_s=1e9))
    with pytest.raises(ConfigError, match=r"^WacohConfig.sensitivities\[3\] \(Mx"):
        WacohSensor(WacohConfig(port="/dev/ttyUSB0", sensitivities=Sensitivities(moment=(1e9, 1638.0, 1638.0))))


def test_a_unit_off_nominal_is_configured_through_nominal_sensitivities() -> None:
    sheet = [33.6, 33.5, 33.7, 1690.0, 1685.0, 1688.0]  # 2-3 % above the model: outside the default band
    with pytest.raises(ConfigError, match="sensitivities"):
        WacohConfig.from_dict({"port": "p", "sensitivities": sheet}, "x")
    cfg = WacohConfig.from_dict({"port": "p", "sensitivities": sheet, "nominal_sensitivities": sheet}, "x")
    assert cfg.sensitivities is not None
    assert cfg.sensitivities.values == tuple(sheet) == cfg.nominal_sensitivities.values


def test_config_requires_the_port() -> None:
    with pytest.raises(ConfigError, match=r"^cell.yaml: devices.sensor.port is required$"):
        WacohConfig.from_dict({}, "cell.yaml: devices.sensor")


# ------------------------------------------------------------------------------------ emulator, raw bytes
def test_emulator_answers_the_command_set_byte_exactly(make_emulator: EmulatorFactory) -> None:
    emulator = make_emulator(Source(np.array([0, 0, 10.0, 0, 0, 0])), offset_lsb=np.zeros(6), noise=0.0)
    with serial.Serial(emulator.tty_path, 921600, timeout=0.5) as port:
        port.write(b"p")
        assert port.read_until(b"\n") == b"32.800,32.815,32.835,1653.801,1634.816,1636.136\r\n"
        port.write(b"R")
        record = port.read(27)
        assert record == b"0200020002148200020002000\r\n"  # Fz = +10 N at 32.835 LSB/N -> 8192 + 328
        port.write(b"R")
        assert port.read(27)[0:1] == b"1"  # the record number wraps 0-9
        port.write(b"T")
        assert port.read_until(b"\n") == b"0190\r\n"  # 25 degC * 16
        port.write(b"0F")
        assert port.read_until(b"\n") == b"1\r\n"
        port.write(b"8F0F")
        assert port.read_until(b"\n") == b"8\r\n"
        port.write(b"V")
        assert port.read_until(b"\n").endswith(b"\r\n")
        port.write(b"S")
        streamed = port.read(27 * 20)
        port.write(b"E")
        time.sleep(0.02)
        port.reset_input_buffer()
        assert not emulator.streaming
        assert len(streamed) == 27 * 20
        for i in range(20):
            decode_counts(streamed[27 * i : 27 * (i + 1)])


# ------------------------------------------------------------------------------------ connect
@pytest.mark.parametrize("sheet", [None, REAL_UNIT_SENSITIVITIES])
def test_connect_reads_sensitivities_with_p(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], sheet: Sensitivities | None
) -> None:
    emulator = make_emulator(Source())
    sensor = connect(sensors, emulator, sensitivities=sheet and list(sheet.values))
    assert sensor.sensitivities_source == "sensor"
    assert sensor.sensitivities == REAL_UNIT_SENSITIVITIES
    assert emulator.commands.get("p") == 2  # two agreeing replies
    assert emulator.commands.get("E", 0) >= 1  # streaming stopped before anything else


def test_a_p_reply_off_the_calibration_sheet_is_refused_and_the_sheet_used(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], caplog: pytest.LogCaptureFixture
) -> None:
    """FALLBACK is another unit's sheet (or a typo): the sensor's true values are 0.2-1.8 % off it."""
    emulator = make_emulator(Source())
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    sensor = connect(sensors, emulator, sensitivities=list(FALLBACK.values), timeout_s=SLACK_TIMEOUT_S)
    assert (sensor.sensitivities, sensor.sensitivities_source) == (FALLBACK, "config")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "Fx = 32.8 LSB/N is not within 0.1% of the calibration sheet's 32.5" in warnings[0]


def test_a_p_reply_within_the_sheets_tolerance_is_believed() -> None:
    """The sheet may be printed with fewer decimals than the reply: that stays well within 0.1 %."""
    rounded = Sensitivities(force=(32.8, 32.82, 32.84), moment=(1653.8, 1634.8, 1636.1))
    sensor, _ = scripted_sensor([REAL_LINE, REAL_LINE], sheet=rounded)
    assert sensor._request_sensitivities() == (REAL_UNIT_SENSITIVITIES, "sensor")


def test_connect_falls_back_when_p_is_never_answered(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], caplog: pytest.LogCaptureFixture
) -> None:
    emulator = make_emulator(Source(), faults=FaultConfig(ignore_p=True))
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    sensor = connect(sensors, emulator, sensitivities=list(FALLBACK.values), timeout_s=0.05)
    # A bounded number of asks, each bounded by timeout_s: connect cannot hang on a silent `p`.
    assert 1 <= emulator.commands.get("p", 0) <= P_ATTEMPTS
    assert sensor.sensitivities_source == "config"
    assert sensor.sensitivities == FALLBACK
    assert any("no reply to 'p'" in r.getMessage() for r in caplog.records)
    assert sensor.read().valid  # the link itself is fine


def test_connect_survives_streaming_left_on_by_an_earlier_session(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source())
    with serial.Serial(emulator.tty_path, 921600) as port:
        port.write(b"S")  # ... and the session ends without `E`
    time.sleep(0.03)
    sensor = connect(sensors, emulator, timeout_s=SLACK_TIMEOUT_S)
    assert sensor.sensitivities_source == "sensor"
    assert not emulator.streaming
    assert all(sensor.read().valid for _ in range(20))


def test_filter_setting_is_sent(make_emulator: EmulatorFactory, sensors: list[WacohSensor]) -> None:
    emulator = make_emulator(Source())
    connect(sensors, emulator, filter=4)
    time.sleep(0.02)
    assert emulator.filter_n == 4 and emulator.commands.get("4F") == 1


def test_connect_under_line_faults_gets_either_the_true_or_the_configured_sensitivities(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    sources = []
    for seed in range(8):
        emulator = make_emulator(Source(), seed=seed, faults=FaultConfig(garbage_prob=0.5, split_prob=0.5))
        sensor = connect(sensors, emulator)
        expected = REAL_UNIT_SENSITIVITIES if sensor.sensitivities_source == "sensor" else NOMINAL
        assert sensor.sensitivities == expected  # never a half-parsed mixture
        sources.append(sensor.sensitivities_source)
    assert sources.count("sensor") >= 6  # a garbled reply is asked again (2 clean of 6 needed: 0.89 each)


class ScriptedPort:
    """A stand-in for the serial port that answers each `p` with the next scripted reply."""

    timeout: float | None = None

    def __init__(self, replies: list[bytes]) -> None:
        self.replies = list(replies)
        self.buffer = bytearray()
        self.asked = 0

    def reset_input_buffer(self) -> None:
        self.buffer.clear()

    def write(self, data: bytes) -> int:
        if data == b"p" and self.replies:
            self.asked += 1
            self.buffer += self.replies.pop(0)
        return len(data)

    def read(self, size: int) -> bytes:
        out = bytes(self.buffer[:size])
        del self.buffer[:size]
        return out


def scripted_sensor(replies: list[bytes], sheet: Sensitivities | None = None) -> tuple[WacohSensor, ScriptedPort]:
    """A sensor whose `p` replies are scripted; without a `sheet` it falls back to NOMINAL."""
    sensor = WacohSensor(WacohConfig(port="scripted", sensitivities=sheet, timeout_s=0.002))
    sensor.p_timeout_s = 0.002  # a scripted reply is there at once: a reply cut before its LF need not wait long
    port = ScriptedPort(replies)
    sensor._link.ser = port
    return sensor, port


@settings(max_examples=300, deadline=500)
@given(st.lists(st.one_of(st.just(REAL_LINE), corruptions), min_size=6, max_size=6))
def test_corrupted_p_replies_give_the_exact_sensitivities_or_the_fallback_never_a_wrong_value(
    replies: list[bytes],
) -> None:
    """The real driver's `p` exchange, each reply clean or corrupted (bit flips, truncation, inserted
    bytes): it ends with the sensor's exact sensitivities or, having refused the replies, the
    configured ones; never a wrong value, never another exception.  (Two replies hit by the very same
    corruption are left out: no check could tell them from the truth; see the repeated corruption below.)"""
    replies = [r for i, r in enumerate(replies) if r == REAL_LINE or r not in replies[:i]]
    replies = [r if r.endswith(b"\n") else r + b"\n" for r in replies]  # every scripted reply is a line
    sensor, port = scripted_sensor(replies)
    try:
        sens, source = sensor._request_sensitivities()
    except ProtocolError as exc:  # the driver's own error is allowed, as one line
        assert "\n" not in str(exc)
        return
    if source == "sensor":
        assert sens == REAL_UNIT_SENSITIVITIES
    else:
        assert sens == NOMINAL
    if replies[:2] == [REAL_LINE, REAL_LINE] or replies[:6].count(REAL_LINE) >= 2 and all(
            _refused(r) for r in replies[:6] if r != REAL_LINE):
        assert source == "sensor"  # two clean replies and nothing else plausible: believed


def _refused(line: bytes) -> bool:
    try:
        parse_sensitivities(line, Sensitivities(), SENSITIVITY_TOLERANCE)
    except ProtocolError:
        return True
    return False


# "Wrong": more than 0.1 % off the true value (about 3 LSB at full scale).  A flip in the last printed
# digit (32.835 -> 32.834, 1653.801 -> 1653.809) is at most 0.03 %: below that and harmless.
WRONG = 0.001


def _fuzz_p_exchanges(sheet: Sensitivities | None) -> tuple[int, int, int, float]:
    """1000 `p` exchanges in which every reply is corrupted by the emulator's bit flips: even trials a fresh
    corruption per reply, odd ones a single corruption repeated in every reply (which makes "two replies
    agree").  Returns (accepted, wrong accepted, wrong accepted from repeated corruptions, worst error)."""
    rng = np.random.default_rng(20240611)
    truth = REAL_UNIT_SENSITIVITIES.as_array()
    accepted, wrong, wrong_repeated, worst = 0, 0, 0, 0.0
    for trial in range(1000):
        repeated = trial % 2 == 1
        flips = draw_bit_flips(len(REAL_LINE), rng)
        replies = [flip_bits(REAL_LINE, flips if repeated else draw_bit_flips(len(REAL_LINE), rng))
                   for _ in range(6)]
        assert REAL_LINE not in replies
        sensor, _ = scripted_sensor(replies, sheet=sheet)
        sens, source = sensor._request_sensitivities()
        if source == "config":
            assert sens == (sheet or NOMINAL)
            continue
        accepted += 1
        error = float(np.max(np.abs(sens.as_array() / truth - 1.0)))
        worst = max(worst, error)
        wrong += error > WRONG
        wrong_repeated += error > WRONG and repeated
    return accepted, wrong, wrong_repeated, worst


def test_with_the_calibration_sheet_no_corrupted_p_reply_gives_a_wrong_scale() -> None:
    """The emulated cell's configuration carries the unit's sheet.  A reply is believed only within 0.1 % of
    it: 0 of 1000 corrupted exchanges end with a wrong scale (the band alone let 13 through, up to 1.22 %
    off, every one a repeated corruption); the few believed are at most 0.06 % off (digits after the point)."""
    accepted, wrong, _, worst = _fuzz_p_exchanges(REAL_UNIT_SENSITIVITIES)
    assert wrong == 0
    assert worst <= SHEET_TOLERANCE
    assert accepted < 50


def test_without_a_sheet_only_a_repeated_corruption_can_give_a_wrong_scale() -> None:
    """No check on the replies tells a corruption repeated identically in every reply, changing a digit
    within the band, from a unit that really reports those values: asking more often or voting only
    gathers more copies of it.  Fresh corruptions never agree, so none of them is believed wrong; a
    repeated one may be, bounded by the band plus the real unit's own 0.97 % from nominal."""
    _, wrong, wrong_repeated, worst = _fuzz_p_exchanges(None)
    own_offset = float(np.max(np.abs(REAL_UNIT_SENSITIVITIES.as_array() / NOMINAL.as_array() - 1.0)))
    assert wrong == wrong_repeated  # 0 of the 500 fresh corruptions
    assert wrong_repeated < 25  # 13 of the 500 repeated ones with this seed
    assert worst <= SENSITIVITY_TOLERANCE + own_offset


def test_the_default_cell_config_carries_the_emulated_units_sheet() -> None:
    """The emulated cell passes devices.sensor.settings to the driver: its `p` is checked against the sheet."""
    from cell.config import load_config

    settings = load_config().devices.sensor.settings
    cfg = WacohConfig.from_dict({**settings, "port": "emulated"}, "config/cell.yaml: devices.sensor.settings")
    assert cfg.sensitivities == REAL_UNIT_SENSITIVITIES


@pytest.mark.parametrize("sheet", [None, REAL_UNIT_SENSITIVITIES])
def test_a_repeated_p_corruption_from_the_emulator_is_refused_or_harmless(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], sheet: Sensitivities | None
) -> None:
    for seed in range(4):
        emulator = make_emulator(Source(), seed=seed, faults=FaultConfig(corrupt_p_prob=1.0, corrupt_p_repeat=True))
        sensor = connect(sensors, emulator, sensitivities=sheet and list(sheet.values), timeout_s=SLACK_TIMEOUT_S)
        assert emulator.p_corrupted == emulator.commands["p"] >= 1
        if sensor.sensitivities_source == "config":
            assert sensor.sensitivities == (sheet or NOMINAL)
        elif sheet is not None:
            assert np.all(np.abs(sensor.sensitivities.as_array() / sheet.as_array() - 1.0) <= WRONG)
        else:
            off = np.abs(sensor.sensitivities.as_array() / NOMINAL.as_array() - 1.0)
            assert np.all(off <= SENSITIVITY_TOLERANCE)
        assert sensor.read().valid  # records are not corrupted by this fault


@pytest.mark.parametrize("name", ["garbage_prob", "split_prob", "drop_crlf_prob", "drop_reply_prob",
                                  "reply_delay_prob", "corrupt_p_prob"])
@pytest.mark.parametrize("value", [1.5, -0.1, float("nan"), "0.5", True])
def test_the_emulator_refuses_a_fault_probability_outside_0_1(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf"^FaultConfig.{name} must be a probability from 0 to 1, got ") as err:
        FaultConfig(**{name: value})  # type: ignore[arg-type]
    assert "\n" not in str(err.value)
    faults = FaultConfig()
    with pytest.raises(ValueError, match=rf"^FaultConfig.{name} must be a probability"):
        setattr(faults, name, value)  # a fault command after construction is checked too
    assert getattr(faults, name) == FaultConfig().__dict__[name]


@pytest.mark.parametrize("byte", [0x1C, 0x1D, 0x1E, 0x1F])
def test_a_control_byte_in_every_p_reply_falls_back_with_a_warning(
    byte: int, caplog: pytest.LogCaptureFixture
) -> None:
    """One flipped bit turns CR into 0x1D: that raised an uncaught ValueError at connect."""
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    sensor, port = scripted_sensor([REAL_LINE[:-2] + bytes([byte]) + b"\n"] * 6)
    assert sensor._request_sensitivities() == (NOMINAL, "config")
    assert port.asked == 6
    warning = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "not one line ending in CR LF" in warning[0] and "\n" not in warning[0]


def test_an_implausible_p_reply_is_refused_naming_the_axis(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    lost_dot = b"32.800,32.815,32.835,1653.801,1634816,1636.136\r\n"
    sensor, _ = scripted_sensor([lost_dot] * 6)
    assert sensor._request_sensitivities() == (NOMINAL, "config")
    assert any("My = 1.63482e+06" in r.getMessage() for r in caplog.records)
    # One bad reply among good ones costs nothing but a request.
    sensor, port = scripted_sensor([lost_dot, REAL_LINE, REAL_LINE])
    assert sensor._request_sensitivities() == (REAL_UNIT_SENSITIVITIES, "sensor")
    assert port.asked == 3
