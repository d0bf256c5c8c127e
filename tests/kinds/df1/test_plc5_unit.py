"""The PLC-5 unit: word range read / write and read-modify-write, against the simulated PLC-5.

Both variants of the simulator (``typed_logical`` refuse | accept, ``gateway.kinds.df1.sim.plc5``): the unit
never sends a typed logical command, so it works the same with both, and the simulator's
``applied_writes`` prove which command changed memory.  The driver is a real ``Df1Driver`` over an
in-process ``SimStream``.  Expected values come from the simulator's memory (``sim.word``), never
from the unit's own decoding.  Formats: 1770-KF2 p. 5-57, 1785-KE p. 5-5 / 5-6, 1770-6.5.16 p. 7-20.
"""

from __future__ import annotations

import logging
import re
import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest

from gateway.errors import GatewayError, InvalidRequest, ModbusExceptionReply
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.plc5_unit import (
    Plc5BitWrite,
    Plc5Read,
    Plc5Unit,
    Plc5WordWrite,
    plan_plc5,
    point_labels_plc5,
)
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.slc500 import Slc500Options
from gateway.modbus.mapping import Half, Scan, Table
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.full_duplex.transaction import read_back_for
from gateway.protocols.df1.pccc import LogicalBinaryAddress, ReadModifyWriteRequest, WordRangeRead, WordRangeWrite
from gateway.protocols.df1.plc5_address import parse_plc5_address
from gateway.sim.serve import SimStream

VARIANTS = ("refuse", "accept")

MAP = [
    MapItem("holding", 0, "N7:0", 4),
    MapItem("holding", 10, "F8:2", 1, "float32"),
    MapItem("input", 0, "T4:1.ACC", 2),
    MapItem("coil", 0, "B3/5", 3),
    MapItem("discrete", 0, "T4:1/DN", 1),
]


def test_plan_uses_plc5_addresses_and_word_positions() -> None:
    plan = plan_plc5(MAP)
    reads = sorted((str(b.request.address), b.request.words) for b in plan.blocks if isinstance(b.request, Plc5Read))
    # B3 word 0; F8:2 two words; N7:0-3; T4:1 .. T4:2.ACC (T4:1 ACC is word 5, T4:2 ACC word 8 of the file)
    assert reads == [("B3:0", 1), ("F8:2", 2), ("N7:0", 4), ("T4:1.CTL", 6)]
    assert plan.holding[2].write == Plc5WordWrite(parse_plc5_address("N7:2"))
    assert plan.holding[10].write == Plc5WordWrite(parse_plc5_address("F8:2"))
    assert plan.coils[2].write == Plc5BitWrite(parse_plc5_address("B3:0"), 7)
    assert plan.input[1].write is None


def test_plan_refuses_what_the_plc5_map_cannot_mean() -> None:
    with pytest.raises(InvalidRequest, match="float32"):
        plan_plc5([MapItem("holding", 0, "F8:0", 1)])
    with pytest.raises(InvalidRequest, match="not a bit"):
        plan_plc5([MapItem("holding", 0, "B3/5", 1)])
    with pytest.raises(InvalidRequest, match="octal"):
        plan_plc5([MapItem("input", 0, "I:018", 1)])


def test_read_back_of_word_range_write_and_rmw() -> None:
    """A write whose reply was lost is settled by reading the same words back (never resent)."""
    n7 = LogicalBinaryAddress.of(0, 7, 0)
    back = read_back_for(WordRangeWrite(n7, b"\x01\x00\x02\x00"))
    assert back is not None and back.request == WordRangeRead(n7, 4)
    assert back.holds(b"\x01\x00\x02\x00") and not back.holds(b"\x01\x00\x02\x01")
    rmw = read_back_for(ReadModifyWriteRequest(((n7, 0xFFFF & ~0x0030 | 0x0010, 0x0010),)))  # /4 on, /5 off
    assert rmw is not None and rmw.request == WordRangeRead(n7, 2)
    assert rmw.holds((0x0010 | 0x8001).to_bytes(2, "little"))  # other bits are the ladder's: not compared
    assert not rmw.holds((0x0030).to_bytes(2, "little")) and not rmw.holds(b"\x00\x00")


