"""The controller's own Modbus table (joint angles, error, E-stop, running) as a cross-check of the Ethernet Slave's."""

from __future__ import annotations

import functools
import logging
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from drivers.errors import LifecycleError, LinkLostError, ProtocolError
from drivers.interfaces import ArmState
from drivers.tm5.ethernet_config import TMEthernetConfig
from drivers.tm5.ethernet_slave import SlaveState
from drivers.tm5.modbus_replies import exception_name, first_line
from drivers.tm5.registers import (
    DI_COUNT,
    DI_ERROR,
    DI_ESTOP,
    DI_FIRST,
    DI_RUNNING,
    DI_RUNS,
    IR_JOINTS,
    N_JOINTS,
    regs_to_floats,
)

log = logging.getLogger(__name__)


class SlaveTables(Protocol):
    """What the cross-check reads of a connected arm on TM's Ethernet Slave (`drivers.tm5.ethernet.TMEthernetArm`)."""

    config: TMEthernetConfig

    @property
    def endpoint(self) -> str: ...

    @property
    def latest_table(self) -> SlaveState | None: ...

    def read_state(self) -> ArmState: ...

UNIT_ID = 1  # TM's Modbus server answers unit 1 (docs tm5-700.md section 3)
# Both tables read the same encoders: at rest they differ by float32 rounding (~1e-5 deg).  A wrong table or
# another machine behind the port is off by far more; the arm's own motion between the two reads is allowed
# on top, joint by joint (speed x the time between them).
JOINT_TOLERANCE_DEG = 0.5
# Either sample may be this old when read: the broadcast comes every ~16 ms, and how often the controller
# refreshes its Modbus table is not documented.
SAMPLE_AGE_S = 0.05
_POLL_S = 0.002  # between polls of the broadcast while waiting for the next table
# The flags compared: (name, discrete input, the Ethernet Slave's item and field).  7208 (E-stop) comes from
# a low-confidence source: a disagreement on it alone on a healthy arm points at the register, not the arm.
_FLAGS = (("error", DI_ERROR, "Robot_Error", "robot_error"),
          ("project_running", DI_RUNNING, "Project_Run", "project_run"),
          ("estop", DI_ESTOP, "ESTOP", "estop"))


@dataclass(frozen=True)
class ModbusTable:
    """One reading of the controller's own Modbus table, SI: joint angles [rad], flags, host receive time."""

    q: np.ndarray
    error: bool
    project_running: bool
    estop: bool
    t: float  # time.monotonic() when the reply arrived


@dataclass(frozen=True)
class CrossCheck:
    """The Modbus table against the Ethernet Slave's tables around it: how far the joints differ, which flags do."""

    endpoint: str
    joint_diff_deg: tuple[float, ...]  # |Modbus - Ethernet Slave| per joint
    worst_joint: int  # 1-based: the joint furthest over its allowance (or the largest difference when none is)
    allowed_deg: float  # that joint's allowance: JOINT_TOLERANCE_DEG plus its motion between the two reads
    joints_agree: bool
    differing_flags: tuple[str, ...]  # "estop (Modbus 7208 True, Ethernet Slave ESTOP False)", ...
    unchecked_flags: tuple[str, ...]  # flags the Ethernet Slave's table does not carry

    @property
    def agrees(self) -> bool:
        return self.joints_agree and not self.differing_flags

    @property
    def max_joint_diff_deg(self) -> float:
        return max(self.joint_diff_deg)

    def summary(self) -> str:
        """One line: what was compared and how it came out."""
        worst = self.joint_diff_deg[self.worst_joint - 1]
        joints = (f"joints within {self.max_joint_diff_deg:.3f} deg of the Ethernet Slave's (allowed "
                  f"{self.allowed_deg:.2f})" if self.joints_agree else
                  f"joint {self.worst_joint} reads {worst:.3f} deg off the Ethernet Slave's (allowed "
                  f"{self.allowed_deg:.2f}; joints off by {', '.join(f'{d:.3f}' for d in self.joint_diff_deg)} deg)")
        flags = (f"flags differ: {'; '.join(self.differing_flags)}" if self.differing_flags else
                 "error, running and E-stop agree")
        unchecked = f" (not in the slave table: {', '.join(self.unchecked_flags)})" if self.unchecked_flags else ""
        return f"Modbus table {self.endpoint}: {joints}; {flags}{unchecked}"

    def as_dict(self) -> dict[str, Any]:
        return {"endpoint": self.endpoint, "agrees": self.agrees,
                "max_joint_diff_deg": round(self.max_joint_diff_deg, 4),
                "joint_diff_deg": [round(d, 4) for d in self.joint_diff_deg], "worst_joint": self.worst_joint,
                "allowed_deg": round(self.allowed_deg, 4), "differing_flags": list(self.differing_flags),
                "unchecked_flags": list(self.unchecked_flags)}


