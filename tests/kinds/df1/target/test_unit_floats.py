"""DF1 target mode: an F element's two registers in the order README gives (``word_order``, "F and
L: which register holds the high word", default ``"high-first"``), both ways: a PLC's write read
over Modbus, a Modbus write read by the PLC.

Values: IEEE 754 single 1.5 is 3FC00000 hex, 3.1415927 is 40490FDB hex; on the DF1 wire an F
element is little-endian with its low-order word first (SLC 5/03-5/05 PCCC replies), so 1.5 is
the bytes 00 00 C0 3F.
"""

from __future__ import annotations

import asyncio

from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import PcccHeader, ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite

from .plc_line import STATION, Plc

UNIT = 5


def config(port: int) -> str:
    return f"""
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "plc"
protocol = "df1"
role = "target"
port = "socket://127.0.0.1:{port}"
station = {STATION}
checksum = "crc"
unit = {UNIT}

[[link.file]]
file = 8
type = "F"
elements = 2
start = 200

[[link.file]]
file = 9
type = "F"
elements = 2
start = 300
word_order = "low-first"
"""


async def test_float_registers_follow_word_order_both_ways() -> None:
    plc = Plc()
    server = await asyncio.start_server(plc.connected, "127.0.0.1", 0)
    try:
        async with Gateway(parse_config(config(server.sockets[0].getsockname()[1]))) as gw:
            modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
            await modbus.connect()
            try:
                for file in (8, 9):
                    write = ProtectedTypedLogicalWrite(FileType.FLOAT, file, 0, 0, bytes.fromhex("0000C03F"))
                    assert PcccHeader.decode(await plc.msg(write)).sts == 0
                high_first = await modbus.read_holding_registers(200, count=2, device_id=UNIT)
                low_first = await modbus.read_holding_registers(300, count=2, device_id=UNIT)
                assert list(high_first.registers) == [0x3FC0, 0x0000]
                assert list(low_first.registers) == [0x0000, 0x3FC0]

                assert not (await modbus.write_registers(202, [0x4049, 0x0FDB], device_id=UNIT)).isError()
                assert not (await modbus.write_registers(302, [0x0FDB, 0x4049], device_id=UNIT)).isError()
                for file in (8, 9):
                    reply = await plc.msg(ProtectedTypedLogicalRead(FileType.FLOAT, file, 1, 0, 4))
                    assert PcccHeader.decode(reply).sts == 0 and reply[6:] == bytes.fromhex("DB0F4940"), file
            finally:
                modbus.close()
    finally:
        server.close()
        await server.wait_closed()