def make_sim(variant: str, **options: Any) -> Plc5Simulator:
    return Plc5Simulator(Slc500Options(checksum=Checksum.BCC, **options), ladder=False,
                         variants={"typed_logical": variant})


@asynccontextmanager
async def plc5_unit(sim: Plc5Simulator, items: list[MapItem] = MAP, **options: Any) -> AsyncIterator[Plc5Unit]:
    async def opener(url: str, settings: Any, **_: Any) -> SimStream:
        return SimStream(sim)

    driver = Df1Driver("sim://plc5", checksum=Checksum.BCC, timeout=0.3, retries=2, opener=opener)
    await driver.start()
    try:
        yield Plc5Unit(driver=driver, items=items, unit_id=1, name="plc5", **options)
    finally:
        await driver.close()


async def refresh(unit: Plc5Unit) -> None:
    for index, block in enumerate(unit.plan.blocks):
        unit.cache.store(index, await unit.read_block(block), unit._loop_time())


async def write_registers(unit: Plc5Unit, address: int, values: list[int]) -> None:
    async with unit.driver.write_session() as line:
        for step in unit._register_steps(unit.check_register_write(address, values)):
            await step.run(line)


async def write_coils(unit: Plc5Unit, address: int, values: list[bool]) -> int:
    points = unit.plan.coils
    steps = unit._bit_steps([(address + i, points[address + i], v) for i, v in enumerate(values)])
    async with unit.driver.write_session() as line:
        for step in steps:
            await step.run(line)
    return len(steps)


@pytest.mark.parametrize("variant", VARIANTS)
async def test_reads_are_word_range_reads(variant: str) -> None:
    sim = make_sim(variant)
    sim.set_word("N7", 2, 0xBEEF)
    sim.set_word("T4", 1, 1234, sub=2)
    sim.set_word("T4", 1, 1 << 13, sub=0)  # DN
    async with plc5_unit(sim) as unit:
        await refresh(unit)
        assert unit.read_registers(Table.HOLDING, 0, 4) == [sim.word("N7", k) for k in range(4)]
        assert unit.read_registers(Table.HOLDING, 2, 1) == [0xBEEF]
        assert unit.read_registers(Table.INPUT, 0, 2) == [1234, sim.word("T4", 2, sub=2)]
        assert unit.read_bits(Table.DISCRETE, 0, 1) == [True]
        high, low = unit.read_registers(Table.HOLDING, 10, 2)
        assert struct.unpack(">f", struct.pack(">HH", high, low))[0] == pytest.approx(sim.float_value("F8", 2))
    assert set(sim.counters.commands) == {"word_range_read"}  # 4 blocks, nothing typed logical


@pytest.mark.parametrize("variant", VARIANTS)
async def test_writes_are_word_range_write_and_rmw(variant: str) -> None:
    sim = make_sim(variant)
    sim.set_word("B3", 0, 0x8001)
    async with plc5_unit(sim) as unit:
        await write_registers(unit, 1, [11, 22, 33])  # N7:1-3 in one word range write
        assert [sim.word("N7", k) for k in (1, 2, 3)] == [11, 22, 33]
        raw = struct.unpack(">I", struct.pack(">f", 2.5))[0]
        await write_registers(unit, 10, [raw >> 16, raw & 0xFFFF])
        assert sim.float_value("F8", 2) == 2.5
        assert await write_coils(unit, 0, [True, False, True]) == 1  # B3/5, /6, /7: one RMW
        assert sim.word("B3", 0) == 0x8001 | 1 << 5 | 1 << 7
        await write_coils(unit, 0, [False])
        assert sim.word("B3", 0) == 0x8001 | 1 << 7  # the ladder's bits 0 and 15 untouched
    kinds = [kind for kind, _where, _data in sim.applied_writes]
    assert kinds == ["word_range_write", "word_range_write", "read_modify_write", "read_modify_write"]
    assert sim.applied_writes[0][1] == "N7:1" and sim.applied_writes[0][2] == bytes.fromhex("0B 00 16 00 21 00")


