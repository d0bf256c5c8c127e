"""The Modbus TCP server over real sockets on 127.0.0.1, with a plain dict store as backend."""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import shutil
import ssl
import struct
import subprocess
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymodbus.client import AsyncModbusTcpClient, AsyncModbusTlsClient

from gateway.errors import ModbusExceptionReply
from gateway.modbus.admission import host_allowed, peer_host
from gateway.modbus.server import (
    IPNetwork,
    ModbusBackend,
    ModbusTcpServer,
    make_tls_context,
)

HOST = "127.0.0.1"
UNIT = 1
SIZE = 1000  # addresses 0..999 of each table exist


class DictBackend:
    """A real, minimal backend: four tables (shared by its units) in dicts, addresses 0..size-1.

    ``write_gate``: when set, writes wait for it (``write_started`` tells they are waiting).
    ``read_gate``: the same for reads. ``fail``: raised by every call when set.
    ``calls`` records (method, unit, address) in the order the server made the calls.
    """

    def __init__(self, units: Sequence[int] = (UNIT,), size: int = SIZE) -> None:
        self.units = set(units)
        self.size = size
        self.coils: dict[int, bool] = {}
        self.discrete_inputs: dict[int, bool] = {a: a % 3 == 0 for a in range(size)}
        self.holding: dict[int, int] = {}
        self.input_registers: dict[int, int] = {a: (a * 7) & 0xFFFF for a in range(size)}
        self.calls: list[tuple[str, int, int]] = []
        self.write_gate: asyncio.Event | None = None
        self.read_gate: asyncio.Event | None = None
        self.write_started = asyncio.Event()
        self.fail: Exception | None = None

    def has_unit(self, unit: int) -> bool:
        return unit in self.units

    async def _enter(self, method: str, unit: int, address: int, count: int, write: bool) -> None:
        self.calls.append((method, unit, address))
        if self.fail is not None:
            raise self.fail
        if address + count > self.size:
            raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_DATA_ADDRESS)
        gate = self.write_gate if write else self.read_gate
        if write:
            self.write_started.set()
        if gate is not None:
            await gate.wait()

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        await self._enter("read_coils", unit, address, count, False)
        return [self.coils.get(a, False) for a in range(address, address + count)]

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        await self._enter("read_discrete_inputs", unit, address, count, False)
        return [self.discrete_inputs[a] for a in range(address, address + count)]

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        await self._enter("read_holding_registers", unit, address, count, False)
        return [self.holding.get(a, 0) for a in range(address, address + count)]

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        await self._enter("read_input_registers", unit, address, count, False)
        return [self.input_registers[a] for a in range(address, address + count)]

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        await self._enter("write_coils", unit, address, len(values), True)
        for offset, value in enumerate(values):
            self.coils[address + offset] = value

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        await self._enter("write_registers", unit, address, len(values), True)
        for offset, value in enumerate(values):
            self.holding[address + offset] = value


def _typed(backend: DictBackend) -> ModbusBackend:
    return backend  # mypy checks that DictBackend implements the Protocol


@pytest.fixture
def backend() -> DictBackend:
    return DictBackend()


@pytest.fixture
async def server(backend: DictBackend) -> AsyncIterator[ModbusTcpServer]:
    modbus = ModbusTcpServer(_typed(backend), HOST, 0, max_in_flight_per_connection=4)
    await modbus.start()
    yield modbus
    await modbus.close()


# -- raw client helpers -------------------------------------------------------------------


