"""The hardware boundary: the `Arm` and `ForceSensor` interfaces every driver (real or simulated) implements.

Lifecycle, in the spirit of ros2_control:

    DISCONNECTED --connect()--> CONNECTED (inactive: state readable, no commands)
    CONNECTED --arm()--> ARMED (commands accepted)
    any --fault--> FAULT (commands refused; state may still be readable) --arm()--> ARMED
    any --disconnect()--> DISCONNECTED

The public methods here do all validation and bookkeeping; a concrete driver overrides only the
underscore "wire" methods, so real and simulated drivers share exactly the same checks.
All quantities are SI (rad, rad/s, N·m, N, m, s); drivers convert at their wire only.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from drivers.errors import CommandRejectedError, DriverError, LifecycleError

log = logging.getLogger(__name__)


class Lifecycle(enum.Enum):
    DISCONNECTED = "disconnected"
    CONNECTED = "connected"
    ARMED = "armed"
    FAULT = "fault"


@dataclass(frozen=True)
class ArmStatus:
    """Status flags reported by the arm controller."""

    error: bool = False
    estop: bool = False
    project_running: bool = True
    paused: bool = False
    protective_stop: bool = False

    @property
    def ok(self) -> bool:
        return not (self.error or self.estop or self.protective_stop)


# How far beyond a joint's range a reported position may lie (encoder and servo overshoot at a
# hard limit) before the reading is refused [rad].
LIMIT_TOLERANCE_RAD = 0.05


def vector_text(values: object) -> str:
    """A vector for a one-line message: every element, on one line (numpy's repr breaks long arrays)."""
    arr = np.asarray(values, dtype=float).ravel()
    return "[" + ", ".join(f"{v:.6g}" for v in arr.tolist()) + "]"


@dataclass(frozen=True)
class ArmState:
    """One timestamped sample of the arm: joint positions, speeds and measured motor torques."""

    t: float  # s, device time (sim time in simulation, host receive time for real hardware)
    q: np.ndarray  # rad
    dq: np.ndarray  # rad/s
    tau: np.ndarray  # N·m, measured joint (motor) torque
    status: ArmStatus = field(default_factory=ArmStatus)
    seq: int = 0  # device sequence counter; must advance between samples


@dataclass(frozen=True)
class Wrench:
    """One timestamped 6-axis wrench in the sensor/tool frame: force [N] and moment [N·m].

    Convention of the whole cell: the wrench the tool exerts on the environment, so pressing the
    tool along its own +z axis onto a surface gives a positive Fz.  Missing data is NaN, never 0.
    """

    t: float
    force: np.ndarray  # (3,) N
    torque: np.ndarray  # (3,) N·m

    @property
    def vector(self) -> np.ndarray:
        return np.concatenate([self.force, self.torque])

    @property
    def valid(self) -> bool:
        return bool(np.isfinite(self.force).all() and np.isfinite(self.torque).all())


@dataclass(frozen=True)
class JointLimits:
    """Position, speed and torque limits per joint (SI)."""

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    @property
    def n(self) -> int:
        return int(self.lower.shape[0])


@dataclass(frozen=True)
class SentCommand:
    """What an `Arm.send_target` actually sent after clipping, and whether clipping happened."""

    q: np.ndarray
    clipped: bool
    requested: np.ndarray


class Arm(ABC):
    """A position-commanded serial arm.

    `send_target` clips a joint-position target to the joint limits and to the largest step the
    joint speed limit allows in one control period (`dt`), then hands it to `_write_target`.
    """

    def __init__(self, limits: JointLimits, dt: float, speed_scale: float = 1.0) -> None:
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"control period must be positive, got {dt!r}")
        self.limits = limits
        self.dt = dt
        self.speed_scale = speed_scale
        self._lifecycle = Lifecycle.DISCONNECTED
        self._fault_reason: str | None = None
        self._last_sent: np.ndarray | None = None
        # Whether this connection was ever armed: only then may it have moved the arm, and only then
        # does disconnecting command a stop (a read-only session, `main.py status`, leaves the robot
        # side as it found it: a stop there latches a hold another program would have to clear).
        self._was_armed = False
        self._lock = threading.RLock()

    # ----------------------------------------------------------------------------- lifecycle
    @property
    def lifecycle(self) -> Lifecycle:
        return self._lifecycle

    @property
    def fault_reason(self) -> str | None:
        return self._fault_reason

    @property
    def n_joints(self) -> int:
        return self.limits.n

    def connect(self) -> None:
        with self._lock:
            if self._lifecycle is not Lifecycle.DISCONNECTED:
                return
            self._connect()
            self._lifecycle = Lifecycle.CONNECTED
            self._was_armed = False

    def disconnect(self) -> None:
        with self._lock:
            if self._lifecycle is Lifecycle.DISCONNECTED:
                return
            try:
                if self._was_armed:
                    self.stop()
            except DriverError as exc:  # a dead link cannot take a stop; the device's watchdog does
                log.warning("stop before disconnect failed: %s", exc)
            finally:
                self._disconnect()
                self._lifecycle = Lifecycle.DISCONNECTED
                self._last_sent = None

    def arm(self) -> None:
        """Allow commands (also the way out of FAULT).  The first target is held at the current pose."""
        with self._lock:
            if self._lifecycle is Lifecycle.DISCONNECTED:
                raise LifecycleError("cannot arm: the arm is not connected")
            self._arm()
            state = self.read_state()
            if not state.status.ok:
                raise LifecycleError(f"cannot arm: controller reports {state.status}")
            self._last_sent = np.array(state.q, dtype=float)
            self._fault_reason = None
            self._lifecycle = Lifecycle.ARMED
            self._was_armed = True

    def fault(self, reason: str) -> None:
        """Enter FAULT: stop at once and refuse commands until re-armed."""
        with self._lock:
            if self._lifecycle is Lifecycle.DISCONNECTED:
                return
            self._fault_reason = reason
            self._lifecycle = Lifecycle.FAULT
            # The link may be the fault; the device's own watchdog stops the arm then.
            with contextlib.suppress(DriverError):
                self._stop()

    def stop(self) -> None:
        """Stop motion now.  Always allowed; leaves ARMED for CONNECTED (a stop must be re-armed)."""
        with self._lock:
            if self._lifecycle is Lifecycle.DISCONNECTED:
                return
            self._stop()
            if self._lifecycle is Lifecycle.ARMED:
                self._lifecycle = Lifecycle.CONNECTED

    def __enter__(self) -> Arm:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    # ----------------------------------------------------------------------------- data
    def read_state(self) -> ArmState:
        with self._lock:
            if self._lifecycle is Lifecycle.DISCONNECTED:
                raise LifecycleError("cannot read state: the arm is not connected")
            try:
                state = self._read_state()
            except DriverError as exc:  # link lost, stale data, a malformed reply: all fault the arm
                self.fault(str(exc))
                raise
            for name in ("q", "dq", "tau"):
                value = getattr(state, name)
                # (Array methods, not numpy's dispatching functions: this runs every control period.)
                if value.shape != (self.n_joints,) or not np.isfinite(value).all():
                    reason = f"arm state field {name} is invalid: {vector_text(value)}"
                    self.fault(reason)
                    raise DriverError(reason)
            # A position outside the joint's range is a wrong reading (or a wrong limit), never a
            # state to command from: a target near it would be clipped toward the reading, not the range.
            lim = self.limits
            outside = (state.q < lim.lower - LIMIT_TOLERANCE_RAD) | (state.q > lim.upper + LIMIT_TOLERANCE_RAD)
            if outside.any():
                j = int(np.flatnonzero(outside)[0])
                reason = (f"joint {j + 1} reported at {np.degrees(state.q[j]):.4g} deg, outside its limits "
                          f"[{np.degrees(lim.lower[j]):.4g}, {np.degrees(lim.upper[j]):.4g}] deg")
                self.fault(reason)
                raise DriverError(reason)
            # The controller in error, E-stop or protective stop: the driver refuses commands itself
            # (the control loop's safety check stops too, but the boundary must not rely on it).
            if not state.status.ok and self._lifecycle is Lifecycle.ARMED:
                flags = [k for k in ("error", "estop", "protective_stop") if getattr(state.status, k)]
                self.fault(f"controller reports {', '.join(flags)}")
            return state

    def send_target(self, q_target: np.ndarray) -> SentCommand:
        """Validate, clip and send one joint-position target; returns what was actually sent."""
        with self._lock:
            if self._lifecycle is not Lifecycle.ARMED:
                why = f" ({self._fault_reason})" if self._fault_reason else ""
                raise LifecycleError(f"command refused: arm is {self._lifecycle.value}{why}")
            requested = np.asarray(q_target, dtype=float)
            if requested.shape != (self.n_joints,):
                raise CommandRejectedError(
                    f"command refused: target has shape {requested.shape}, expected ({self.n_joints},)"
                )
            if not np.isfinite(requested).all():
                raise CommandRejectedError(f"command refused: non-finite target {vector_text(requested)}")
            # Clipped as np.clip does (a finite target), without its dispatch: this runs every control period.
            q = np.minimum(np.maximum(requested, self.limits.lower), self.limits.upper)
            assert self._last_sent is not None
            max_step = self.limits.velocity * self.speed_scale * self.dt
            q = np.minimum(np.maximum(q, self._last_sent - max_step), self._last_sent + max_step)
            clipped = bool((np.abs(q - requested) > 1e-12).any())
            try:
                self._write_target(q)
            except DriverError as exc:
                self.fault(str(exc))
                raise
            self._last_sent = q
            return SentCommand(q=q, clipped=clipped, requested=requested)

    @property
    def last_sent(self) -> np.ndarray | None:
        return None if self._last_sent is None else self._last_sent.copy()

    # ----------------------------------------------------------------------------- wire
    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...

    def _arm(self) -> None:  # noqa: B027 - optional hook, most devices need nothing here
        """Device-side preparation before accepting commands (clear a protective stop, etc.)."""

    @abstractmethod
    def _read_state(self) -> ArmState: ...

    @abstractmethod
    def _write_target(self, q: np.ndarray) -> None: ...

    @abstractmethod
    def _stop(self) -> None: ...


