"""Reads served from the register images against the decoder they replaced, and staleness after writes.

The reference below is a copy of the read path as it was before the images (commit 7bd7acd,
``Unit.read_registers`` / ``read_bits`` decoding the raw block bytes on every read, served
through the server's async backend path).  The differential test builds random plans (random
blocks, codecs and bit positions), stores, patches and reads at random times, and compares
the whole reply frames of both paths byte for byte.
"""

from __future__ import annotations

import asyncio
import struct
from bisect import bisect_right
from collections.abc import Coroutine, Sequence
from dataclasses import dataclass
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.app import GatewayBackend
from gateway.errors import ControllerRefused, ModbusExceptionReply
from gateway.kinds.df1 import plan as df1_plan
from gateway.kinds.slc_ascii import plan as slc_plan
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.plan import slc_ascii_plan
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.modbus.mapping import (
    STATUS_BASE,
    BitPoint,
    Block,
    Plan,
    RegisterPoint,
    Scan,
    Table,
)
from gateway.modbus.mapping import Codec as CodecType
from gateway.modbus.server import ModbusTcpServer
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
        return now - self.unit.cache.newest > self.unit._silent_after

    def _stale(self, block: int | None = None) -> ModbusExceptionReply:
        refused = self.unit.poller.refused.get(block) if block is not None else None
        if refused is not None:
            return ModbusExceptionReply(DEVICE_FAILURE, str(refused[0]))
        return ModbusExceptionReply(TARGET_FAILED, "stale")

    def read_registers(self, table: Table, address: int, count: int) -> list[int]:
        now = self.now
        assert not (table is Table.INPUT and address >= STATUS_BASE)
        points = self.unit.plan.registers(table)
        stamps, data, max_age = self.unit.cache.stamps, self.unit.cache.data, self.unit._max_age
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
        stamps, data, max_age = self.unit.cache.stamps, self.unit.cache.data, self.unit._max_age
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

    async def _write_register(self, target: object, value: int) -> None:
        raise AssertionError("not written")

    async def _write_bit(self, target: object, value: bool) -> None:
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
    max_age = unit._max_age[0]
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