def frame(tid: int, pdu: bytes, unit: int = UNIT, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


def read_request(tid: int, function_code: int, address: int, count: int, unit: int = UNIT) -> bytes:
    return frame(tid, struct.pack(">BHH", function_code, address, count), unit)


async def read_reply(reader: asyncio.StreamReader) -> tuple[int, int, bytes]:
    """One reply: (transaction id, unit, PDU), within 2 s."""
    async with asyncio.timeout(2.0):
        header = await reader.readexactly(7)
        tid, protocol, length, unit = struct.unpack(">HHHB", header)
        assert protocol == 0
        pdu = await reader.readexactly(length - 1)
    return tid, unit, pdu


async def connect(
    server: ModbusTcpServer, ssl_context: ssl.SSLContext | None = None
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    if ssl_context is None:
        return await asyncio.open_connection(HOST, server.port)
    return await asyncio.open_connection(HOST, server.port, ssl=ssl_context, server_hostname="localhost")


async def closed_by_peer(reader: asyncio.StreamReader, within: float = 2.0) -> bool:
    """True when the server closes the connection within ``within`` s (any data is read past)."""
    try:
        async with asyncio.timeout(within):
            while await reader.read(4096):
                pass
    except (ConnectionResetError, BrokenPipeError, ssl.SSLError):
        return True
    except TimeoutError:
        return False
    return True


async def close_writer(writer: asyncio.StreamWriter) -> None:
    writer.close()
    try:
        await writer.wait_closed()
    except (ConnectionError, ssl.SSLError):
        pass


async def wait_until(predicate: Callable[[], bool]) -> None:
    """Poll ``predicate`` (server state that has no event to wait on) for up to 2 s."""
    async with asyncio.timeout(2.0):
        while not predicate():  # noqa: ASYNC110
            await asyncio.sleep(0.005)


async def exchange(server: ModbusTcpServer, request: bytes) -> tuple[int, int, bytes]:
    reader, writer = await connect(server)
    try:
        writer.write(request)
        return await read_reply(reader)
    finally:
        await close_writer(writer)


# -- a real Modbus client -----------------------------------------------------------------


async def test_pymodbus_client_every_function_code(server: ModbusTcpServer, backend: DictBackend) -> None:
    client = AsyncModbusTcpClient(HOST, port=server.port, timeout=2, retries=0)
    assert await client.connect()
    try:
        reply = await client.write_coil(10, True, device_id=UNIT)
        assert not reply.isError() and reply.address == 10 and reply.bits[0] is True
        reply = await client.write_coils(20, [True, False, True, True, False, False, True, False, True])
        assert not reply.isError() and reply.address == 20 and reply.count == 9
        reply = await client.read_coils(10, count=19, device_id=UNIT)
        assert not reply.isError()
        expected = [True] + [False] * 9 + [True, False, True, True, False, False, True, False, True]
        assert reply.bits[:19] == expected

        reply = await client.read_discrete_inputs(5, count=10, device_id=UNIT)
        assert reply.bits[:10] == [a % 3 == 0 for a in range(5, 15)]

        reply = await client.write_register(100, 0xBEEF, device_id=UNIT)
        assert not reply.isError() and reply.registers == [0xBEEF]
        reply = await client.write_registers(101, [1, 2, 0xFFFF], device_id=UNIT)
        assert not reply.isError() and reply.address == 101 and reply.count == 3
        reply = await client.read_holding_registers(100, count=4, device_id=UNIT)
        assert reply.registers == [0xBEEF, 1, 2, 0xFFFF]

        reply = await client.read_input_registers(0, count=125, device_id=UNIT)
        assert reply.registers == [(a * 7) & 0xFFFF for a in range(125)]
        reply = await client.read_coils(SIZE - 1, count=2, device_id=UNIT)
        assert reply.isError() and reply.exception_code == 0x02
    finally:
        client.close()
    assert backend.coils[10] is True and backend.coils[28] is True
    assert backend.holding[100] == 0xBEEF
    counters = server.counters
    assert counters.requests[1] == 2 and counters.requests[3] == 1 and counters.requests[15] == 1
    assert counters.connections_accepted == 1


async def test_largest_requests() -> None:
    backend = DictBackend(size=2000)
    modbus = ModbusTcpServer(backend, HOST, 0)
    await modbus.start()
    client = AsyncModbusTcpClient(HOST, port=modbus.port, timeout=2, retries=0)
    assert await client.connect()
    try:
        values = [True, False, False] * 656  # 1968 coils, the FC15 maximum
        assert not (await client.write_coils(0, values)).isError()
        reply = await client.read_coils(0, count=2000)  # the FC1 maximum
        assert reply.bits[:2000] == values + [False] * 32
        reply = await client.read_discrete_inputs(0, count=2000)
        assert reply.bits[:2000] == [a % 3 == 0 for a in range(2000)]
        registers = list(range(1000, 1123))  # 123 registers, the FC16 maximum
        assert not (await client.write_registers(500, registers)).isError()
        reply = await client.read_holding_registers(499, count=125)  # the FC3 maximum
        assert reply.registers == [0, *registers, 0]
    finally:
        client.close()
        await modbus.close()


# -- pipelining and concurrency -----------------------------------------------------------


async def test_two_requests_in_one_segment(server: ModbusTcpServer, backend: DictBackend) -> None:
    backend.holding.update({0: 11, 1: 22})
    reader, writer = await connect(server)
    try:
        writer.write(read_request(0x1234, 3, 0, 1) + read_request(0x5678, 4, 3, 2))
        replies = {tid: pdu for tid, _, pdu in [await read_reply(reader), await read_reply(reader)]}
        assert replies == {
            0x1234: struct.pack(">BBH", 3, 2, 11),
            0x5678: struct.pack(">BBHH", 4, 4, 21, 28),
        }
    finally:
        await close_writer(writer)


async def test_many_pipelined_requests_beyond_in_flight_limit(
    server: ModbusTcpServer, backend: DictBackend
) -> None:
    backend.holding.update({a: a + 1000 for a in range(100)})
    reader, writer = await connect(server)
    try:
        writer.write(b"".join(read_request(tid, 3, tid, 1) for tid in range(100)))
        replies = dict([(tid, pdu) for tid, _, pdu in [await read_reply(reader) for _ in range(100)]])
        assert replies == {tid: struct.pack(">BBH", 3, 2, tid + 1000) for tid in range(100)}
        assert [address for _, _, address in backend.calls] == list(range(100))  # arrival order
    finally:
        await close_writer(writer)


async def test_read_answered_while_write_pending(server: ModbusTcpServer, backend: DictBackend) -> None:
    backend.write_gate = asyncio.Event()
    backend.holding[7] = 77
    reader, writer = await connect(server)
    try:
        writer.write(frame(10, struct.pack(">BHH", 6, 7, 1234)))
        await asyncio.wait_for(backend.write_started.wait(), 2)
        writer.write(read_request(11, 3, 7, 1))
        tid, _, pdu = await read_reply(reader)
        assert (tid, pdu) == (11, struct.pack(">BBH", 3, 2, 77))
        backend.write_gate.set()
        tid, _, pdu = await read_reply(reader)
        assert (tid, pdu) == (10, struct.pack(">BHH", 6, 7, 1234))
        assert [method for method, _, _ in backend.calls] == ["write_registers", "read_holding_registers"]
    finally:
        await close_writer(writer)


async def test_in_flight_limit_holds_back_the_backend(backend: DictBackend) -> None:
    backend.read_gate = asyncio.Event()
    modbus = ModbusTcpServer(backend, HOST, 0, max_in_flight_per_connection=2)
    await modbus.start()
    reader, writer = await connect(modbus)
    try:
        writer.write(b"".join(read_request(tid, 3, tid, 1) for tid in range(5)))
        await wait_until(lambda: len(backend.calls) == 2)
        await asyncio.sleep(0.05)
        assert len(backend.calls) == 2  # the other three wait for a free slot
        backend.read_gate.set()
        tids = sorted([(await read_reply(reader))[0] for _ in range(5)])
        assert tids == [0, 1, 2, 3, 4]
        assert [address for _, _, address in backend.calls] == [0, 1, 2, 3, 4]
    finally:
        await close_writer(writer)
        await modbus.close()


async def test_client_that_does_not_read_stops_being_read(backend: DictBackend) -> None:
    """Replies pile up in the socket buffers, then the server stops reading (bounded memory)."""
    modbus = ModbusTcpServer(backend, HOST, 0)
    await modbus.start()
    reader, writer = await connect(modbus)
    count = 40_000  # 10 MB of replies: more than loopback socket buffers hold
    try:
        writer.write(b"".join(read_request(tid & 0xFFFF, 3, 0, 125) for tid in range(count)))
        calls = -1
        async with asyncio.timeout(5):
            while calls != len(backend.calls):  # until the server stops taking requests
                calls = len(backend.calls)
                await asyncio.sleep(0.2)
        assert calls < count
        for tid in range(count):
            assert (await read_reply(reader))[0] == tid & 0xFFFF
    finally:
        await close_writer(writer)
        await modbus.close()


async def test_bytes_one_at_a_time(server: ModbusTcpServer, backend: DictBackend) -> None:
    backend.holding[3] = 0x0102
    reader, writer = await connect(server)
    try:
        data = read_request(1, 3, 3, 1) + frame(2, struct.pack(">BHH", 6, 4, 9))
        for byte in data:
            writer.write(bytes([byte]))
            await writer.drain()
            await asyncio.sleep(0.002)
        replies = {tid: pdu for tid, _, pdu in [await read_reply(reader), await read_reply(reader)]}
        assert replies == {1: bytes([3, 2, 1, 2]), 2: struct.pack(">BHH", 6, 4, 9)}
        assert backend.holding[4] == 9
    finally:
        await close_writer(writer)


async def test_request_with_trailing_partial_frame(server: ModbusTcpServer) -> None:
    reader, writer = await connect(server)
    try:
        second = read_request(2, 4, 0, 1)
        writer.write(read_request(1, 4, 1, 1) + second[:5])
        assert (await read_reply(reader))[0] == 1
        await asyncio.sleep(0.02)
        writer.write(second[5:])
        assert await read_reply(reader) == (2, UNIT, struct.pack(">BBH", 4, 2, 0))
    finally:
        await close_writer(writer)


# -- framing errors -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad",
    [
        frame(1, bytes([3, 0, 0, 0, 1]), protocol=1),
        struct.pack(">HHHB", 1, 0, 1, UNIT),  # length 1: no function code
        struct.pack(">HHHB", 1, 0, 255, UNIT) + bytes(254),  # length 255: PDU over 253 bytes
        struct.pack(">HHHB", 1, 0, 0xFFFF, UNIT),
    ],
    ids=["protocol-id-1", "length-1", "length-255", "length-65535"],
)
async def test_bad_header_closes_only_that_connection(server: ModbusTcpServer, bad: bytes) -> None:
    good_reader, good_writer = await connect(server)
    bad_reader, bad_writer = await connect(server)
    try:
        good_writer.write(read_request(1, 3, 0, 1))
        assert (await read_reply(good_reader))[0] == 1
        bad_writer.write(bad)
        assert await closed_by_peer(bad_reader)
        good_writer.write(read_request(2, 3, 0, 1))
        assert (await read_reply(good_reader))[0] == 2
        assert server.counters.connections_dropped == 1
        await wait_until(lambda: server.connection_count == 1)
    finally:
        await close_writer(good_writer)
        await close_writer(bad_writer)


async def test_replies_before_bad_header_are_sent(server: ModbusTcpServer) -> None:
    reader, writer = await connect(server)
    try:
        writer.write(frame(5, bytes([0x2B])) + frame(6, bytes([3, 0, 0, 0, 1]), protocol=7))
        assert await read_reply(reader) == (5, UNIT, bytes([0xAB, 0x01]))
        assert await closed_by_peer(reader)
    finally:
        await close_writer(writer)


# -- exception replies --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [
        (struct.pack(">BHH", 1, 0, 0), 0x03),
        (struct.pack(">BHH", 1, 0, 2001), 0x03),
        (struct.pack(">BHH", 2, 0, 0), 0x03),
        (struct.pack(">BHH", 2, 0, 2001), 0x03),
        (struct.pack(">BHH", 3, 0, 0), 0x03),
        (struct.pack(">BHH", 3, 0, 126), 0x03),
        (struct.pack(">BHH", 4, 0, 126), 0x03),
        (struct.pack(">BHH", 4, 0xFFFF, 2), 0x02),  # past address 65535
        (struct.pack(">BHHB", 3, 0, 1, 0), 0x03),  # one byte too many
        (struct.pack(">BH", 3, 0), 0x03),  # too short
        (struct.pack(">BHH", 5, 0, 0x1234), 0x03),
        (struct.pack(">BHH", 5, 0, 0x00FF), 0x03),
        (struct.pack(">BH", 6, 0), 0x03),
        (struct.pack(">BHHB", 15, 0, 0, 0), 0x03),
        (struct.pack(">BHHB", 15, 0, 1969, 247) + bytes(247), 0x03),
        (struct.pack(">BHHB", 15, 0, 9, 1) + b"\x01", 0x03),  # byte count should be 2
        (struct.pack(">BHHB", 15, 0, 9, 2) + b"\x01", 0x03),  # one data byte missing
        (struct.pack(">BHHB", 16, 0, 0, 0), 0x03),
        (struct.pack(">BHHB", 16, 0, 124, 2) + bytes(2), 0x03),
        (struct.pack(">BHHB", 16, 0, 2, 2) + bytes(2), 0x03),  # byte count should be 4
        (struct.pack(">BHHB", 16, 0, 2, 4) + bytes(6), 0x03),  # extra data
        (struct.pack(">BHH", 16, 0, 2), 0x03),  # no byte count
        (struct.pack(">BHHB", 16, 0xFFFF, 2, 4) + bytes(4), 0x02),
        (bytes([0x07]), 0x01),
        (bytes([0x08, 0, 0, 0, 0]), 0x01),
        (struct.pack(">BHHHHB", 0x17, 0, 1, 0, 1, 2) + bytes(2), 0x01),  # pymodbus knows it, we don't
        (bytes([0x2B, 0x0E, 1, 0]), 0x01),
        (bytes([0x83, 0, 0, 0, 1]), 0x01),
        (bytes([0x00]), 0x01),
        (struct.pack(">BHH", 3, SIZE, 1), 0x02),  # from the backend
        (struct.pack(">BHH", 6, SIZE, 1), 0x02),  # from the backend
    ],
)
async def test_exception_replies(
    server: ModbusTcpServer, backend: DictBackend, pdu: bytes, expected: int
) -> None:
    tid, unit, reply = await exchange(server, frame(0xABCD, pdu))
    assert (tid, unit, reply) == (0xABCD, UNIT, bytes([pdu[0] | 0x80, expected]))
    assert server.counters.exceptions == {expected: 1}
    if expected != 0x02:
        assert backend.calls == []


