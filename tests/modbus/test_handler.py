"""The Modbus request handler (``gateway/modbus/handler.py``) against the specification, over TCP.

Requests go in as bytes on a real socket to a :class:`ModbusTcpServer` on 127.0.0.1; replies are
checked against what the Modbus Application Protocol Specification V1.1b3 (sections 4, 6 and 7)
says they must be: the MBAP header of the request (transaction id 0-65535, unit), the function
code or its exception, the exception code (0x01 unknown function, 0x03 bad quantity or length,
0x02 range past address 65535, 0x0A unknown unit, 0x04 backend failure), the echo of a write,
and read data the backend held.

``SpecBackend`` has all 65536 addresses of each table, a "hole" (0xF000-0xF00F) where it answers
0x02 itself, and a failing unit; ``read_now=True`` gives it the read fast path of
:data:`gateway.modbus.handler.ReadNow` (reads answered inside ``data_received``), ``False``
the backend coroutines (one task per request).
"""

from __future__ import annotations

import asyncio
import logging
import struct
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.errors import ModbusExceptionReply
from gateway.modbus.server import ModbusBackend, ModbusTcpServer

HOST = "127.0.0.1"
UNITS = (1, 2)  # served units
FAILING_UNIT = 3  # known, but every backend call raises
UNKNOWN_UNITS = (0, 9, 247)
HOLE = range(0xF000, 0xF010)  # addresses the backend answers 0x02 for
LIMITS = {1: 2000, 2: 2000, 3: 125, 4: 125, 15: 1968, 16: 123}
WRITES = frozenset({5, 6, 15, 16})


def initial(table: str, address: int) -> int:
    """The value every address of every table holds before any write (a pattern, not zeros)."""
    if table == "holding":
        return (address * 31 + 7) & 0xFFFF
    if table == "input":
        return (address * 7 + 1) & 0xFFFF
    if table == "coil":
        return int(address % 3 == 0)
    return int(address % 5 == 0)  # discrete


@dataclass
class SpecBackend:
    """A real backend over four 65536-address tables (writes kept in ``written``)."""

    read_now_path: bool
    written: dict[tuple[str, int], int] = field(default_factory=dict)
    #: every backend write call: (table, unit, address, values)
    writes: list[tuple[str, int, int, tuple[int, ...]]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.read_now_path:
            self.read_now = self._read_now

    def value(self, table: str, address: int) -> int:
        return self.written.get((table, address), initial(table, address))

    def _check(self, unit: int, address: int, count: int) -> None:
        if unit == FAILING_UNIT:
            raise RuntimeError("the link of this unit is broken")
        if address < HOLE.stop and address + count > HOLE.start:
            raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_DATA_ADDRESS)

    def has_unit(self, unit: int) -> bool:
        return unit in UNITS or unit == FAILING_UNIT

    def _values(self, table: str, unit: int, address: int, count: int) -> list[int]:
        self._check(unit, address, count)
        return [self.value(table, a) for a in range(address, address + count)]

    def _read_now(self, unit: int, function_code: int, address: int, count: int) -> bytes:
        table = {1: "coil", 2: "discrete", 3: "holding", 4: "input"}[function_code]
        values = self._values(table, unit, address, count)
        if function_code in (3, 4):
            return struct.pack(f">{count}H", *values)
        packed = bytearray((count + 7) // 8)
        for i, bit in enumerate(values):
            packed[i // 8] |= bit << (i % 8)
        return bytes(packed)

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return [bool(v) for v in self._values("coil", unit, address, count)]

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return [bool(v) for v in self._values("discrete", unit, address, count)]

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self._values("holding", unit, address, count)

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self._values("input", unit, address, count)

    def _write(self, table: str, unit: int, address: int, values: Sequence[int]) -> None:
        self._check(unit, address, len(values))
        self.writes.append((table, unit, address, tuple(values)))
        for offset, value in enumerate(values):
            self.written[(table, address + offset)] = value

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        self._write("coil", unit, address, [int(v) for v in values])

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        self._write("holding", unit, address, list(values))


def _typed(backend: SpecBackend) -> ModbusBackend:
    return backend  # mypy checks that SpecBackend implements the Protocol


@asynccontextmanager
async def serving(backend: SpecBackend) -> AsyncIterator[tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    server = ModbusTcpServer(_typed(backend), HOST, 0, max_in_flight_per_connection=4)
    await server.start()
    reader, writer = await asyncio.open_connection(HOST, server.port)
    try:
        yield reader, writer
    finally:
        writer.close()
        try:
            await writer.wait_closed()
        except ConnectionError:
            pass
        await server.close()


def frame(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def read_reply(reader: asyncio.StreamReader) -> tuple[int, int, bytes]:
    """One reply frame: (transaction id, unit, PDU).  The 2 s bound only keeps a broken server
    from hanging the test (as in modbus/test_server.py); nothing here depends on how fast the reply
    comes."""
    async with asyncio.timeout(2.0):
        header = await reader.readexactly(7)
        tid, protocol, length, unit = struct.unpack(">HHHB", header)
        assert protocol == 0, f"reply with protocol id {protocol}"
        assert length >= 2, f"reply with MBAP length {length}"
        pdu = await reader.readexactly(length - 1)
    return tid, unit, pdu


# --- what the specification says the reply is --------------------------------------------------


@dataclass(frozen=True)
class Expected:
    """The reply a request must get: an exception code, a write's echo, or read data."""

    function_code: int
    exception: int | None = None
    echo: bytes | None = None
    read: tuple[str, int, int] | None = None  # table, address, count
    #: answered inside data_received (refused before the backend, or the read fast path)
    at_once: bool = True


def expected_reply(unit: int, pdu: bytes, read_now_path: bool) -> Expected:
    """The specification's reply (V1.1b3, 6.1-6.12 and the state diagrams of each function)."""
    fc = pdu[0]

    def exc(code: int, at_once: bool = True) -> Expected:
        return Expected(fc, exception=code, at_once=at_once)

    if unit not in UNITS and unit != FAILING_UNIT:
        return exc(0x0A)
    if fc in (1, 2, 3, 4):
        if len(pdu) != 5:
            return exc(0x03)
        address, count = struct.unpack_from(">HH", pdu, 1)
        if not 1 <= count <= LIMITS[fc]:
            return exc(0x03)
        if address + count > 0x10000:
            return exc(0x02)
        if unit == FAILING_UNIT:
            return exc(0x04, read_now_path)
        if address < HOLE.stop and address + count > HOLE.start:
            return exc(0x02, read_now_path)
        table = {1: "coil", 2: "discrete", 3: "holding", 4: "input"}[fc]
        return Expected(fc, read=(table, address, count), at_once=read_now_path)
    if fc in (5, 6):
        if len(pdu) != 5:
            return exc(0x03)
        address, value = struct.unpack_from(">HH", pdu, 1)
        if fc == 5 and value not in (0xFF00, 0x0000):
            return exc(0x03)
        count = 1
    elif fc in (15, 16):
        if len(pdu) < 6:
            return exc(0x03)
        address, count, byte_count = struct.unpack_from(">HHB", pdu, 1)
        wanted = (count + 7) // 8 if fc == 15 else 2 * count
        if not 1 <= count <= LIMITS[fc] or byte_count != wanted or len(pdu) != 6 + byte_count:
            return exc(0x03)
        if address + count > 0x10000:
            return exc(0x02)
    else:
        return exc(0x01)
    if unit == FAILING_UNIT:
        return exc(0x04, False)
    if address < HOLE.stop and address + count > HOLE.start:
        return exc(0x02, False)
    return Expected(fc, echo=pdu[:5], at_once=False)


def write_values(pdu: bytes) -> tuple[str, int, tuple[int, ...]]:
    """The table, address and values a well-formed write request carries."""
    fc = pdu[0]
    if fc in (5, 6):
        address, value = struct.unpack_from(">HH", pdu, 1)
        return ("coil", address, (int(value == 0xFF00),)) if fc == 5 else ("holding", address, (value,))
    address, count = struct.unpack_from(">HH", pdu, 1)
    data = pdu[6:]
    if fc == 15:
        return "coil", address, tuple((data[i // 8] >> (i % 8)) & 1 for i in range(count))
    return "holding", address, struct.unpack(f">{count}H", data)


def check_reply(request: tuple[int, int, bytes], reply: tuple[int, int, bytes], expected: Expected,
                held: dict[tuple[str, int], set[int]]) -> None:
    tid, unit, _ = request
    reply_tid, reply_unit, reply_pdu = reply
    assert (reply_tid, reply_unit) == (tid, unit), f"reply {reply} to request {request}"
    if expected.exception is not None:
        assert reply_pdu == bytes([expected.function_code | 0x80, expected.exception]), (request, reply)
    elif expected.echo is not None:
        assert reply_pdu == expected.echo, (request, reply)
    else:
        assert expected.read is not None
        table, address, count = expected.read
        fc = expected.function_code
        size = 2 * count if fc in (3, 4) else (count + 7) // 8
        assert reply_pdu[:2] == bytes([fc, size]) and len(reply_pdu) == 2 + size, (request, reply)
        data = reply_pdu[2:]
        if fc in (3, 4):
            values = struct.unpack(f">{count}H", data)
        else:
            values = tuple((data[i // 8] >> (i % 8)) & 1 for i in range(count))
            assert data[-1] >> (count - 8 * (size - 1)) == 0, "bits past the count are not zero"
        for offset, value in enumerate(values):
            a = address + offset
            assert value in held.get((table, a), {initial(table, a)}), f"{table} {a} = {value}: never held"


# --- two bugs a mutation run found the suite missed --------------------------------------------------


@pytest.mark.parametrize("read_now_path", [True, False], ids=["read_now", "backend_call"])
@pytest.mark.parametrize("function_code", [1, 2, 3, 4])
async def test_a_read_ending_at_register_65535_is_served_one_past_it_is_0x02(
    read_now_path: bool, function_code: int
) -> None:
    """A read of the last addresses of the 16-bit space is legal (V1.1b3: addresses 0-65535)."""
    backend = SpecBackend(read_now_path)
    async with serving(backend) as (reader, writer):
        for count in (1, 2, LIMITS[function_code]):
            for address in (0x10000 - count, 0x10000 - count + 1)[: 1 if count == 1 else 2]:
                pdu = struct.pack(">BHH", function_code, address, count)
                writer.write(frame(7, 1, pdu))
                check_reply((7, 1, pdu), await read_reply(reader), expected_reply(1, pdu, read_now_path), {})
        # the last register alone, by value
        pdu = struct.pack(">BHH", function_code, 0xFFFF, 1)
        writer.write(frame(8, 1, pdu))
        _, _, reply = await read_reply(reader)
        table = {1: "coil", 2: "discrete", 3: "holding", 4: "input"}[function_code]
        last = initial(table, 0xFFFF)
        assert reply == (bytes([function_code, 2]) + struct.pack(">H", last) if function_code in (3, 4)
                         else bytes([function_code, 1, last]))


@pytest.mark.parametrize("function_code", [15, 16])
async def test_a_write_ending_at_register_65535_is_applied_one_past_it_is_0x02(function_code: int) -> None:
    backend = SpecBackend(read_now_path=True)
    async with serving(backend) as (reader, writer):
        for count in (1, 3):
            for address in (0x10000 - count, 0x10000 - count + 1)[: 1 if count == 1 else 2]:
                if function_code == 15:
                    pdu = struct.pack(">BHHB", 15, address, count, 1) + bytes([0b101])
                else:
                    pdu = struct.pack(f">BHHB{count}H", 16, address, count, 2 * count, *range(100, 100 + count))
                writer.write(frame(9, 2, pdu))
                check_reply((9, 2, pdu), await read_reply(reader), expected_reply(2, pdu, True), {})
    table = "coil" if function_code == 15 else "holding"
    assert [(t, a, len(v)) for t, _, a, v in backend.writes] == [(table, 0xFFFF, 1), (table, 0xFFFD, 3)]


@dataclass
class FlagBackend(SpecBackend):
    """A backend with a data attribute named ``read_now`` (a flag, no function)."""

    read_now: bool = False


async def test_a_backend_whose_read_now_is_no_function_is_read_through_its_coroutines() -> None:
    """``read_now`` is the fast path only when the backend's attribute of that name can be called;
    any other value of it (here a flag) leaves reads to the backend's read coroutines."""
    backend = FlagBackend(read_now_path=False)
    async with serving(backend) as (reader, writer):
        for function_code in (1, 3):
            pdu = struct.pack(">BHH", function_code, 10, 4)
            writer.write(frame(5, 1, pdu))
            check_reply((5, 1, pdu), await read_reply(reader), expected_reply(1, pdu, False), {})


TIDS = (0, 1, 0xFF, 0x100, 0x1234, 0x8000, 0xFF00, 0xFFFE, 0xFFFF)


@pytest.mark.parametrize("read_now_path", [True, False], ids=["read_now", "backend_call"])
async def test_every_reply_carries_its_requests_transaction_id_from_0_to_65535(read_now_path: bool) -> None:
    """SCADA masters count transaction ids up to 65535 and drop a reply whose id is not theirs:
    write echoes, reads and exception replies all carry the request's whole 16-bit id."""
    requests = [
        struct.pack(">BHH", 5, 10, 0xFF00),
        struct.pack(">BHH", 6, 11, 0xBEEF),
        struct.pack(">BHHB", 15, 12, 9, 2) + bytes([0xA5, 0x01]),
        struct.pack(">BHHBHH", 16, 13, 2, 4, 1, 0xFFFF),
        struct.pack(">BHH", 3, 11, 3),
        struct.pack(">BHH", 1, 10, 3),
        struct.pack(">BHH", 4, 0, 126),  # 0x03
        struct.pack(">BHH", 6, HOLE.start, 1),  # 0x02 from the backend
        bytes([0x2B, 0x0E, 1, 0]),  # 0x01
    ]
    backend = SpecBackend(read_now_path)
    held: dict[tuple[str, int], set[int]] = {}
    async with serving(backend) as (reader, writer):
        for tid in TIDS:
            for unit in (1, 2, FAILING_UNIT, 9):
                for pdu in requests:
                    if pdu[0] in WRITES and expected_reply(unit, pdu, read_now_path).echo is not None:
                        table, address, values = write_values(pdu)
                        for offset, value in enumerate(values):
                            held.setdefault((table, address + offset), {initial(table, address + offset)}).add(value)
                    writer.write(frame(tid, unit, pdu))
                    reply = await read_reply(reader)
                    check_reply((tid, unit, pdu), reply, expected_reply(unit, pdu, read_now_path), held)


async def test_writes_reach_the_backend_with_the_values_of_the_request() -> None:
    backend = SpecBackend(read_now_path=True)
    requests = [
        struct.pack(">BHH", 5, 10, 0xFF00),
        struct.pack(">BHH", 5, 11, 0x0000),
        struct.pack(">BHH", 6, 12, 0xBEEF),
        struct.pack(">BHHB", 15, 20, 10, 2) + bytes([0b10100101, 0b11111110]),
        struct.pack(">BHHBHHH", 16, 30, 3, 6, 0, 0x7FFF, 0xFFFF),
    ]
    async with serving(backend) as (reader, writer):
        for n, pdu in enumerate(requests):
            writer.write(frame(300 + n, 2, pdu))
            assert await read_reply(reader) == (300 + n, 2, pdu[:5])
    assert backend.writes == [
        ("coil", 2, 10, (1,)),
        ("coil", 2, 11, (0,)),
        ("holding", 2, 12, (0xBEEF,)),
        ("coil", 2, 20, (1, 0, 1, 0, 0, 1, 0, 1, 0, 1)),
        ("holding", 2, 30, (0, 0x7FFF, 0xFFFF)),
    ]


# --- pipelined request streams (hypothesis) -------------------------------------------------------


@st.composite
def requests(draw: st.DrawFn) -> tuple[int, bytes]:
    """(unit, PDU): a request of a served function code (often at the edges of the address space
    and of the counts, sometimes broken in one place), or any PDU at all."""
    unit = draw(st.sampled_from([1, 1, 1, 2, 2, FAILING_UNIT, *UNKNOWN_UNITS]))
    if draw(st.integers(0, 9)) == 0:
        return unit, draw(st.binary(min_size=1, max_size=253))
    fc = draw(st.sampled_from([1, 2, 3, 4, 5, 6, 15, 16]))
    limit = LIMITS.get(fc, 1)
    count = draw(st.sampled_from([1, 2, limit]) | st.integers(1, limit) | st.sampled_from([0, limit + 1, 0xFFFF]))
    end = max(0, 0x10000 - max(count, 1))  # the range ends at register 65535
    where = draw(st.sampled_from(["end", "end", "past", "zero", "last", "hole", "hole", "any", "any", "any"]))
    address = {"end": end, "past": min(end + 1, 0xFFFF), "zero": 0, "last": 0xFFFF,
               "hole": draw(st.sampled_from([HOLE.start - 1, HOLE.stop - 1, max(0, HOLE.start - count)]))
               if where == "hole" else 0,
               "any": draw(st.integers(0, 0xFFFF)) if where == "any" else 0}[where]
    if fc in (5, 6):
        value = draw(st.sampled_from([0xFF00, 0x0000]) | st.integers(0, 0xFFFF))
        pdu = struct.pack(">BHH", fc, address, value)
    elif fc in (15, 16):
        byte_count = min((count + 7) // 8 if fc == 15 else 2 * count, 247)
        byte_count = draw(st.just(byte_count) | st.just(byte_count) | st.integers(0, 247))
        pdu = struct.pack(">BHHB", fc, address, count & 0xFFFF, byte_count)
        pdu += draw(st.binary(min_size=byte_count, max_size=byte_count))
    else:
        pdu = struct.pack(">BHH", fc, address, count & 0xFFFF)
    broken = draw(st.sampled_from(["none", "none", "none", "truncate", "extend"]))
    if broken == "truncate":
        pdu = pdu[: draw(st.integers(1, len(pdu) - 1))]
    elif broken == "extend":
        pdu += draw(st.binary(min_size=1, max_size=4))
    return unit, pdu[:253]


@st.composite
def streams(draw: st.DrawFn) -> tuple[list[tuple[int, int, bytes]], list[bytes], bool]:
    """Requests with distinct transaction ids (0-65535), their bytes cut into segments at arbitrary
    points (many requests in one segment, a request across several), and maybe a bad MBAP header
    at the end (the connection must then close)."""
    pairs = draw(st.lists(requests(), min_size=1, max_size=40))
    tids = draw(st.lists(st.sampled_from(TIDS) | st.integers(0, 0xFFFF), min_size=len(pairs), max_size=len(pairs),
                         unique=True))
    reqs = [(tid, unit, pdu) for tid, (unit, pdu) in zip(tids, pairs, strict=True)]
    bad_tail = draw(st.integers(0, 4)) == 0
    data = b"".join(frame(*r) for r in reqs)
    if bad_tail:
        data += struct.pack(">HHHB", 1, 0, draw(st.sampled_from([0, 1, 255, 0xFFFF])), 1) + b"\x03"
    cuts = sorted(draw(st.sets(st.integers(1, max(1, len(data) - 1)), max_size=12)))
    segments = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True) if a < b]
    return reqs, segments, bad_tail


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(stream=streams(), read_now_path=st.booleans())
async def test_pipelined_streams_every_request_gets_its_own_reply_in_a_valid_order(
    stream: tuple[list[tuple[int, int, bytes]], list[bytes], bool], read_now_path: bool
) -> None:
    """Every request of a pipelined stream is answered once, with its transaction id, unit and
    function code, and the reply the specification gives it.  Order: replies answered at once
    (refusals, reads served from memory) come in request order, and so do replies from the backend
    (it answers in call order here); a backend reply may be overtaken only by an at-once reply to a
    later request.  After a bad MBAP header the connection closes: every at-once reply to a request
    before it has been sent, and backend replies still in flight may be lost."""
    reqs, segments, bad_tail = stream
    backend = SpecBackend(read_now_path)
    expected = [expected_reply(unit, pdu, read_now_path) for _, unit, pdu in reqs]
    held: dict[tuple[str, int], set[int]] = {}
    for (_, _, pdu), exp in zip(reqs, expected, strict=True):
        if exp.echo is not None:
            table, address, values = write_values(pdu)
            for offset, value in enumerate(values):
                held.setdefault((table, address + offset), {initial(table, address + offset)}).add(value)
    index = {tid: n for n, (tid, _, _) in enumerate(reqs)}
    order: list[int] = []
    async with serving(backend) as (reader, writer):
        try:
            for segment in segments:
                writer.write(segment)
                await writer.drain()
        except ConnectionError:
            assert bad_tail, "the server closed a connection that kept to the protocol"
        while len(order) < len(reqs):
            try:
                tid, unit, pdu = await read_reply(reader)
            except (asyncio.IncompleteReadError, ConnectionError):
                assert bad_tail, f"connection closed after {len(order)} of {len(reqs)} replies"
                break
            assert tid in index, f"reply with transaction id {tid}, which no request had"
            n = index[tid]
            assert n not in order, f"two replies to transaction id {tid}"
            check_reply(reqs[n], (tid, unit, pdu), expected[n], held)
            order.append(n)
        if bad_tail:
            try:
                rest = await reader.read()
            except ConnectionError:  # closed with a reset: nothing more came either
                rest = b""
            assert rest == b"", "data after the replies, on a connection that must close"
    answered = set(order)
    for n, exp in enumerate(expected):
        assert n in answered or (bad_tail and not exp.at_once), f"request {reqs[n]} got no reply"
    for i, first in enumerate(order):
        for later in order[i + 1 :]:
            if later < first:  # the reply to an earlier request came after this one
                assert not expected[later].at_once and expected[first].at_once, (
                    f"reply to request {first} came before the reply to request {later}"
                )
    # the writes reached the backend with the requests' values, once each, in request order (after a
    # bad header: those before it, and at least every one echoed)
    calls = [(table, address, values) for table, _, address, values in backend.writes]
    wanted = [write_values(reqs[n][2]) for n, exp in enumerate(expected) if exp.echo is not None]
    if bad_tail:
        echoed = sum(1 for n in answered if expected[n].echo is not None)
        assert calls == wanted[: len(calls)] and len(calls) >= echoed
    else:
        assert calls == wanted


# --- counters, the backend-failure log and the audit trail ------------------------------------


async def test_backend_failures_are_counted_each_and_logged_with_traceback_once_per_type(
    caplog: pytest.LogCaptureFixture,
) -> None:
    backend = SpecBackend(read_now_path=False)
    server = ModbusTcpServer(_typed(backend), HOST, 0)
    await server.start()
    reader, writer = await asyncio.open_connection(HOST, server.port)
    caplog.set_level(logging.DEBUG, logger="gateway.modbus.server")
    try:
        for n in range(3):
            writer.write(frame(n, FAILING_UNIT, struct.pack(">BHH", 3, 0, 1)))
            assert (await read_reply(reader))[2] == bytes([0x83, 0x04])
        assert server.counters.backend_errors == 3
        assert server.counters.exceptions.get(0x04) == 3
        failures = [r for r in caplog.records if "backend failed" in r.getMessage()]
        assert [r.levelno for r in failures] == [logging.ERROR, logging.DEBUG, logging.DEBUG]
        assert failures[0].exc_info is not None
    finally:
        writer.close()
        await server.close()


@pytest.mark.parametrize("read_now_path", [True, False], ids=["read_now", "backend_call"])
async def test_every_write_is_audited_with_its_function_code_span_and_outcome(
    read_now_path: bool, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="gateway.audit")
    backend = SpecBackend(read_now_path)
    requests = [
        (2, struct.pack(">BHH", 6, 12, 0xBEEF), "FC6 holding 12: ok"),
        (2, struct.pack(">BHHBHH", 16, 30, 2, 4, 1, 2), "FC16 holding 30-31: ok"),
        (2, struct.pack(">BHH", 5, 7, 0xFF00), "FC5 coil 7: ok"),
        (2, struct.pack(">BHHB", 15, 20, 3, 1) + b"\x05", "FC15 coil 20-22: ok"),
        (2, struct.pack(">BHH", 6, HOLE.start, 1), f"FC6 holding {HOLE.start}: 0x02 "),
        (FAILING_UNIT, struct.pack(">BHH", 6, 1, 1), "FC6 holding 1: 0x04 RuntimeError"),
    ]
    async with serving(backend) as (reader, writer):
        for n, (unit, pdu, _) in enumerate(requests):
            writer.write(frame(1000 + n, unit, pdu))
            await read_reply(reader)
    lines = [r.getMessage() for r in caplog.records if r.name == "gateway.audit"]
    assert len(lines) == len(requests)
    for line, (unit, _, expected) in zip(lines, requests, strict=True):
        assert f"unit {unit} {expected}" in line, (line, expected)


@dataclass
class CodeBackend(SpecBackend):
    """Every write answers ModbusExceptionReply(code); every read_now returns one byte too many."""

    code: int = 0x01

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        raise ModbusExceptionReply(self.code, "from the backend")

    def _read_now(self, unit: int, function_code: int, address: int, count: int) -> bytes:
        return super()._read_now(unit, function_code, address, count) + b"\x00"


@pytest.mark.parametrize(("code", "answered"), [(0x01, 0x01), (0xFF, 0xFF), (0x0B, 0x0B), (0x00, 0x04),
                                                (0x100, 0x04), (-1, 0x04)])
async def test_a_backend_exception_code_is_answered_if_it_fits_a_byte_else_0x04(code: int, answered: int) -> None:
    backend = CodeBackend(read_now_path=True, code=code)
    async with serving(backend) as (reader, writer):
        writer.write(frame(77, 1, struct.pack(">BHH", 6, 3, 9)))
        assert await read_reply(reader) == (77, 1, bytes([0x86, answered]))


async def test_a_backend_returning_the_wrong_number_of_bytes_is_a_device_failure(
    caplog: pytest.LogCaptureFixture,
) -> None:
    backend = CodeBackend(read_now_path=True)
    async with serving(backend) as (reader, writer):
        writer.write(frame(78, 1, struct.pack(">BHH", 3, 3, 2)))
        assert await read_reply(reader) == (78, 1, bytes([0x83, 0x04]))
    assert any("returned 5 data bytes for 2 values (4 expected)" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(("pdu", "accepted"), [
    (struct.pack(">BHHB", 15, 0, 1968, 246) + bytes(246), True),  # the FC15 maximum
    (struct.pack(">BHHB", 15, 0, 1969, 247) + bytes(247), False),
    (struct.pack(">BHHB", 15, 0, 8, 1) + b"\xff", True),  # 8 coils: one byte, not two
    (struct.pack(">BHHB", 15, 0, 8, 2) + b"\xff\x00", False),
    (struct.pack(">BHHB", 15, 0, 9, 2) + b"\xff\x01", True),
    (struct.pack(">BHHB", 16, 0, 123, 246) + bytes(246), True),  # the FC16 maximum
])
async def test_write_quantities_at_the_limits_of_the_specification(pdu: bytes, accepted: bool) -> None:
    backend = SpecBackend(read_now_path=True)
    async with serving(backend) as (reader, writer):
        writer.write(frame(79, 1, pdu[:253]))
        _, _, reply = await read_reply(reader)
    assert reply == (pdu[:5] if accepted else bytes([pdu[0] | 0x80, 0x03]))


async def test_requests_are_counted_by_function_code_unknown_ones_too() -> None:
    backend = SpecBackend(read_now_path=True)
    server = ModbusTcpServer(_typed(backend), HOST, 0)
    await server.start()
    reader, writer = await asyncio.open_connection(HOST, server.port)
    try:
        for n, pdu in enumerate([struct.pack(">BHH", 3, 0, 1)] * 3 + [struct.pack(">BHH", 6, 0, 1), b"\x2b\x0e"]):
            writer.write(frame(n, 1 if n != 2 else 9, pdu))
            await read_reply(reader)
        assert server.counters.requests == {3: 3, 6: 1, 0x2B: 1}
        assert server.counters.exceptions == {0x0A: 1, 0x01: 1}
    finally:
        writer.close()
        await server.close()
