"""The Modbus TCP wire: the MBAP header, the function codes served, the protocol's limits.

Frame layout (Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3)::

    0      2      4      6    7     8
    +------+------+------+----+-----+---------------------+
    | tid  | pid  | len  |unit| fc  | data (len - 2 bytes) |
    +------+------+------+----+-----+---------------------+
     u16 BE u16=0  u16    u8   u8
                   len counts unit + PDU: 2..254 (a PDU is at most 253 bytes)

Every header and reply frame is packed and unpacked with a precompiled :class:`struct.Struct`
from here; :data:`REGISTER_FRAMES` holds one per register count, so that a whole FC3/FC4 reply,
MBAP header included, is one ``pack`` (why: :mod:`gateway.modbus.handler`).  No I/O, no state.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Final

from gateway.errors import ModbusExceptionReply

__all__ = [
    "ADDRESS_COUNT",
    "ADDRESS_COUNT_BYTES",
    "BIT_READS",
    "COIL_OFF",
    "COIL_ON",
    "EXCEPTION_FRAME",
    "GATEWAY_PATH_UNAVAILABLE",
    "ILLEGAL_DATA_ADDRESS",
    "ILLEGAL_DATA_VALUE",
    "ILLEGAL_FUNCTION",
    "MAX_LENGTH",
    "MAX_READ_BITS",
    "MAX_READ_REGISTERS",
    "MAX_WRITE_BITS",
    "MAX_WRITE_REGISTERS",
    "MBAP",
    "MIN_LENGTH",
    "MULTIPLE_WRITES",
    "READ_HEAD",
    "REGISTER_FRAMES",
    "REGISTER_READS",
    "SERVER_DEVICE_FAILURE",
    "SINGLE_WRITES",
    "WRITE_FUNCTION_CODES",
    "FunctionCode",
]


class FunctionCode(IntEnum):
    """Function codes served (Modbus Application Protocol Specification V1.1b3, 6.1-6.12)."""

    READ_COILS = 0x01  # 6.1
    READ_DISCRETE_INPUTS = 0x02  # 6.2
    READ_HOLDING_REGISTERS = 0x03  # 6.3
    READ_INPUT_REGISTERS = 0x04  # 6.4
    WRITE_SINGLE_COIL = 0x05  # 6.5
    WRITE_SINGLE_REGISTER = 0x06  # 6.6
    WRITE_MULTIPLE_COILS = 0x0F  # 6.11
    WRITE_MULTIPLE_REGISTERS = 0x10  # 6.12


REGISTER_READS: Final = frozenset({FunctionCode.READ_HOLDING_REGISTERS, FunctionCode.READ_INPUT_REGISTERS})
BIT_READS: Final = frozenset({FunctionCode.READ_COILS, FunctionCode.READ_DISCRETE_INPUTS})
SINGLE_WRITES: Final = frozenset({FunctionCode.WRITE_SINGLE_COIL, FunctionCode.WRITE_SINGLE_REGISTER})
MULTIPLE_WRITES: Final = frozenset({FunctionCode.WRITE_MULTIPLE_COILS, FunctionCode.WRITE_MULTIPLE_REGISTERS})

#: Function codes that change data (Modbus Application Protocol V1.1b3, 6.5, 6.6, 6.11, 6.12, 6.16,
#: 6.17): a client without write rights gets 0x01 for each, before anything else is checked.
WRITE_FUNCTION_CODES: Final = frozenset({0x05, 0x06, 0x0F, 0x10, 0x16, 0x17})

# Protocol limits (Modbus Application Protocol Specification V1.1b3, 6.1-6.12).
MAX_READ_BITS: Final = 2000
MAX_READ_REGISTERS: Final = 125
MAX_WRITE_BITS: Final = 1968
MAX_WRITE_REGISTERS: Final = 123
COIL_ON: Final = 0xFF00
COIL_OFF: Final = 0x0000
MIN_LENGTH: Final = 2  # MBAP length field: unit id + function code
MAX_LENGTH: Final = 254  # unit id + 253-byte PDU

MBAP: Final = struct.Struct(">HHHB")  # tid, protocol id, length, unit
ADDRESS_COUNT: Final = struct.Struct(">HH")  # from PDU offset 1: address, count or value
ADDRESS_COUNT_BYTES: Final = struct.Struct(">HHB")  # from PDU offset 1: FC15/FC16 header
EXCEPTION_FRAME: Final = struct.Struct(">HHHBBB")  # MBAP, fc | 0x80, exception code
#: ``REGISTER_FRAMES[n]``: a whole FC3/FC4 reply frame of n registers: MBAP, fc, byte count, values.
REGISTER_FRAMES: Final = [struct.Struct(f">HHHBBB{n}H") for n in range(MAX_READ_REGISTERS + 1)]
READ_HEAD: Final = struct.Struct(">HHHBBB")  # MBAP, fc, byte count (the data follows)

# The exception codes the server itself answers (the backend may raise any other).
ILLEGAL_FUNCTION: Final = ModbusExceptionReply.ILLEGAL_FUNCTION
ILLEGAL_DATA_ADDRESS: Final = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS
ILLEGAL_DATA_VALUE: Final = ModbusExceptionReply.ILLEGAL_DATA_VALUE
SERVER_DEVICE_FAILURE: Final = ModbusExceptionReply.SERVER_DEVICE_FAILURE
GATEWAY_PATH_UNAVAILABLE: Final = ModbusExceptionReply.GATEWAY_PATH_UNAVAILABLE
