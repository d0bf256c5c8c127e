"""The SLC 100/150 default map (``gateway.kinds.slc_ascii.plan``) as a Modbus client reads it.

Expected values from README ("SLC 100 / 150 ...: fixed map") and the plan's module doc: register n
of the first 64 holding registers is the controller's word at byte address 2n, most significant
byte first; 0-31 the accumulators of 901-932, 32-63 their presets, "protect bit masked": bit 15 of
a preset is its protect bit, never data, so a preset word 8000H | 1234 reads 1234.
"""

from __future__ import annotations

import asyncio

import pytest

from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.plan import (
    SlcBitWrite,
    SlcWordWrite,
    byte_read,
    plan_byte_blocks,
    plan_lines,
    slc_ascii_plan,
)
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.modbus import mapping
from gateway.modbus.mapping import Scan, Table

from .units import unit_with


def _word_at(unit: SlcAsciiUnit, byte_address: int, raw: int) -> None:
    """The controller's word at ``byte_address`` is ``raw`` (MSB first), read now."""
    now = asyncio.get_running_loop().time()
    for index, block in enumerate(unit.plan.blocks):
        start, count = byte_read(block)
        if start <= byte_address and byte_address + 2 <= start + count:
            data = bytearray(unit.cache.data[index])
            data[byte_address - start : byte_address - start + 2] = raw.to_bytes(2, "big")
            unit.cache.store(index, bytes(data), now)
            return
    raise AssertionError(f"no block reads the word at {byte_address:#x}")


async def test_presets_and_accumulators_are_served_with_the_protect_bit_masked() -> None:
    unit = SlcAsciiUnit(driver=SlcAsciiDriver("sim://slc150?ladder=0"), unit_id=1, name="slc", stale_after=60.0)
    for block_index, block in enumerate(unit.plan.blocks):
        unit.cache.store(block_index, bytes(block.size), asyncio.get_running_loop().time())
    _word_at(unit, 0x40, 0x8000 | 1234)  # 901.PRE, protected
    _word_at(unit, 0x42, 4321)  # 902.PRE, not protected
    _word_at(unit, 0x7E, 0x8000 | 9999)  # 932.PRE, protected
    _word_at(unit, 0x00, 17)  # 901.ACC
    _word_at(unit, 0x02, 9000)  # 902.ACC
    assert unit.read_registers(Table.HOLDING, 32, 2) == [1234, 4321]
    assert unit.read_registers(Table.HOLDING, 63, 1) == [9999]
    assert unit.read_registers(Table.HOLDING, 0, 2) == [17, 9000]


# --- the byte reads (manual "Reading Data": command 02 reads 1 or 2 bytes; the word tables' last
# bytes 3FH and 7FH are read only as the second byte of a read at 3EH / 7EH; E4H-E7H (immediate
# rung bits) and 113H on (beyond the access code byte 112H) are not in the readable list)

FAST, SLOW = Scan.FAST, Scan.SLOW


def test_contiguous_bytes_are_read_two_at_a_time() -> None:
    # the output state table 96H-9CH: 7 bytes, 4 reads (the fewest at 2 bytes a read)
    assert plan_byte_blocks(range(0x96, 0x9D), FAST) == [(0x96, 2, FAST), (0x98, 2, FAST), (0x9A, 2, FAST),
                                                         (0x9C, 1, FAST)]
    assert plan_byte_blocks(range(0x96, 0x99), SLOW) == [(0x96, 2, SLOW), (0x98, 1, SLOW)]


def test_unsorted_and_repeated_addresses_are_each_read_once() -> None:
    assert plan_byte_blocks([0x9C, 0x97, 0x96, 0x97, 0x9C], FAST) == [(0x96, 2, FAST), (0x9C, 1, FAST)]
    assert plan_byte_blocks([], FAST) == []


def test_separate_bytes_get_separate_reads() -> None:
    assert plan_byte_blocks([0x84, 0x86, 0x88], SLOW) == [(0x84, 1, SLOW), (0x86, 1, SLOW), (0x88, 1, SLOW)]


def test_the_last_byte_of_a_word_table_is_read_with_its_msb() -> None:
    assert plan_byte_blocks([0x3F], FAST) == [(0x3E, 2, FAST)]
    assert plan_byte_blocks([0x7F], SLOW) == [(0x7E, 2, SLOW)]
    # 3FH-40H is no read (3FH is no start address): 3EH-3FH, then 40H-41H
    assert plan_byte_blocks([0x3F, 0x40, 0x41], FAST) == [(0x3E, 2, FAST), (0x40, 2, FAST)]


def test_a_read_never_reaches_past_the_readable_list() -> None:
    # E3H is the last readable byte before E4H (not readable); 112H is the last of the map
    assert plan_byte_blocks([0xE3], FAST) == [(0xE3, 1, FAST)]
    assert plan_byte_blocks([0x112], SLOW) == [(0x112, 1, SLOW)]
    assert plan_byte_blocks([0xE2, 0xE3], FAST) == [(0xE2, 2, FAST)]


