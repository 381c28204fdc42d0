"""A serial port for a request/reply device: opened 8N1, no flow control; writes; reads bounded by a deadline."""

from __future__ import annotations

import contextlib
import logging
import os
import select
import termios
import time
from pathlib import Path

import serial

from drivers.errors import LinkLostError

log = logging.getLogger(__name__)

# What a vanished port raises: pyserial's errors, raw OS errors, and termios.error (not an OSError)
# from tcflush; TypeError when pyserial's fd is already gone.
LINK_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error, TypeError)

# Bit times per byte on an 8N1 line: start + 8 data + stop.
_BITS_PER_BYTE = 10
# pyserial reads block at most this long, so deadlines are kept to within a slice and a stream
# reader notices a stop request promptly without changing the port timeout per call (a tcsetattr).
READ_SLICE_S = 0.005
# A write is bounded like a read: the reply timeout plus a few byte times (and the bytes' own time on the
# line), so a wedged adapter holds a per-cycle command no longer than a missing reply would.  The bound is
# on the port *accepting* the bytes, checked only while it takes none: pyserial checks its write deadline
# after the bytes went out, so a thread descheduled between the call and that check saw a sent command as
# timed out.
WRITE_SLACK_BYTES = 4
# Where Linux shows a USB-serial adapter's latency timer (ms): the longest it holds received bytes back before
# passing them on when fewer than a USB packet arrived.  FTDI's default is 16 ms, longer than a reply timeout.
_SYSFS_TTY = Path("/sys/class/tty")


def latency_timer_ms(device: str, sysfs_tty: Path = _SYSFS_TTY) -> int | None:
    """The USB-serial adapter's latency timer behind `device` (a /dev path or a /dev/serial/by-id link), or None
    where the system shows none (not Linux, not a USB-serial adapter, a pseudo-terminal, a URL port)."""
    try:
        name = Path(os.path.realpath(device)).name
        return int((sysfs_tty / name / "device" / "latency_timer").read_text().strip())
    except (OSError, ValueError):
        return None