async def test_unknown_unit(server: ModbusTcpServer, backend: DictBackend) -> None:
    tid, unit, reply = await exchange(server, read_request(3, 3, 0, 1, unit=9))
    assert (tid, unit, reply) == (3, 9, bytes([0x83, 0x0A]))
    assert backend.calls == []


@pytest.mark.parametrize("code", [0x02, 0x04, 0x06, 0x0B])
async def test_backend_exception_reply_is_answered(
    server: ModbusTcpServer, backend: DictBackend, code: int
) -> None:
    backend.fail = ModbusExceptionReply(code)
    assert await exchange(server, frame(1, struct.pack(">BHH", 5, 0, 0xFF00))) == (
        1,
        UNIT,
        bytes([0x85, code]),
    )
    assert await exchange(server, read_request(2, 2, 0, 1)) == (2, UNIT, bytes([0x82, code]))


async def test_backend_failure_is_0x04_and_logged_once_with_traceback(
    server: ModbusTcpServer, backend: DictBackend, caplog: pytest.LogCaptureFixture
) -> None:
    backend.fail = RuntimeError("boom")
    caplog.set_level(logging.ERROR, logger="gateway.modbus.server")
    for tid in range(3):
        assert await exchange(server, read_request(tid, 3, 0, 1)) == (tid, UNIT, bytes([0x83, 0x04]))
    errors = [record for record in caplog.records if record.levelno >= logging.ERROR]
    assert len(errors) == 1
    assert errors[0].exc_info is not None and "boom" in str(errors[0].exc_info[1])
    assert server.counters.backend_errors == 3 and server.counters.exceptions == {0x04: 3}


