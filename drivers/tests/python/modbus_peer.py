"""Independent Modbus TCP peer for geocal's modbus_table driver tests (pymodbus 3.x,
SimDevice API; tested with 3.16). Same register map as drivers/tests/modbus_table.rs:

  holding 100-101  target, 32-bit signed, big word order (high word first)
  holding 110      command: 1 = go, 0 = clear
  input   200-201  actual (encoder) angle, same encoding as the target
  input   300      status: bit 0 in position, bit 1 moving, bit 2 fault, bit 3 ack
  input   301      fault code

Shared register space (input and holding read the same words). Behaviour: on go, the
target is copied to the actual angle and the status shows in position and ack; a write
of 0 to the command register clears the ack.

Usage: python3 modbus_peer.py --port PORT
"""

import argparse
import asyncio
import logging

from pymodbus.constants import ExcCodes  # noqa: F401  (fails early on too old a pymodbus)
from pymodbus.server import StartAsyncTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

TARGET, COMMAND, ACTUAL, STATUS, FAULT_CODE = 100, 110, 200, 300, 301
IN_POSITION, ACK = 1 << 0, 1 << 3
GO = 1
WRITES = (6, 16)


async def action(function_code, start_address, address, count, registers, set_values):
    """Called before each access; `registers` is the whole block, modified in place."""
    if function_code not in WRITES or not set_values:
        return None
    if not address <= COMMAND < address + len(set_values):
        return None
    value = set_values[COMMAND - address]
    base = start_address
    if value == GO:
        # The target may be written in the same request.
        words = [registers[TARGET - base], registers[TARGET + 1 - base]]
        for i in range(2):
            if address <= TARGET + i < address + len(set_values):
                words[i] = set_values[TARGET + i - address]
        registers[ACTUAL - base] = words[0]
        registers[ACTUAL + 1 - base] = words[1]
        registers[STATUS - base] = IN_POSITION | ACK
    else:
        registers[STATUS - base] &= ~ACK & 0xFFFF
    return None


async def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--unit", type=int, default=1)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    device = SimDevice(
        id=args.unit,
        simdata=[SimData(0, count=400, values=0, datatype=DataType.REGISTERS)],
        action=action,
    )
    await StartAsyncTcpServer(context=device, address=("127.0.0.1", args.port))


if __name__ == "__main__":
    asyncio.run(main())