@pytest.mark.parametrize("variant", VARIANTS)
async def test_lost_write_reply_is_settled_by_read_back_never_resent(variant: str) -> None:
    """Every write executed, its reply never sent (``drop``): the read-back proves it, sent once.
    (The RMW: ``test_full_duplex_driver_settles_a_read_modify_write_as_a_write``.)"""
    sim = make_sim(variant, drop=1, faults_on="writes", link_ack_timeout=5.0)
    async with plc5_unit(sim) as unit:
        await write_registers(unit, 0, [7, 8])
        assert isinstance(unit.driver, Df1Driver)
        counters = unit.driver.transaction_counters
        assert counters.read_backs == 1 and counters.verified == 1 and counters.unknown == 0
    assert sim.word("N7", 0) == 7 and sim.word("N7", 1) == 8
    assert [kind for kind, _w, _d in sim.applied_writes] == ["word_range_write"]


def test_one_definition_of_a_write() -> None:
    """Drivers, cores and the simulators' fault injection share one list of the commands that
    change a controller; a PLC-5 read-modify-write (the coil write) is one of them."""
    from gateway.kinds.df1.sim.slc500_line import is_write_packet
    from gateway.protocols.df1.pccc import encode_command, is_write

    n7 = LogicalBinaryAddress.of(0, 7, 0)
    rmw = ReadModifyWriteRequest(((n7, 0xFFEF, 0x0010),))
    assert is_write(rmw) and is_write(WordRangeWrite(n7, b"\x01\x00"))
    assert not is_write(WordRangeRead(n7, 2))
    assert is_write_packet(encode_command(rmw, dst=1, src=0, tns=7))
    assert not is_write_packet(encode_command(WordRangeRead(n7, 2), dst=1, src=0, tns=7))


async def test_full_duplex_driver_settles_a_read_modify_write_as_a_write() -> None:
    """``Df1Driver.execute`` without ``write=``: a RMW whose reply is lost is never sent again with a
    new TNS; a read-back of the word settles it."""
    sim = make_sim("refuse", drop=1, faults_on="writes")
    n7 = LogicalBinaryAddress.of(0, 7, 0)

    async def opener(url: str, settings: Any, **_: Any) -> SimStream:
        return SimStream(sim)

    driver = Df1Driver("sim://plc5", checksum=Checksum.BCC, timeout=0.3, retries=2, opener=opener)
    await driver.start()
    try:
        await driver.execute(ReadModifyWriteRequest(((n7, 0xFFEF, 0x0010),)), "coil")
        assert driver.transaction_counters.read_backs >= 1 and driver.transaction_counters.verified == 1
        assert sim.word("N7", 0) & 0x0010
    finally:
        await driver.close()


def test_plc5_packet_limits_come_from_one_table() -> None:
    """Word range commands (what the gateway polls a PLC-5 with) and typed logical commands to a
    PLC-5 have different limits in the manuals; one table holds both and everything reads it."""
    from gateway.kinds.df1 import plc5_unit
    from gateway.kinds.df1.sim import plc5 as sim_plc5
    from gateway.protocols.df1.pccc import ProcessorFamily
    from gateway.protocols.df1.pccc.limits import PLC5_TYPED_LOGICAL, PLC5_WORD_RANGE

    assert (PLC5_WORD_RANGE.max_read_bytes, PLC5_WORD_RANGE.max_write_bytes) == (244, 239)
    assert ProcessorFamily.PLC5.limits is PLC5_TYPED_LOGICAL
    assert (PLC5_TYPED_LOGICAL.max_read_bytes, PLC5_TYPED_LOGICAL.max_write_bytes) == (230, 222)
    assert plc5_unit.PLC5_MAX_READ_BYTES == sim_plc5.MAX_WORD_RANGE_READ == PLC5_WORD_RANGE.max_read_bytes
    assert plc5_unit.PLC5_MAX_WRITE_BYTES == sim_plc5.MAX_WORD_RANGE_WRITE == PLC5_WORD_RANGE.max_write_bytes
    n7 = LogicalBinaryAddress.of(0, 7, 0)
    WordRangeRead(n7, PLC5_WORD_RANGE.max_read_bytes)
    with pytest.raises(InvalidRequest):
        WordRangeRead(n7, PLC5_WORD_RANGE.max_read_bytes + 2)
    room = PLC5_WORD_RANGE.max_write_bytes - len(n7.encode())
    WordRangeWrite(n7, bytes(room - room % 2))
    with pytest.raises(InvalidRequest):
        WordRangeWrite(n7, bytes(room - room % 2 + 2))