async def test_backend_returning_wrong_values_is_0x04(server: ModbusTcpServer, backend: DictBackend) -> None:
    backend.holding[0] = 0x10000  # not a 16-bit register
    assert await exchange(server, read_request(1, 3, 0, 1)) == (1, UNIT, bytes([0x83, 0x04]))


# -- connection management ----------------------------------------------------------------


async def test_max_connections(backend: DictBackend, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    modbus = ModbusTcpServer(backend, HOST, 0, max_connections=2)
    await modbus.start()
    writers = []
    try:
        kept = []
        for tid in range(2):
            reader, writer = await connect(modbus)
            writers.append(writer)
            writer.write(read_request(tid, 3, 0, 1))
            assert (await read_reply(reader))[0] == tid
            kept.append(reader)
        for _ in range(3):
            reader, writer = await connect(modbus)
            writers.append(writer)
            assert await closed_by_peer(reader)
        assert modbus.connection_count == 2
        assert modbus.counters.connections_refused == 3
        refusals = [record for record in caplog.records if "refused" in record.getMessage()]
        assert len(refusals) == 1  # once per burst
        await close_writer(writers[0])
        await wait_until(lambda: modbus.connection_count == 1)
        reader, writer = await connect(modbus)
        writers.append(writer)
        writer.write(read_request(9, 3, 0, 1))
        assert (await read_reply(reader))[0] == 9
        assert modbus.counters.connections_accepted == 3
    finally:
        for writer in writers:
            await close_writer(writer)
        await modbus.close()


async def test_allow_list_refuses_peer_outside(backend: DictBackend) -> None:
    modbus = ModbusTcpServer(backend, HOST, 0, allow=[ipaddress.IPv4Network("10.0.0.0/8")])
    await modbus.start()
    try:
        reader, writer = await connect(modbus)
        writer.write(read_request(1, 3, 0, 1))
        assert await closed_by_peer(reader)
        await close_writer(writer)
        assert modbus.counters.connections_refused == 1
        assert modbus.counters.connections_accepted == 0
        assert backend.calls == []
    finally:
        await modbus.close()


async def test_allow_list_accepts_peer_inside(backend: DictBackend) -> None:
    allow: list[IPNetwork] = [ipaddress.IPv6Network("fd00::/8"), ipaddress.IPv4Network("127.0.0.0/8")]
    modbus = ModbusTcpServer(backend, HOST, 0, allow=allow)
    await modbus.start()
    try:
        assert (await exchange(modbus, read_request(1, 3, 0, 1)))[0] == 1
    finally:
        await modbus.close()


def test_allow_list_handles_ipv4_mapped_ipv6() -> None:
    def allowed(peer: object, allow: Sequence[IPNetwork]) -> bool:
        return host_allowed(peer_host(peer), allow)

    allow = [ipaddress.IPv4Network("10.0.0.0/8")]
    assert allowed(("::ffff:10.1.2.3", 502, 0, 0), allow)
    assert not allowed(("::ffff:11.1.2.3", 502, 0, 0), allow)
    assert not allowed(("fd00::1", 502, 0, 0), allow)
    assert allowed(("fd00::1", 502, 0, 0), [ipaddress.IPv6Network("fd00::/8")])
    assert not allowed(None, allow)


async def test_idle_timeout(backend: DictBackend) -> None:
    modbus = ModbusTcpServer(backend, HOST, 0, idle_timeout=0.3)
    await modbus.start()
    try:
        silent_reader, silent_writer = await connect(modbus)
        busy_reader, busy_writer = await connect(modbus)
        for tid in range(6):  # 0.6 s of traffic, every 0.1 s
            busy_writer.write(read_request(tid, 3, 0, 1))
            assert (await read_reply(busy_reader))[0] == tid
            await asyncio.sleep(0.1)
        assert await closed_by_peer(silent_reader, within=0.1)
        busy_writer.write(read_request(99, 3, 0, 1))
        assert (await read_reply(busy_reader))[0] == 99
        assert await closed_by_peer(busy_reader, within=1.0)
        assert modbus.counters.connections_dropped == 2
        await close_writer(silent_writer)
        await close_writer(busy_writer)
    finally:
        await modbus.close()


async def test_idle_timeout_spares_a_request_in_flight(backend: DictBackend) -> None:
    backend.write_gate = asyncio.Event()
    modbus = ModbusTcpServer(backend, HOST, 0, idle_timeout=0.2)
    await modbus.start()
    try:
        reader, writer = await connect(modbus)
        writer.write(frame(1, struct.pack(">BHH", 6, 0, 5)))
        await asyncio.sleep(0.5)
        backend.write_gate.set()
        assert await read_reply(reader) == (1, UNIT, struct.pack(">BHH", 6, 0, 5))
        await close_writer(writer)
    finally:
        await modbus.close()


async def test_close_lets_requests_in_flight_finish(backend: DictBackend) -> None:
    backend.write_gate = asyncio.Event()
    modbus = ModbusTcpServer(backend, HOST, 0)
    await modbus.start()
    port = modbus.port
    reader, writer = await connect(modbus)
    writer.write(frame(1, struct.pack(">BHH", 5, 3, 0xFF00)))
    await asyncio.wait_for(backend.write_started.wait(), 2)
    closing = asyncio.create_task(modbus.close())
    await asyncio.sleep(0.05)
    with pytest.raises(OSError):
        await asyncio.open_connection(HOST, port)  # no longer accepting
    backend.write_gate.set()
    assert await read_reply(reader) == (1, UNIT, struct.pack(">BHH", 5, 3, 0xFF00))
    await asyncio.wait_for(closing, 3)
    assert await closed_by_peer(reader)
    assert modbus.connection_count == 0
    await close_writer(writer)


async def test_close_cancels_requests_after_grace(backend: DictBackend) -> None:
    backend.read_gate = asyncio.Event()  # never set
    modbus = ModbusTcpServer(backend, HOST, 0)
    await modbus.start()
    reader, writer = await connect(modbus)
    writer.write(read_request(1, 3, 0, 1))
    await wait_until(lambda: len(backend.calls) == 1)
    await asyncio.wait_for(modbus.close(grace=0.1), 2)
    assert await closed_by_peer(reader)
    await close_writer(writer)


async def test_serve_forever_closes_when_cancelled(backend: DictBackend) -> None:
    modbus = ModbusTcpServer(backend, HOST, 0)
    serving = asyncio.create_task(modbus.serve_forever())
    await wait_until(lambda: modbus._server is not None)
    reader, writer = await connect(modbus)
    writer.write(read_request(1, 3, 0, 1))
    assert (await read_reply(reader))[0] == 1
    serving.cancel()
    with pytest.raises(asyncio.CancelledError):
        await serving
    assert await closed_by_peer(reader)
    await close_writer(writer)


# -- TLS ----------------------------------------------------------------------------------


def _openssl(command: str, *arguments: str, cwd: Path) -> None:
    """Run ``openssl`` with the words of ``command`` then ``arguments`` (which may hold spaces)."""
    subprocess.run(
        ["openssl", *command.split(), *arguments], cwd=cwd, check=True, capture_output=True, timeout=30
    )


def _make_certificates(directory: Path) -> None:
    """A CA, a server certificate for localhost/127.0.0.1, a client certificate and a rogue one."""
    new_key = "-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes"
    _openssl(f"req -x509 {new_key} -keyout ca.key -out ca.pem -days 2 -subj", "/CN=test CA", cwd=directory)
    _openssl(
        f"req -x509 {new_key} -keyout rogue.key -out rogue.pem -days 2 -subj", "/CN=rogue", cwd=directory
    )
    (directory / "server.ext").write_text(
        "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth\n"
    )
    (directory / "client.ext").write_text("extendedKeyUsage=clientAuth\n")
    for name in ("server", "client"):
        _openssl(f"req {new_key} -keyout {name}.key -out {name}.csr -subj /CN={name}", cwd=directory)
        _openssl(
            f"x509 -req -in {name}.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 2"
            f" -out {name}.pem -extfile {name}.ext",
            cwd=directory,
        )


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("neither the cryptography package nor the openssl command is available")
    directory = tmp_path_factory.mktemp("tls")
    _make_certificates(directory)
    return directory


def _client_context(certificates: Path, cert: str | None = "client") -> ssl.SSLContext:
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(certificates / "ca.pem"))
    if cert is not None:
        context.load_cert_chain(certificates / f"{cert}.pem", certificates / f"{cert}.key")
    return context


