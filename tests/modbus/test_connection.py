"""One client connection (``gateway.modbus.connection``): a read that waits for its data (``read_wait``)
holds the requests of its connection behind it, so that the replies keep the order of the requests;
other connections do not wait for it.  Real sockets on 127.0.0.1, a backend serving from memory.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from collections.abc import AsyncIterator, Sequence

import pytest

from gateway.errors import ModbusExceptionReply, StaleRead
from gateway.modbus.server import ModbusTcpServer
from tests.waiting import until as wait_until

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


async def test_a_client_that_stops_sending_gets_the_replies_in_flight_then_the_end(
        server: ModbusTcpServer, backend: ImageBackend) -> None:
    """A half-close (the client's EOF) with a read still waiting: its reply is sent, then the server
    closes its side."""
    reader, writer = await asyncio.open_connection(HOST, server.port)
    try:
        writer.write(read_request(1, STALE))
        await asyncio.wait_for(backend.waiting.wait(), 5.0)
        writer.write_eof()
        await asyncio.sleep(0.05)  # the EOF reaches the server while the read waits
        backend.fresh.set()
        assert await read_reply(reader) == (1, [1100])
        assert await asyncio.wait_for(reader.read(), 5.0) == b""  # then the end
    finally:
        writer.close()


@pytest.fixture
async def timed_server(backend: ImageBackend) -> AsyncIterator[ModbusTcpServer]:
    """frame_timeout 2 s: a connection is stalled after a grace of min(1 s, 2 s / 2) = 1 s."""
    modbus = ModbusTcpServer(backend, HOST, 0, frame_timeout=2.0)
    await modbus.start()
    yield modbus
    await modbus.close()


async def test_a_connection_that_sends_nothing_is_stalled_after_the_grace(timed_server: ModbusTcpServer) -> None:
    loop = asyncio.get_running_loop()
    before = loop.time()
    _reader, writer = await asyncio.open_connection(HOST, timed_server.port)
    try:
        await wait_until(lambda: timed_server.connection_count == 1)
        (connection,) = timed_server._connections
        assert connection.stalled_since() is None  # just connected
        await asyncio.sleep(0.8)  # past a third of frame_timeout, not past the grace
        if loop.time() - before < 1.0:  # (a loaded machine may have slept longer: nothing to check)
            assert connection.stalled_since() is None
        await asyncio.sleep(0.25)
        since = connection.stalled_since()
        assert since is not None and before <= since <= loop.time() - 1.0
        writer.write(read_request(1, 7))  # a complete request: not stalled any more
        await wait_until(lambda: connection.stalled_since() is None)
    finally:
        writer.close()


async def test_a_connection_with_an_incomplete_frame_is_stalled_from_when_it_began(
        timed_server: ModbusTcpServer) -> None:
    loop = asyncio.get_running_loop()
    _reader, writer = await asyncio.open_connection(HOST, timed_server.port)
    try:
        await wait_until(lambda: timed_server.connection_count == 1)
        (connection,) = timed_server._connections
        await asyncio.sleep(0.3)
        began = loop.time()
        writer.write(read_request(1, 7)[:3])  # the first bytes of the stream, and no more
        await asyncio.sleep(1.1)
        since = connection.stalled_since()
        assert since is not None and since >= began  # not since the connection was made
    finally:
        writer.close()


async def test_a_dropped_connection_is_logged_with_the_server_and_the_peer(
        server: ModbusTcpServer, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    reader, writer = await asyncio.open_connection(HOST, server.port)
    host, port = writer.get_extra_info("sockname")[:2]
    try:
        writer.write(struct.pack(">HHHB", 1, 7, 6, UNIT) + bytes(5))  # protocol id 7
        assert await asyncio.wait_for(reader.read(), 5.0) == b""
    finally:
        writer.close()
    (line,) = [r.getMessage() for r in caplog.records if "closing connection" in r.getMessage()]
    assert line.startswith(f"modbus: closing connection from {host}:{port}: bad MBAP header (protocol id 7")


async def test_the_frame_clock_restarts_for_each_new_incomplete_frame(backend: ImageBackend) -> None:
    """frame_timeout 0.4 s: frame A's first bytes at 0, the rest of A and B's first bytes at 0.25; B is
    timed from 0.25 (dropped at about 0.65), not from A's start."""
    modbus = ModbusTcpServer(backend, HOST, 0, frame_timeout=0.4)
    await modbus.start()
    loop = asyncio.get_running_loop()
    reader, writer = await asyncio.open_connection(HOST, modbus.port)
    try:
        a, b = read_request(1, 7), read_request(2, 8)
        start = loop.time()
        writer.write(a[:3])
        await asyncio.sleep(0.25)
        writer.write(a[3:] + b[:3])
        assert await read_reply(reader) == (1, [1007])
        await asyncio.sleep(max(0.0, start + 0.5 - loop.time()))
        if loop.time() - start < 0.6:  # (a loaded machine may have slept past B's deadline)
            assert modbus.connection_count == 1  # B's clock started at 0.25: not timed out at 0.5
        assert await asyncio.wait_for(reader.read(), 2.0) == b""  # but it does time out
    finally:
        writer.close()
        await modbus.close()


async def test_a_connection_is_not_idle_while_a_request_is_in_flight(backend: ImageBackend) -> None:
    """idle_timeout 0.3 s: a read that waits 0.4 s for its data, then another request at once: served."""
    modbus = ModbusTcpServer(backend, HOST, 0, idle_timeout=0.3)
    await modbus.start()
    reader, writer = await asyncio.open_connection(HOST, modbus.port)
    try:
        writer.write(read_request(1, STALE))
        await asyncio.wait_for(backend.waiting.wait(), 5.0)
        await asyncio.sleep(0.4)
        backend.fresh.set()
        assert await read_reply(reader) == (1, [1100])
        writer.write(read_request(2, 7))
        assert await read_reply(reader) == (2, [1007])
    finally:
        writer.close()
        await modbus.close()
