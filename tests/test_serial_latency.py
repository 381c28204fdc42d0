"""The serial link asks for the tty's low-latency mode; a USB adapter's latency timer is read where Linux shows it."""

from __future__ import annotations

import os

import pytest
import serial

from drivers.serial_link import SerialLink, latency_timer_ms


def test_the_latency_timer_is_read_behind_a_by_id_link(tmp_path):
    sysfs = tmp_path / "sys"
    (sysfs / "ttyUSB7" / "device").mkdir(parents=True)
    (sysfs / "ttyUSB7" / "device" / "latency_timer").write_text("16\n")
    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "ttyUSB7").touch()
    link = tmp_path / "usb-FTDI_FT232R_A1B2C3-if00-port0"
    link.symlink_to(dev / "ttyUSB7")
    assert latency_timer_ms(str(link), sysfs) == 16
    assert latency_timer_ms(str(dev / "ttyUSB7"), sysfs) == 16
    (sysfs / "ttyUSB7" / "device" / "latency_timer").write_text("sixteen\n")
    assert latency_timer_ms(str(link), sysfs) is None  # unreadable: shown as unknown, not guessed
    assert latency_timer_ms(str(tmp_path / "nothing"), sysfs) is None
    assert latency_timer_ms("loop://", sysfs) is None


class FakePort:
    """What `serial_for_url` returns, without a device: records the low-latency request."""

    def __init__(self, refuse: bool) -> None:
        self.refuse = refuse
        self.requests: list[bool] = []

    def fileno(self) -> int:
        raise NotImplementedError

    def set_low_latency_mode(self, on: bool) -> None:
        self.requests.append(on)
        if self.refuse:
            raise ValueError("Failed to update ASYNC_LOW_LATENCY flag to True: [Errno 25] Inappropriate ioctl")


@pytest.mark.parametrize("refuse", [False, True])
def test_the_port_asks_for_low_latency_and_opens_without_it(monkeypatch, refuse):
    port = FakePort(refuse)
    monkeypatch.setattr(serial, "serial_for_url", lambda *args, **kwargs: port)
    link = SerialLink("/dev/ttyUSB7", 921600, 0.005, "WACOH sensor")
    link.open()
    assert port.requests == [True]
    assert link.low_latency is not refuse and link.ser is port


def test_a_pseudo_terminal_opens_without_low_latency():
    master, slave = os.openpty()
    try:
        link = SerialLink(os.ttyname(slave), 921600, 0.005, "WACOH sensor")
        link.open()
        try:
            assert link.low_latency is False and link.fd is not None  # a pty has no ASYNC_LOW_LATENCY to set
        finally:
            link.close()
    finally:
        os.close(master)
        os.close(slave)