async def _refused_at_first_read(modbus: ModbusTcpServer, certificates: Path, cert: str | None) -> None:
    """A TLS client with ``cert`` is refused: at the handshake or, TLS 1.3, at its first read."""
    with pytest.raises((ssl.SSLError, ConnectionError, asyncio.IncompleteReadError)):
        reader, writer = await connect(modbus, _client_context(certificates, cert))
        try:
            writer.write(read_request(1, 3, 0, 1))
            await read_reply(reader)
        finally:
            await close_writer(writer)


async def _tls_server(
    backend: DictBackend, certificates: Path, allow: Sequence[ipaddress.IPv4Network] | None = None
) -> ModbusTcpServer:
    context = make_tls_context(
        certificates / "server.pem", certificates / "server.key", client_ca=str(certificates / "ca.pem")
    )
    modbus = ModbusTcpServer(backend, HOST, 0, ssl_context=context, allow=allow)
    await modbus.start()
    return modbus


async def test_tls_with_client_certificate(backend: DictBackend, certificates: Path) -> None:
    backend.holding.update({0: 5, 1: 6})
    modbus = await _tls_server(backend, certificates)
    try:
        reader, writer = await connect(modbus, _client_context(certificates))
        writer.write(read_request(1, 3, 0, 1) + read_request(2, 3, 1, 1))  # pipelined
        replies = {tid: pdu for tid, _, pdu in [await read_reply(reader), await read_reply(reader)]}
        assert replies == {1: bytes([3, 2, 0, 5]), 2: bytes([3, 2, 0, 6])}
        writer.write(frame(3, bytes([3, 0, 0, 0, 1]), protocol=2))
        assert await closed_by_peer(reader)
        await close_writer(writer)

        client = AsyncModbusTlsClient(
            "localhost", port=modbus.port, sslctx=_client_context(certificates), timeout=2, retries=0
        )
        assert await client.connect()
        try:
            assert not (await client.write_registers(10, [7, 8, 9])).isError()
            assert (await client.read_holding_registers(10, count=3)).registers == [7, 8, 9]
        finally:
            client.close()
    finally:
        await modbus.close()