def test_max_count_bounds_the_read() -> None:
    assert plan_byte_blocks(range(0x96, 0x99), FAST, max_count=1) == [(0x96, 1, FAST), (0x97, 1, FAST),
                                                                      (0x98, 1, FAST)]


def test_the_default_map_reads_its_rows_in_two_scan_classes() -> None:
    # Fast: what the program changes every scan: accumulators 00H-3FH, outputs/inputs/relays/fine
    # timer bits 96H-BBH, timer/counter/sequencer output and overflow bits DCH-E3H.  Slow: presets
    # 40H-7FH, error bits and force select 84H-95H, step counters BCH-DBH, force state 102H-111H.
    # All at 2 bytes a read: fast 32 + 19 + 4 reads, slow 32 + 9 + 16 + 8.
    assert plan_lines(slc_ascii_plan()) == [
        "fast 55 reads of 1-2 bytes covering 0x0000-0x003F, 0x0096-0x00BB, 0x00DC-0x00E3",
        "slow 65 reads of 1-2 bytes covering 0x0040-0x007F, 0x0084-0x0095, 0x00BC-0x00DB, 0x0102-0x0111",
    ]


def test_plan_lines_joins_adjacent_reads_and_keeps_gaps() -> None:
    plan: mapping.Plan[SlcWordWrite, SlcBitWrite] = mapping.Plan()
    for start, count, scan in ((0x9C, 1, SLOW), (0x96, 2, SLOW), (0x98, 2, SLOW), (0x00, 2, FAST)):
        plan.blocks.append(mapping.Block((start, count), count, scan, "test"))
    assert plan_lines(plan) == [
        "slow 3 reads of 1-2 bytes covering 0x0096-0x0099, 0x009C-0x009C",
        "fast 1 reads of 1-2 bytes covering 0x0000-0x0001",
    ]


def test_a_block_that_is_no_byte_read_is_refused() -> None:
    block = mapping.Block((7, 0, 2), 2, FAST, "N7:0")
    with pytest.raises(TypeError, match="N7:0: not an SLC 100/150 byte read"):
        byte_read(block)


# --- what the Modbus client reads (README / docs/reference/modbus-map.md, fixed map; the user
# address table of the manual for the bits)


async def test_input_registers_serve_step_counters_error_bits_and_force_tables() -> None:
    unit = unit_with({0xBC: 7, 0xDB: 200, 0x84: 0x12, 0x85: 0x34, 0x86: 0xAB, 0x87: 0xCD, 0x94: 1, 0x95: 2,
                      0x102: 0x56, 0x103: 0x78, 0x110: 3, 0x111: 4})
    assert unit.read_registers(Table.INPUT, 0, 1) == [7]  # 901.STEP at BCH
    assert unit.read_registers(Table.INPUT, 31, 1) == [200]  # 932.STEP at DBH
    assert unit.read_registers(Table.INPUT, 66, 9) == [0x1234, 0xABCD, 0, 0, 0, 0, 0, 0, 0x0102]
    assert unit.read_registers(Table.INPUT, 129, 8) == [0x5678, 0, 0, 0, 0, 0, 0, 0x0304]


async def test_bits_are_served_at_their_user_addresses() -> None:
    unit = unit_with({0x96: 0x80, 0x9D: 0x01, 0xA4: 0x04, 0xA6: 0x01, 0xB4: 0x80, 0xBA: 0x80})
    assert unit.read_bits(Table.DISCRETE, 18, 1) == [True]  # output 18: 96H bit 7
    assert unit.read_bits(Table.DISCRETE, 11, 2) == [False, False]
    assert unit.read_bits(Table.DISCRETE, 1, 2) == [True, False]  # input 1: 9DH bit 0
    assert unit.read_bits(Table.DISCRETE, 9, 2) == [True, False]  # input 9: A4H bit 2
    assert unit.read_bits(Table.COIL, 701, 1) == [True]  # relay 701: A6H bit 0
    assert unit.read_bits(Table.COIL, 820, 1) == [True]  # relay 820: B4H bit 7
    assert unit.read_bits(Table.COIL, 868, 1) == [True]  # relay 868: BAH bit 7
    assert unit.read_bits(Table.DISCRETE, 868, 1) == [True]


def test_relays_701_to_820_are_writable_coils_821_to_868_are_not() -> None:
    plan = slc_ascii_plan()
    assert sorted(plan.coils) == list(range(701, 869))
    assert plan.coils[701].write == SlcBitWrite(0xA6, 0)
    assert plan.coils[820].write == SlcBitWrite(0xB4, 7)
    assert plan.coils[821].write is None
    assert plan.coils[868].write is None
    assert plan.holding[0].write == SlcWordWrite(0x00)  # 901.ACC
    assert plan.holding[63].write == SlcWordWrite(0x7E)  # 932.PRE
    assert plan.holding[0].max_value == plan.holding[63].max_value == 9999
