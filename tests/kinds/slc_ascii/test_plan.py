"""The SLC 100/150 default map (``gateway.kinds.slc_ascii.plan``) as a Modbus client reads it.

Expected values from README ("SLC 100 / 150 ...: fixed map") and the plan's module doc: register n
of the first 64 holding registers is the controller's word at byte address 2n, most significant
byte first; 0-31 the accumulators of 901-932, 32-63 their presets, "protect bit masked": bit 15 of
a preset is its protect bit, never data, so a preset word 8000H | 1234 reads 1234.
"""

from __future__ import annotations

import asyncio

from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.plan import byte_read
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.modbus.mapping import Table


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
