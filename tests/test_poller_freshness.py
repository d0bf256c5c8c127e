"""The poller on a unit's image: demand from reads, values before a loss, and the line that cannot keep up.

An SLC 150 unit (its plan and image); its driver is never started: the poller's block reads are a
script, so the tests decide what the controller answers and when.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator

import pytest

from gateway.errors import LinkDown, ModbusExceptionReply
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.modbus.mapping import Block, Table
from tests.waiting import until

TARGET_FAILED = ModbusExceptionReply.GATEWAY_TARGET_FAILED


class Controller:
    """Block reads: each answers after ``delay`` seconds, or fails with ``error`` while it is set."""

    def __init__(self, unit: SlcAsciiUnit) -> None:
        self.unit = unit
        self.delay = 0.001
        self.error: Exception | None = None
        self.reads: list[int] = []

    async def __call__(self, block: Block) -> bytes:
        index = self.unit.plan.blocks.index(block)
        await asyncio.sleep(self.delay)
        if self.error is not None:
            raise self.error
        self.reads.append(index)
        return bytes(block.size)


def make_unit(stale_after: float = 5.0, background_interval: float = 30.0) -> tuple[SlcAsciiUnit, Controller]:
    unit = SlcAsciiUnit(driver=SlcAsciiDriver("sim://slc150?ladder=0"), unit_id=1, name="press-1",
                        stale_after=stale_after, fast_interval=0.0, slow_interval=0.0,
                        background_interval=background_interval)
    controller = Controller(unit)
    assert unit.poller is not None
    unit.poller._read_block = controller
    unit.poller._responding = lambda: True
    unit.poller._ready = None  # the driver never opens its port: nothing to wait for
    unit.poller._down_wait = 0.005
    return unit, controller


@pytest.fixture
async def running() -> AsyncIterator[tuple[SlcAsciiUnit, Controller]]:
    unit, controller = make_unit()
    task = asyncio.create_task(unit.run())
    yield unit, controller
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


def block_of(unit: SlcAsciiUnit, address: int) -> int:
    return unit.plan.holding[address].block


async def test_reads_from_the_image_make_their_blocks_demanded(running: tuple[SlcAsciiUnit, Controller]) -> None:
    unit, _ = running
    assert unit.schedule is not None
    await until(lambda: unit.poller is not None and unit.poller.available)
    await until(lambda: all(unit.cache.stamps[block_of(unit, a)] > -1e9 for a in range(4)))
    loop = asyncio.get_running_loop()
    unit.read_register_bytes(Table.HOLDING, 0, 4)  # answered inside data_received: one dict store
    with contextlib.suppress(ModbusExceptionReply):
        unit.read_bit_bytes(Table.COIL, 701, 8)  # a read answered 0x0B is demand too
    await until(lambda: unit.schedule is not None and len(unit.schedule.demanded(loop.time())) > 0)
    now = loop.time()
    demanded = set(unit.schedule.demanded(now))
    assert {block_of(unit, a) for a in range(4)} <= demanded
    assert unit.plan.coils[701].block in demanded
    assert block_of(unit, 40) not in demanded


async def test_values_read_before_a_loss_are_not_served_after_it_until_read_again(
    running: tuple[SlcAsciiUnit, Controller],
) -> None:
    """The controller may have been replaced while the link was down: after it answers again, only
    the blocks read since are served."""
    unit, controller = running
    assert unit.schedule is not None
    first, other = block_of(unit, 0), block_of(unit, 1)
    await until(lambda: unit.cache.stamps[first] > -1e9 and unit.cache.stamps[other] > -1e9)
    unit.schedule.hold(other, 1e9)  # from now on the poller does not read `other` on its own
    reads = len(controller.reads)
    await until(lambda: len(controller.reads) >= reads + 2)  # (a read of it on the line is over)
    assert len(unit.read_register_bytes(Table.HOLDING, 1, 1)) == 2  # served before the loss
    controller.error = LinkDown("gone")
    await until(lambda: unit.poller is not None and not unit.poller.available)
    controller.error = None
    await until(lambda: controller.reads.count(first) >= 2 and unit.poller is not None and unit.poller.available)
    assert len(unit.read_register_bytes(Table.HOLDING, 0, 1)) == 2  # read again: served
    with pytest.raises(ModbusExceptionReply) as stale:
        unit.read_register_bytes(Table.HOLDING, 1, 1)  # read before the loss: not served
    assert stale.value.code == TARGET_FAILED
    unit.schedule.hold(other, 0.0)
    await until(lambda: controller.reads.count(other) >= 2)
    assert len(unit.read_register_bytes(Table.HOLDING, 1, 1)) == 2


@pytest.mark.looptime
async def test_a_line_that_cannot_keep_up_says_so_once_with_what_to_change(caplog: pytest.LogCaptureFixture) -> None:
    # stale_after 0.2 s; 120 blocks of 4 ms each take about 0.5 s: the plan cannot be refreshed in time
    unit, controller = make_unit(stale_after=0.2, background_interval=0.0)
    controller.delay = 0.004
    caplog.set_level(logging.WARNING, "gateway.poller")
    task = asyncio.create_task(unit.run())
    try:
        await until(lambda: unit.poller is not None and unit.poller.behind_text is not None, 20.0)
        late = unit.schedule.late_reads if unit.schedule is not None else 0
        await until(lambda: unit.schedule is not None and unit.schedule.late_reads >= late + 200, 20.0)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    lines = [r.getMessage() for r in caplog.records if r.name == "gateway.poller"]
    behind = [line for line in lines if "refreshes its" in line]
    assert len(behind) == 1, lines
    assert behind[0].startswith("link press-1 refreshes its 120 blocks every ")
    assert behind[0].endswith(" s; stale_after is 0.2 s: raise stale_after, or map fewer addresses")
    assert unit.poller is not None
    # the status page shows the same warning, its figure kept current (the log says it once): on a
    # loaded machine the refresh period measured since the log line may differ by a tenth
    shown = re.fullmatch(r"link press-1 refreshes its 120 blocks every (\d+\.\d) s; stale_after is 0\.2 s: "
                         r"raise stale_after, or map fewer addresses", unit.poller.behind_text or "")
    assert shown is not None, unit.poller.behind_text
    assert float(shown.group(1)) > 0.2  # longer than stale_after: that is what it warns of
