"""A WACOH WEF-6A200-4-RCD emulator on a pseudo-terminal, with seeded fault injection, for the real serial driver."""

from __future__ import annotations

import argparse
import logging
import math
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from drivers.wacoh.codec import (
    N_CHANNELS,
    RAW_MAX,
    RAW_ZERO,
    RECORD_LEN,
    Sensitivities,
    cell_to_sensor,
    encode_record,
)

log = logging.getLogger(__name__)

# One real unit's factory sensitivities (fact sheet): what `p` answers unless told otherwise.
REAL_UNIT_SENSITIVITIES = Sensitivities(force=(32.800, 32.815, 32.835), moment=(1653.801, 1634.816, 1636.136))
MAX_OFFSET_LSB = 655.0  # unloaded output sits within 8192 +- 655
VERSION_TEXT = b"WEF-6A200-4-RCD emulator 1.0"
# `O` counts only if the three arrive close together (the sensor wants them ~1 ms apart).
_ZERO_WINDOW_S = 0.05
_ZERO_REPEATS = 3
# What advances the record number (byte 0): the fact sheet says only "a wrapping counter".  "reply": one per
# record sent (the reference drivers' reading); "sample": the sensor's own sampling clock, one per
# `sample_period_s` whatever is asked; "constant": never (always 0).
CounterMode = Literal["reply", "sample", "constant"]
COUNTER_MODES: tuple[CounterMode, ...] = ("reply", "sample", "constant")


_PROBABILITIES = ("split_prob", "garbage_prob", "drop_crlf_prob", "drop_reply_prob", "reply_delay_prob",
                  "corrupt_p_prob")
_DURATIONS_S = ("split_max_delay_s", "reply_delay_s", "reply_delay_jitter_s", "p_delay_s")
_COUNTS = ("garbage_max_len", "late_replies", "ignore_first_p")
_COUNT_MIN = {"garbage_max_len": 1}


@dataclass
class FaultConfig:
    """Seeded misbehaviour of the line and the sensor; probabilities are per reply.

    Every field is checked whenever it is set (at construction and by a fault command later): a
    probability outside [0, 1] is a one-line ValueError, never a fault that silently saturates.
    """

    split_prob: float = 0.0  # write a reply in 2-4 pieces ...
    split_max_delay_s: float = 0.001  # ... with a pause of up to this between pieces
    garbage_prob: float = 0.0  # write 1..garbage_max_len random bytes before a reply
    garbage_max_len: int = 8
    drop_crlf_prob: float = 0.0  # send a data record without its CR LF
    drop_reply_prob: float = 0.0  # do not send a reply (or streamed record) at all
    ignore_p: bool = False  # never answer `p` (some models do not)
    ignore_first_p: int = 0  # answer none of the first this many `p`s (the rest as usual)
    p_delay_s: float = 0.0  # answer `p` this late (a model slow to format it), records as usual
    reply_delay_s: float = 0.0  # send a reply this late (what the line and the adapter add) ...
    reply_delay_prob: float = 1.0  # ... with this probability; replies stay in order (a later one waits) ...
    reply_delay_jitter_s: float = 0.0  # ... plus up to this much more, uniformly (a line's varying latency)
    late_replies: int = 0  # the next this many replies are reply_delay_s late whatever reply_delay_prob (counts down)
    corrupt_p_prob: float = 0.0  # flip 1..3 random bits of a `p` reply (a noisy line: no checksum catches it) ...
    corrupt_p_repeat: bool = False  # ... the same bits every time (a corruption that repeats)

    def __setattr__(self, name: str, value: object) -> None:
        _check_fault(name, value)
        super().__setattr__(name, value)


def _check_fault(name: str, value: object) -> None:
    number = float(value) if isinstance(value, int | float) and not isinstance(value, bool) else math.nan
    if name in _PROBABILITIES and not 0.0 <= number <= 1.0:  # NaN fails every comparison
        raise ValueError(f"FaultConfig.{name} must be a probability from 0 to 1, got {value!r}")
    if name in _DURATIONS_S and not (math.isfinite(number) and number >= 0.0):
        raise ValueError(f"FaultConfig.{name} must be a finite number of seconds >= 0, got {value!r}")
    least = _COUNT_MIN.get(name, 0)
    if name in _COUNTS and not (isinstance(value, int) and not isinstance(value, bool) and value >= least):
        raise ValueError(f"FaultConfig.{name} must be an integer >= {least}, got {value!r}")


def draw_bit_flips(n_bytes: int, rng: np.random.Generator, most: int = 3) -> list[int]:
    """1..`most` distinct bit positions (byte * 8 + bit) of an `n_bytes` reply: the corruption of one reply."""
    n = int(rng.integers(1, min(most, 8 * n_bytes) + 1))
    return sorted(int(b) for b in rng.choice(8 * n_bytes, n, replace=False))