def read_modbus_table(host: str, port: int, timeout_s: float) -> ModbusTable:
    """Connect, read input registers 7013-7024 and the documented discrete inputs (7200-7202, 7204, 7208),
    close.  Each step is bounded by `timeout_s`; LinkLostError (no server, no reply) or ProtocolError (exception
    reply, bad data), one line."""
    endpoint = f"{host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise LinkLostError(f"TM Modbus table {endpoint}: no Modbus/TCP server answers "
                            f"({exc.strerror or first_line(exc)})") from None
    # retries=0: one try per request, so an unanswered one costs timeout_s, not several.
    client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0, name="tm5-table")
    client.socket = sock  # the connection made above, whose failure names its reason (connect() only logs it)
    try:
        regs = _call(client, endpoint, f"read input registers {IR_JOINTS}", timeout_s,
                     lambda c: c.read_input_registers(IR_JOINTS, count=2 * N_JOINTS, device_id=UNIT_ID)).registers
        # The documented inputs only, run by run: a controller may refuse a read over the undocumented ones.
        bits = [False] * DI_COUNT
        for address, count in DI_RUNS:
            got = _call(client, endpoint, f"read discrete inputs {address}", timeout_s,
                        functools.partial(_read_inputs, address=address, count=count)).bits
            if len(got) < count:
                raise ProtocolError(f"TM Modbus table {endpoint}: asked {count} discrete inputs at {address}, "
                                    f"got {len(got)}")
            bits[address - DI_FIRST:address - DI_FIRST + count] = [bool(b) for b in got[:count]]
        t = time.monotonic()
    finally:
        client.close()
    if len(regs) != 2 * N_JOINTS:
        raise ProtocolError(f"TM Modbus table {endpoint}: asked {2 * N_JOINTS} registers at {IR_JOINTS}, "
                            f"got {len(regs)}")
    q_deg = regs_to_floats(regs)
    if not np.all(np.isfinite(q_deg)):
        raise ProtocolError(f"TM Modbus table {endpoint}: joint angles at {IR_JOINTS} hold non-finite values "
                            f"{q_deg.tolist()}")
    return ModbusTable(q=np.radians(q_deg), error=bool(bits[DI_ERROR - DI_FIRST]),
                       project_running=bool(bits[DI_RUNNING - DI_FIRST]), estop=bool(bits[DI_ESTOP - DI_FIRST]),
                       t=t)


Sample = tuple[SlaveState, float]  # an Ethernet Slave table and the host's monotonic time of its arrival


def compare(table: ModbusTable, slaves: Sequence[Sample], endpoint: str,
            tolerance_deg: float = JOINT_TOLERANCE_DEG) -> CrossCheck:
    """The Modbus reading against the Ethernet Slave tables around it (the last before it and the first after,
    say): each joint against the sample it is closest to, each flag differing only when it differs from all of
    them, so that motion or a flag's edge between the two reads is no disagreement."""
    if not slaves:
        raise ValueError("compare needs at least one Ethernet Slave table")
    diffs, overs, alloweds = [], [], []
    for slave, t in slaves:
        diff = np.abs(np.degrees(table.q - slave.q))
        # The joints move between the two samples: allow each its own speed over the time between them.
        allowed = tolerance_deg + np.degrees(np.abs(slave.dq)) * (abs(table.t - t) + SAMPLE_AGE_S)
        diffs.append(diff)
        overs.append(diff - allowed)
        alloweds.append(allowed)
    best = np.argmin(np.asarray(overs), axis=0)  # per joint, the sample it agrees with best
    cols = np.arange(N_JOINTS)
    diff = np.asarray(diffs)[best, cols]
    over = np.asarray(overs)[best, cols]
    allowed = np.asarray(alloweds)[best, cols]
    worst = int(np.argmax(over)) if np.any(over > 0) else int(np.argmax(diff))
    differing, unchecked = [], []
    for name, address, item, field in _FLAGS:
        modbus_value = getattr(table, name)
        seen = [bool(v) for v in (getattr(slave, field) for slave, _ in slaves) if v is not None]
        if not seen:
            unchecked.append(name)
        elif modbus_value not in seen:
            differing.append(f"{name} (Modbus {address} {modbus_value}, Ethernet Slave {item} {seen[-1]})")
    return CrossCheck(endpoint=endpoint, joint_diff_deg=tuple(float(d) for d in diff), worst_joint=worst + 1,
                      allowed_deg=float(allowed[worst]), joints_agree=bool(np.all(over <= 0)),
                      differing_flags=tuple(differing), unchecked_flags=tuple(unchecked))


