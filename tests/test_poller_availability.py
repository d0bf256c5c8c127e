"""The poller's own data availability: ``available``, ``last_error``, ``last_success``, one log per change.

Home Assistant's ``DataUpdateCoordinator`` is the model: "unavailable" once when polls start
failing, "back online" once when they recover, never per retry; and never the driver's
"link down"/"up" said a second time (the poller stays at DEBUG when the link is the cause).
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from collections.abc import AsyncIterator, Callable
from typing import cast

import pytest

from gateway.cache import BlockCache
from gateway.errors import ControllerRefused, GatewayError, LinkDown, LinkTimeout, ProtocolError
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.modbus.mapping import Block, Scan
from gateway.poller import MAX_STAGGER, Poller, default_stagger
from gateway.sim import get_simulator
from tests.waiting import until


def blocks(n: int) -> list[Block]:
    return [Block(i, 2, Scan.FAST, f"block {i}") for i in range(n)]


class Script:
    """Block reads that fail with ``error(index)`` while it returns an error."""

    def __init__(self) -> None:
        self.error: Callable[[int], GatewayError | None] = lambda index: None
        self.reads = 0

    async def __call__(self, block: Block) -> bytes:
        self.reads += 1
        await asyncio.sleep(0)
        index = block.request
        assert isinstance(index, int)
        error = self.error(index)
        if error is not None:
            raise error
        return b"\x00\x01"


async def rounds(script: Script, n: int) -> None:
    """Let ``n`` more block reads run (a round stopped by a lost link reads one)."""
    start = script.reads
    await until(lambda: script.reads >= start + n)


def poller_lines(caplog: pytest.LogCaptureFixture, level: int = logging.INFO) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "gateway.poller" and r.levelno >= level]


@pytest.fixture
def script() -> Script:
    return Script()


@pytest.fixture
async def running(script: Script, caplog: pytest.LogCaptureFixture) -> AsyncIterator[Poller]:
    """A poller of 3 blocks that has read its first data (the log from its start on)."""
    caplog.set_level(logging.DEBUG, "gateway.poller")
    poller = Poller("p", blocks(3), BlockCache([2] * 3), script, fast_interval=0.002, slow_interval=0.01,
                    down_wait=0.002, stagger=0, responding=lambda: True)
    task = asyncio.create_task(poller.run())
    await until(lambda: poller.available)
    yield poller
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


async def test_available_after_the_first_block_read_and_the_first_data_is_not_news(
    script: Script, running: Poller, caplog: pytest.LogCaptureFixture
) -> None:
    fresh = Poller("q", blocks(1), BlockCache([2]), script)
    assert not fresh.available and fresh.last_success is None and fresh.last_error is None
    poller = running
    assert poller.last_success is not None
    before = poller.last_success
    await rounds(script, 3)
    assert poller.last_success > before
    assert poller_lines(caplog) == []


async def test_a_lost_link_is_the_drivers_to_log_the_poller_says_it_at_debug_once(
    script: Script, running: Poller, caplog: pytest.LogCaptureFixture
) -> None:
    poller = running
    lost = LinkDown("link p is down: closed")
    script.error = lambda index: lost
    await until(lambda: not poller.available)
    await rounds(script, 20)
    assert poller.last_error is lost and not poller.available
    script.error = lambda index: None
    await until(lambda: poller.available)
    assert poller_lines(caplog) == []  # nothing at INFO or above: the driver logs down and up
    debug = poller_lines(caplog, logging.DEBUG)
    assert debug.count("link p: unavailable: link p is down: closed") == 1, debug
    assert poller.last_error is lost  # kept after recovery, for diagnosis
    assert poller.availability_changes == 3  # available, unavailable, available


async def test_one_failed_block_of_a_round_leaves_the_data_available(
    script: Script, running: Poller, caplog: pytest.LogCaptureFixture
) -> None:
    poller = running
    script.error = lambda index: LinkTimeout("no valid answer") if index == 1 else None
    await rounds(script, 20)
    assert poller.available and isinstance(poller.last_error, LinkTimeout)
    assert poller.availability_changes == 1
    assert not [line for line in poller_lines(caplog, logging.DEBUG) if "unavailable" in line]


@pytest.mark.parametrize(
    "error",
    [ControllerRefused("controller refused read (;E: illegal in this mode)", command="read"),
     ProtocolError("read block: 4 data bytes in the reply, 2 expected")],
    ids=["refused", "protocol"],
)
async def test_a_controller_that_answers_without_data_is_warned_once_and_back_online_once(
    error: GatewayError, script: Script, running: Poller, caplog: pytest.LogCaptureFixture
) -> None:
    poller = running
    script.error = lambda index: error
    await until(lambda: not poller.available)
    reads = script.reads
    await until(lambda: script.reads >= reads + 30)  # many failed rounds (refusals: every 10 ms)
    script.error = lambda index: None
    await until(lambda: poller.available)
    lines = [line for line in poller_lines(caplog) if "unavailable" in line or "online" in line]
    assert lines == [f"link p: unavailable: {error} (the controller answers, but no block of the map could be read)",
                     "link p: back online"]


async def test_no_data_after_a_lost_link_is_warned_and_its_recovery_said(
    script: Script, running: Poller, caplog: pytest.LogCaptureFixture
) -> None:
    # The link drops (the driver's news), comes back, but the controller now refuses every read
    # (program mode after a power cycle): that the poller must say, once.
    poller = running
    script.error = lambda index: LinkDown("gone")
    await until(lambda: not poller.available)
    refused = ControllerRefused("controller refused read", command="read")
    script.error = lambda index: refused
    await until(lambda: poller.last_error is refused)
    await rounds(script, 10)
    script.error = lambda index: LinkDown("gone again")
    await rounds(script, 10)
    script.error = lambda index: None
    await until(lambda: poller.available)
    lines = poller_lines(caplog)
    assert [line.split(":")[1].strip() for line in lines if "unavailable" in line or "online" in line] == [
        "unavailable", "back online"], lines


async def test_one_message_per_change_with_the_real_driver(caplog: pytest.LogCaptureFixture) -> None:
    """A controller that goes silent and comes back: the driver's two lines, none of the poller's."""
    url = f"sim://slc150?ladder=0&instance={uuid.uuid4().hex}"
    sim = get_simulator(url)
    driver = SlcAsciiDriver(url, name="slc", timeout=0.01, retries=1, down_after_failures=3, down_after_seconds=60)
    caplog.set_level(logging.INFO)

    async def read(block: Block) -> bytes:
        address, count = cast(tuple[int, int], block.request)
        return await driver.read(address, count)

    reads = [Block((0x40 + 2 * i, 2), 2, Scan.FAST, f"word {i}") for i in range(3)]
    poller = Poller("slc", reads, BlockCache([2] * 3), read, fast_interval=0.005, down_wait=0.005,
                    stagger=0, responding=lambda: driver.available)
    async with asyncio.timeout(20), driver:
        task = asyncio.create_task(poller.run())
        try:
            await until(lambda: poller.available)
            sim.faults.drop = 1
            await until(lambda: not poller.available and not driver.available)
            errors = driver.counters.errors
            await until(lambda: driver.counters.errors >= errors + 5)  # more failed polls: no more lines
            sim.faults.drop = 0
            await until(lambda: poller.available and driver.available)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
    lines = [r.getMessage() for r in caplog.records if r.name in ("gateway.poller", "gateway.link")
             and r.levelno >= logging.INFO]
    assert [line.split(":")[1].strip() for line in lines] == ["up (sim", "down", "up (sim"], lines


@pytest.mark.looptime
async def test_stagger_delays_the_first_poll(script: Script) -> None:
    poller = Poller("p", blocks(1), BlockCache([2]), script, fast_interval=0.01, stagger=0.15)
    loop = asyncio.get_running_loop()
    start = loop.time()
    task = asyncio.create_task(poller.run())
    try:
        await until(lambda: script.reads > 0)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert loop.time() - start >= 0.15
    assert poller.stagger == 0.15


def test_the_default_stagger_spreads_links_over_the_fast_interval_the_same_on_every_start() -> None:
    names = [f"line {n}" for n in range(50)]
    delays = [default_stagger(name, 0.5) for name in names]
    assert delays == [default_stagger(name, 0.5) for name in names]  # deterministic
    assert all(0 <= d < 0.5 for d in delays) and len(set(delays)) == len(delays)
    assert min(delays) < 0.1 and max(delays) > 0.4  # spread over the interval
    assert all(default_stagger(name, 60.0) < MAX_STAGGER for name in names)  # the first data is not held
    assert default_stagger("a", 0.0) == 0.0  # polling continuously: nothing to spread
    poller = Poller("line 7", [], BlockCache([]), Script(), fast_interval=0.5)
    assert poller.stagger == default_stagger("line 7", 0.5)