@pytest.mark.parametrize("cert", [None, "rogue"], ids=["no-client-cert", "untrusted-client-cert"])
async def test_tls_refuses_client_without_trusted_certificate(
    backend: DictBackend, certificates: Path, cert: str | None
) -> None:
    modbus = await _tls_server(backend, certificates)
    try:
        # TLS 1.3: the client may finish its side of the handshake before the server checks
        # its certificate, so the refusal shows at the first read.
        await _refused_at_first_read(modbus, certificates, cert)
        assert backend.calls == []
        await wait_until(lambda: modbus.connection_count == 0)
        assert modbus.counters.connections_dropped == 1
    finally:
        await modbus.close()


async def test_tls_allow_list_refuses_before_handshake(backend: DictBackend, certificates: Path) -> None:
    modbus = await _tls_server(backend, certificates, allow=[ipaddress.IPv4Network("10.0.0.0/8")])
    try:
        with pytest.raises((ssl.SSLError, ConnectionError)):
            await connect(modbus, _client_context(certificates))
        assert modbus.counters.connections_refused == 1
    finally:
        await modbus.close()


# -- fuzzing ------------------------------------------------------------------------------

_LIMITS = {1: 2000, 2: 2000, 3: 125, 4: 125, 5: 1, 6: 1, 15: 1968, 16: 123}


