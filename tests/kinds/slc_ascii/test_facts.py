"""The SLC 100/150 memory map is stated once (protocols/slc_ascii/memory_map.py); the plan, the
commands, the driver's fault read and the simulator derive their addresses from it.

Expected values from shared/docs/slc100-150-ascii-protocol.md ("The Memory Map", "Mode
Selection", "Reading Data").
"""

from __future__ import annotations

import pytest

from gateway.kinds.slc_ascii import sim
from gateway.kinds.slc_ascii.plan import slc_ascii_plan
from gateway.modbus.mapping import Scan
from gateway.protocols.slc_ascii import commands
from gateway.protocols.slc_ascii import memory_map as mm


def test_the_named_rows_are_the_manuals() -> None:
    assert (mm.ACCUMULATORS.start, mm.ACCUMULATORS.end) == (0x00, 0x3F)
    assert (mm.PRESETS.start, mm.PRESETS.end) == (0x40, 0x7F)
    assert (mm.ERROR_BITS_REGION.start, mm.ERROR_BITS_REGION.end) == (0x84, 0x85)
    assert (mm.STEP_COUNTERS.start, mm.STEP_COUNTERS.end) == (0xBC, 0xDB)
    assert (mm.FORCE_STATE.start, mm.FORCE_STATE.end) == (0x102, 0x111)
    assert mm.MODE_ADDRESS == 0x0101 and mm.ERROR_BITS_REGION.start == 0x84
    assert mm.MAP_SIZE == 0x113  # 0000H .. 0112H, the access code byte
    assert (mm.accumulator_address(932), mm.preset_address(901), mm.step_counter_address(932)) == (0x3E, 0x40, 0xDB)


def test_the_others_take_the_maps_addresses() -> None:
    assert commands.MODE_ADDRESS is mm.MODE_ADDRESS
    assert commands.set_mode(commands.Mode.RUN).params == bytes((0x01, 0x01, commands.Mode.RUN))
    simulator = sim.SlcAsciiSimulator()
    assert len(simulator.memory) == 0x113


def test_the_plan_reads_the_maps_rows() -> None:
    plan = slc_ascii_plan()
    read: dict[Scan, set[int]] = {Scan.FAST: set(), Scan.SLOW: set()}
    for block in plan.blocks:
        start, count = block.request  # (address, count)
        read[block.scan].update(range(start, start + count))
    assert read[Scan.FAST] == {*range(0x00, 0x40), *range(0x96, 0xBC), *range(0xDC, 0xE4)}
    assert read[Scan.SLOW] == {*range(0x40, 0x80), *range(0x84, 0x96), *range(0xBC, 0xDC), *range(0x102, 0x112)}
    assert plan.input[0x84 // 2].offset == 0 and plan.blocks[plan.input[0x84 // 2].block].request == (0x84, 2)


def test_is_write_is_the_reply_and_an_upload_is_not_repeated() -> None:
    """"Specific Commands": a write (word, byte, mode, sequencer preset, reset accumulator,
    download block) is answered ;R, a read, an FRN read and an upload with data.  An upload moves
    the block pointer on ("Upload and Download"), so it is no more repeatable than a write."""
    assert commands.write_word(0x40, 1).is_write and commands.set_mode(commands.Mode.RUN).is_write
    assert not commands.read_bytes(0x84, 2).is_write and not commands.read_frn().is_write
    assert commands.read_bytes(0x84, 2).repeatable and not commands.write_word(0x40, 1).repeatable
    upload = commands.upload_block()
    assert upload.reply is commands.ReplyKind.DATA and not upload.is_write and not upload.repeatable


def test_the_simulator_takes_the_maps_rows_and_write_rules() -> None:
    """Its program's cells and what its writes accept are the map's: presets 100 + 10 n at 40H.. with
    932's preset and accumulator protected (bit 7 of the MSB), step counters at BCH.., the byte write
    00A6H-00B4H only, the word write at even 0000H-007EH only."""
    simulator = sim.SlcAsciiSimulator()
    assert simulator.word(0x40) == 100 and simulator.word(0x7E) == 0x8000 | 500 and simulator.word(0x3E) == 0x8000 | 7
    assert simulator.memory[0xBC + 6] == 1
    assert simulator._write_byte(0xA6, 1) is None  # the write rules themselves, without a line
    assert simulator._write_word(0x40, 9999) is None
    for address in (0xB5, 0x96):
        with pytest.raises(sim._AnswerE):  # answered ;E
            simulator._write_byte(address, 1)
    for address in (0x41, 0x80, 0x3E):  # odd, beyond the presets, a protected accumulator
        with pytest.raises(sim._AnswerE):
            simulator._write_word(address, 1)
    with pytest.raises(sim._AnswerE):
        simulator._write_word(0x42, 10000)