# --- the map: what each Modbus point is in the PLC-5 (docs/guide/df1-full-duplex.md, "PLC-5 addresses") ----------

LABEL_MAP = [
    MapItem("holding", 0, "N7:0", 2, "uint16"),
    MapItem("holding", 10, "F8:2", 2, "float32"),  # high-first (the default): F8:2 = 10-11, F8:3 = 12-13
    MapItem("holding", 20, "F8:0", 1, "float32", "low-first"),
    MapItem("coil", 0, "B3/5", 20, "bool"),  # bits of a word file step through consecutive bits: B3/5 .. B3/24
    MapItem("coil", 30, "B3/0", 2, "bool"),
    MapItem("discrete", 0, "T4:0/DN", 3, "bool"),  # structured members step through elements
    MapItem("input", 0, "T4:1.ACC", 2),
    MapItem("input", 10, "I:010", 2),  # octal: rack/group words 8 and 9 of file 1
]


def test_point_labels_name_each_point_in_plc5_notation() -> None:
    """Every point's label is a PLC-5 address naming the word (or bit) the point is; both registers of a
    float carry the float's address; the type is the entry's, the description names the entry."""
    labels = point_labels_plc5(LABEL_MAP)
    expected = {
        (Table.HOLDING, 0): "N7:0", (Table.HOLDING, 1): "N7:1",
        (Table.HOLDING, 10): "F8:2", (Table.HOLDING, 11): "F8:2", (Table.HOLDING, 12): "F8:3",
        (Table.HOLDING, 13): "F8:3", (Table.HOLDING, 20): "F8:0", (Table.HOLDING, 21): "F8:0",
        (Table.COIL, 0): "B3/5", (Table.COIL, 10): "B3/15", (Table.COIL, 11): "B3/16", (Table.COIL, 16): "B3/21",
        (Table.COIL, 19): "B3/24", (Table.COIL, 30): "B3/0", (Table.COIL, 31): "B3/1",
        (Table.DISCRETE, 0): "T4:0/DN", (Table.DISCRETE, 1): "T4:1/DN", (Table.DISCRETE, 2): "T4:2/DN",
        (Table.INPUT, 0): "T4:1.ACC", (Table.INPUT, 1): "T4:2.ACC",
        (Table.INPUT, 10): "I:010", (Table.INPUT, 11): "I:011",
    }
    for point, address in expected.items():
        assert parse_plc5_address(labels[point].address) == parse_plc5_address(address), point
    assert str(labels[Table.HOLDING, 1].address) == "N7:1" and labels[Table.INPUT, 0].address == "T4:1.ACC"
    assert len(labels) == 2 + 4 + 2 + 20 + 2 + 3 + 2 + 2
    for item in LABEL_MAP:
        label = labels[Table(item.table), item.start]
        assert label.type == item.type
        assert item.address in label.description and str(item.count) in label.description