class SerialLink:
    """One serial port (a pyserial port or URL); `label` names the device in errors ("WACOH sensor").

    Every failure of an open port raises LinkLostError naming the device, the port and what failed.
    """

    def __init__(self, url: str, baudrate: int, timeout_s: float, label: str) -> None:
        self.url = url
        self.baudrate = baudrate
        self.timeout_s = timeout_s  # per request, plus the reply's own time on the wire
        self.label = label
        self.ser: serial.Serial | None = None
        self.fd: int | None = None  # None: a URL port without a file descriptor
        self.low_latency = False  # whether the tty driver took the low-latency request at open

    def open(self) -> None:
        try:
            self.ser = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                xonxoff=False,
                rtscts=False,
                dsrdtr=False,
                timeout=min(self.timeout_s, READ_SLICE_S),
                write_timeout=self.write_bound(1),  # what bounds a URL port's writes (see `write`)
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkLostError(f"{self.label}: cannot open {self.url}: {exc}") from None
        try:
            self.fd = self.ser.fileno()
        except (AttributeError, NotImplementedError, OSError, ValueError, serial.SerialException):  # e.g. loop://
            self.fd = None
        self.low_latency = self._request_low_latency()

    def _request_low_latency(self) -> bool:
        """Ask the tty driver to pass received bytes on at once (Linux's ASYNC_LOW_LATENCY: an FTDI adapter's
        latency timer goes from 16 ms to 1 ms), so that a reply is not held back past the reply timeout.  A port
        that does not take it (a pseudo-terminal, a URL port, another OS, a driver without the flag) keeps its own
        behaviour; `latency_timer_ms` tells what that is where the system shows it."""
        setter = getattr(self.ser, "set_low_latency_mode", None)
        if setter is None:
            return False
        try:
            setter(True)
        except (ValueError, serial.SerialException, OSError, termios.error) as exc:
            log.debug("%s on %s: low-latency mode not available: %s", self.label, self.url, exc)
            return False
        return True

    def close(self) -> None:
        ser, self.ser, self.fd = self.ser, None, None
        if ser is not None:
            try:
                ser.close()
            except LINK_ERRORS as exc:
                log.debug("%s on %s: close failed: %s", self.label, self.url, exc)

    @property
    def port(self) -> serial.Serial:
        """The open port; LinkLostError when it is not open."""
        if self.ser is None:
            raise LinkLostError(f"{self.label} on {self.url}: port is not open")
        return self.ser

    def link_lost(self, what: str, exc: BaseException) -> LinkLostError:
        return LinkLostError(f"{self.label} on {self.url}: {what} failed: {exc}")

    def write_bound(self, n_bytes: int) -> float:
        """Seconds a write of `n_bytes` may wait for the port to take them: the reply timeout plus
        WRITE_SLACK_BYTES byte times and the bytes' own time on the line."""
        return self.timeout_s + self.wire_time(n_bytes + WRITE_SLACK_BYTES)

    def write(self, data: bytes, what: str) -> None:
        """Send `data`; LinkLostError naming `what` if the port fails, or takes none of the rest of it within
        `write_bound` (a wedged adapter, a line held off)."""
        port = self.port
        bound = self.write_bound(len(data))
        deadline = time.monotonic() + bound
        try:
            if self.fd is None:  # a URL port: pyserial's own bound (set at open) applies
                port.write(data)
                return
            view = memoryview(data)
            while view:
                # The descriptor is non-blocking (pyserial opens it so): this takes what fits now.
                with contextlib.suppress(BlockingIOError):
                    view = view[os.write(self.fd, view):]
                if view:
                    _, writable, _ = select.select([], [self.fd], [], max(0.0, deadline - time.monotonic()))
                    if not writable:
                        raise self._write_timed_out(what, bound, len(data) - len(view), len(data))
        except serial.SerialTimeoutException:
            raise self._write_timed_out(what, bound, None, len(data)) from None
        except LINK_ERRORS as exc:
            raise self.link_lost(what, exc) from None

    def _write_timed_out(self, what: str, bound: float, sent: int | None, total: int) -> LinkLostError:
        part = "" if sent is None else f" ({sent} of {total} bytes sent)"
        return LinkLostError(f"{self.label} on {self.url}: {what} failed: the port took no data for "
                             f"{bound * 1e3:.1f} ms{part}; the adapter or line is stuck")

    def discard_input(self) -> None:
        try:
            self.port.reset_input_buffer()
        except LINK_ERRORS as exc:
            raise self.link_lost("clearing input", exc) from None

    def read_chunk(self, size: int, deadline: float) -> bytes:
        """Up to `size` bytes of what has arrived, waiting for the first one until `deadline` at most
        (b'' then).  The wait is the time left, not pyserial's per-read timeout: a read loop that
        restarted that timeout overshot the deadline by up to a whole timeout."""
        port = self.port
        left = max(0.0, deadline - time.monotonic())
        try:
            if self.fd is None:
                port.timeout = left  # URL ports: no descriptor to wait on
                return bytes(port.read(size))
            readable, _, _ = select.select([self.fd], [], [], left)
            if not readable:
                return b""
            # At least 1 byte after select said readable: a vanished device reads as an error then.
            return bytes(port.read(max(1, min(size, port.in_waiting))))
        except LINK_ERRORS as exc:
            raise self.link_lost("read", exc) from None

    def wire_time(self, n_bytes: int) -> float:
        """Seconds `n_bytes` take on the line."""
        return n_bytes * _BITS_PER_BYTE / self.baudrate

    def reply_deadline(self, reply_bytes: int) -> float:
        # The timeout plus the reply's own time on the wire, so slow baud rates do not time out early.
        return time.monotonic() + self.timeout_s + self.wire_time(reply_bytes)
