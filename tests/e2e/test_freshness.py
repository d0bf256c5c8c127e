"""What clients read stays fresh on a controller that takes its time (``docs/guide/freshness.md``).

The whole gateway (driver, poller and schedule, cache, unit, Modbus server on 127.0.0.1) against
the in-process SLC 150 simulator; the poller's block reads go through a wrapper that adds the
controller's answer time (uniform within a bound, as a real controller answers at the end of its
scan) or holds one block's read, so the tests control what the line can do.
"""

from __future__ import annotations

import asyncio
import random
import struct
import uuid
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.errors import StaleRead
from gateway.modbus.mapping import Block, Table
from gateway.sim import get_simulator
from gateway.unit import Unit
from tests.e2e.modbus_support import HOST, connect, exception_code
from tests.net import mbap
from tests.waiting import until

TARGET_FAILED = 0x0B


def config(**keys: Any) -> Any:
    extra = "".join(f"{key} = {value!r}\n" for key, value in keys.items())
    return parse_config(f'[modbus]\nlisten = "127.0.0.1:0"\n\n[[link]]\nname = "press-1"\nprotocol = "slc-ascii"\n'
                        f'port = "sim://slc150?ladder=0&instance={uuid.uuid4().hex}"\nunit = 1\n{extra}')


ReadBlock = Callable[[Block], Awaitable[bytes]]


def answer_time(unit: Unit[Any, Any], wrap: Callable[[ReadBlock], ReadBlock]) -> None:
    """Put ``wrap`` around the poller's block reads (the controller's answer time, a held block)."""
    assert unit.poller is not None
    unit.poller._read_block = wrap(unit.poller._read_block)


def uniform_delay(bound: float, seed: int = 29) -> Callable[[ReadBlock], ReadBlock]:
    rng = random.Random(seed)

    def wrap(read: ReadBlock) -> ReadBlock:
        async def slow(block: Block) -> bytes:
            await asyncio.sleep(rng.uniform(0.0, bound))
            return await read(block)
        return slow
    return wrap


pytestmark = pytest.mark.usefixtures("forget_simulators")


def block_of(unit: Unit[Any, Any], table: Table, address: int) -> int:
    points = unit.plan.registers(table) if table in (Table.HOLDING, Table.INPUT) else unit.plan.bits(table)
    return points[address].block