def test_plan_word_order_and_consecutive_values() -> None:
    """float32 high-first: the first register is the high word; low-first: the low word (config
    reference, ``word_order``); a count steps through consecutive floats / bits / elements."""
    plan = plan_plc5(LABEL_MAP)
    for first, f8 in ((10, "F8:2"), (12, "F8:3"), (20, "F8:0")):
        assert plan.holding[first].write == plan.holding[first + 1].write == Plc5WordWrite(parse_plc5_address(f8))
    assert (plan.holding[10].codec.half, plan.holding[11].codec.half) == (Half.HIGH, Half.LOW)
    assert (plan.holding[12].codec.half, plan.holding[13].codec.half) == (Half.HIGH, Half.LOW)
    assert (plan.holding[20].codec.half, plan.holding[21].codec.half) == (Half.LOW, Half.HIGH)
    assert plan.coils[11].write == Plc5BitWrite(parse_plc5_address("B3:1"), 0)
    assert plan.coils[30].write == Plc5BitWrite(parse_plc5_address("B3:0"), 0)
    assert plan.discrete[2].write is None


def test_a_structure_word_address_counts_its_words() -> None:
    """``T4:1`` (no member) names the timer's first word; a count reads on word by word as a word range
    read does (1770-6.5.16 ch. 7): T4:1 x3 is T4:1's control word, preset and accumulator."""
    labels = point_labels_plc5([MapItem("input", 0, "T4:1", 3)])
    words = [parse_plc5_address(labels[Table.INPUT, k].address) for k in range(3)]
    assert words == [parse_plc5_address(a) for a in ("T4:1.CTL", "T4:1.PRE", "T4:1.ACC")]


def test_plan_blocks_hold_at_most_max_read_bytes() -> None:
    """A long run is split into word range reads of at most ``max_read_bytes`` data bytes; each block
    reads whole words (2 bytes each) and is labelled as check-config prints it (``N7:0 (10 words)``)."""
    plan = plan_plc5([MapItem("holding", 0, "N7:0", 20)], max_read_bytes=20)
    blocks = [(str(b.request.address), b.request.words, b.size, b.label) for b in plan.blocks
              if isinstance(b.request, Plc5Read)]
    assert blocks == [("N7:0", 10, 20, "N7:0 (10 words)"), ("N7:10", 10, 20, "N7:10 (10 words)")]
    # register k is word k: bytes 2 * (k - first word of its block), low byte first
    assert [(plan.holding[k].block, plan.holding[k].offset) for k in (0, 9, 10, 15, 19)] == [
        (0, 0), (0, 18), (1, 0), (1, 10), (1, 18)]


def test_a_word_mapped_fast_and_slow_is_read_fast() -> None:
    """A word that a fast entry maps is read in the fast class, also for the slow entry mapping it;
    words only slow entries map are read in the slow class; fast blocks come first (check-config)."""
    plan = plan_plc5([
        MapItem("input", 0, "N7:0", 4, scan="slow"),
        MapItem("holding", 0, "N7:0", 1),
        MapItem("holding", 5, "B3:0", 1, scan="slow"),
    ])
    blocks = [(b.scan, str(b.request.address), b.request.words) for b in plan.blocks
              if isinstance(b.request, Plc5Read)]
    assert blocks == [(Scan.FAST, "N7:0", 1), (Scan.SLOW, "B3:0", 1), (Scan.SLOW, "N7:1", 3)]
    assert plan.input[0].block == plan.holding[0].block == 0
    assert [plan.input[k].block for k in (1, 2, 3)] == [2, 2, 2]


# --- the unit on the simulated PLC-5 ----------------------------------------------------------------------------------


