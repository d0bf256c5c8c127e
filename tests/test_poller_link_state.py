"""Availability on a bad line: a failed block never restarts a scan, one failure is not a lost link."""

from __future__ import annotations

import asyncio
import logging
import uuid

import pytest

from gateway.cache import BlockCache
from gateway.errors import LinkDown, LinkTimeout
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.modbus.mapping import Block, Scan
from gateway.poller import Poller
from gateway.sim import get_simulator


def blocks(n: int, scan: Scan = Scan.SLOW) -> list[Block]:
    return [Block(i, 2, scan, f"block {i}") for i in range(n)]


async def run_poller(poller: Poller, until: int, reads: list[int]) -> None:
    task = asyncio.create_task(poller.run())
    try:
        for _ in range(5000):
            if len(reads) >= until:
                break
            await asyncio.sleep(0.001)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_a_failed_block_is_followed_by_the_next_and_retried_in_its_turn() -> None:
    reads: list[int] = []
    failing = {2: 1, 5: 1}  # these blocks fail once

    async def read_block(block: Block) -> bytes:
        index = block.request
        assert isinstance(index, int)
        reads.append(index)
        if failing.get(index):
            failing[index] -= 1
            raise LinkTimeout("lost")
        return b"\x00\x01"

    cache = BlockCache([2] * 8)
    poller = Poller("p", blocks(8), cache, read_block, slow_interval=0.0, responding=lambda: True)
    await run_poller(poller, 16, reads)
    assert reads[:16] == list(range(8)) + list(range(8))  # no restart from block 0 after a failure
    assert poller.block_errors == 2


async def test_a_scan_stopped_by_a_lost_link_resumes_where_it_stopped() -> None:
    reads: list[int] = []
    down_once = [True]

    async def read_block(block: Block) -> bytes:
        index = block.request
        assert isinstance(index, int)
        reads.append(index)
        if index == 3 and down_once[0]:
            down_once[0] = False
            raise LinkDown("gone")
        return b"\x00\x01"

    poller = Poller("p", blocks(6), BlockCache([2] * 6), read_block, slow_interval=0.0, down_wait=0.01)
    await run_poller(poller, 10, reads)
    assert reads[:10] == [0, 1, 2, 3, 3, 4, 5, 0, 1, 2]


async def test_link_goes_down_after_n_failures_in_a_row_not_one(caplog: pytest.LogCaptureFixture) -> None:
    url = f"sim://slc150?ladder=0&instance={uuid.uuid4().hex}"
    sim = get_simulator(url)
    driver = SlcAsciiDriver(url, timeout=0.01, retries=1, down_after_failures=3, down_after_seconds=60)
    caplog.set_level(logging.INFO, "gateway.link")
    async with asyncio.timeout(10), driver:
        await driver.read(0x40, 2)
        assert driver.available and driver.state_changes == 1
        sim.faults.drop = 1
        for n in range(1, 5):
            with pytest.raises(LinkTimeout):
                await driver.read(0x40, 2)
            assert driver.available is (n < 3), n
        sim.faults.drop = 0
        await driver.read(0x40, 2)
        assert driver.available
    assert driver.state_changes == 3  # up, down, up: each once
    lines = [r.getMessage() for r in caplog.records if r.name == "gateway.link"]
    assert sum("down" in line for line in lines) == 1
    assert sum(": up" in line for line in lines) == 2


async def test_link_goes_down_after_t_seconds_without_a_valid_reply() -> None:
    url = f"sim://slc150?ladder=0&instance={uuid.uuid4().hex}"
    sim = get_simulator(url)
    driver = SlcAsciiDriver(url, timeout=0.01, retries=1, down_after_failures=1000, down_after_seconds=0.3)
    async with asyncio.timeout(10), driver:
        await driver.read(0x40, 2)
        sim.faults.drop = 1
        loop = asyncio.get_running_loop()
        silent_since = loop.time()
        while driver.available:
            with pytest.raises(LinkTimeout):
                await driver.read(0x40, 2)
        assert loop.time() - silent_since >= 0.3
        assert driver.counters.errors >= 2
