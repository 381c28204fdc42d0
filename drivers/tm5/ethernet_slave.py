"""The Ethernet Slave's `$TMSVR` data table (port 5891): binary item records decoded to SI, and their encoder."""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError

N_JOINTS = 6
REQUIRED_ITEMS = ("Joint_Angle", "Joint_Speed", "Joint_Torque")
# The items without which the cell cannot see that the controller will not, or must not, move: arming needs
# them all (TM's own driver requires every default item but the torque statistics and Ctrl_AI1), and a table
# that loses one while armed stops the arm.  Robot_Link = 0 means motion scripts do not run: streamed speeds
# would pile up unseen in the position loop and all act once the link returns.
SAFETY_ITEMS = ("Robot_Link", "Robot_Error", "Project_Run", "Project_Pause", "Safeguard_A", "ESTOP")

MODE_RESPONSE = 0
MODE_BINARY = 1
MODE_STRING = 2
MODE_JSON = 3
_MODE_NAMES = {MODE_STRING: "STRING", MODE_JSON: "JSON"}
_SETTING = "TMflow > Setting > Connection > Ethernet Slave"

# Mode-0 status codes of the Ethernet Slave.
RESPONSE_CODES = {"00": "OK", "01": "NotSupport", "02": "WritePermission", "03": "InvalidData", "04": "NotExist",
                  "05": "ReadOnly", "06": "ModeError", "07": "ValueError"}


class SlaveTableError(ProtocolError):
    """The Ethernet Slave is set up in a way this driver cannot use; the message says what to change in TMflow."""


@dataclass(frozen=True)
class SvrFrame:
    """A `$TMSVR` DATA field split into its transaction id, mode and content."""

    id: str
    mode: int
    content: bytes


@dataclass(frozen=True)
class SlaveState:
    """One decoded data table, SI: rad, rad/s, N·m; m and rad for the poses.  Absent optional items are None."""

    id: str
    q: np.ndarray
    dq: np.ndarray
    tau: np.ndarray
    robot_error: bool | None = None
    estop: bool | None = None
    safeguard: bool | None = None  # Safeguard_A: 1 = the safeguard (protective stop) input is triggered
    project_run: bool | None = None
    project_pause: bool | None = None
    error_code: int | None = None
    robot_link: bool | None = None
    ma_mode: int | None = None  # 0 none, 1 Auto, 2 Manual
    project_speed: int | None = None  # %
    flange_pose: np.ndarray | None = None  # Coord_Robot_Flange: x, y, z [m], rx, ry, rz [rad]
    tool_pose: np.ndarray | None = None  # Coord_Robot_Tool, same units
    items: tuple[str, ...] = ()  # every item the table carries, in its order

    @property
    def missing_safety_items(self) -> tuple[str, ...]:
        """The SAFETY_ITEMS this table lacks, in SAFETY_ITEMS order."""
        return tuple(name for name in SAFETY_ITEMS if name not in self.items)


def parse_svr(data: bytes) -> SvrFrame:
    """Split `ID,MODE,CONTENT` (the content may hold commas and binary)."""
    c1 = data.find(b",")
    c2 = data.find(b",", c1 + 1) if c1 >= 0 else -1
    if c1 < 0 or c2 < 0:
        raise ProtocolError(f"TMSVR data {data[:24]!r} is not ID,MODE,CONTENT")
    tid, mode = data[:c1], data[c1 + 1:c2]
    if not tid.isalnum() or not mode.isdigit() or len(mode) > 2:
        raise ProtocolError(f"TMSVR data starts with {data[:c2 + 1]!r}: expected an alphanumeric id and a mode")
    return SvrFrame(tid.decode("ascii"), int(mode), data[c2 + 1:])


def encode_svr(tid: str, mode: int, content: bytes | str) -> bytes:
    """The DATA field `ID,MODE,CONTENT` (frame it with tm_packet.encode_packet("TMSVR", ...))."""
    raw = content.encode("utf-8") if isinstance(content, str) else content
    return f"{tid},{mode},".encode("ascii") + raw


def parse_items(content: bytes) -> dict[str, bytes]:
    """Mode-1 content: records `u16 name length, name, u16 value length, value` back to back (little-endian)."""
    items: dict[str, bytes] = {}
    i, n = 0, len(content)
    while i < n:
        if i + 2 > n:
            raise ProtocolError(f"TMSVR table: truncated item name length at byte {i} of {n}")
        (name_len,) = struct.unpack_from("<H", content, i)
        j = i + 2 + name_len
        if j + 2 > n:
            raise ProtocolError(f"TMSVR table: item name of {name_len} bytes at byte {i} runs past the end ({n})")
        try:
            name = content[i + 2:j].decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError(f"TMSVR table: item name at byte {i} is not ASCII: {content[i + 2:j]!r}") from None
        (value_len,) = struct.unpack_from("<H", content, j)
        k = j + 2 + value_len
        if k > n:
            raise ProtocolError(f"TMSVR table: value of {name} ({value_len} bytes) runs past the end ({n})")
        items[name] = content[j + 2:k]
        i = k
    return items


def encode_items(items: Iterable[tuple[str, bytes]]) -> bytes:
    """Mode-1 content from (name, value bytes) pairs, in order."""
    out = bytearray()
    for name, value in items:
        raw = name.encode("ascii")
        out += struct.pack("<H", len(raw)) + raw + struct.pack("<H", len(value)) + value
    return bytes(out)


