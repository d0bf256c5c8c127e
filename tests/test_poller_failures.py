"""The poller on failing links (``gateway.poller``): a link the driver reports down after failed reads
is a lost link (nothing read before it is served after it, one probe every ``down_wait``), and a
block the controller refused is no longer refused once it is read again.

Rates are counted against the loop's own clock over the window the test let pass (an upper bound
only: a loaded machine makes fewer probes, never more), never against a wall-clock deadline.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest

from gateway.cache import BlockCache
from gateway.errors import ControllerRefused, GatewayError, LinkTimeout
from gateway.modbus.mapping import Block, Scan
from gateway.poller import Poller
from gateway.schedule import NEVER
from tests.waiting import until

DOWN_WAIT = 0.05


def blocks(n: int) -> list[Block]:
    return [Block(i, 2, Scan.FAST, f"block {i}") for i in range(n)]


class Line:
    """Block reads answered (``data``) or failing with ``error(index)``, each read's loop time kept."""

    def __init__(self) -> None:
        self.error: Callable[[int], GatewayError | None] = lambda index: None
        self.up = True  # the driver's verdict (``responding``)
        self.times: list[float] = []
        self.failed: list[float] = []

    async def __call__(self, block: Block) -> bytes:
        loop = asyncio.get_running_loop()
        self.times.append(loop.time())
        await asyncio.sleep(0)
        index = block.request
        assert isinstance(index, int)
        error = self.error(index)
        if error is not None:
            self.failed.append(loop.time())
            raise error
        return b"\x00\x01"


class RecordingCache(BlockCache):
    """A block cache that keeps the times :meth:`expire_before` was called with."""

    def __init__(self, sizes: list[int]) -> None:
        super().__init__(sizes)
        self.expired: list[float] = []

    def expire_before(self, when: float) -> None:
        self.expired.append(when)
        super().expire_before(when)


@pytest.fixture
def line() -> Line:
    return Line()


@pytest.fixture
async def poller(line: Line) -> AsyncIterator[Poller]:
    """A poller of 3 blocks that read its first data; its driver's verdict is ``line.up``."""
    poller = Poller("p", blocks(3), RecordingCache([2] * 3), line, fast_interval=0.001, slow_interval=0.01,
                    down_wait=DOWN_WAIT, stagger=0, responding=lambda: line.up)
    task = asyncio.create_task(poller.run())
    await until(lambda: poller.available and poller.cache.stamps[2] > float("-inf"))
    yield poller
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


def timeouts(line: Line) -> None:
    """The controller stops answering; the driver says the link is down (several timeouts in a row)."""
    line.error = lambda index: LinkTimeout("no answer")
    line.up = False


async def test_a_link_down_by_timeouts_is_lost_what_was_read_before_is_not_served_after_it(
        poller: Poller, line: Line) -> None:
    cache = poller.cache
    assert isinstance(cache, RecordingCache)
    read_before = max(cache.stamps)
    timeouts(line)
    await until(lambda: len(line.failed) >= 3)
    assert cache.expired == []  # not yet: nothing is read during the outage
    line.error = lambda index: None
    line.up = True
    await until(lambda: bool(cache.expired))
    # the first answer after the loss: every value read before it is served no more until read again
    assert cache.expired[0] > read_before
    answered_again = min(t for t in line.times if t > line.failed[-1])
    assert cache.expired[0] < answered_again  # lost during the outage, not at its end


async def test_a_down_link_is_probed_once_every_down_wait_not_in_a_busy_loop(poller: Poller, line: Line) -> None:
    loop = asyncio.get_running_loop()
    timeouts(line)
    await until(lambda: len(line.failed) >= 2)
    start, probes = loop.time(), len(line.failed)
    await until(lambda: loop.time() - start >= 4 * DOWN_WAIT, what="the window")
    window, made = loop.time() - start, len(line.failed) - probes
    assert made >= 1  # it does probe
    # one probe per down_wait at most (one more at the window's edge)
    assert made <= window / DOWN_WAIT + 1, (made, window)
    gaps = [b - a for a, b in zip(line.failed[probes - 1:], line.failed[probes:], strict=False)]
    assert min(gaps) >= DOWN_WAIT * 0.9  # (the loop's timer granularity)


async def test_a_failure_on_a_link_the_driver_still_calls_up_is_not_a_loss(poller: Poller, line: Line) -> None:
    cache = poller.cache
    assert isinstance(cache, RecordingCache)
    line.error = lambda index: LinkTimeout("one lost reply") if index == 1 else None
    await until(lambda: len(line.failed) >= 3)
    line.error = lambda index: None
    count = len(line.times)
    await until(lambda: len(line.times) >= count + 6)
    assert cache.expired == []  # the other blocks answered meanwhile: nothing to expire


async def test_a_refused_block_read_again_is_no_longer_refused(poller: Poller, line: Line) -> None:
    refusal = ControllerRefused("controller refused read (program mode)", command="read")
    line.error = lambda index: refusal if index == 1 else None
    await until(lambda: 1 in poller.refused)
    assert poller.refused[1][0] is refusal
    line.error = lambda index: None
    refused_at = poller.refused[1][1]
    await until(lambda: poller.cache.stamps[1] > refused_at, what="block 1 read again")
    assert poller.refused == {}


async def test_only_the_block_read_again_leaves_the_refused() -> None:
    line = Line()
    refusal = ControllerRefused("controller refused read", command="read")
    line.error = lambda index: refusal if index in (0, 2) else None
    poller = Poller("p", blocks(3), BlockCache([2] * 3), line, fast_interval=0.001, slow_interval=0.01,
                    down_wait=DOWN_WAIT, stagger=0, responding=lambda: True)
    task = asyncio.create_task(poller.run())
    try:
        await until(lambda: set(poller.refused) == {0, 2})
        line.error = lambda index: refusal if index == 2 else None
        refused_at = poller.refused[0][1]
        await until(lambda: poller.cache.stamps[0] > refused_at, what="block 0 read again")
        assert set(poller.refused) == {2}
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