async def test_public_writes_reach_the_plc5_and_the_image() -> None:
    """FC6 / FC16 / FC5 / FC15 through the unit's write API: one word (``34 12``: low byte first, KF2
    p. 5-57), a run of words, a negative float, coils by RMW; the image serves the confirmed values."""
    sim = make_sim("refuse")
    sim.set_word("B3", 0, 1 << 6)  # bit 6 on, bit 0 off
    async with plc5_unit(sim, write_timeout=10.0) as unit:
        await refresh(unit)
        await unit.write_registers(0, [0x1234])
        assert sim.word("N7", 0) == 0x1234 and sim.applied_writes[-1] == ("word_range_write", "N7:0", b"\x34\x12")
        await unit.write_registers(1, [11, 22, 33])
        assert [sim.word("N7", k) for k in (1, 2, 3)] == [11, 22, 33]
        raw = struct.unpack(">I", struct.pack(">f", -2.5))[0]  # 0xC0200000: the high bit set
        await unit.write_registers(10, [raw >> 16, raw & 0xFFFF])
        assert sim.float_value("F8", 2) == -2.5
        await unit.write_bits(0, [True, False, True])  # B3/5 on, /6 off, /7 on: one RMW
        assert sim.word("B3", 0) == 1 << 5 | 1 << 7
        # confirmed writes are in the image at once (no read since)
        assert unit.read_registers(Table.HOLDING, 0, 4) == [0x1234, 11, 22, 33]
        assert unit.read_registers(Table.HOLDING, 10, 2) == [0xC020, 0x0000]
        assert unit.read_bits(Table.COIL, 0, 3) == [True, False, True]
    assert [kind for kind, _w, _d in sim.applied_writes] == ["word_range_write"] * 3 + ["read_modify_write"]


async def test_the_write_bit_primitive_changes_one_bit() -> None:
    """The unit's one-coil write (``Unit._write_bit``): one RMW of the word, only that bit changes."""
    sim = make_sim("refuse")
    sim.set_word("B3", 1, 0x8001)
    async with plc5_unit(sim) as unit, unit.driver.write_session() as line:
        await unit._write_bit(Plc5BitWrite(parse_plc5_address("B3:1"), 4), True, line)
        assert sim.word("B3", 1) == 0x8011
        await unit._write_bit(Plc5BitWrite(parse_plc5_address("B3:1"), 15), False, line)
        assert sim.word("B3", 1) == 0x0011
    assert [kind for kind, _w, _d in sim.applied_writes] == ["read_modify_write"] * 2


async def test_coils_across_a_word_boundary_are_one_rmw_per_word() -> None:
    sim = make_sim("refuse")
    sim.set_word("B3", 0, 0x0001)
    sim.set_word("B3", 1, 0x8000)
    async with plc5_unit(sim, [MapItem("coil", 0, "B3/14", 4, "bool")]) as unit:
        assert await write_coils(unit, 0, [True, True, True, True]) == 2  # B3/14-15, B3/16-17
    assert sim.word("B3", 0) == 0xC001 and sim.word("B3", 1) == 0x8003


async def test_word_range_writes_hold_at_most_max_write_bytes() -> None:
    """``max_write_bytes`` counts the address (N7:0: ``07 00 07 00``, 4 bytes, 1770-6.5.16 p. 13-12) and
    the data: 10 bytes leave 3 words per word range write."""
    sim = make_sim("refuse")
    async with plc5_unit(sim, [MapItem("holding", 0, "N7:0", 7)], max_write_bytes=10) as unit:
        await write_registers(unit, 0, [1, 2, 3, 4, 5, 6, 7])
    assert [(w, d) for _k, w, d in sim.applied_writes] == [
        ("N7:0", bytes.fromhex("0100 0200 0300")), ("N7:3", bytes.fromhex("0400 0500 0600")),
        ("N7:6", bytes.fromhex("0700"))]


async def test_one_word_range_write_covers_only_neighbours_of_one_plain_file() -> None:
    """Words of other files, gaps and timer members are written each with its own command: one word range
    write writes consecutive words only, so nothing between them changes."""
    sim = make_sim("refuse")
    items = [MapItem("holding", 0, "N7:0", 2), MapItem("holding", 2, "N7:5", 1), MapItem("holding", 3, "N10:6", 1),
             MapItem("holding", 4, "T4:1.ACC", 2)]
    before = {("N7", 2): sim.word("N7", 2), ("N7", 6): sim.word("N7", 6), ("T4", 2): sim.word("T4", 2)}
    async with plc5_unit(sim, items) as unit:
        await write_registers(unit, 0, [1, 2, 3, 4, 100, 200])
    assert [sim.word("N7", 0), sim.word("N7", 1), sim.word("N7", 5), sim.word("N10", 6)] == [1, 2, 3, 4]
    assert sim.word("T4", 1, sub=2) == 100 and sim.word("T4", 2, sub=2) == 200
    assert {key: sim.word(*key) for key in before} == before
    assert [w for _k, w, _d in sim.applied_writes] == ["N7:0", "N7:5", "N10:6", "T4:1.ACC", "T4:2.ACC"]


