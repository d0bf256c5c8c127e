"""A write whose outcome was unknown but which a read-back proved not applied is sent again (issue 43, item 6b).

The N7:20 case of the issue: a DCMD on a DF1 full-duplex line with faults was not applied, the read-back gave the
previous value, and the gateway answered "may or may not have been applied".  On full duplex the read-back runs
after the write (the controller runs commands in order), so the value from before the write proves the write was
not applied: the one write path (``gateway.unit_writes``, ``UnitWrites._run_steps`` -> ``run_step``) sends it
again within ``write_timeout``, and the controller applies it exactly once.  Where nothing proves it (the gateway
holds no value from before, the read-back shows a third value, the processor itself rewrites the word, a float a
controller may store as another pattern, half duplex), the outcome stays unknown: 0x0B, counted and logged, never
sent again.

The same rule for the SLC 500 (typed logical write, masked write) and the PLC-5 (word range write,
read-modify-write): ``PcccUnit.proves_not_applied``.

No mocks: a ``Df1Unit`` / ``Plc5Unit`` on the full-duplex driver talking to the SLC 500 / PLC-5 simulator through a
``SimStream``; the simulator loses the first write frame whole (``lose_in``, only that one).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest

from gateway.errors import ModbusExceptionReply
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.half.driver import Df1Station
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.plc5_unit import Plc5Unit
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.kinds.df1.unit import Df1Unit, PcccUnit
from gateway.modbus.mapping import Table
from gateway.protocols.df1.framing import Checksum
from gateway.sim.serve import SimStream

from ..half.lines import make_driver

ITEMS = [
    MapItem("holding", 30, "N7:20", 3),
    MapItem("holding", 40, "F8:2", 1, "float32"),
    MapItem("holding", 50, "T4:1.PRE", 1),
    MapItem("holding", 51, "T4:2.ACC", 1),
    MapItem("coil", 0, "B3:1/0", 4),
]
#: The controller models, and the names their applied-writes logs give a word write and a bit write.
MODELS: dict[str, tuple[type[Slc500Simulator], str, str]] = {
    "slc500": (Slc500Simulator, "write", "masked_write"),
    "plc5": (Plc5Simulator, "word_range_write", "read_modify_write"),
}
models = pytest.mark.parametrize("model", list(MODELS))


def simulator(lost_writes: int, model: str = "slc500") -> Slc500Simulator:
    """An SLC 5/04 (a PLC-5) that loses the first ``lost_writes`` write frames whole (the controller never sees
    them)."""
    sim = MODELS[model][0].from_options({"seed": "43", "lose_in": "1", "faults_on": "writes"}, ladder=False)
    strikes = sim._strikes

    def only_the_first(frame: bytes) -> bool:
        return sim.counters.lost_in < lost_writes and strikes(frame)

    sim._strikes = only_the_first  # type: ignore[method-assign]
    return sim


def a_unit(driver: Any, plc5: bool, **options: Any) -> PcccUnit[Any, Any]:
    if plc5:
        return Plc5Unit(driver=driver, items=ITEMS, unit_id=1, name="plc5", **options)
    return Df1Unit(driver=driver, items=ITEMS, max_read_bytes=236, unit_id=1, name="slc", **options)


@asynccontextmanager
async def unit_on(sim: Slc500Simulator, **options: Any) -> AsyncIterator[PcccUnit[Any, Any]]:
    async def opener(url: str, settings: Any, **_: Any) -> SimStream:
        return SimStream(sim)

    driver = Df1Driver("sim://slc504", checksum=Checksum(sim.options.checksum), timeout=0.05, ack_timeout=0.05,
                       retries=2, opener=opener)
    await driver.start()
    try:
        yield a_unit(driver, isinstance(sim, Plc5Simulator), **options)
    finally:
        await driver.close()


async def read_all(unit: PcccUnit[Any, Any]) -> None:
    """Every block read once from the controller: the image holds the values from before the writes."""
    for index, block in enumerate(unit.plan.blocks):
        unit.store(index, await unit.read_block(block), unit._loop_time())


def float_registers(value: float) -> list[int]:
    raw = struct.unpack("<I", struct.pack("<f", value))[0]
    return [raw >> 16, raw & 0xFFFF]  # high word first (the map's word_order)


@models
async def test_a_write_proven_not_applied_is_sent_again_and_applied_exactly_once(model: str) -> None:
    sim = simulator(lost_writes=1, model=model)
    sim.set_word("N7", 20, 7)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unit.write_registers(30, [1234])  # answered: applied
        assert sim.word("N7", 20) == 1234
        assert sim.applied_writes == [(MODELS[model][1], "N7:20", (1234).to_bytes(2, "little"))]  # exactly once
        assert sim.counters.lost_in == 1  # the first frame was lost: the read-back showed 7
        assert (unit.write_tally.retried, unit.write_tally.unknown) == (1, 0)
        assert unit.read_registers(Table.HOLDING, 30, 1) == [1234]


@models
async def test_words_written_in_one_command_proven_not_applied_are_sent_again_once(model: str) -> None:
    sim = simulator(lost_writes=1, model=model)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        before = [sim.word("N7", k) for k in (20, 21, 22)]
        await unit.write_registers(30, [1, 2, 3])  # N7:20-22 in one command
        assert sim.applied_writes == [(MODELS[model][1], "N7:20", bytes.fromhex("0100 0200 0300"))]
        assert [sim.word("N7", k) for k in (20, 21, 22)] == [1, 2, 3] != before
        assert unit.write_tally.retried == 1


@models
async def test_a_float_proven_not_applied_is_sent_again_once(model: str) -> None:
    sim = simulator(lost_writes=1, model=model)
    sim.set_float("F8", 2, 2.5)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unit.write_registers(40, float_registers(-1.75))
        assert sim.float_value("F8", 2) == -1.75
        assert sim.applied_writes == [(MODELS[model][1], "F8:2", struct.pack("<f", -1.75))]
        assert unit.write_tally.retried == 1


@models
async def test_a_coil_write_proven_not_applied_is_sent_again_and_applied_exactly_once(model: str) -> None:
    sim = simulator(lost_writes=1, model=model)
    sim.set_word("B3", 1, 0xA5A5)  # bit 1 is 0
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unit.write_bits(1, [True])  # B3:1/1
        assert sim.word("B3", 1) == 0xA5A7
        assert [entry[:2] for entry in sim.applied_writes] == [(MODELS[model][2], "B3:1")]
        assert unit.write_tally.retried == 1


async def unknown_and_never_resent(unit: PcccUnit[Any, Any], sim: Slc500Simulator, address: int,
                                   values: list[int], caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, "gateway.unit"), pytest.raises(ModbusExceptionReply) as caught:
        await unit.write_registers(address, values)
    assert caught.value.code == 0x0B
    assert sim.applied_writes == []
    assert sim.counters.lost_in == 1  # sent once
    assert (unit.write_tally.retried, unit.write_tally.unknown) == (0, 1)
    assert "outcome unknown" in caplog.text


@models
async def test_without_a_value_from_before_the_outcome_stays_unknown_counted_and_never_resent(
        model: str, caplog: pytest.LogCaptureFixture) -> None:
    sim = simulator(lost_writes=1, model=model)
    sim.set_word("N7", 20, 7)
    async with unit_on(sim, write_timeout=5.0) as unit:  # nothing read: the image holds nothing from before
        await unknown_and_never_resent(unit, sim, 30, [1234], caplog)
        assert sim.word("N7", 20) == 7


@models
async def test_a_read_back_showing_neither_the_old_nor_the_new_value_stays_unknown(
        model: str, caplog: pytest.LogCaptureFixture) -> None:
    sim = simulator(lost_writes=1, model=model)
    sim.set_word("N7", 20, 7)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)  # the image holds 7
        sim.set_word("N7", 20, 99)  # the ladder changed it since: the read-back shows 99
        await unknown_and_never_resent(unit, sim, 30, [1234], caplog)
        assert sim.word("N7", 20) == 99


@models
async def test_a_word_the_processor_rewrites_itself_stays_unknown(model: str, caplog: pytest.LogCaptureFixture) -> None:
    """T4:2.ACC shows its old value after the lost write, but a timer's accumulator is the processor's too (a TON
    on a false rung zeroes it every scan): no proof."""
    sim = simulator(lost_writes=1, model=model)
    sim.set_word("T4", 2, 0, sub=2)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unknown_and_never_resent(unit, sim, 51, [600], caplog)
        assert sim.word("T4", 2, sub=2) == 0


@models
async def test_a_preset_proven_not_applied_is_sent_again_once(model: str) -> None:
    """A timer's .PRE is written only by the program and the gateway (the processor never changes it): a read-back
    showing the preset from before proves the write was not applied."""
    sim = simulator(lost_writes=1, model=model)
    sim.set_word("T4", 1, 500, sub=1)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unit.write_registers(50, [600])
        assert sim.word("T4", 1, sub=1) == 600
        assert [entry[:2] for entry in sim.applied_writes] == [(MODELS[model][1], "T4:1.PRE")]
        assert (unit.write_tally.retried, unit.write_tally.unknown) == (1, 0)


@models
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -0.0, 1e-45])
async def test_a_float_a_controller_may_keep_as_another_pattern_stays_unknown(
        model: str, value: float, caplog: pytest.LogCaptureFixture) -> None:
    """A NaN, an infinity, -0.0 or a subnormal may be stored as another pattern (+0.0 for -0.0 or a subnormal
    flushed to zero): a read-back showing the old value proves nothing."""
    sim = simulator(lost_writes=1, model=model)
    sim.set_float("F8", 2, 0.0)
    async with unit_on(sim, write_timeout=5.0) as unit:
        await read_all(unit)
        await unknown_and_never_resent(unit, sim, 40, float_registers(value), caplog)


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


@pytest.mark.parametrize("plc5", [False, True], ids=["slc500", "plc5"])
async def test_half_duplex_never_takes_the_value_from_before_as_proof(plc5: bool) -> None:
    """The same step and read-back: proof on full duplex, none on a half-duplex station (the slave may still
    hold the write in its queue).  Nothing is sent: the rule alone."""
    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,), model="plc5" if plc5 else "slc504"))
    full = a_unit(Df1Driver("sim://slc504"), plc5)
    half = a_unit(make_driver(line, (1,)).station(1), plc5)
    assert isinstance(half.driver, Df1Station)
    old = (7).to_bytes(2, "little")
    for unit in (full, half):
        for index, block in enumerate(unit.plan.blocks):
            unit.store(index, old * (block.size // 2), 1.0)
        [step] = unit._register_steps([(30, unit.plan.holding[30], 1234)])
        assert unit.proves_not_applied(step, old) is (unit is full)
        assert not unit.proves_not_applied(step, (99).to_bytes(2, "little"))  # neither old nor new
