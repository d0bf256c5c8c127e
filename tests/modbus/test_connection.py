"""One client connection (``gateway.modbus.connection``): a read that waits for its data (``read_wait``)
holds the requests of its connection behind it, so that the replies keep the order of the requests;
other connections do not wait for it.  Real sockets on 127.0.0.1, a backend serving from memory.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator, Sequence

import pytest

from gateway.errors import ModbusExceptionReply, StaleRead
from gateway.modbus.server import ModbusTcpServer

HOST = "127.0.0.1"
UNIT = 1
STALE = 100  # holding register 100 is not read yet: a read of it waits


class ImageBackend:
    """Registers served from memory (``read_now``): register a holds a + 1000, but ``STALE`` waits
    (``StaleRead``) until ``fresh`` is set."""

    def __init__(self) -> None:
        self.fresh = asyncio.Event()
        self.waiting = asyncio.Event()  # a read waits for the stale register

    def has_unit(self, unit: int) -> bool:
        return unit == UNIT

    async def _wait(self) -> None:
        self.waiting.set()
        await self.fresh.wait()

    def read_now(self, unit: int, function_code: int, address: int, count: int) -> bytes:
        if function_code != 3:
            raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_FUNCTION)
        if address <= STALE < address + count and not self.fresh.is_set():
            raise StaleRead("not read yet", self._wait, read_wait=10.0)
        return struct.pack(f">{count}H", *(a + 1000 for a in range(address, address + count)))

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_FUNCTION)

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_FUNCTION)

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        raise AssertionError("served from memory (read_now)")

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_FUNCTION)

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_FUNCTION)

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_FUNCTION)


@pytest.fixture
def backend() -> ImageBackend:
    return ImageBackend()


@pytest.fixture
async def server(backend: ImageBackend) -> AsyncIterator[ModbusTcpServer]:
    modbus = ModbusTcpServer(backend, HOST, 0)
    await modbus.start()
    yield modbus
    await modbus.close()


def read_request(tid: int, address: int, count: int = 1) -> bytes:
    return struct.pack(">HHHBBHH", tid, 0, 6, UNIT, 3, address, count)


async def read_reply(reader: asyncio.StreamReader) -> tuple[int, list[int]]:
    """One FC3 reply: (transaction id, registers)."""
    async with asyncio.timeout(5.0):
        tid, protocol, length, unit = struct.unpack(">HHHB", await reader.readexactly(7))
        pdu = await reader.readexactly(length - 1)
    assert (protocol, unit, pdu[0]) == (0, UNIT, 3), pdu.hex()
    return tid, list(struct.unpack(f">{pdu[1] // 2}H", pdu[2:]))


async def test_requests_after_a_waiting_read_are_answered_after_it_in_request_order(
        server: ModbusTcpServer, backend: ImageBackend) -> None:
    reader, writer = await asyncio.open_connection(HOST, server.port)
    try:
        # a fresh read and the stale one, pipelined in one segment
        writer.write(read_request(1, 7) + read_request(2, STALE) + read_request(3, 8))
        assert await read_reply(reader) == (1, [1007])  # before the waiting read: at once
        await asyncio.wait_for(backend.waiting.wait(), 5.0)
        # requests that come while it waits: held behind it too
        writer.write(read_request(4, 9, 2))
        await writer.drain()
        await asyncio.sleep(0.05)  # let them reach the server (it must not answer them yet)
        backend.fresh.set()
        replies = [await read_reply(reader) for _ in range(3)]
        assert replies == [(2, [1100]), (3, [1008]), (4, [1009, 1010])]
    finally:
        writer.close()


async def test_another_connection_does_not_wait_for_a_waiting_read(
        server: ModbusTcpServer, backend: ImageBackend) -> None:
    held_reader, held_writer = await asyncio.open_connection(HOST, server.port)
    reader, writer = await asyncio.open_connection(HOST, server.port)
    try:
        held_writer.write(read_request(1, STALE))
        await asyncio.wait_for(backend.waiting.wait(), 5.0)
        held_writer.write(read_request(2, 5))
        writer.write(read_request(9, 5))
        assert await read_reply(reader) == (9, [1005])  # answered while the other connection waits
        backend.fresh.set()
        assert [await read_reply(held_reader) for _ in range(2)] == [(1, [1100]), (2, [1005])]
    finally:
        held_writer.close()
        writer.close()