async def test_a_write_refused_part_way_names_what_was_written(caplog: pytest.LogCaptureFixture) -> None:
    """The controller refuses the second command (no file N99): the answer is the exception and a
    WARNING names the registers written (docs/guide/reads-and-writes.md)."""
    sim = make_sim("refuse")
    items = [MapItem("holding", 0, "N7:0", 3), MapItem("holding", 3, "N99:0", 1)]
    async with plc5_unit(sim, items, write_timeout=10.0) as unit:
        with caplog.at_level(logging.WARNING), pytest.raises(ModbusExceptionReply):
            await unit.write_registers(0, [1, 2, 3, 4])
        assert unit.partial_writes == 1
    assert [sim.word("N7", k) for k in range(3)] == [1, 2, 3]
    assert "holding 0-2 written, holding 3 and after not" in caplog.text


async def test_refusals_name_the_block_or_the_bits() -> None:
    """A read or coil write the PLC-5 refuses (no file N99 / B99) says which block or bits it was."""
    sim = make_sim("refuse")
    items = [MapItem("input", 0, "N99:0", 2), MapItem("coil", 0, "B99/5", 2, "bool")]
    async with plc5_unit(sim, items) as unit:
        with pytest.raises(GatewayError, match=re.escape("read N99:0 (2 words)")):
            await unit.read_block(next(b for b in unit.plan.blocks if b.size == 4))
        with pytest.raises(ModbusExceptionReply) as refused:
            await write_coils(unit, 0, [True, False])
    assert refused.value.__cause__ is not None
    assert re.search(r"B99:0/5\W6\b", str(refused.value.__cause__))


async def test_max_read_bytes_sets_the_units_blocks() -> None:
    sim = make_sim("refuse")
    async with plc5_unit(sim, [MapItem("holding", 0, "N7:0", 20)], max_read_bytes=20) as unit:
        assert [b.size for b in unit.plan.blocks] == [20, 20]


async def test_coils_read_each_bit_of_its_word() -> None:
    """B3/0 x16 are bits 0-15 of B3:0 (the word read low byte first, KF2 p. 5-57): only bit 8 and 15 on."""
    sim = make_sim("refuse")
    sim.set_word("B3", 0, 0x8100)
    async with plc5_unit(sim, [MapItem("coil", 0, "B3/0", 16, "bool")]) as unit:
        await refresh(unit)
        assert unit.read_bits(Table.COIL, 0, 16) == [k in (8, 15) for k in range(16)]


async def test_floats_read_in_their_word_order() -> None:
    """F8:2 x2 high-first and F8:0 low-first: 1.1 is 0x3F8CCCCD in IEEE 754 single precision."""
    sim = make_sim("refuse")
    sim.set_float("F8", 0, 1.1)
    sim.set_float("F8", 2, -2.5)  # 0xC0200000
    sim.set_float("F8", 3, 1.1)
    sim.set_float("F8", 4, 7.0)  # 0x40E00000, mapped by nothing
    items = [MapItem("holding", 10, "F8:2", 2, "float32"), MapItem("holding", 20, "F8:0", 1, "float32", "low-first")]
    async with plc5_unit(sim, items) as unit:
        await refresh(unit)
        assert unit.read_registers(Table.HOLDING, 10, 4) == [0xC020, 0x0000, 0x3F8C, 0xCCCD]
        assert unit.read_registers(Table.HOLDING, 20, 2) == [0xCCCD, 0x3F8C]