def value_bool(v: bool) -> bytes:
    return b"\x01" if v else b"\x00"


def value_int(v: int) -> bytes:
    return struct.pack("<i", int(v))


def value_floats(values: Iterable[float]) -> bytes:
    arr = np.asarray(list(values), dtype="<f4")
    return arr.tobytes()


def check_mode(frame: SvrFrame) -> None:
    """Refuse a table this driver cannot read (STRING or JSON), naming the TMflow setting to change."""
    if frame.mode in _MODE_NAMES:
        raise SlaveTableError(
            f"Ethernet Slave data table is {_MODE_NAMES[frame.mode]}: set Communication Mode to BINARY in {_SETTING}")
    if frame.mode != MODE_BINARY:
        raise ProtocolError(f"TMSVR broadcast in mode {frame.mode}: expected mode 1 (binary table)")


def decode_table(frame: SvrFrame) -> SlaveState:
    """A mode-1 table to SI; refuses other modes and a table without joint angles, speeds and torques."""
    check_mode(frame)
    items = parse_items(frame.content)
    missing = [name for name in REQUIRED_ITEMS if name not in items]
    if missing:
        raise SlaveTableError(
            f"Ethernet Slave data table lacks {', '.join(missing)}: in {_SETTING} > Data Table Setting import TM's "
            "Data_Table_Setting_TM_ROS_Default.xml or tick these items")
    q_deg = _floats(items, "Joint_Angle", N_JOINTS)
    dq_deg = _floats(items, "Joint_Speed", N_JOINTS)
    tau_mnm = _floats(items, "Joint_Torque", N_JOINTS)
    return SlaveState(
        id=frame.id,
        q=np.radians(q_deg),
        dq=np.radians(dq_deg),
        tau=tau_mnm / 1000.0,
        robot_error=_flag(items, "Robot_Error"),
        estop=_flag(items, "ESTOP"),
        safeguard=_flag(items, "Safeguard_A"),
        project_run=_flag(items, "Project_Run"),
        project_pause=_flag(items, "Project_Pause"),
        error_code=_int(items, "Error_Code", signed=False),
        robot_link=_flag(items, "Robot_Link"),
        ma_mode=_int(items, "MA_Mode"),
        project_speed=_int(items, "Project_Speed"),
        flange_pose=_pose(items, "Coord_Robot_Flange"),
        tool_pose=_pose(items, "Coord_Robot_Tool"),
        items=tuple(items),
    )


def missing_items_message(missing: tuple[str, ...] | list[str], what: str) -> str:
    """One line naming the safety items a table lacks and where in TMflow to add them."""
    return (f"Ethernet Slave data table lacks {', '.join(missing)}: {what}; in {_SETTING} > Data Table Setting "
            "import TM's Data_Table_Setting_TM_ROS_Default.xml or tick these items")


def _floats(items: dict[str, bytes], name: str, count: int) -> np.ndarray:
    raw = items[name]
    if len(raw) != 4 * count:
        raise ProtocolError(f"TMSVR table: {name} has {len(raw)} bytes, expected {count} float32 ({4 * count})")
    values = np.frombuffer(raw, dtype="<f4").astype(float)
    if not np.all(np.isfinite(values)):
        raise ProtocolError(f"TMSVR table: {name} holds non-finite values {values!r}")
    return values


def _int(items: dict[str, bytes], name: str, *, signed: bool = True) -> int | None:
    raw = items.get(name)
    if raw is None:
        return None
    if len(raw) not in (1, 2, 4):
        raise ProtocolError(f"TMSVR table: {name} has {len(raw)} bytes, expected an integer of 1, 2 or 4")
    return int.from_bytes(raw, "little", signed=signed and len(raw) > 1)


def _flag(items: dict[str, bytes], name: str) -> bool | None:
    value = _int(items, name)
    return None if value is None else value != 0


def _pose(items: dict[str, bytes], name: str) -> np.ndarray | None:
    if name not in items:
        return None
    v = _floats(items, name, 6)
    return np.concatenate([v[:3] / 1000.0, np.radians(v[3:])])


def encode_state_items(q: np.ndarray, dq: np.ndarray, tau: np.ndarray, *, robot_error: bool = False,
                       estop: bool = False, project_run: bool = True, project_pause: bool = False,
                       safeguard: bool = False, error_code: int = 0, robot_link: bool = True, ma_mode: int = 1,
                       project_speed: int = 100) -> list[tuple[str, bytes]]:
    """The items of the default table this driver reads, from SI values (the emulator's broadcast)."""
    for name, arr in (("q", q), ("dq", dq), ("tau", tau)):
        if len(arr) != N_JOINTS or not all(math.isfinite(float(x)) for x in arr):
            raise ValueError(f"{name} must be {N_JOINTS} finite values, got {arr!r}")
    return [
        ("Robot_Link", value_bool(robot_link)),
        ("Robot_Error", value_bool(robot_error)),
        ("Project_Run", value_bool(project_run)),
        ("Project_Pause", value_bool(project_pause)),
        ("Safeguard_A", value_bool(safeguard)),
        ("ESTOP", value_bool(estop)),
        ("Error_Code", value_int(error_code)),
        ("Joint_Angle", value_floats(np.degrees(q))),
        ("Joint_Speed", value_floats(np.degrees(dq))),
        ("Joint_Torque", value_floats(np.asarray(tau) * 1000.0)),
        ("Project_Speed", value_int(project_speed)),
        ("MA_Mode", value_int(ma_mode)),
    ]
