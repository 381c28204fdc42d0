"""The typed error family every layer of the cell raises and catches."""

from __future__ import annotations


class CellError(Exception):
    """Base of every expected error: the CLI prints its one-line message and exits non-zero.

    The message is one line by construction: control characters that came in with user input (a
    key or value read from a file) are shown escaped, never as line breaks."""

    exit_code = 1

    def __str__(self) -> str:
        text = super().__str__()
        if text.isprintable():
            return text
        return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class ConfigError(CellError):
    """A config file, plant profile or CLI argument is wrong; the message names the field."""

    exit_code = 2


class DataError(CellError):
    """A data file (recording, dataset, artefact) is malformed; the message names file and column."""

    exit_code = 2


class RecordingError(CellError):
    """The run's recording could not be written (disk full, folder not writable); the arm is stopped."""


class DriverError(CellError):
    """Something went wrong at the hardware boundary."""

    kind = "driver error"


class LinkLostError(DriverError):
    """The connection to a device is gone (socket closed, port vanished, no reply in time)."""

    kind = "link lost"


class StaleDataError(DriverError):
    """The device answers but its data stopped advancing (frozen counter or timestamp)."""

    kind = "stale data"


class ProtocolError(DriverError):
    """A reply did not follow the protocol (bad frame, bad length, exception reply)."""

    kind = "protocol error"


class LifecycleError(DriverError):
    """A call is not allowed in the device's current lifecycle state (e.g. a command before arming)."""

    kind = "not allowed now"


class CommandRejectedError(DriverError):
    """A command was refused before reaching the device (NaN/inf, wrong shape)."""

    kind = "command rejected"


class SafetyStopError(CellError):
    """A safety limit tripped; the arm has been stopped.  `reason` says which limit and by how much."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason
