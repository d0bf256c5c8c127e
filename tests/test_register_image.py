"""Reads served from the register images against the decoder they replaced, and staleness after writes.

The reference below is a copy of the read path as it was before the images (commit 7bd7acd,
``Unit.read_registers`` / ``read_bits`` decoding the raw block bytes on every read, served
through the server's async backend path).  The differential test builds random plans (random
blocks, codecs and bit positions), stores, patches and reads at random times, and compares
the whole reply frames of both paths byte for byte.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from bisect import bisect_right
from collections.abc import AsyncIterator, Coroutine, Sequence
from dataclasses import dataclass
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.clients import Client, current_client
from gateway.errors import ControllerRefused, ModbusExceptionReply, StaleRead
from gateway.kinds.df1 import plan as df1_plan
from gateway.kinds.slc_ascii import plan as slc_plan
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.plan import slc_ascii_plan
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.line_driver import LineLease
from gateway.link_health import LineCounters
from gateway.modbus.backend import GatewayBackend
from gateway.modbus.mapping import (
    STATUS_BASE,
    BitPoint,
    Block,
    Half,
    Plan,
    RegisterPoint,
    Scan,
    Table,
)
from gateway.modbus.mapping import Codec as CodecType
from gateway.modbus.server import ModbusTcpServer
from gateway.poller import LineShare
from gateway.unit import Unit


class Codec:
    """The codecs of the built-in link kinds (each kind has its own)."""

    U16_BE = slc_plan.U16_BE
    U16_BE_MASKED = slc_plan.U16_BE_MASKED
    U8 = slc_plan.U8
    U16_LE = df1_plan.U16_LE
    F32_HIGH = df1_plan.F32_HIGH
    F32_LOW = df1_plan.F32_LOW


ALL_CODECS = [Codec.U16_BE, Codec.U16_BE_MASKED, Codec.U8, Codec.U16_LE, Codec.F32_HIGH, Codec.F32_LOW]

ILLEGAL_ADDRESS = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS
TARGET_FAILED = ModbusExceptionReply.GATEWAY_TARGET_FAILED
DEVICE_FAILURE = ModbusExceptionReply.SERVER_DEVICE_FAILURE

# --- the reference: the read path before the images (copied, do not "fix") -------------------

_U16_LE = Codec.U16_LE
_U16_BE = Codec.U16_BE
_U16_BE_MASKED = Codec.U16_BE_MASKED
_STRIDE_2 = (_U16_LE, _U16_BE, _U16_BE_MASKED)


@dataclass(frozen=True, slots=True)
class _Run:
    first: int
    last: int
    block: int
    offset: int
    codec: CodecType


def _register_runs(points: dict[int, RegisterPoint]) -> tuple[list[int], list[_Run]]:
    runs: list[_Run] = []
    for address in sorted(points):
        p = points[address]
        if runs:
            r = runs[-1]
            if (
                p.codec in _STRIDE_2
                and r.codec is p.codec
                and r.block == p.block
                and r.last == address - 1
                and p.offset == r.offset + 2 * (address - r.first)
            ):
                runs[-1] = _Run(r.first, address, r.block, r.offset, r.codec)
                continue
        runs.append(_Run(address, address, p.block, p.offset, p.codec))
    return [r.first for r in runs], runs


def _decode(point: RegisterPoint, data: bytearray) -> int:
    o = point.offset
    codec = point.codec
    if codec is Codec.U16_BE_MASKED:
        return ((data[o] & 0x7F) << 8) | data[o + 1]
    if codec is Codec.U16_BE:
        return (data[o] << 8) | data[o + 1]
    if codec is Codec.U16_LE:
        return data[o] | (data[o + 1] << 8)
    if codec is Codec.U8:
        return data[o]
    raw: int = struct.unpack_from("<I", data, o)[0]
    return (raw >> 16) if codec is Codec.F32_HIGH else (raw & 0xFFFF)


class ReferenceReader:
    """The old ``Unit`` read path over the same plan and cache as the unit under test."""

    def __init__(self, unit: Unit) -> None:
        self.unit = unit
        self.now = 0.0
        self._runs = {table: _register_runs(unit.plan.registers(table)) for table in (Table.HOLDING, Table.INPUT)}

    def _silent(self, now: float) -> bool:
        return now - self.unit.cache.newest > self.unit.freshness.silent_after

    def _stale(self, block: int | None = None) -> ModbusExceptionReply:
        refused = self.unit.poller.refused.get(block) if block is not None else None
        if refused is not None:
            return ModbusExceptionReply(DEVICE_FAILURE, str(refused[0]))
        return ModbusExceptionReply(TARGET_FAILED, "stale")

    def read_registers(self, table: Table, address: int, count: int) -> list[int]:
        now = self.now
        assert not (table is Table.INPUT and address >= STATUS_BASE)
        points = self.unit.plan.registers(table)
        stamps, data, max_age = self.unit.cache.stamps, self.unit.cache.data, self.unit.freshness.limits
        if self._silent(now):
            if all(a in points for a in range(address, address + count)):
                raise self._stale()
        starts, runs = self._runs[table]
        out: list[int] = []
        a, end = address, address + count
        i = bisect_right(starts, a) - 1
        while a < end:
            if i < 0 or i >= len(runs) or runs[i].last < a or runs[i].first > a:
                raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"{table.value} register {a} is not mapped")
            run = runs[i]
            block = run.block
            if now - stamps[block] > max_age[block]:
                raise self._stale(block)
            n = min(end, run.last + 1) - a
            offset = run.offset + 2 * (a - run.first)
            if run.codec is _U16_LE:
                out.extend(struct.unpack_from(f"<{n}H", data[block], offset))
            elif run.codec is _U16_BE_MASKED:
                out.extend(v & 0x7FFF for v in struct.unpack_from(f">{n}H", data[block], offset))
            elif run.codec is _U16_BE:
                out.extend(struct.unpack_from(f">{n}H", data[block], offset))
            else:
                out.append(_decode(points[a], data[block]))
            a += n
            i += 1
        return out

    def read_bits(self, table: Table, address: int, count: int) -> list[bool]:
        now = self.now
        points = self.unit.plan.bits(table)
        stamps, data, max_age = self.unit.cache.stamps, self.unit.cache.data, self.unit.freshness.limits
        if self._silent(now):
            if all(a in points for a in range(address, address + count)):
                raise self._stale()
        out: list[bool] = []
        block = -1
        raw = bytearray()
        for a in range(address, address + count):
            point = points.get(a)
            if point is None:
                raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"{table.value} {a} is not mapped")
            if point.block != block:
                block = point.block
                if now - stamps[block] > max_age[block]:
                    raise self._stale(block)
                raw = data[block]
            out.append(bool(raw[point.offset] >> point.bit & 1))
        return out


class ReferenceBackend:
    """The old backend: async reads (the server's task path), decoded per read."""

    def __init__(self, reader: ReferenceReader) -> None:
        self.reader = reader

    def has_unit(self, unit: int) -> bool:
        return unit == 1

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return self.reader.read_bits(Table.COIL, address, count)

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return self.reader.read_bits(Table.DISCRETE, address, count)

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self.reader.read_registers(Table.HOLDING, address, count)

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self.reader.read_registers(Table.INPUT, address, count)

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        raise AssertionError("not used")

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        raise AssertionError("not used")


def run_now(reply: bytes | Coroutine[Any, Any, bytes]) -> bytes:
    """A reply frame of ``ModbusTcpServer._request``: at once, or its coroutine run to the end."""
    if isinstance(reply, bytes):
        return reply
    try:
        reply.send(None)
    except StopIteration as done:
        frame: bytes = done.value
        return frame
    raise AssertionError("the reference read suspended")


# --- the unit under test ------------------------------------------------------------------


class ClockedUnit(Unit):
    """A unit over any plan whose clock the test sets (reads only; nothing is polled)."""

    now = 0.0

    def _loop_time(self) -> float:
        return self.now

    async def read_block(self, block: Block) -> bytes:
        raise AssertionError("not polled")

    async def _write_register(self, target: object, value: int, line: LineLease) -> None:
        raise AssertionError("not written")

    async def _write_bit(self, target: object, value: bool, line: LineLease) -> None:
        raise AssertionError("not written")

    @property
    def last_fault_number(self) -> int:
        return 0


CODEC_BYTES = {
    Codec.U16_BE: 2,
    Codec.U16_BE_MASKED: 2,
    Codec.U16_LE: 2,
    Codec.U8: 1,
    Codec.F32_HIGH: 4,
    Codec.F32_LOW: 4,
}
#: dyadic times and ages: every sum and difference below is exact in floating point
TIMES = st.integers(0, 48).map(lambda k: k / 4)  # coarse: reads often fall on a deadline


@st.composite
def plans(draw: st.DrawFn) -> Plan:
    sizes = draw(st.lists(st.integers(1, 12), min_size=1, max_size=8))
    scans = draw(st.lists(st.sampled_from(Scan), min_size=len(sizes), max_size=len(sizes)))
    plan = Plan(blocks=[Block(None, size, scan) for size, scan in zip(sizes, scans, strict=True)])
    for table in (Table.HOLDING, Table.INPUT):
        points = plan.registers(table)
        # runs of consecutive addresses (segments), sometimes a whole run from one block
        for first in draw(st.lists(st.integers(0, 40), max_size=5, unique=True)):
            length = draw(st.integers(1, 8))
            codec = draw(st.sampled_from(ALL_CODECS))
            block = draw(st.integers(0, len(sizes) - 1))
            stride = draw(st.sampled_from([0, 1, 2, 4]))
            for k in range(length):
                if draw(st.booleans()):  # each point its own way
                    codec = draw(st.sampled_from(ALL_CODECS))
                    block = draw(st.integers(0, len(sizes) - 1))
                width = CODEC_BYTES[codec]
                if sizes[block] < width:
                    continue
                offset = (k * stride) % (sizes[block] - width + 1)
                if draw(st.booleans()):
                    offset = draw(st.integers(0, sizes[block] - width))
                points[first + k] = RegisterPoint(block, offset, codec)
    for table in (Table.COIL, Table.DISCRETE):
        points_b = plan.bits(table)
        for first in draw(st.lists(st.integers(0, 60), max_size=4, unique=True)):
            length = draw(st.integers(1, 24))
            block = draw(st.integers(0, len(sizes) - 1))
            start = draw(st.integers(0, 8 * sizes[block] - 1))
            for k in range(length):
                if draw(st.integers(0, 4)) == 0:
                    block = draw(st.integers(0, len(sizes) - 1))
                    start = draw(st.integers(0, 8 * sizes[block] - 1)) - k
                position = (start + k) % (8 * sizes[block])
                points_b[first + k] = BitPoint(block, position // 8, position % 8)
    return plan


@st.composite
def operations(draw: st.DrawFn, plan: Plan) -> list[tuple[Any, ...]]:
    ops: list[tuple[Any, ...]] = []
    n_blocks = len(plan.blocks)
    for _ in range(draw(st.integers(1, 30))):
        kind = draw(st.sampled_from(["store", "store", "patch", "read", "read", "read", "refuse"]))
        block = draw(st.integers(0, n_blocks - 1))
        size = plan.blocks[block].size
        if kind == "store":
            ops.append(("store", block, draw(st.binary(min_size=size, max_size=size)), draw(TIMES)))
        elif kind == "patch":
            offset = draw(st.integers(0, size - 1))
            ops.append(("patch", block, offset, draw(st.binary(min_size=1, max_size=size - offset))))
        elif kind == "refuse":
            ops.append(("refuse", block, draw(st.booleans())))
        else:
            function_code = draw(st.sampled_from([1, 2, 3, 4]))
            count = draw(st.integers(1, 12 if function_code >= 3 else 40))
            table = {1: Table.COIL, 2: Table.DISCRETE, 3: Table.HOLDING, 4: Table.INPUT}[function_code]
            mapped = sorted(plan.registers(table) if function_code >= 3 else plan.bits(table))
            if mapped and draw(st.integers(0, 4)):
                address = max(0, draw(st.sampled_from(mapped)) - draw(st.integers(0, 2)))
            else:
                address = draw(st.integers(0, 70))
            # mostly shortly after the last store: some blocks fresh, some just stale
            stores = [op[3] for op in ops if op[0] == "store"]
            now = stores[-1] + draw(st.integers(0, 12)) / 4 if stores and draw(st.integers(0, 4)) else draw(TIMES)
            ops.append(("read", function_code, address, count, now))
    return ops


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), stale_after=st.sampled_from([0.5, 1.0, 2.0]), fast=st.sampled_from([0.0, 0.25, 1.0]))
def test_image_replies_equal_the_old_decoder(data: st.DataObject, stale_after: float, fast: float) -> None:
    plan = data.draw(plans())
    driver = SlcAsciiDriver("sim://slc150?ladder=0")
    unit = ClockedUnit(unit_id=1, name="random", driver=driver, plan=plan, stale_after=stale_after,
                       fast_interval=fast, slow_interval=4.0)
    reference = ReferenceReader(unit)
    new = ModbusTcpServer(GatewayBackend([unit]), "127.0.0.1", 0)
    old = ModbusTcpServer(ReferenceBackend(reference), "127.0.0.1", 0)
    tid = 0
    for op in data.draw(operations(plan)):
        if op[0] == "store":
            unit.cache.store(op[1], op[2], op[3])
        elif op[0] == "patch":
            unit.cache.patch(op[1], op[2], op[3])
        elif op[0] == "refuse":
            if op[2]:
                unit.poller.refused[op[1]] = (ControllerRefused("refused"), 0.0)
            else:
                unit.poller.refused.pop(op[1], None)
        else:
            _, function_code, address, count, now = op
            unit.now = reference.now = now
            tid += 1
            pdu = struct.pack(">BHH", function_code, address, count)
            assert run_now(new._request(tid, 1, pdu)) == run_now(old._request(tid, 1, pdu)), op
            fast_blocks = [i for i, b in enumerate(plan.blocks) if b.scan is Scan.FAST]
            expected_age = unit.cache.oldest_age(fast_blocks, now) if fast_blocks else 0.0
            assert unit.cache.oldest_fast_age(now) == expected_age


def test_default_slc_map_replies_equal_the_old_decoder() -> None:
    """Every read of the SLC 100/150 default map, fresh, against the old decoder."""
    unit = ClockedUnit(unit_id=1, name="slc", driver=SlcAsciiDriver("sim://slc150?ladder=0"),
                       plan=slc_ascii_plan())
    for block, spec in enumerate(unit.plan.blocks):
        unit.cache.store(block, bytes((block * 37 + k * 101) & 0xFF for k in range(spec.size)), 100.0)
    reference = ReferenceReader(unit)
    unit.now = reference.now = 101.0
    new = ModbusTcpServer(GatewayBackend([unit]), "127.0.0.1", 0)
    old = ModbusTcpServer(ReferenceBackend(reference), "127.0.0.1", 0)
    for function_code, addresses, widths in ((3, range(0, 66), (1, 2, 60, 64)), (4, range(0, 140), (1, 2, 9, 32)),
                                             (1, range(695, 870), (1, 8, 64)), (2, range(0, 990, 7), (1, 17, 64))):
        for address in addresses:
            for count in widths:
                pdu = struct.pack(">BHH", function_code, address, count)
                assert run_now(new._request(1, 1, pdu)) == run_now(old._request(1, 1, pdu)), (function_code, address)


# --- a confirmed write never makes stale data look fresh -----------------------------------


@pytest.fixture
async def slc_unit() -> Any:
    """An SLC 150 unit on the in-process simulator; its driver runs, its poller does not."""
    url = "sim://slc150?ladder=0"
    unit = SlcAsciiUnit(driver=SlcAsciiDriver(url, timeout=0.2), unit_id=1, name="slc", stale_after=1.0,
                        fast_interval=0.0, slow_interval=10.0)
    async with unit.driver:
        yield unit


def _fill(unit: Unit, old_blocks: set[int]) -> None:
    """Every block read now, except ``old_blocks``: read long ago (stale), though the link answers."""
    now = asyncio.get_running_loop().time()
    for block, spec in enumerate(unit.plan.blocks):
        when = now - 100.0 if block in old_blocks else now
        unit.cache.store(block, bytes(spec.size), when)


async def test_confirmed_register_write_into_an_old_block_stays_stale(slc_unit: SlcAsciiUnit) -> None:
    unit = slc_unit
    target = unit.plan.holding[5].block
    _fill(unit, {target})
    assert unit.read_registers(Table.HOLDING, 4, 1) == [0]  # a neighbour in a fresh block serves
    await unit.write_registers(5, [4321])  # the controller confirms it
    assert unit.cache.data[target][unit.plan.holding[5].offset :][:2] == (4321).to_bytes(2, "big")
    for address, count in ((5, 1), (4, 3), (0, 64)):
        with pytest.raises(ModbusExceptionReply) as stale:
            unit.read_register_bytes(Table.HOLDING, address, count)
        assert stale.value.code == TARGET_FAILED
    # The server's reply too: exception 0x0B, not the written value.
    server = ModbusTcpServer(GatewayBackend([unit]), "127.0.0.1", 0)
    assert server._request(7, 1, struct.pack(">BHH", 3, 5, 1)) == bytes.fromhex("0007 0000 0003 01 83 0b")
    # Once the block is read again, the value written (now in the controller) is served.
    unit.cache.store(target, await unit.read_block(unit.plan.blocks[target]), asyncio.get_running_loop().time())
    assert unit.read_registers(Table.HOLDING, 5, 1) == [4321]


async def test_confirmed_coil_write_into_an_old_block_stays_stale(slc_unit: SlcAsciiUnit) -> None:
    unit = slc_unit
    target = unit.plan.coils[703].block
    _fill(unit, {target})
    fresh = next(a for a, p in unit.plan.coils.items() if p.block != target)
    assert unit.read_bits(Table.COIL, fresh, 1) == [False]
    await unit.write_bits(703, [True])
    point = unit.plan.coils[703]
    assert unit.cache.data[target][point.offset] >> point.bit & 1
    with pytest.raises(ModbusExceptionReply) as stale:
        unit.read_bit_bytes(Table.COIL, 703, 1)
    assert stale.value.code == TARGET_FAILED
    with pytest.raises(ModbusExceptionReply):
        unit.read_bit_bytes(Table.DISCRETE, 703, 1)  # the same relay as a discrete input


async def test_write_patches_the_image_of_a_fresh_block(slc_unit: SlcAsciiUnit) -> None:
    unit = slc_unit
    _fill(unit, set())
    await unit.write_registers(40, [1111, 2222])
    assert unit.read_registers(Table.HOLDING, 39, 4) == [0, 1111, 2222, 0]
    await unit.write_bits(709, [True, False, True])
    assert unit.read_bits(Table.COIL, 709, 3) == [True, False, True]


@pytest.mark.parametrize("scan", list(Scan))
def test_freshness_boundary_equals_the_old_decoder(scan: Scan) -> None:
    """A value is served at exactly its block's max age and not 1/8 s later (two blocks, one older)."""
    plan = Plan(blocks=[Block(None, 2, scan), Block(None, 2, Scan.FAST)])
    plan.holding[0] = RegisterPoint(0, 0, Codec.U16_BE)
    plan.holding[1] = RegisterPoint(1, 0, Codec.U16_LE)
    plan.coils[0] = BitPoint(0, 1, 3)
    unit = ClockedUnit(unit_id=1, name="edge", driver=SlcAsciiDriver("sim://slc150?ladder=0"), plan=plan,
                       stale_after=1.0, fast_interval=0.5, slow_interval=4.0)
    reference = ReferenceReader(unit)
    new = ModbusTcpServer(GatewayBackend([unit]), "127.0.0.1", 0)
    old = ModbusTcpServer(ReferenceBackend(reference), "127.0.0.1", 0)
    unit.cache.store(0, b"\x12\x34", 10.0)
    max_age = unit.freshness.limits[0]
    for now in (10.0 + max_age - 0.125, 10.0 + max_age, 10.0 + max_age + 0.125):
        unit.cache.store(1, b"\x56\x78", now)  # the link answers: never silent
        unit.now = reference.now = now
        replies = set()
        for pdu in (b"\x03\x00\x00\x00\x02", b"\x03\x00\x00\x00\x01", b"\x01\x00\x00\x00\x01"):
            reply = run_now(new._request(1, 1, pdu))
            assert reply == run_now(old._request(1, 1, pdu)), (now, pdu)
            replies.add(reply[7] & 0x80)
        assert replies == ({0x80} if now > 10.0 + max_age else {0})


def _code_at(unit: ClockedUnit, now: float, address: int) -> int | None:
    """The exception code a read of one holding register gets at ``now`` (None: served)."""
    unit.now = now
    try:
        unit.read_registers(Table.HOLDING, address, 1)
    except ModbusExceptionReply as exc:
        return exc.code
    return None


def test_the_silent_link_limit_and_the_slow_values_age_are_the_documented_ones() -> None:
    """The limits as README ("Reads, staleness and writes") and ``gateway/unit.py``'s module doc
    state them, with the values here: ``stale_after`` 5 s, ``fast_interval`` 1 s,
    ``slow_interval`` 10 s.

    * "A slow-class value read every 10 s with ``stale_after = 5`` is served for up to 15 s after
      its last read, while the link answers": served at 15 s, 0x0B at 15.125 s.
    * "no value outlives a silent link by more than ``stale_after`` (plus ``fast_interval``)",
      i.e. stale once the controller has answered no poll for ``stale_after`` plus the shortest
      scan period: 5 + min(1, 10) = 6 s.  The slow value too: served at 6 s, 0x0B at 6.125 s.
    """
    plan = Plan(blocks=[Block(None, 2, Scan.SLOW), Block(None, 2, Scan.FAST)])
    plan.holding[0] = RegisterPoint(0, 0, Codec.U16_BE)
    plan.holding[1] = RegisterPoint(1, 0, Codec.U16_BE)
    unit = ClockedUnit(unit_id=1, name="limits", driver=SlcAsciiDriver("sim://slc150?ladder=0"), plan=plan,
                       stale_after=5.0, fast_interval=1.0, slow_interval=10.0)
    unit.cache.store(0, b"\x00\x01", 100.0)
    unit.cache.store(1, b"\x00\x02", 100.0)
    # the link answers: the fast block is read every second, the slow one not again
    for now in range(101, 116):
        unit.cache.store(1, b"\x00\x02", float(now))
        assert _code_at(unit, float(now), 0) is None
    unit.cache.store(1, b"\x00\x02", 115.125)
    assert _code_at(unit, 115.125, 0) == TARGET_FAILED

    # the same two blocks read at 200, then the link is silent
    unit.cache.store(0, b"\x00\x01", 200.0)
    unit.cache.store(1, b"\x00\x02", 200.0)
    assert _code_at(unit, 206.0, 0) is None
    assert _code_at(unit, 206.125, 0) == TARGET_FAILED  # a slow value 6.125 s old: 9 s inside its own limit
    assert _code_at(unit, 206.125, 1) == TARGET_FAILED


async def test_pipelined_reads_answered_in_order_with_their_own_ids() -> None:
    """200 reads in one segment (more than a turn of the loop takes): every reply, in order, own id."""
    plan = slc_ascii_plan()
    unit = ClockedUnit(unit_id=1, name="slc", driver=SlcAsciiDriver("sim://slc150?ladder=0"), plan=plan)
    for block, spec in enumerate(plan.blocks):
        unit.cache.store(block, bytes((block + k) & 0xFF for k in range(spec.size)), 100.0)
    unit.now = 100.5
    server = ModbusTcpServer(GatewayBackend([unit]), "127.0.0.1", 0)
    await server.start()
    try:
        requests = [(3, 0, 60), (1, 701, 64), (4, 1000, 3), (3, 64, 1), (2, 1, 18)]
        expected = {}
        frames = b""
        for tid in range(200):
            pdu = struct.pack(">BHH", *requests[tid % len(requests)])
            expected[tid] = run_now(server._request(tid, 1, pdu))[7:]
            frames += struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(frames)
        for tid in range(200):
            async with asyncio.timeout(2.0):
                header = await reader.readexactly(7)
                body = await reader.readexactly(struct.unpack_from(">H", header, 4)[0] - 1)
            assert struct.unpack_from(">H", header)[0] == tid
            if tid % len(requests) != 2:  # the status block counts requests: skip its values
                assert body == expected[tid], tid
        writer.close()
    finally:
        await server.close()


# --- the generic unit (gateway/unit.py) over a controller in memory --------------------------------
#
# The rules are those of gateway/unit.py's module doc, the status block's reference
# (docs/reference/status-block.md) and the write path's (README "Reads, staleness and writes"):
# exceptions by cause, the status registers, image patches after confirmed writes, partial writes
# logged, the write_timeout answers and their audit lines.

BE = CodecType("be", 0, 1)  # high byte first
LE = CodecType("le", 1, 0)  # low byte first
BYTE = CodecType("byte", None, 0)  # one byte, high byte 0
SPLIT = CodecType("split", 3, 0)  # low byte at the offset, high byte 3 further
GAP_BE = CodecType("gap-be", 0, 2)  # high byte at the offset, low byte 2 further
GAP_LE = CodecType("gap-le", 2, 0)  # low byte at the offset, high byte 2 further
HIGH = CodecType("f32-high", 0, 1, half=Half.HIGH)
LOW = CodecType("f32-low", 0, 1, half=Half.LOW)


def memory_plan() -> Plan[str, str]:
    """Block 0 (20 bytes, fast): holding 0-7 in every byte layout, a 32-bit pair at 4-5, 7 read
    only; coils 0-2 in byte 18 (bits 0, 3, 5; 2 read only).  Block 1 (12 bytes, slow): two
    32-bit pairs at 8-11, the second with halves of two different values; 12 and 13 with their
    bytes 2 apart, interleaved (bytes 8-11)."""
    plan: Plan[str, str] = Plan(blocks=[Block(None, 20, Scan.FAST), Block(None, 12, Scan.SLOW)])
    for address, offset, codec, target in (
        (0, 0, BE, "w0"), (1, 2, LE, "w1"), (2, 4, BYTE, "w2"), (3, 5, SPLIT, "w3"),
        (4, 10, HIGH, "f"), (5, 12, LOW, "f"), (6, 14, BE, "w6"), (7, 16, BE, None),
    ):
        plan.holding[address] = RegisterPoint(0, offset, codec, target, max_value=9999 if address == 1 else 0xFFFF)
    for address, offset, codec, target in (
        (8, 0, HIGH, "p"), (9, 2, LOW, "p"), (10, 4, HIGH, "q"), (11, 6, LOW, "r"), (12, 8, GAP_BE, "g1"),
        (13, 9, GAP_LE, "g2"),
    ):
        plan.holding[address] = RegisterPoint(1, offset, codec, target)
    for address, bit, target in ((0, 0, "c0"), (1, 3, "c1"), (2, 5, None)):
        plan.coils[address] = BitPoint(0, 18, bit, target)
    for address in range(16):  # discrete inputs 0-15: the bits of bytes 18 and 19, least significant first
        plan.discrete[address] = BitPoint(0, 18 + address // 8, address % 8)
    return plan


class FakeDriver:
    """A driver (``gateway.line_driver.UnitDriver``) whose line is always free."""

    def __init__(self) -> None:
        self.name = "mem"
        self.url = "mem://"
        self.counters = LineCounters()
        self.last_error = ""
        self.state_since: float | None = None
        self.write_burst = 1
        self.poll_burst = 2
        self.available = True
        self.connected = True

    @contextlib.asynccontextmanager
    async def write_session(self) -> AsyncIterator[LineLease]:
        yield LineLease()

    async def first_attempt(self) -> None:
        pass


class MemoryUnit(Unit[str, str]):
    """A unit whose controller is a list of the commands it applied; a target in ``refuse`` is
    refused (as a PLC refuses a protected file); ``gate``, when set, holds every command until it
    is opened; ``now``, when set, is the unit's clock."""

    def __init__(self, **options: Any) -> None:
        options.setdefault("driver", FakeDriver())
        options.setdefault("plan", memory_plan())
        super().__init__(unit_id=1, name="mem", **options)
        self.applied: list[tuple[str, int]] = []
        self.refuse: set[str] = set()
        self.gate: asyncio.Event | None = None
        self.now: float | None = None
        self.fault = 0
        self.image_refuses: dict[str, str] = {}

    def _loop_time(self) -> float:
        return self.now if self.now is not None else super()._loop_time()

    async def read_block(self, block: Block) -> bytes:
        await asyncio.Event().wait()  # a line that never answers: the poller runs, nothing is read
        raise AssertionError("not reached")

    async def _command(self, target: str, value: int) -> None:
        if self.gate is not None:
            await self.gate.wait()
        if target in self.refuse:
            raise ControllerRefused(f"{target} is protected")
        self.applied.append((target, value))

    async def _write_register(self, target: str, value: int, line: LineLease) -> None:
        await self._command(target, value)

    async def _write_bit(self, target: str, value: bool, line: LineLease) -> None:
        await self._command(target, int(value))

    def _refused_by_image(self, point: RegisterPoint[str]) -> str | None:
        return self.image_refuses.get(point.write or "")

    @property
    def last_fault_number(self) -> int:
        return self.fault


class PairUnit(MemoryUnit):
    """A unit whose controller takes a 32-bit value in one command."""

    async def _write_pair(self, target: str, raw: int, line: LineLease) -> None:
        await self._command(target, raw)


def _fresh(unit: MemoryUnit, now: float | None = None) -> None:
    """Every block read at ``now`` (the unit's clock; default: the loop's, which writes need)."""
    unit.now = now
    if now is None:
        now = asyncio.get_running_loop().time()
    for block, spec in enumerate(unit.plan.blocks):
        unit.cache.store(block, bytes(spec.size) if block else bytes(18) + b"\x0a\x01", now)


def _raised(call: Any, *args: Any) -> ModbusExceptionReply:
    with pytest.raises(ModbusExceptionReply) as info:
        call(*args)
    return info.value


async def _write_raised(write: Any) -> ModbusExceptionReply:
    with pytest.raises(ModbusExceptionReply) as info:
        await write
    return info.value


def test_the_status_block_registers() -> None:
    """docs/reference/status-block.md: 1000 link up (1) / down (0); 1001 age of the oldest
    fast-class value in 100 ms units, 65535 never read or saturated; 1002 last fault; 1003-1010
    32-bit counters, high word first; 1011 the link's state (0 up, 1 stale, 2 down); a read past 1011
    is refused 0x02."""
    unit = MemoryUnit(stale_after=5.0)
    driver = unit.driver
    assert isinstance(driver, FakeDriver)
    driver.counters.transactions = 0x12345
    driver.counters.errors = 7
    driver.counters.retries_by_kind = {"nak": 3, "enq": 1}
    unit.fault = 0x10000  # wider than its register: saturated
    unit.now = 50.0
    # never read: the controller answers, its data is stale (state 1)
    assert unit.read_registers(Table.INPUT, 1000, 12) == [1, 65535, 65535, 1, 0x2345, 0, 7, 0, 4, 0, 0, 1]
    assert unit.status_values(50.0)["data_age"] == 65535  # never read
    unit.cache.store(0, bytes(20), 100.0)
    unit.cache.store(1, bytes(12), 90.0)  # slow: not in the age
    for now, tenths in ((100.5, 5), (103.0, 30), (100.0 + 6553.4, 65534), (100.0 + 7000.0, 65535)):
        unit.now = now
        assert unit.read_registers(Table.INPUT, 1001, 1) == [tenths], now
        assert unit.status_values(now)["data_age"] == tenths
    unit.now = 100.5
    assert unit.read_registers(Table.INPUT, 1011, 1) == [0]  # fresh: up
    driver.available = False
    assert unit.read_registers(Table.INPUT, 1000, 1) == [0]
    assert unit.read_registers(Table.INPUT, 1011, 1) == [2]  # down
    error = _raised(unit.read_register_bytes, Table.INPUT, 1011, 2)
    assert error.code == ModbusExceptionReply.ILLEGAL_DATA_ADDRESS


class HeardUnit(MemoryUnit):
    """A unit whose kind's runner fills the image (not polled)."""

    POLLED = False


def test_the_data_age_of_a_unit_not_polled_is_the_time_since_its_peer_was_heard() -> None:
    unit = HeardUnit()
    unit.heard(100.0)
    unit.now = 100.5
    assert unit.read_registers(Table.INPUT, 1001, 1) == [5]


def test_bits_are_read_least_significant_first_across_bytes() -> None:
    unit = MemoryUnit()
    _fresh(unit, 100.0)  # byte 18 0b1010, byte 19 0b0001
    assert unit.read_bits(Table.DISCRETE, 0, 16) == [i in (1, 3, 8) for i in range(16)]


def test_reads_note_demand_and_a_silent_controller_answers_stale() -> None:
    """Silent: no answer for ``stale_after`` plus the shortest scan period (here 1 + 0.5 s)."""
    unit = MemoryUnit(stale_after=1.0, fast_interval=0.5, slow_interval=4.0)
    _fresh(unit, 100.0)
    unit.now = 101.5  # silent exactly at its limit: not yet
    assert unit.read_registers(Table.HOLDING, 0, 2) == [0, 0]
    assert unit.demand.keys == {(Table.HOLDING, 0, 2): 101.5}
    unit.now = 105.0  # the slow block (read at 100) is within its own limit, but the line is silent
    error = _raised(unit.read_registers, Table.HOLDING, 8, 2)
    assert (error.code, str(error)) == (TARGET_FAILED, "mem: no fresh data (stale after 1 s)")
    error = _raised(unit.read_registers, Table.HOLDING, 20, 1)
    assert (error.code, str(error)) == (ILLEGAL_ADDRESS, "holding register 20 is not mapped")


async def test_a_stale_read_on_a_link_that_is_up_may_wait_for_its_block() -> None:
    driver = FakeDriver()
    unit = MemoryUnit(stale_after=1.0, fast_interval=0.5, read_wait=0.5, driver=driver)
    poller = asyncio.create_task(unit.run())
    try:
        await asyncio.sleep(0.01)
        now = asyncio.get_running_loop().time()
        unit.cache.store(0, bytes(20), now - 10.0)
        unit.cache.store(1, bytes(12), now)  # the line answers: not silent
        error = _raised(unit.read_register_bytes, Table.HOLDING, 0, 1)
        assert isinstance(error, StaleRead) and error.read_wait == 0.5
        assert str(error) == "mem: no fresh data (stale after 1 s)"
        waited = error.wait()  # asks the poller for block 0 (which never comes)
        assert isinstance(waited, asyncio.Future) and not waited.done()
        assert unit.poller is not None and unit.poller.read_waits == 1
        driver.available = False
        assert not isinstance(_raised(unit.read_register_bytes, Table.HOLDING, 0, 1), StaleRead)
        driver.available = True
        unit.read_wait = 0.0
        assert not isinstance(_raised(unit.read_register_bytes, Table.HOLDING, 0, 1), StaleRead)
    finally:
        poller.cancel()
        await asyncio.gather(poller, return_exceptions=True)


async def test_confirmed_writes_patch_each_register_layout() -> None:
    unit = PairUnit()
    _fresh(unit)
    await unit.write_registers(0, [0x1234, 0x1234, 0xAB, 0x1234])
    await unit.write_registers(3, [0x0102, 0x4049, 0x0FDB, 0x0506])  # the pair of 4-5 in one command
    assert unit.applied == [("w0", 0x1234), ("w1", 0x1234), ("w2", 0xAB), ("w3", 0x1234),
                            ("w3", 0x0102), ("f", 0x40490FDB), ("w6", 0x0506)]
    data = unit.cache.data[0]
    assert data[0:2] == b"\x12\x34" and data[2:4] == b"\x34\x12" and data[4] == 0xAB
    assert (data[8], data[5]) == (0x01, 0x02)  # the split register: high byte 3 after the low
    assert data[10:14] == b"\x40\x49\x0f\xdb" and data[14:16] == b"\x05\x06"
    assert unit.read_registers(Table.HOLDING, 0, 7) == [0x1234, 0x1234, 0xAB, 0x0102, 0x4049, 0x0FDB, 0x0506]
    await unit.write_registers(1, [0x0A0B])  # its two bytes only: the byte of register 2 after them stays
    assert unit.cache.data[0][2:5] == b"\x0b\x0a\xab"
    await unit.write_registers(12, [0x1234, 0x5678])
    assert unit.cache.data[1][8:12] == b"\x12\x78\x34\x56"
    assert unit.read_registers(Table.HOLDING, 12, 2) == [0x1234, 0x5678]
    assert (unit.write_requests, unit.write_failures) == (4, 0)


async def test_confirmed_coil_writes_change_their_bit_only() -> None:
    unit = MemoryUnit()
    _fresh(unit)  # coil byte 0b1010: coil 1 (bit 3) on, bit 1 (no coil) on
    await unit.write_bits(0, [True, False])
    assert unit.cache.data[0][18] == 0b0011
    await unit.write_bits(0, [False])
    assert unit.cache.data[0][18] == 0b0010
    assert unit.applied == [("c0", 1), ("c1", 0), ("c0", 0)]
    error = await _write_raised(unit.write_bits(1, [True, True]))
    assert (error.code, str(error)) == (ILLEGAL_ADDRESS, "coil 2 is not writable")


@pytest.mark.parametrize(
    ("address", "values", "code", "message"),
    [
        (0, [1, 10000], 0x03, "holding register 1: 10000 > 9999"),
        (3, [1, 2, 3, 4, 5], 0x02, "holding register 7 is not writable"),
        (4, [1], 0x02, "holding register 4 is half of a 32-bit value: write both of its registers in one request"),
        (5, [1, 2], 0x02, "holding register 5 is half of a 32-bit value: write both of its registers in one request"),
        (8, [1, 2, 3, 4], 0x02,
         "holding register 10 is half of a 32-bit value: write both of its registers in one request"),
        (1, [5, 6], 0x04, "holding register 2: the file is protected; nothing written"),
    ],
)
async def test_a_write_is_checked_whole_before_anything_is_sent(
    address: int, values: list[int], code: int, message: str
) -> None:
    unit = PairUnit()
    _fresh(unit)
    unit.image_refuses["w2"] = "the file is protected"
    error = await _write_raised(unit.write_registers(address, values))
    assert (error.code, str(error)) == (code, message)
    assert unit.applied == []
    await unit.write_registers(1, [9999])  # the largest value allowed


async def test_a_32_bit_pair_on_a_unit_without_32_bit_registers_is_refused() -> None:
    unit = MemoryUnit()
    _fresh(unit)
    error = await _write_raised(unit.write_registers(4, [1, 2]))
    assert (error.code, str(error)) == (ILLEGAL_ADDRESS, "this unit has no 32-bit registers")
    assert (unit.write_requests, unit.write_failures) == (1, 1)


async def test_a_refused_write_is_answered_0x04_and_a_partial_one_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    unit = PairUnit()
    _fresh(unit)
    unit.refuse = {"w6"}
    error = await _write_raised(unit.write_registers(0, [1, 2, 3, 4, 5, 6, 7]))
    assert error.code == DEVICE_FAILURE and "w6 is protected" in str(error)
    assert unit.cache.data[0][14:16] == b"\x00\x00"  # not written: not patched
    assert "write partly applied: holding 0-5 written, holding 6 and after not" in caplog.text
    unit.refuse = {"f"}
    await _write_raised(unit.write_registers(3, [1, 2, 3]))
    assert "write partly applied: holding 3 written, holding 4-5 and after not" in caplog.text
    unit.refuse = {"w2"}
    await _write_raised(unit.write_registers(0, [1, 2, 3]))
    assert "write partly applied: holding 0-1 written, holding 2 and after not" in caplog.text
    assert (unit.partial_writes, unit.write_requests, unit.write_failures) == (3, 3, 3)
    unit.refuse = {"w0"}
    await _write_raised(unit.write_registers(0, [1]))  # nothing applied: not partial
    assert unit.partial_writes == 3



def test_a_write_footprint_is_the_word_its_target_changes() -> None:
    unit = MemoryUnit()

    @dataclass(frozen=True)
    class Word:
        address: str

    footprint: Any = unit._footprint  # any kind's target: one with an address, or the address itself
    assert footprint(Word("N7:0")) == "N7:0"
    assert footprint("w0") == "w0"


async def test_write_timeout_answers_and_their_audit_lines(caplog: pytest.LogCaptureFixture) -> None:
    """README: a write still waiting for the line at write_timeout is withdrawn (nothing written);
    one on the line is answered 0x0B and its outcome is audited; a multi-command write sends nothing
    more after its answer."""
    caplog.set_level(logging.INFO, logger="gateway.audit")
    unit = MemoryUnit(write_timeout=0.05)
    _fresh(unit)
    unit.now = None
    unit.gate = asyncio.Event()
    on_line = asyncio.ensure_future(unit.write_registers(0, [1, 2]))
    await asyncio.sleep(0)
    waiting = asyncio.ensure_future(unit.write_registers(6, [3]))
    started = asyncio.get_running_loop().time()
    first, second = await asyncio.gather(_write_raised(on_line), _write_raised(waiting))
    assert asyncio.get_running_loop().time() - started < 0.5
    assert first.code == second.code == TARGET_FAILED
    assert "no verdict within write_timeout (0.05 s)" in str(first)
    assert "the write was withdrawn, nothing was written" in str(second)
    assert "unit 1: holding 6 not sent within write_timeout 0.05 s: withdrawn, nothing written" in caplog.messages
    unit.gate.set()
    for _ in range(100):
        if "then:" in caplog.text:
            break
        await asyncio.sleep(0.01)
    assert unit.applied == [("w0", 1)]  # the second command was not sent after the answer
    assert "unit 1: holding 0-1 answered 0x0B at write_timeout 0.05 s, then: " in caplog.text
    assert "(write_timeout passed before this command); answered 0x0B" in caplog.text
    assert (unit.write_requests, unit.write_failures, unit.write_latency.count) == (2, 2, 2)
    assert unit.write_latency.total < 1.0

    for refused, verdict in (({"w6"}, "w6 is protected"), (set(), "applied")):
        unit.gate = asyncio.Event()
        unit.refuse = refused
        await _write_raised(unit.write_registers(6, [4]))
        unit.gate.set()
        line = f"unit 1: holding 6 answered 0x0B at write_timeout 0.05 s, then: {verdict}"
        for _ in range(100):
            if line in caplog.messages:
                break
            await asyncio.sleep(0.01)
        assert line in caplog.messages

    unit.gate = asyncio.Event()  # never opened: the gateway stops with the write on the line
    await _write_raised(unit.write_registers(6, [6]))
    worker = unit.writes._worker
    assert worker is not None
    worker.cancel()
    await asyncio.gather(worker, return_exceptions=True)
    await asyncio.sleep(0)
    assert (
        "unit 1: holding 6 answered 0x0B at write_timeout 0.05 s, then: not known (the gateway stopped before its "
        "verdict)" in caplog.messages
    )


def test_writable_ranges_let_a_write_through_only_whole_in_one_range_of_its_table() -> None:
    """``writable``: a write must lie whole in one range of its own table (else 0x02)."""
    unit = MemoryUnit(writable=[(Table.HOLDING, 1, 3), (Table.COIL, 0, 0)])
    allowed = {(1, 3): True, (1, 1): True, (3, 1): True, (0, 1): False, (3, 2): False, (0, 5): False, (4, 1): False}
    for (address, count), expected in allowed.items():
        try:
            unit._check_writable(Table.HOLDING, address, count)
        except ModbusExceptionReply as error:
            assert (expected, error.code) == (False, ILLEGAL_ADDRESS), (address, count)
        else:
            assert expected, (address, count)
    unit._check_writable(Table.COIL, 0, 1)
    error = _raised(unit._check_writable, Table.COIL, 1, 1)
    assert (error.code, str(error)) == (ILLEGAL_ADDRESS, "coil 1 is not in a writable range")
    error = _raised(MemoryUnit(read_only=True)._check_writable, Table.HOLDING, 1, 1)
    assert (error.code, str(error)) == (ILLEGAL_ADDRESS, "mem is read only")


async def test_a_partial_coil_write_is_logged_by_coil(caplog: pytest.LogCaptureFixture) -> None:
    unit = MemoryUnit()
    _fresh(unit)
    unit.refuse = {"c1"}
    await _write_raised(unit.write_bits(0, [True, True]))
    assert "write partly applied: coil 0 written, coil 1 and after not" in caplog.text
    assert unit.applied == [("c0", 1)] and unit.cache.data[0][18] & 1


def test_the_poller_and_write_queue_take_the_units_options() -> None:
    driver, share = FakeDriver(), LineShare()
    unit = MemoryUnit(driver=driver, line_share=share, fast_interval=1.0, slow_interval=4.0, stagger=0.25,
                      demand_hold=7.0, background_interval=45.0, write_queue_per_client=3, write_queue_per_link=5)
    assert (unit.writes.per_client, unit.writes.per_link) == (3, 5)
    poller, schedule = unit.poller, unit.schedule
    assert poller is not None and schedule is not None
    assert poller.schedule is schedule and poller.demand is unit.demand and poller._share is share
    assert (poller.fast_interval, poller.slow_interval, poller.stagger) == (1.0, 4.0, 0.25)
    assert (schedule.period, schedule.demand_hold, schedule.background) == ([1.0, 4.0], 7.0, [45.0, 45.0])
    assert poller._ready == driver.first_attempt
    responding = poller._responding
    assert responding is not None and responding()
    driver.available = False
    assert not responding()


def test_a_unit_with_an_empty_map_serves_its_status_block() -> None:
    unit = MemoryUnit(plan=Plan())
    unit.now = 10.0
    assert unit.read_registers(Table.INPUT, 1000, 1) == [1]


async def test_a_command_due_at_the_write_deadline_is_not_sent() -> None:
    """The write was answered 0x0B at its deadline: nothing more of it goes out from then on."""
    unit = MemoryUnit()
    _fresh(unit)
    start = unit.now = asyncio.get_running_loop().time()
    command = unit._command

    async def first_takes_the_whole_timeout(target: str, value: int) -> None:
        await command(target, value)
        unit.now = start + unit.write_timeout

    unit._command = first_takes_the_whole_timeout  # type: ignore[method-assign]
    error = await _write_raised(unit.write_registers(0, [1, 2]))
    assert (error.code, unit.applied) == (TARGET_FAILED, [("w0", 1)])


async def test_the_write_queue_bound_is_per_client() -> None:
    """write_queue_per_client: a client with that many writes waiting is answered 0x06 (busy), another
    client is not."""
    unit = MemoryUnit(write_queue_per_client=1, write_timeout=2.0)
    _fresh(unit)
    unit.gate = asyncio.Event()

    async def write_as(client: Client, address: int) -> ModbusExceptionReply | None:
        current_client.set(client)
        try:
            await unit.write_registers(address, [1])
        except ModbusExceptionReply as error:
            return error
        return None

    a, b = Client("10.0.0.1:1"), Client("10.0.0.2:1")
    first = asyncio.create_task(write_as(a, 0))
    await asyncio.sleep(0.01)  # on the line (held at the gate)
    queued = asyncio.create_task(write_as(a, 1))
    await asyncio.sleep(0)
    busy = asyncio.create_task(write_as(a, 2))
    other = asyncio.create_task(write_as(b, 3))
    await asyncio.sleep(0.2)
    unit.gate.set()
    results = await asyncio.gather(first, queued, busy, other)
    assert [None if r is None else r.code for r in results] == [None, None, 0x06, None]


class RefusingUnit(MemoryUnit):
    """Block 0 reads (zeros); the controller refuses to give block 1, as a PLC in program mode may."""

    async def read_block(self, block: Block) -> bytes:
        if block is self.plan.blocks[1]:
            raise ControllerRefused("N7 is protected")
        return bytes(block.size)


async def test_data_the_controller_refuses_to_give_is_answered_0x04_with_its_reason() -> None:
    """The module doc: controller refused -> 0x04, not 0x0B (the link is up, the data will not come)."""
    unit = RefusingUnit(fast_interval=0.05, slow_interval=0.1)
    poller = asyncio.create_task(unit.run())
    try:
        for _ in range(200):
            if unit.poller is not None and 1 in unit.poller.refused:
                break
            await asyncio.sleep(0.01)
        error = _raised(unit.read_register_bytes, Table.HOLDING, 8, 1)
        assert (error.code, str(error)) == (DEVICE_FAILURE, "mem: N7 is protected")
        assert unit.read_registers(Table.HOLDING, 0, 1) == [0]  # block 0 serves
    finally:
        poller.cancel()
        await asyncio.gather(poller, return_exceptions=True)


def test_a_unit_built_without_options_has_the_documented_defaults() -> None:
    """docs/reference/config.md: stale_after 5, fast_interval 0, slow_interval 10, demand_hold 60,
    background_interval 60, read_wait 0.5, write_burst 1, poll_burst 2, write_queue_per_client 8,
    write_queue_per_link 32, write_timeout 0.9; not read_only, every address writable."""
    unit = MemoryUnit()
    schedule, poller = unit.schedule, unit.poller
    assert schedule is not None and poller is not None
    assert (unit.stale_after, schedule.stale_after, schedule.demand_hold) == (5.0, 5.0, 60.0)
    assert schedule.period == [0.0, 10.0] and schedule.background == [60.0, 60.0]
    assert (poller.fast_interval, poller.slow_interval, unit.read_wait) == (0.0, 10.0, 0.5)
    assert (unit.driver.write_burst, unit.driver.poll_burst) == (1, 2)
    assert (unit.writes.per_client, unit.writes.per_link, unit.write_timeout) == (8, 32, 0.9)
    assert (unit.read_only, unit.writable) == (False, ())
