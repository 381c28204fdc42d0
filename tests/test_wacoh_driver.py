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
from drivers.wacoh.codec import decode_counts
from drivers.wacoh.config import WacohConfig
from drivers.wacoh.driver import WacohSensor
from sim.wacoh_emulator import REAL_UNIT_SENSITIVITIES, FaultConfig
from tests.test_wacoh_codec import REAL_LINE, corruptions
from tests.wacoh_fixtures import FALLBACK, SLACK_TIMEOUT_S, EmulatorFactory, Source, connect

pytestmark = pytest.mark.timeout(25)


# ------------------------------------------------------------------------------------ config
def test_config_defaults() -> None:
    cfg = WacohConfig.from_dict({"port": "/dev/ttyUSB0"}, "config/cell.yaml: devices.sensor")
    assert (cfg.baudrate, cfg.timeout_s, cfg.tare, cfg.tare_samples, cfg.filter, cfg.mode) == (
        921600, 0.05, "software", 50, None, "poll"
    )
    assert cfg.sensitivities.values == (32.8, 32.8, 32.8, 1638.0, 1638.0, 1638.0)


def test_config_accepts_every_field() -> None:
    cfg = WacohConfig.from_dict(
        {"port": "/dev/ttyUSB1", "baudrate": 115200, "timeout_s": 0.1, "tare": "sensor", "tare_samples": 10,
         "filter": 4, "mode": "stream", "sensitivities": [32.8, 32.815, 32.835, 1653.801, 1634.816, 1636.136],
         "max_consecutive_failures": 3},
        "x",
    )
    assert cfg.filter == 4 and cfg.mode == "stream" and cfg.sensitivities.moment[0] == 1653.801


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"baudrate": "fast"}, "config/cell.yaml: devices.sensor.baudrate must be a positive integer, got 'fast'"),
        ({"baudrate": 0}, "devices.sensor.baudrate must be a positive integer, got 0"),
        ({"timeout_s": -1}, "devices.sensor.timeout_s must be a positive number, got -1"),
        ({"timeout_s": True}, "devices.sensor.timeout_s must be a positive number, got True"),
        ({"filter": 3}, "devices.sensor.filter must be one of [1, 2, 4, 8], got 3"),
        ({"mode": "push"}, "devices.sensor.mode must be one of ['poll', 'stream'], got 'push'"),
        ({"tare": "hardware"}, "devices.sensor.tare must be one of ['sensor', 'software'], got 'hardware'"),
        ({"tare_samples": 2.5}, "devices.sensor.tare_samples must be a positive integer, got 2.5"),
        ({"sensitivities": [32.8] * 5}, "devices.sensor.sensitivities must be a list of 6 positive numbers"),
        ({"sensitivities": [32.8] * 5 + [0.0]}, "devices.sensor.sensitivities must be a list of 6 positive"),
        ({"port": ""}, "devices.sensor.port must be a non-empty string"),
        ({"sensitivity_tolerance": 1.5}, "devices.sensor.sensitivity_tolerance must be a number between 0 and 1"),
        ({"nominal_sensitivities": [32.8] * 3}, "devices.sensor.nominal_sensitivities must be a list of 6"),
        ({"bauds": 9600}, "config/cell.yaml: devices.sensor: unknown key 'bauds'"),
    ],
)
def test_config_errors_name_the_field(settings: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        WacohConfig.from_dict({"port": "/dev/ttyUSB0", **settings}, "config/cell.yaml: devices.sensor")
    assert message in str(err.value)
    assert "\n" not in str(err.value)


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
def test_connect_reads_sensitivities_with_p(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor]
) -> None:
    emulator = make_emulator(Source())
    sensor = connect(sensors, emulator, sensitivities=list(FALLBACK.values))
    assert sensor.sensitivities_source == "sensor"
    assert sensor.sensitivities == REAL_UNIT_SENSITIVITIES
    assert emulator.commands.get("p") == 2  # two agreeing replies
    assert emulator.commands.get("E", 0) >= 1  # streaming stopped before anything else


def test_connect_falls_back_when_p_is_never_answered(
    make_emulator: EmulatorFactory, sensors: list[WacohSensor], caplog: pytest.LogCaptureFixture
) -> None:
    emulator = make_emulator(Source(), faults=FaultConfig(ignore_p=True))
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    t0 = time.monotonic()
    sensor = connect(sensors, emulator, sensitivities=list(FALLBACK.values), timeout_s=0.05)
    assert time.monotonic() - t0 < 0.5
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
        sensor = connect(sensors, emulator, sensitivities=list(FALLBACK.values))
        expected = REAL_UNIT_SENSITIVITIES if sensor.sensitivities_source == "sensor" else FALLBACK
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


def scripted_sensor(replies: list[bytes]) -> tuple[WacohSensor, ScriptedPort]:
    sensor = WacohSensor(WacohConfig(port="scripted", sensitivities=FALLBACK, timeout_s=0.002))
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
    corruption are left out: no check could tell them from the truth.)"""
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
        assert sens == FALLBACK
    if replies[:6].count(REAL_LINE) >= 2:
        assert source == "sensor"


@pytest.mark.parametrize("byte", [0x1C, 0x1D, 0x1E, 0x1F])
def test_a_control_byte_in_every_p_reply_falls_back_with_a_warning(
    byte: int, caplog: pytest.LogCaptureFixture
) -> None:
    """One flipped bit turns CR into 0x1D: that raised an uncaught ValueError at connect."""
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    sensor, port = scripted_sensor([REAL_LINE[:-2] + bytes([byte]) + b"\n"] * 6)
    assert sensor._request_sensitivities() == (FALLBACK, "config")
    assert port.asked == 6
    warning = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "not one line ending in CR LF" in warning[0] and "\n" not in warning[0]


def test_an_implausible_p_reply_is_refused_naming_the_axis(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.wacoh.driver")
    lost_dot = b"32.800,32.815,32.835,1653.801,1634816,1636.136\r\n"
    sensor, _ = scripted_sensor([lost_dot] * 6)
    assert sensor._request_sensitivities() == (FALLBACK, "config")
    assert any("My = 1.63482e+06" in r.getMessage() for r in caplog.records)
    # One bad reply among good ones costs nothing but a request.
    sensor, port = scripted_sensor([lost_dot, REAL_LINE, REAL_LINE])
    assert sensor._request_sensitivities() == (REAL_UNIT_SENSITIVITIES, "sensor")
    assert port.asked == 3