def flip_bits(payload: bytes, flips: list[int]) -> bytes:
    """`payload` with the bits at `flips` (byte * 8 + bit) inverted; distinct flips always change it."""
    out = bytearray(payload)
    for position in flips:
        out[position // 8] ^= 1 << (position % 8)
    return bytes(out)


class WacohEmulator:
    """Answers the DynPick command set byte-exactly on the master side of a pty; drivers open `tty_path`.

    `wrench_source()` gives the true (6,) wrench [N, N·m] in the cell convention each time a record is
    made; the emulator maps it to the sensor's axes, converts to counts with its sensitivities, adds
    its unloaded offset and noise, applies the zero from `O` and the moving-average filter, then
    quantises to integer LSB and saturates at 0..0x3FFF.  `counter` chooses what advances the record
    number (COUNTER_MODES); `clock` is the sampling clock of `counter="sample"`.
    """

    def __init__(
        self,
        wrench_source: Callable[[], np.ndarray],
        sensitivities: Sensitivities = REAL_UNIT_SENSITIVITIES,
        offset_lsb: np.ndarray | None = None,
        noise: float = 0.3,
        seed: int = 0,
        faults: FaultConfig | None = None,
        stream_period_s: float = 0.001,
        temperature_c: float = 25.0,
        counter: CounterMode = "reply",
        sample_period_s: float = 0.001,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if counter not in COUNTER_MODES:
            raise ValueError(f"counter must be one of {list(COUNTER_MODES)}, got {counter!r}")
        if not (math.isfinite(sample_period_s) and sample_period_s > 0):
            raise ValueError(f"sample_period_s must be a finite number of seconds > 0, got {sample_period_s!r}")
        offset_rng, noise_rng, fault_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
        self.wrench_source = wrench_source
        self.sensitivities = sensitivities
        self._scale = sensitivities.as_array()
        if offset_lsb is None:
            offset_lsb = offset_rng.uniform(-MAX_OFFSET_LSB, MAX_OFFSET_LSB, N_CHANNELS)
        self.offset_lsb = np.asarray(offset_lsb, dtype=float).reshape(N_CHANNELS)
        self.noise = float(noise)
        self.faults = faults or FaultConfig()
        self.stream_period_s = stream_period_s
        self.temperature_c = temperature_c
        self.counter = counter
        self.sample_period_s = sample_period_s
        self._clock = clock
        self._clock0 = clock()
        self._noise_rng = noise_rng
        self._fault_rng = fault_rng
        # Sensor state.
        self.filter_n = 1
        self.streaming = False
        self._zero_shift = np.zeros(N_CHANNELS)  # counts removed by the last `O` x3
        self._history: deque[np.ndarray] = deque(maxlen=8)
        self._record_no = 0
        self._zero_count = 0
        self._last_zero_t = -math.inf
        self._pending_digit: int | None = None
        self._delayed: deque[tuple[float, bytes]] = deque()  # (due time, bytes) of delayed replies, in order
        self._p_flips: list[int] | None = None  # the repeated corruption of `p`, once drawn
        # Statistics for tests.
        self.commands: dict[str, int] = {}
        self.records_sent = 0
        self.replies_dropped = 0
        self.zero_events = 0
        self.bytes_overflowed = 0
        self.replies_delayed = 0
        self.p_corrupted = 0
        # Plumbing.
        self._master: int | None = None
        self._slave: int | None = None
        self._wake_r: int | None = None
        self._wake_w: int | None = None
        self._tty_path: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ------------------------------------------------------------------ lifecycle
    @property
    def tty_path(self) -> str:
        if self._tty_path is None:
            raise RuntimeError("emulator not started")
        return self._tty_path

    def start(self) -> str:
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        master, slave = os.openpty()
        # Raw line discipline, as a serial port: no echo, no CR/LF translation, no signals.
        tty.setraw(slave)
        # Keep our slave fd open so the master never sees a hang-up between driver sessions;
        # non-blocking writes so a reader that stops reading costs data (like a UART), not a stuck thread.
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._wake_r, self._wake_w = os.pipe()
        self._tty_path = os.ttyname(slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="wacoh-emulator", daemon=True)
        self._thread.start()
        log.debug("WACOH emulator on %s", self._tty_path)
        return self._tty_path

    def stop(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            assert self._wake_w is not None
            os.write(self._wake_w, b"x")
            thread.join(timeout=2.0)
            if thread.is_alive():
                log.error("WACOH emulator thread did not stop")
        for name in ("_master", "_slave", "_wake_r", "_wake_w"):
            fd = getattr(self, name)
            if fd is not None:
                os.close(fd)
                setattr(self, name, None)
        self.streaming = False

    def __enter__(self) -> WacohEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ serving loop
    def _serve(self) -> None:
        assert self._master is not None and self._wake_r is not None
        master, wake = self._master, self._wake_r
        next_record = time.monotonic()
        while not self._stop.is_set():
            wake_at = [next_record] if self.streaming else []
            if self._delayed:
                wake_at.append(self._delayed[0][0])
            timeout = max(0.0, min(wake_at) - time.monotonic()) if wake_at else None
            ready, _, _ = select.select([master, wake], [], [], timeout)
            self._flush_delayed()
            if wake in ready:
                return
            if master in ready:
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError as exc:  # EIO: no slave open any more
                    log.debug("WACOH emulator: read failed: %s", exc)
                    return
                was_streaming = self.streaming
                for byte in data:
                    self._command(byte)
                if self.streaming and not was_streaming:
                    next_record = time.monotonic()
            if self.streaming and time.monotonic() >= next_record:
                self._send_record()
                # Keep the nominal rate, but do not burst to catch up after a stall.
                next_record = max(next_record + self.stream_period_s, time.monotonic())

    def _command(self, byte: int) -> None:
        c = chr(byte)
        if self._pending_digit is not None:
            digit, self._pending_digit = self._pending_digit, None
            if c == "F":
                self._count(f"{digit}F")
                self._filter_command(digit)
                return
            # a digit not followed by F is not a command: ignore it and read c afresh
        if 0x30 <= byte <= 0x39:  # an ASCII digit starts a filter command ('4F', '0F')
            self._pending_digit = byte - 0x30
            return
        if c != "O":
            self._zero_count = 0
        self._count(c)
        if c == "R":
            self._send_record()
        elif c == "p":
            ignored = self.faults.ignore_p or self.commands["p"] <= self.faults.ignore_first_p
            if not ignored:
                s = self.sensitivities.values
                reply = self._maybe_corrupt_p(",".join(f"{v:.3f}" for v in s).encode() + b"\r\n")
                self._send(reply, extra_delay_s=self.faults.p_delay_s)
        elif c == "O":
            self._zero_command()
        elif c == "V":
            self._send(VERSION_TEXT + b"\r\n")
        elif c == "T":
            self._send(b"%04X\r\n" % (int(round(self.temperature_c * 16)) & 0xFFFF))
        elif c == "S":
            self.streaming = True
        elif c == "E":
            self.streaming = False
        # The sensor sends no error reply: anything else is ignored.

    def _maybe_corrupt_p(self, reply: bytes) -> bytes:
        f, rng = self.faults, self._fault_rng
        if not (f.corrupt_p_prob and rng.random() < f.corrupt_p_prob):
            return reply
        flips = self._p_flips if f.corrupt_p_repeat and self._p_flips is not None else draw_bit_flips(len(reply), rng)
        if f.corrupt_p_repeat:
            self._p_flips = flips
        self.p_corrupted += 1
        return flip_bits(reply, flips)

    def _count(self, name: str) -> None:
        self.commands[name] = self.commands.get(name, 0) + 1

    def _filter_command(self, digit: int) -> None:
        if digit == 0:
            self._send(b"%d\r\n" % self.filter_n)
        elif digit in (1, 2, 4, 8):
            self.filter_n = digit

    def _zero_command(self) -> None:
        now = time.monotonic()
        if now - self._last_zero_t > _ZERO_WINDOW_S:
            self._zero_count = 0
        self._zero_count += 1
        self._last_zero_t = now
        if self._zero_count >= _ZERO_REPEATS:
            self._zero_count = 0
            # Zero at the current load: from now on this analog level reads 8192.
            self._zero_shift = self._analog(self._true_wrench()) - RAW_ZERO + self._zero_shift
            self._history.clear()
            self.zero_events += 1

    # ------------------------------------------------------------------ records
    def _true_wrench(self) -> np.ndarray:
        w = np.asarray(self.wrench_source(), dtype=float).reshape(N_CHANNELS)
        if not np.all(np.isfinite(w)):
            raise ValueError(f"wrench_source returned a non-finite wrench {w}")
        return cell_to_sensor(w)

    def _analog(self, w_sensor: np.ndarray) -> np.ndarray:
        """Counts before quantisation (after the `O` zero)."""
        noise = self._noise_rng.normal(0.0, self.noise, N_CHANNELS) if self.noise > 0 else 0.0
        return RAW_ZERO + self.offset_lsb + self._scale * w_sensor + noise - self._zero_shift

    def make_counts(self, w_sensor: np.ndarray) -> np.ndarray:
        """One sample through the sensor's chain: analog, moving average, quantise, saturate."""
        self._history.append(self._analog(w_sensor))
        window = list(self._history)[-self.filter_n :]
        averaged = np.mean(window, axis=0)
        return np.clip(np.rint(averaged), 0, RAW_MAX).astype(int)

    def _send_record(self) -> None:
        try:
            w = self._true_wrench()
        except Exception:  # a broken source is the test's bug: say so, send nothing (like a lost reply)
            log.exception("WACOH emulator: wrench_source failed")
            return
        record = encode_record(self.record_number(), self.make_counts(w))
        self._record_no = (self._record_no + 1) % 10
        self.records_sent += 1
        self._send(record, is_record=True)

    def record_number(self) -> int:
        """Byte 0 of the record made now (see COUNTER_MODES)."""
        if self.counter == "reply":
            return self._record_no
        if self.counter == "sample":
            return int((self._clock() - self._clock0) // self.sample_period_s) % 10
        return 0

    # ------------------------------------------------------------------ the wire, with faults
    def _send(self, payload: bytes, is_record: bool = False, extra_delay_s: float = 0.0) -> None:
        f, rng = self.faults, self._fault_rng
        if f.drop_reply_prob and rng.random() < f.drop_reply_prob:
            self.replies_dropped += 1
            return
        forced = f.late_replies > 0  # this reply is late whatever reply_delay_prob
        if forced:
            f.late_replies -= 1
        if is_record and f.drop_crlf_prob and rng.random() < f.drop_crlf_prob:
            assert len(payload) == RECORD_LEN
            payload = payload[:-2]
        if f.garbage_prob and rng.random() < f.garbage_prob:
            payload = rng.bytes(int(rng.integers(1, f.garbage_max_len + 1))) + payload
        if f.split_prob and len(payload) > 1 and rng.random() < f.split_prob:
            n_cuts = int(rng.integers(1, min(3, len(payload) - 1) + 1))
            cuts = sorted(int(c) for c in rng.choice(np.arange(1, len(payload)), n_cuts, replace=False))
            pieces = [payload[a:b] for a, b in zip([0, *cuts], [*cuts, len(payload)], strict=True)]
            for i, piece in enumerate(pieces):
                if i:
                    time.sleep(float(rng.uniform(0.0, f.split_max_delay_s)))
                self._write(piece, extra_delay_s, forced)
        else:
            self._write(payload, extra_delay_s, forced)

    def _write(self, data: bytes, extra_delay_s: float = 0.0, forced: bool = False) -> None:
        f = self.faults
        late = f.reply_delay_s > 0 and (forced or self._fault_rng.random() < f.reply_delay_prob)
        if late or extra_delay_s > 0 or self._delayed:
            # Due after the delay if late, and never before a reply still waiting (a line keeps order).
            delay = f.reply_delay_s + float(self._fault_rng.uniform(0.0, f.reply_delay_jitter_s)) if late else 0.0
            due = time.monotonic() + delay + extra_delay_s
            if self._delayed:
                due = max(due, self._delayed[-1][0])
            self._delayed.append((due, data))
            self.replies_delayed += late
            return
        self._write_now(data)

    def _flush_delayed(self) -> None:
        now = time.monotonic()
        while self._delayed and self._delayed[0][0] <= now:
            self._write_now(self._delayed.popleft()[1])

    def _write_now(self, data: bytes) -> None:
        assert self._master is not None
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0
        except OSError as exc:
            log.debug("WACOH emulator: write failed: %s", exc)
            return
        # Nobody reading: the rest is lost, as on a UART whose receiver overflowed.
        self.bytes_overflowed += len(data) - written


# ------------------------------------------------------------------------------------ standalone
def synthetic_wrench(t: float) -> np.ndarray:
    """A gently varying load: a light press in z with slow side forces and moments."""
    return np.array([
        2.0 * math.sin(0.5 * t),
        1.5 * math.cos(0.3 * t),
        20.0 + 10.0 * math.sin(0.7 * t),
        0.10 * math.sin(0.4 * t),
        0.05 * math.cos(0.6 * t),
        0.02 * math.sin(0.2 * t),
    ])


def serve(seed: int, faults: FaultConfig | None = None) -> int:
    """Serve until KeyboardInterrupt; prints the tty path (one line) for the user's driver to open."""
    t0 = time.monotonic()
    with WacohEmulator(lambda: synthetic_wrench(time.monotonic() - t0), seed=seed, faults=faults) as emulator:
        print(emulator.tty_path, flush=True)  # the one stdout line: the path a driver opens
        try:
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
    return 0


def emulate_sensor_main(seed: int = 0) -> int:
    """Entry of `main.py emulate sensor`."""
    return serve(seed, None)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=0)
    raise SystemExit(emulate_sensor_main(parser.parse_args().seed))
