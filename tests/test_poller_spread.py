"""The poller reads in the schedule's order: the fast class first at start, slow blocks between fast
reads as each falls due (never the whole slow class at once), demanded blocks first, and a block a
waiting read asks for before anything else (``docs/guide/freshness.md``)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable

import pytest

from gateway.cache import BlockCache
from gateway.errors import LinkDown
from gateway.modbus.mapping import Block, Scan
from gateway.poller import LineShare, Poller
from gateway.schedule import Schedule
from tests.waiting import until


def plan(fast: int, slow: int, prefix: str = "") -> list[Block]:
    blocks = [Block((prefix, "f", n), 1, Scan.FAST, f"{prefix}f{n}") for n in range(fast)]
    return blocks + [Block((prefix, "s", n), 1, Scan.SLOW, f"{prefix}s{n}") for n in range(slow)]


async def run_for(poller: Poller, seconds: float) -> None:
    task = asyncio.create_task(poller.run())
    await asyncio.sleep(seconds)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


async def test_fast_class_first_at_start_and_slow_blocks_between_fast_reads() -> None:
    reads: list[str] = []

    async def read(block: Block) -> bytes:
        reads.append(block.label)
        await asyncio.sleep(0.005)
        return b"\0"

    # 4 slow blocks due every 0.2 s, two fast blocks read continuously; nobody demands anything
    poller = Poller("p", plan(2, 4), BlockCache([1] * 6), read, fast_interval=0.0, slow_interval=0.2, stagger=0)
    await run_for(poller, 0.8)
    assert reads[:2] == ["f0", "f1"]  # never the whole slow class before any fast block
    assert set(reads[2:6]) == {"s0", "s1", "s2", "s3"}  # then each slow block once
    # every slow block is read again every 0.2 s (its period; the line has room) ...
    for n in range(4):
        times = [i for i, label in enumerate(reads) if label == f"s{n}"]
        assert len(times) >= 3, reads
    # ... between fast reads: never the 4 slow blocks back to back after start
    runs, run = [], 0
    for label in reads[6:]:
        run = run + 1 if label.startswith("s") else 0
        runs.append(run)
    assert max(runs) < 4, reads


async def test_a_block_a_read_waits_for_goes_first() -> None:
    reads: list[str] = []

    async def read(block: Block) -> bytes:
        reads.append(block.label)
        await asyncio.sleep(0.005)
        return b"\0"

    poller = Poller("p", plan(8, 0), BlockCache([1] * 8), read, stagger=0)
    task = asyncio.create_task(poller.run())
    try:
        await until(lambda: len(reads) >= 3)
        waited = poller.wait_for([6])
        asked = len(reads)
        await asyncio.wait_for(waited, 1.0)
        assert reads.index("f6", asked) <= asked + 1  # at most the read on the line before it
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_a_wait_ends_when_the_link_is_lost() -> None:
    lost = asyncio.Event()

    async def read(block: Block) -> bytes:
        await asyncio.sleep(0.005)
        if lost.is_set():
            raise LinkDown("gone")
        return b"\0"

    poller = Poller("p", plan(2, 0), BlockCache([1] * 2), read, stagger=0, down_wait=0.01)
    task = asyncio.create_task(poller.run())
    try:
        await until(lambda: poller.available)
        lost.set()
        waited = poller.wait_for([1])
        await asyncio.wait_for(waited, 1.0)  # done, not hanging until a read that cannot come
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


@pytest.mark.looptime
async def test_stations_sharing_a_line_one_stations_background_yields_to_anothers_urgent_reads() -> None:
    """Two pollers on one line: A has a demanded fast block, B nobody reads.  B's wanted reads wait
    while A's urgent read is on the line; B's blocks still come within their background period."""
    on_line: list[str] = []
    share = LineShare()

    def reader(log: list[str]) -> Callable[[Block], Awaitable[bytes]]:
        async def read(block: Block) -> bytes:
            log.append(block.label)
            on_line.append(block.label)
            await asyncio.sleep(0.01)
            return b"\0"
        return read

    a_reads: list[str] = []
    b_reads: list[str] = []
    a = Poller("a", plan(1, 0, "a"), BlockCache([1]), reader(a_reads), stagger=0, share=share)
    b = Poller("b", plan(4, 0, "b"), BlockCache([1] * 4), reader(b_reads), stagger=0, share=share)
    b.schedule.background = [0.3] * 4  # nobody reads B: each of its blocks at least every 0.3 s
    tasks = [asyncio.create_task(p.run()) for p in (a, b)]
    try:
        await asyncio.sleep(0.05)
        a.schedule.demand([0], asyncio.get_running_loop().time() + 10)  # a client reads A all along
        start = len(b_reads)
        await asyncio.sleep(1.0)
        after = len(b_reads) - start
        # a client waiting for one of B's blocks does not wait for A's urgent reads to end
        await asyncio.wait_for(b.wait_for([2]), 0.1)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    # B reads only when its blocks are urgent (every 0.3 s each): about 4 x 1.0 / 0.3, not the
    # half of the line (about 50 reads) round robin would give it
    assert 4 <= after <= 20, (after, len(a_reads))
    assert len(a_reads) > 3 * after


async def test_every_read_that_waits_is_counted_and_one_for_no_block_is_done_at_once() -> None:
    """``read_waits`` (the status page's "reads that waited") counts each ``wait_for``."""

    async def read(block: Block) -> bytes:
        await asyncio.sleep(0.005)
        return b"\0"

    poller = Poller("p", plan(2, 0), BlockCache([1] * 2), read, stagger=0)
    nothing = poller.wait_for([])
    assert nothing.done()
    task = asyncio.create_task(poller.run())
    try:
        await asyncio.wait_for(poller.wait_for([0]), 1.0)
        await asyncio.wait_for(poller.wait_for([1, 0]), 1.0)
        assert poller.read_waits == 3
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def test_the_line_share_marks_each_poller_and_others_are_the_rest() -> None:
    share = LineShare()
    a, b = object(), object()
    share.mark(a, True)
    assert not share.others(a) and share.others(b)  # a's own urgent reads hold nobody up but others
    share.mark(b, True)
    share.mark(a, False)
    assert share.others(a) and not share.others(b)
    share.mark(b, False)
    assert not share.others(a) and not share.others(b)


@pytest.mark.looptime
@pytest.mark.parametrize("demanded", [False, True])
async def test_a_line_that_cannot_keep_up_is_warned_of_once_over_many_rounds(
        demanded: bool, caplog: pytest.LogCaptureFixture) -> None:
    """Every read comes after its stale limit (0.1 s + P, P = 0 s, reads of 0.05 s, 4 blocks): one warning
    for as long as that lasts, naming the demanded blocks when clients read them."""

    async def read(block: Block) -> bytes:
        await asyncio.sleep(0.05)
        return b"\0"

    schedule = Schedule([Scan.FAST] * 4, fast_interval=0.0, slow_interval=10.0, stale_after=0.1,
                        background_interval=0.0, demand_hold=1000.0)
    poller = Poller("p", plan(4, 0), BlockCache([1] * 4), read, stagger=0, schedule=schedule)
    if demanded:
        schedule.demand([0, 1, 2], asyncio.get_running_loop().time())
    caplog.set_level(logging.WARNING, "gateway.poller")
    await run_for(poller, 10.0)  # about 50 rounds
    lines = [r.getMessage() for r in caplog.records if "refreshes its" in r.getMessage()]
    if demanded:
        assert lines == ["link p refreshes its 3 demanded blocks every 0.2 s; stale_after is 0.1 s: "
                         "raise stale_after, or read fewer addresses"]
    else:
        assert lines == ["link p refreshes its 4 blocks every 0.2 s; stale_after is 0.1 s: "
                         "raise stale_after, or map fewer addresses"]
    assert poller.behind is not None
