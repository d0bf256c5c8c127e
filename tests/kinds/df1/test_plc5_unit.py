"""The PLC-5 unit: word range read / write and read-modify-write, against the simulated PLC-5.

Both variants of the simulator (``typed_logical`` refuse | accept, ``gateway.kinds.df1.sim.plc5``): the unit
never sends a typed logical command, so it works the same with both, and the simulator's
``applied_writes`` prove which command changed memory.  The driver is a real ``Df1Driver`` over an
in-process ``SimStream``.  Expected values come from the simulator's memory (``sim.word``), never
from the unit's own decoding.  Formats: 1770-KF2 p. 5-57, 1785-KE p. 5-5 / 5-6, 1770-6.5.16 p. 7-20.
"""

from __future__ import annotations

import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest

from gateway.errors import InvalidRequest
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.plc5_unit import Plc5BitWrite, Plc5Read, Plc5Unit, Plc5WordWrite, plan_plc5
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.slc500 import Slc500Options
from gateway.modbus.mapping import Table
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
async def plc5_unit(sim: Plc5Simulator) -> AsyncIterator[Plc5Unit]:
    async def opener(url: str, settings: Any, **_: Any) -> SimStream:
        return SimStream(sim)

    driver = Df1Driver("sim://plc5", checksum=Checksum.BCC, timeout=0.3, retries=2, opener=opener)
    await driver.start()
    try:
        yield Plc5Unit(driver=driver, items=MAP, unit_id=1, name="plc5")
    finally:
        await driver.close()


async def refresh(unit: Plc5Unit) -> None:
    for index, block in enumerate(unit.plan.blocks):
        unit.cache.store(index, await unit.read_block(block), unit._loop_time())


async def write_registers(unit: Plc5Unit, address: int, values: list[int]) -> None:
    for step in unit._register_steps(unit.check_register_write(address, values)):
        await step.run()


async def write_coils(unit: Plc5Unit, address: int, values: list[bool]) -> int:
    points = unit.plan.coils
    steps = unit._bit_steps([(address + i, points[address + i], v) for i, v in enumerate(values)])
    for step in steps:
        await step.run()
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