class ForceSensor(ABC):
    """A 6-axis force/torque sensor.  Readings are SI in the sensor frame; invalid data is NaN."""

    def __init__(self) -> None:
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        if not self._connected:
            self._connect()
            self._connected = True

    def disconnect(self) -> None:
        if self._connected:
            try:
                self._disconnect()
            finally:
                self._connected = False

    def read(self) -> Wrench:
        if not self._connected:
            raise LifecycleError("cannot read: the force sensor is not connected")
        return self._read()

    def tare(self, samples: int = 50) -> None:
        """Zero the sensor at the current (unloaded) state."""
        if not self._connected:
            raise LifecycleError("cannot tare: the force sensor is not connected")
        self._tare(samples)

    def tare_from_recent(self, samples: int = 50) -> bool:
        """Zero the sensor at the mean of the last `samples` readings it returned, when they are recent enough to be
        the present state (read one after another at a control loop's pace), without waiting for new ones: what a
        control loop calls, where `tare` would hold it for as long as the sensor takes to send `samples` records.
        False, and nothing changed, for a sensor that cannot (the caller then tares with `tare`)."""
        if not self._connected:
            raise LifecycleError("cannot tare: the force sensor is not connected")
        return False

    def __enter__(self) -> ForceSensor:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...

    @abstractmethod
    def _read(self) -> Wrench: ...

    @abstractmethod
    def _tare(self, samples: int) -> None: ...