# --- refusals, failures and rounds, on the loop's fake clock (looptime) ----------------------------------


@pytest.mark.looptime
async def test_refused_blocks_are_logged_three_by_name_then_once_and_retried_every_five_seconds(
        caplog: pytest.LogCaptureFixture) -> None:
    """Program mode refuses every read: three blocks named, one line for the rest, nothing more; each
    block tried again ``min(slow_interval, 5 s)`` after its refusal; a refusal is not a lost link and
    no read for the freshness of the block."""
    line = Line()
    line.error = lambda index: ControllerRefused("program mode", command="read")
    cache = RecordingCache([2] * 6)
    poller = Poller("p", blocks(6), cache, line, fast_interval=0.0, slow_interval=10.0, down_wait=DOWN_WAIT,
                    stagger=0, responding=lambda: True)
    caplog.set_level(logging.WARNING, "gateway.poller")
    task = asyncio.create_task(poller.run())
    await asyncio.sleep(12.0)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    lines = [r.getMessage() for r in caplog.records if "refuse" in r.getMessage()]
    assert lines == [f"link p: the controller refuses to read block {i}: program mode" for i in range(3)] + [
        "link p: more blocks refused; not logging each"]
    assert len(line.times) == 18 and poller.block_errors == 18  # each block at 0, 5 and 10 s
    assert set(poller.refused) == set(range(6))
    assert cache.expired == []  # not a lost link
    assert all(at == NEVER for at in poller.schedule.read_at)


@pytest.mark.looptime
async def test_a_wait_for_two_blocks_ends_when_both_were_read_refused_or_failed() -> None:
    line = Line()
    answered: list[int] = []

    async def read(block: Block) -> bytes:
        await asyncio.sleep(0.1)
        try:
            return await line(block)
        finally:
            answered.append(int(block.request))  # type: ignore[call-overload]

    for error in (ControllerRefused("refused", command="read"), LinkTimeout("lost reply"), None):
        line.error = lambda index, error=error: error if index == 0 else None  # type: ignore[misc]
        answered.clear()
        poller = Poller("p", blocks(4), BlockCache([2] * 4), read, fast_interval=0.0, down_wait=DOWN_WAIT,
                        stagger=0, responding=lambda: True)
        task = asyncio.create_task(poller.run())
        try:
            await asyncio.sleep(1.0)
            asked = len(answered)
            await asyncio.wait_for(poller.wait_for([0, 3]), 5.0)
            assert {0, 3} <= set(answered[asked:]), (error, answered[asked:])  # not done after the first only
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)


@pytest.mark.looptime
async def test_a_block_that_fails_is_no_read_for_its_freshness() -> None:
    line = Line()
    line.error = lambda index: LinkTimeout("lost reply") if index == 1 else None
    poller = Poller("p", blocks(3), BlockCache([2] * 3), slow(line), fast_interval=0.0, down_wait=DOWN_WAIT, stagger=0,
                    responding=lambda: True)
    await run_until_cancelled(poller, 1.0)
    assert poller.schedule.read_at[1] == NEVER and poller.schedule.read_at[0] > 0
    assert poller.block_errors == len(line.failed) > 1


def slow(line: Line) -> Callable[[Block], Awaitable[bytes]]:
    """``line``, each read taking 10 ms (on the fake clock a read that takes no time never lets it move)."""
    async def read(block: Block) -> bytes:
        await asyncio.sleep(0.01)
        return await line(block)
    return read


async def run_until_cancelled(poller: Poller, seconds: float) -> None:
    task = asyncio.create_task(poller.run())
    await asyncio.sleep(seconds)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


@pytest.mark.looptime
async def test_a_round_is_as_many_reads_as_blocks() -> None:
    rounds: list[tuple[int, int]] = []
    poller: Poller | None = None

    async def read(block: Block) -> bytes:
        assert poller is not None
        rounds.append((len(rounds), poller.scans))
        await asyncio.sleep(0.01)
        return b"\x00\x01"

    poller = Poller("p", blocks(3), BlockCache([2] * 3), read, fast_interval=0.0, stagger=0)
    await run_until_cancelled(poller, 1.0)
    assert len(rounds) > 30
    assert all(scans == reads // 3 for reads, scans in rounds), rounds[:12]


@pytest.mark.looptime
async def test_a_first_round_that_fails_is_the_first_change_of_availability_and_says_when() -> None:
    line = Line()
    line.error = lambda index: GatewayError("garbled reply")
    poller = Poller("p", blocks(2), BlockCache([2] * 2), slow(line), fast_interval=0.0, down_wait=DOWN_WAIT, stagger=0,
                    responding=lambda: True)
    await run_until_cancelled(poller, 0.5)
    assert not poller.available and poller.availability_changes == 1
    assert poller.last_error_at is not None and 0 < poller.last_error_at


async def test_a_refused_block_is_no_loss_of_the_link() -> None:
    """The controller answers (it refuses one block): the other blocks' values are not expired."""
    line = Line()
    line.error = lambda index: ControllerRefused("protected", command="read") if index == 1 else None
    cache = RecordingCache([2] * 3)
    poller = Poller("p", blocks(3), cache, line, fast_interval=0.001, slow_interval=0.01, down_wait=DOWN_WAIT,
                    stagger=0, responding=lambda: True)
    task = asyncio.create_task(poller.run())
    try:
        await until(lambda: len(line.failed) >= 3)
        count = len(line.times)
        await until(lambda: len(line.times) >= count + 6)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert cache.expired == []