def check_arm(arm: SlaveTables) -> CrossCheck:
    """The controller's Modbus table (at the arm's host, `modbus_port`, each step bounded by reply_timeout_s)
    against the connected `arm`'s Ethernet Slave tables just before and just after it (doctor, status, arming).
    Blocks on a request and its reply, and on the next broadcast: never call it from the control loop."""
    cfg = arm.config
    if cfg.modbus_port is None:
        raise ValueError("the Modbus cross-check is off (devices.arm.settings.modbus_port is null)")
    before = _sample(arm)
    table = read_modbus_table(cfg.host, cfg.modbus_port, cfg.reply_timeout_s)
    # The first table to arrive after the Modbus reply (or, should none come within a few broadcast periods,
    # the latest: the comparison then allows for the time since).
    seq = arm.read_state().seq
    deadline = time.monotonic() + cfg.stale_after_s
    while arm.read_state().seq == seq and time.monotonic() < deadline:
        time.sleep(_POLL_S)
    return compare(table, [before, _sample(arm)], f"{cfg.host}:{cfg.modbus_port}")


def check_before_arming(arm: SlaveTables) -> None:
    """Refuse to arm (LifecycleError, one line) when the controller's Modbus table disagrees with the Ethernet
    Slave's, or (LinkLostError/ProtocolError) cannot be read: the cell would move on a table it cannot trust."""
    hint = "or set devices.arm.settings.modbus_port: null to arm without the cross-check"
    try:
        check = check_arm(arm)
    except (LinkLostError, ProtocolError) as exc:
        raise type(exc)(f"cannot arm: {exc}; enable the controller's Modbus TCP server (TMflow: Setting > "
                        f"Connection > Modbus), {hint}") from None
    if not check.agrees:
        raise LifecycleError(f"cannot arm: {check.summary()}; devices.arm.settings.host/modbus_port reach another "
                             f"table than the Ethernet Slave's (another machine, or another data table): fix that, "
                             f"{hint}")
    log.info("%s", check.summary())


def _sample(arm: SlaveTables) -> Sample:
    state = arm.read_state()
    table = arm.latest_table
    if table is None:
        raise LinkLostError(f"TM {arm.endpoint}: no Ethernet Slave table to cross-check")
    return table, state.t


def _read_inputs(client: ModbusTcpClient, address: int, count: int) -> ModbusPDU:
    return client.read_discrete_inputs(address, count=count, device_id=UNIT_ID)


def _call(client: ModbusTcpClient, endpoint: str, op: str, timeout_s: float,
          fn: Callable[[ModbusTcpClient], ModbusPDU]) -> ModbusPDU:
    try:
        rr = fn(client)
    except ModbusIOException:
        raise LinkLostError(f"TM Modbus table {endpoint}: {op}: no reply within {timeout_s * 1000:.0f} ms") from None
    except (ModbusException, OSError) as exc:
        raise LinkLostError(f"TM Modbus table {endpoint}: {op}: no valid reply ({first_line(exc)})") from None
    if rr is None:
        raise LinkLostError(f"TM Modbus table {endpoint}: {op}: no reply")
    if rr.isError():
        code = getattr(rr, "exception_code", None)
        raise ProtocolError(f"TM Modbus table {endpoint}: {op}: Modbus exception reply code {code} "
                            f"({exception_name(code)})")
    return rr

