"""Every Modbus write is answered within ``write_timeout``, and what the answer means.

A write still waiting for the line at ``write_timeout`` is withdrawn: answered 0x0B, nothing of
it written.  A write already on the line is answered 0x0B (outcome unknown) and goes on to its
verdict, applied at most once; the audit log gives the outcome.  A multi-command write sends no
further command once it has been answered.

The controller here takes ``slow_delay`` (1 s here) to answer a write (the simulator's
``reply_time=slow_changes`` reading, "edit commands and mode changes" take longer) and the
driver waits for it, so the verdict always comes after ``write_timeout`` (0.2 s).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator

import pytest

from gateway.errors import ModbusExceptionReply
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.sim import get_simulator, reset_simulators

#: Policy on the virtual clock (looptime): every timeout and sleep here is loop time, no real I/O.
pytestmark = pytest.mark.looptime

URL = "sim://slc150?ladder=0&variant=reply_time=slow_changes&slow_delay=1.0&instance=write-timeout"
PRESET_905 = 36  # holding register: preset of 905, controller word 0x48


@pytest.fixture
async def unit() -> AsyncIterator[SlcAsciiUnit]:
    reset_simulators()
    driver = SlcAsciiDriver(URL, timeout=3.0, write_budget=5.0)
    unit = SlcAsciiUnit(driver=driver, unit_id=1, name="slow", stale_after=1.0, write_timeout=0.2)
    async with driver:
        yield unit


def _sim() -> SlcAsciiSimulator:
    sim = get_simulator(URL)
    assert isinstance(sim, SlcAsciiSimulator)
    return sim


def _words(sim: SlcAsciiSimulator) -> list[tuple[int, int]]:
    return [(address, value) for kind, address, value in sim.applied_writes if kind == "word"]


async def _settle(unit: SlcAsciiUnit) -> None:
    """Wait until the write queue has run everything it took (the line is free again)."""
    async with asyncio.timeout(10):
        await unit.writes.drain()


async def test_a_write_on_the_line_at_write_timeout_is_answered_0x0B_and_lands_once(
        unit: SlcAsciiUnit, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="gateway.audit")
    before = unit.driver.counters.transactions
    with pytest.raises(ModbusExceptionReply) as answer:
        await unit.write_registers(PRESET_905, [1234])
    assert answer.value.code == 0x0B
    assert "outcome unknown" in str(answer.value)
    # answered before the controller's verdict came
    assert unit.driver.counters.transactions == before
    await _settle(unit)
    assert _words(_sim()) == [(0x48, 1234)]  # applied, once
    assert any("answered 0x0B at write_timeout" in r.getMessage() and r.getMessage().endswith("then: applied")
               for r in caplog.records), [r.getMessage() for r in caplog.records]


async def test_a_write_still_waiting_at_write_timeout_is_withdrawn_and_never_written(unit: SlcAsciiUnit) -> None:
    first = asyncio.create_task(unit.write_registers(PRESET_905, [1111]))
    await asyncio.sleep(0)  # the first is queued (and taken by the worker) first
    with pytest.raises(ModbusExceptionReply) as answer:
        await unit.write_registers(PRESET_905 + 1, [2222])  # queued behind the first, on the line for 1 s
    assert answer.value.code == 0x0B
    assert "withdrawn" in str(answer.value) and "nothing was written" in str(answer.value)
    with pytest.raises(ModbusExceptionReply):
        await first
    await _settle(unit)
    assert _words(_sim()) == [(0x48, 1111)]  # the withdrawn one never reached the controller


async def test_a_multi_register_write_sends_nothing_more_after_its_answer(unit: SlcAsciiUnit) -> None:
    with pytest.raises(ModbusExceptionReply) as answer:
        await unit.write_registers(PRESET_905, [10, 20, 30])  # three write-word commands
    assert answer.value.code == 0x0B
    await _settle(unit)
    assert _words(_sim()) == [(0x48, 10)]  # the one on the line at the answer, and no other
    assert unit.partial_writes == 1
