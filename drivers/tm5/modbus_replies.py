"""How a Modbus transaction's failure reads: the exception codes' names and the error an exception reply raises."""

from __future__ import annotations

from typing import Any

from drivers.errors import ProtocolError

ILLEGAL_DATA_ADDRESS = 2  # the server has no such address

_EXCEPTION_NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                    4: "server device failure", 5: "acknowledge", 6: "server device busy",
                    8: "memory parity error", 10: "gateway path unavailable", 11: "gateway target no response"}


class ModbusExceptionReply(ProtocolError):
    """The controller answered a request with a Modbus exception (`code`)."""

    def __init__(self, message: str, code: int | None) -> None:
        super().__init__(message)
        self.code = code


def exception_name(code: Any) -> str:
    """The Modbus name of an exception code ("unknown" for any other value)."""
    return _EXCEPTION_NAMES.get(code, "unknown") if isinstance(code, int) else "unknown"


def first_line(exc: BaseException) -> str:
    """An exception's message cut to its first line (pymodbus' can span several), or its type's name."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