@st.composite
def _requests(draw: st.DrawFn) -> bytes:
    """A request PDU of a served function code, valid or broken in one place."""
    function_code = draw(st.sampled_from(sorted(_LIMITS)))
    limit = _LIMITS[function_code]
    address = draw(st.sampled_from([0, 1, SIZE - 2, SIZE, 0xFFFF]) | st.integers(0, 0xFFFF))
    count = draw(st.integers(1, limit) | st.sampled_from([0, limit + 1, 0xFFFF]))
    if function_code in (5, 6):
        value = draw(st.sampled_from([0xFF00, 0x0000]) | st.integers(0, 0xFFFF))
        pdu = struct.pack(">BHH", function_code, address, value)
    elif function_code in (15, 16):
        byte_count = min((count + 7) // 8 if function_code == 15 else 2 * count, 247)
        byte_count = draw(st.just(byte_count) | st.integers(0, 247))
        pdu = struct.pack(">BHHB", function_code, address, count, byte_count)
        pdu += draw(st.binary(min_size=byte_count, max_size=byte_count))
    else:
        pdu = struct.pack(">BHH", function_code, address, count)
    mutation = draw(st.sampled_from(["none", "none", "truncate", "extend"]))
    if mutation == "truncate":
        pdu = pdu[: draw(st.integers(1, len(pdu) - 1))]
    elif mutation == "extend":
        pdu += draw(st.binary(min_size=1, max_size=4))
    return pdu[:253]


_framed_garbage = st.builds(
    lambda tid, unit, pdu: frame(tid, pdu, unit),
    st.integers(0, 0xFFFF),
    st.sampled_from([UNIT, UNIT, UNIT, UNIT, 0, 9]),
    st.one_of(_requests(), _requests(), st.binary(min_size=1, max_size=253)),
)


@settings(
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(chunks=st.lists(st.one_of(_framed_garbage, _framed_garbage, st.binary(max_size=300)), max_size=6))
async def test_fuzz_keeps_serving(
    server: ModbusTcpServer, backend: DictBackend, chunks: list[bytes], caplog: pytest.LogCaptureFixture
) -> None:
    _, writer = await connect(server)
    try:
        for chunk in chunks:
            writer.write(chunk)
            await writer.drain()
        await asyncio.sleep(0.001)  # let the server answer what it can
    except ConnectionError:
        pass  # the server closed a connection that broke the framing
    finally:
        await close_writer(writer)
    # input registers: the fuzz cannot change them
    assert await exchange(server, read_request(7, 4, 6, 1)) == (7, UNIT, bytes([4, 2, 0, 42]))
    problems = [record for record in caplog.records if record.levelno >= logging.ERROR]
    assert problems == []


# -- drops summarised by their cause -----------------------------------------------------------------
#
# A drop is logged once per cause and interval, then counted in one summary line per cause
# ("<server>: <cause>: N more in the last 60 s, from <addresses>"), whatever each drop's details.


def _summaries(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if " more in the last " in r.getMessage()]


async def test_incomplete_frames_timed_out_are_summarised_by_that_cause(
        backend: DictBackend, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    modbus = ModbusTcpServer(backend, HOST, 0, frame_timeout=0.1)
    await modbus.start()
    try:
        for _ in range(2):
            reader, writer = await connect(modbus)
            writer.write(read_request(1, 3, 0, 1)[:5])
            assert await closed_by_peer(reader)
            await close_writer(writer)
    finally:
        await modbus.close()
    assert _summaries(caplog) == ["modbus: incomplete frames timed out: 1 more in the last 60 s, from 127.0.0.1 (1)"]


async def test_failed_tls_handshakes_are_summarised_by_that_cause(
        backend: DictBackend, certificates: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Two handshakes failing for different reasons (no client certificate, an untrusted one): one cause."""
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    modbus = await _tls_server(backend, certificates)
    try:
        for cert in (None, "rogue"):
            await _refused_at_first_read(modbus, certificates, cert)
            await wait_until(lambda: modbus.connection_count == 0)
    finally:
        await modbus.close()
    assert _summaries(caplog) == ["modbus: TLS handshakes failed: 1 more in the last 60 s, from 127.0.0.1 (1)"]


async def test_connections_closed_to_make_room_are_summarised_by_that_cause(
        backend: DictBackend, caplog: pytest.LogCaptureFixture) -> None:
    """max_connections 1: each new connection evicts the one before, which sent nothing (stalled)."""
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    modbus = ModbusTcpServer(backend, HOST, 0, max_connections=1, frame_timeout=0.2)  # stalled after 0.1 s
    await modbus.start()
    writers = []
    try:
        for _ in range(3):
            await asyncio.sleep(0.15)
            _reader, writer = await connect(modbus)
            writers.append(writer)
            await wait_until(lambda: modbus.connection_count == 1)
        assert modbus.counters.connections_dropped == 2
    finally:
        for writer in writers:
            await close_writer(writer)
        await modbus.close()
    assert _summaries(caplog) == [
        "modbus: connections closed to make room: 1 more in the last 60 s, from 127.0.0.1 (1)"]


async def test_a_loopback_client_let_in_for_reads_stays_read_only_with_a_certificate(
        backend: DictBackend, certificates: Path) -> None:
    """``loopback_reads`` lets a loopback peer outside ``allow`` in for reads only: a client certificate
    (whose role would write) does not give it writes (0x01)."""
    context = make_tls_context(
        certificates / "server.pem", certificates / "server.key", client_ca=str(certificates / "ca.pem"))
    modbus = ModbusTcpServer(backend, HOST, 0, ssl_context=context, allow=[ipaddress.ip_network("10.0.0.0/8")],
                             loopback_reads=True)
    await modbus.start()
    try:
        reader, writer = await connect(modbus, _client_context(certificates))
        for tid in (1, 3):
            writer.write(frame(tid, bytes([6, 0, 10, 0, 7])))  # FC6: holding 10 = 7
            assert await read_reply(reader) == (tid, UNIT, bytes([0x86, 0x01]))
        assert modbus.counters.requests.get(6) == 2  # refused requests are requests too (by function code)
        writer.write(read_request(2, 3, 10, 1))
        assert (await read_reply(reader))[2][0] == 3  # reads are served
        await close_writer(writer)
        assert 10 not in backend.holding
    finally:
        await modbus.close()


async def test_a_tls_connection_without_room_after_its_handshake_is_refused_counted_and_named(
        backend: DictBackend, certificates: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    context = make_tls_context(
        certificates / "server.pem", certificates / "server.key", client_ca=str(certificates / "ca.pem"))
    modbus = ModbusTcpServer(backend, HOST, 0, ssl_context=context, max_connections=1)
    await modbus.start()
    try:
        reader, writer = await connect(modbus, _client_context(certificates))
        writer.write(read_request(1, 3, 0, 1))
        await read_reply(reader)  # served: not a connection to close for room
        for refused_so_far in (1, 2):
            with pytest.raises((ssl.SSLError, ConnectionError, asyncio.IncompleteReadError)):
                second_reader, second_writer = await connect(modbus, _client_context(certificates))
                try:
                    second_writer.write(read_request(2, 3, 0, 1))
                    await read_reply(second_reader)
                finally:
                    await close_writer(second_writer)
            await wait_until(lambda n=refused_so_far: modbus.counters.connections_refused == n)  # type: ignore[misc]
        await close_writer(writer)
    finally:
        await modbus.close()
    refused = [r.getMessage() for r in caplog.records if "handshake done but" in r.getMessage()]
    assert refused and "127.0.0.1" in refused[0]
