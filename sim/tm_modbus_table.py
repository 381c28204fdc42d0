"""The TM controller's own Modbus table for the emulators: input registers 7001-7036, discrete inputs 7200-7208."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import numpy as np
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusBaseServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.tm5.registers import (
    COIL_PLAY_PAUSE,
    DI_COUNT,
    DI_ERROR,
    DI_ESTOP,
    DI_FIRST,
    DI_PAUSED,
    DI_RUNNING,
    DI_RUNS,
    IR_COUNT,
    IR_FIRST,
    IR_FLANGE_POSE,
    IR_JOINTS,
    IR_TOOL_POSE,
    USER_AREA_FIRST,
    floats_to_regs,
    pose_to_regs,
)
from sim.plant_api import PlantLike

DI_LINK = DI_FIRST  # 7200: robot link up
_DOCUMENTED_INPUTS = frozenset(a + i for a, n in DI_RUNS for i in range(n))
# pymodbus' non-shared bit blocks address bit b as register b // 16, bit b % 16: keep the base aligned.
assert DI_FIRST % 16 == 0


class ControllerTable:
    """Images of the controller's registers (joint angles, flange and tool poses, status inputs), published
    from a plant and served through a pymodbus access hook: the images are the truth, copied into pymodbus'
    registers before every read."""

    def __init__(self) -> None:
        self.ir = [0] * IR_COUNT
        self.di = [False] * DI_COUNT
        # Serve the documented discrete inputs alone (a controller without 7203, 7205-7207): a read that
        # covers another address gets exception 2, illegal data address.
        self.documented_inputs_only = False

    def screen_request(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        """pymodbus' `trace_pdu` hook: a discrete-input read that covers an undocumented address, while only the
        documented ones are served, is pointed outside the table (pymodbus then answers exception 2, illegal
        data address).  The access hook cannot do this: it sees a bit read's count in whole registers."""
        if (not sending and self.documented_inputs_only and pdu.function_code == 2
                and any(a not in _DOCUMENTED_INPUTS for a in range(pdu.address, pdu.address + pdu.count))):
            pdu.address = 0
        return pdu

    def publish(self, plant: PlantLike, q: np.ndarray, *, error: bool, running: bool, paused: bool, estop: bool,
                joint_offset_deg: float = 0.0) -> None:
        """Joint angles `q` [rad] (plus `joint_offset_deg` on every joint: a table that disagrees), the plant's
        flange and tool poses, and the status inputs."""
        ir = self.ir
        j = IR_JOINTS - IR_FIRST
        ir[j:j + 12] = floats_to_regs(np.degrees(q) + joint_offset_deg, allow_nonfinite=True)
        f = IR_FLANGE_POSE - IR_FIRST
        ir[f:f + 12] = pose_to_regs(*plant.flange_pose(), allow_nonfinite=True)
        t = IR_TOOL_POSE - IR_FIRST
        ir[t:t + 12] = pose_to_regs(*plant.tool_pose(), allow_nonfinite=True)
        di = self.di
        di[DI_LINK - DI_FIRST] = True
        di[DI_ERROR - DI_FIRST] = error
        di[DI_RUNNING - DI_FIRST] = running
        di[DI_PAUSED - DI_FIRST] = paused
        di[DI_ESTOP - DI_FIRST] = estop

    @staticmethod
    def discrete_inputs_block() -> list[SimData]:
        return [SimData(DI_FIRST, count=DI_COUNT, values=False, datatype=DataType.BITS)]

    @staticmethod
    def input_registers_block() -> list[SimData]:
        return [SimData(IR_FIRST, count=IR_COUNT, values=0, datatype=DataType.REGISTERS)]

    def serve_read(self, function_code: int, start: int, address: int, count: int, registers: list[int]) -> bool:
        """Fill pymodbus' registers for a read of this table (function 04 or 02); False for any other request."""
        if function_code == 4:
            registers[address - start:address - start + count] = self.ir[address - IR_FIRST:address - IR_FIRST + count]
            return True
        if function_code == 2:
            registers[DI_FIRST // 16 - start] = sum(1 << i for i, bit in enumerate(self.di) if bit)
            return True
        return False


def table_device(table: ControllerTable, action: Any) -> SimDevice:
    """A device with the controller's table, every unit id.  pymodbus wants all four blocks: the coil and
    holding blocks are placeholders at the controller's addresses, which `action` answers as it chooses."""
    return SimDevice(0, simdata=([SimData(COIL_PLAY_PAUSE, count=2, values=False, datatype=DataType.BITS)],
                                 table.discrete_inputs_block(),
                                 [SimData(USER_AREA_FIRST, count=1, values=0, datatype=DataType.REGISTERS)],
                                 table.input_registers_block()),
                     action=action)


async def start_server(device: SimDevice, host: str, port: int,
                       trace_pdu: Callable[[bool, ModbusPDU], ModbusPDU] | None = None) -> tuple[ModbusTcpServer, int]:
    """Serve `device` on `host:port` in the running loop; (server, bound port).  RuntimeError when the address
    cannot be bound.  `trace_pdu`: pymodbus' hook on every request and reply."""
    server = ModbusTcpServer(device, address=(host, port), trace_pdu=trace_pdu)
    await server.serve_forever(background=True)
    listener: Any = server.transport
    return server, int(listener.sockets[0].getsockname()[1])


async def close_server(server: ModbusTcpServer) -> None:
    """Close the listener and every client connection."""
    await server.shutdown()
    if ModbusBaseServer.active_server is server:  # pymodbus' class-level reference would keep it alive
        ModbusBaseServer.active_server = None
    for _ in range(3):  # let the transports run their connection_lost callbacks (sockets closed)
        await asyncio.sleep(0)
