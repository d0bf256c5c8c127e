"""A SLC 100/150 unit over the simulator whose blocks hold given bytes, read just now (no line traffic)."""

from __future__ import annotations

import asyncio

from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.plan import byte_read
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit


def unit_with(image: dict[int, int]) -> SlcAsciiUnit:
    """A unit whose every block was just read; the bytes of ``image`` (address -> value), others 0."""
    unit = SlcAsciiUnit(driver=SlcAsciiDriver("sim://slc150?ladder=0"), unit_id=1, name="slc", stale_after=60.0)
    now = asyncio.get_running_loop().time()
    for index, block in enumerate(unit.plan.blocks):
        start, count = byte_read(block)
        unit.cache.store(index, bytes(image.get(start + k, 0) for k in range(count)), now)
    return unit
