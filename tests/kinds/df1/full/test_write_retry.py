"""A write whose outcome was unknown but which a read-back proved not applied is sent again (issue 43, item 6b).

The N7:20 case of the issue: a DCMD on a DF1 full-duplex line with faults was not applied, the read-back gave the
previous value, and the gateway answered "may or may not have been applied".  On full duplex the read-back runs
after the write (the controller runs commands in order), so the value from before the write proves the write was
not applied: the one write path (``gateway.unit_writes``, ``UnitWrites._run_steps`` -> ``run_step``) sends it
again within ``write_timeout``, and the controller applies it exactly once.  Where nothing proves it (the gateway
holds no value from before), the outcome stays unknown: 0x0B, counted and logged, never sent again.

No mocks: a ``Df1Unit`` on the full-duplex driver talking to the SLC 500 simulator through a ``SimStream``; the
simulator loses the first write frame whole (``lose_in``, only that one).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest

from gateway.errors import ModbusExceptionReply
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.kinds.df1.unit import Df1Unit
from gateway.modbus.mapping import Table
from gateway.protocols.df1.framing import Checksum
from gateway.sim.serve import SimStream

ITEMS = [MapItem("holding", 30, "N7:20", 1), MapItem("coil", 0, "B3:1/0", 4)]


def simulator(lost_writes: int) -> Slc500Simulator:
    """An SLC 5/04 that loses the first ``lost_writes`` write frames whole (the controller never sees them)."""
    sim = Slc500Simulator.from_options({"seed": "43", "lose_in": "1", "faults_on": "writes"}, ladder=False)
    strikes = sim._strikes

    def only_the_first(frame: bytes) -> bool:
        return sim.counters.lost_in < lost_writes and strikes(frame)

    sim._strikes = only_the_first  # type: ignore[method-assign]
    return sim


@asynccontextmanager
async def unit_on(sim: Slc500Simulator, **options: Any) -> AsyncIterator[Df1Unit]:
    async def opener(url: str, settings: Any, **_: Any) -> SimStream:
        return SimStream(sim)

    driver = Df1Driver("sim://slc504", checksum=Checksum(sim.options.checksum), timeout=0.05, ack_timeout=0.05,
                       retries=2, opener=opener)
    await driver.start()
    try:
        yield Df1Unit(driver=driver, items=ITEMS, max_read_bytes=236, unit_id=1, name="slc", **options)
    finally:
        await driver.close()


async def read_all(unit: Df1Unit) -> None:
    """Every block read once from the controller: the image holds the values from before the writes."""
    for index, block in enumerate(unit.plan.blocks):
        unit.store(index, await unit.read_block(block), unit._loop_time())


async def test_a_write_proven_not_applied_is_sent_again_and_applied_exactly_once() -> None:
    sim = simulator(lost_writes=1)
    sim.set_word("N7", 20, 7)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unit.write_registers(30, [1234])  # answered: applied
        assert sim.word("N7", 20) == 1234
        assert sim.applied_writes == [("write", "N7:20", (1234).to_bytes(2, "little"))]  # exactly once
        assert sim.counters.lost_in == 1  # the first frame was lost: the read-back showed 7
        assert (unit.write_tally.retried, unit.write_tally.unknown) == (1, 0)
        assert unit.read_registers(Table.HOLDING, 30, 1) == [1234]


async def test_a_coil_write_proven_not_applied_is_sent_again_and_applied_exactly_once() -> None:
    sim = simulator(lost_writes=1)
    sim.set_word("B3", 1, 0xA5A5)  # bit 1 is 0
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unit.write_bits(1, [True])  # B3:1/1
        assert sim.word("B3", 1) == 0xA5A7
        assert [entry[:2] for entry in sim.applied_writes] == [("masked_write", "B3:1")]
        assert unit.write_tally.retried == 1


async def test_without_a_value_from_before_the_outcome_stays_unknown_counted_and_never_resent(
        caplog: pytest.LogCaptureFixture) -> None:
    sim = simulator(lost_writes=1)
    sim.set_word("N7", 20, 7)
    async with unit_on(sim, write_timeout=5.0) as unit:  # nothing read: the image holds nothing from before
        with caplog.at_level(logging.WARNING, "gateway.unit"), pytest.raises(ModbusExceptionReply) as caught:
            await unit.write_registers(30, [1234])
        assert caught.value.code == 0x0B
        assert sim.applied_writes == [] and sim.word("N7", 20) == 7
        assert (unit.write_tally.retried, unit.write_tally.unknown) == (0, 1)
        assert "outcome unknown" in caplog.text


async def test_a_write_lost_every_time_ends_at_write_timeout_as_not_written() -> None:
    sim = simulator(lost_writes=1000)
    sim.set_word("N7", 20, 7)
    async with unit_on(sim, write_timeout=3.0) as unit:
        await read_all(unit)
        with pytest.raises(ModbusExceptionReply) as caught:
            await unit.write_registers(30, [1234])
        assert caught.value.code == 0x0B
        assert sim.applied_writes == [] and sim.word("N7", 20) == 7
        assert unit.write_tally.retried >= 1