async def read_reply(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    head = await reader.readexactly(7)
    tid, _, length, _ = struct.unpack(">HHHB", head)
    return tid, await reader.readexactly(length - 1)


# --- demand: a working set that fits the line stays fresh ----------------------------------------


async def test_a_screen_on_a_slow_controller_gets_every_read_with_data() -> None:
    """Answers within 0-100 ms (about 20 transactions/s here): a client reads the accumulators (holding
    0-31, 32 fast blocks) every second and the presets (32-63, 32 slow blocks) every 2 s.  Once the
    set has been read (the first few seconds), every read answers with data.  Reading the fast class
    round after round instead (55 blocks, plus the slow ones) made about half of them 0x0B."""
    async with Gateway(config()) as gw:
        answer_time(gw.units[0], uniform_delay(0.1))
        codes: list[tuple[float, int | None]] = []
        loop = asyncio.get_running_loop()
        start = loop.time()
        async with connect(gw.port) as client:
            for second in range(14):
                codes.append((loop.time() - start, exception_code(await client.read_holding_registers(0, count=32,
                                                                                                   device_id=1))))
                if second % 2 == 0:
                    reply = await client.read_holding_registers(32, count=32, device_id=1)
                    codes.append((loop.time() - start, exception_code(reply)))
                await asyncio.sleep(max(0.0, start + second + 1 - loop.time()))
        unit = gw.units[0]
        assert unit.schedule is not None and unit.poller is not None
        budget, behind = unit.schedule.budget(loop.time()), unit.poller.behind_text
    settled = [code for at, code in codes if at > 5.0]
    assert settled and all(code is None for code in settled), codes
    assert budget.demanded == 64, budget
    assert behind is None  # the set fits: no warning


async def test_at_start_the_blocks_a_client_reads_come_first() -> None:
    """A client reads holding 0-31 from the moment the port opens; the line (20 ms a read, 120 blocks:
    2.4 s for the plan) reads those 32 blocks before most of the others."""
    async with Gateway(config()) as gw:
        unit = gw.units[0]
        others: list[int] = []
        wanted = {block_of(unit, Table.HOLDING, a) for a in range(32)}

        def wrap(read: ReadBlock) -> ReadBlock:
            async def counted(block: Block) -> bytes:
                await asyncio.sleep(0.02)
                data = await read(block)
                index = unit.plan.blocks.index(block)
                if index not in wanted:
                    others.append(index)
                return data
            return counted

        answer_time(unit, wrap)
        async with connect(gw.port) as client:
            while exception_code(await client.read_holding_registers(0, count=32, device_id=1)) is not None:
                pass
            before_first_data = len(others)
    assert before_first_data < 15, before_first_data  # not the 88 other blocks, not the whole slow class


# --- read wait -------------------------------------------------------------------------------------


async def test_a_read_of_data_not_read_yet_waits_for_its_block_and_answers_with_data() -> None:
    async with Gateway(config()) as gw:
        unit = gw.units[0]
        assert unit.poller is not None and unit.schedule is not None
        block = block_of(unit, Table.DISCRETE, 951)
        unit.schedule.hold(block, 1e9)  # the poller would never read it on its own
        await until(lambda: unit.poller is not None and unit.poller.available)
        async with connect(gw.port) as client:
            reply = await client.read_discrete_inputs(951, count=32, device_id=1)
        assert exception_code(reply) is None, reply
        assert unit.poller.read_waits == 1


async def test_read_wait_zero_answers_at_once() -> None:
    async with Gateway(config(read_wait=0.0)) as gw:
        unit = gw.units[0]
        assert unit.poller is not None and unit.schedule is not None
        unit.schedule.hold(block_of(unit, Table.DISCRETE, 951), 1e9)
        await until(lambda: unit.poller is not None and unit.poller.available)
        async with connect(gw.port) as client:
            reply = await client.read_discrete_inputs(951, count=32, device_id=1)
        assert exception_code(reply) == TARGET_FAILED


async def test_a_wait_is_bounded_and_holds_up_no_other_connection_and_keeps_its_connections_order() -> None:
    """The held block's read never ends: the read waiting for it answers 0x0B after read_wait (0.5 s);
    another connection's read is answered from the image meanwhile; on the waiting read's own
    connection, the request after it (in the same segment) is answered after it, in order."""
    release = asyncio.Event()
    async with Gateway(config()) as gw:
        unit = gw.units[0]
        assert unit.poller is not None and unit.schedule is not None
        held = block_of(unit, Table.DISCRETE, 951)
        unit.schedule.hold(held, 1e9)

        def wrap(read: ReadBlock) -> ReadBlock:
            async def holding(block: Block) -> bytes:
                if unit.plan.blocks.index(block) == held:
                    await release.wait()
                return await read(block)
            return holding

        answer_time(unit, wrap)
        async with connect(gw.port) as client:
            while exception_code(await client.read_holding_registers(0, count=8, device_id=1)) is not None:
                pass
        loop = asyncio.get_running_loop()
        reader, writer = await asyncio.open_connection(HOST, gw.port)
        other_reader, other_writer = await asyncio.open_connection(HOST, gw.port)
        try:
            sent = loop.time()
            writer.write(mbap(1, 1, struct.pack(">BHH", 2, 951, 32)) + mbap(2, 1, struct.pack(">BHH", 3, 0, 8)))
            await writer.drain()
            await asyncio.sleep(0.05)
            other_writer.write(mbap(9, 1, struct.pack(">BHH", 3, 0, 8)))
            await other_writer.drain()
            tid, pdu = await asyncio.wait_for(read_reply(other_reader), 1.0)
            other_answered = loop.time() - sent
            assert (tid, pdu[0]) == (9, 3)  # data, from the image, while the first connection waits
            first = await asyncio.wait_for(read_reply(reader), 3.0)
            waited = loop.time() - sent
            second = await asyncio.wait_for(read_reply(reader), 1.0)
        finally:
            release.set()
            for w in (writer, other_writer):
                w.close()
    assert first == (1, bytes([0x82, TARGET_FAILED])), first  # 0x0B after the wait
    assert second[0] == 2 and second[1][0] == 3  # the request behind it, answered after it
    assert other_answered < waited
    assert 0.5 <= waited < 0.5 + 2.0, waited  # read_wait, not the client's timeout


async def test_a_link_that_is_down_answers_at_once() -> None:
    async with Gateway(config(timeout=0.05, retries=0, down_after_failures=1)) as gw:
        unit = gw.units[0]
        assert unit.poller is not None
        await until(lambda: unit.driver.available)
        sim = get_simulator(unit.driver.url)
        sim.faults.drop = 1
        await until(lambda: not unit.driver.available)
        with pytest.raises(Exception) as stale:
            for block in range(len(unit.plan.blocks)):
                unit.images.expire(block)
            unit.read_register_bytes(Table.HOLDING, 0, 1)
        assert not isinstance(stale.value, StaleRead) and getattr(stale.value, "code", None) == TARGET_FAILED
