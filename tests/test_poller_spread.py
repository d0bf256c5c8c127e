"""The poller reads the slow class whole at start, then spreads its periodic scans over fast rounds."""

from __future__ import annotations

import asyncio

from gateway.cache import BlockCache
from gateway.modbus.mapping import Block, Scan
from gateway.poller import Poller


async def test_periodic_slow_scans_are_spread_over_the_fast_rounds() -> None:
    blocks = [Block(("f", n), 1, Scan.FAST, f"f{n}") for n in range(2)]
    blocks += [Block(("s", n), 1, Scan.SLOW, f"s{n}") for n in range(4)]
    reads: list[str] = []

    async def read(block: Block) -> bytes:
        reads.append(block.label)
        return b"\0"

    poller = Poller("p", blocks, BlockCache([1] * len(blocks)), read, fast_interval=0.05, slow_interval=0.2)
    task = asyncio.create_task(poller.run())
    await asyncio.sleep(0.6)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert reads[:6] == ["s0", "s1", "s2", "s3", "f0", "f1"]  # the whole slow class first
    rounds: list[list[str]] = []
    for label in reads[6:]:
        if label == "f0" or not rounds:
            rounds.append([])
        rounds[-1].append(label)
    slow_per_round = [sum(label.startswith("s") for label in r) for r in rounds]
    # spread over half the slow interval: ceil(4 blocks x 0.05 s / 0.1 s) = 2 slow blocks before
    # a fast round, never 4 at once
    assert max(slow_per_round) == 2, rounds
    assert sum(slow_per_round) >= 4, rounds  # a periodic slow scan did complete
