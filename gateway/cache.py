"""The memory image of one controller: the raw bytes of each read block and when it was read.

A block that fails to read keeps its last bytes and ages; readers decide from the age whether
a value is fresh enough to serve.  A confirmed write patches the bytes it changed (the time
stays the time of the last read, so a write never makes stale data look fresh).

With ``images`` (:class:`gateway.image.Images`), every stored block is also decoded at once into
the Modbus tables' images and its points' deadlines are set; a patch re-decodes the block into
the images and leaves the deadlines alone.  The raw bytes stay for what needs them (writes that
patch one byte of a block, traces).

Listeners (``listeners``: ``f(block, now)``) hear of every store (``now``: its read time) and
every patch (``now`` None), after the images are updated: the Sparkplug edge node publishes
from them.

The oldest read time of the ``fast`` blocks (the status block's data age) is kept as blocks are
stored: the fast blocks are held in the order of their last store, so the oldest is the first.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from gateway.schedule import NEVER

if TYPE_CHECKING:
    from gateway.image import Images

__all__ = ["BlockCache"]


class BlockCache:
    """Bytes and read times of the blocks of a read plan, by block index."""

    __slots__ = ("_fast_order", "_fast_sorted", "data", "images", "listeners", "newest", "stamps")

    def __init__(self, sizes: Sequence[int], *, images: Images | None = None, fast: Sequence[int] = ()) -> None:
        self.data = [bytearray(size) for size in sizes]
        #: loop time of the last successful read of each block; NEVER before the first
        self.stamps = [NEVER] * len(sizes)
        #: loop time of the last successful read of any block (the controller last answered)
        self.newest = NEVER
        self.images = images
        #: the fast blocks, least recently stored first (a dict keeps insertion order)
        self._fast_order: dict[int, None] = dict.fromkeys(fast)
        #: False after a store that went back in time (then the order is rebuilt when asked)
        self._fast_sorted = True
        #: called after each store (block, read time) and patch (block, None)
        self.listeners: list[Callable[[int, float | None], None]] = []

    def store(self, block: int, data: bytes, now: float) -> None:
        target = self.data[block]
        if len(data) != len(target):
            raise ValueError(f"block {block}: {len(data)} bytes read, {len(target)} expected")
        target[:] = data
        order = self._fast_order
        if block in order:
            if now < self.newest:
                self._fast_sorted = False
            del order[block]
            order[block] = None
        self.stamps[block] = now
        self.newest = max(self.newest, now)
        images = self.images
        if images is not None:
            images.decode(block, target)
            images.stamp(block, now)
        for listener in self.listeners:
            listener(block, now)

    def patch(self, block: int, offset: int, data: bytes) -> None:
        """Apply a write the controller confirmed (the block's read time is kept)."""
        target = self.data[block]
        target[offset : offset + len(data)] = data
        if self.images is not None:
            self.images.decode(block, target)
        for listener in self.listeners:
            listener(block, None)

    def expire_before(self, when: float) -> None:
        """Serve no value read before ``when`` (a link loss): each stays stale until its block is read
        again.  The bytes and read times stay (the status page shows the last value, and its age)."""
        images = self.images
        if images is None:
            return
        for block, stamp in enumerate(self.stamps):
            if stamp < when:
                images.expire(block)

    def age(self, block: int, now: float) -> float:
        return now - self.stamps[block]

    def oldest_age(self, blocks: Sequence[int], now: float) -> float:
        if not blocks:
            return 0.0
        return now - min(self.stamps[i] for i in blocks)

    def oldest_fast_age(self, now: float) -> float:
        """Age of the least recently read ``fast`` block (0.0 without fast blocks), in O(1)."""
        order = self._fast_order
        if not order:
            return 0.0
        if not self._fast_sorted:
            stamps = self.stamps
            self._fast_order = order = dict.fromkeys(sorted(order, key=stamps.__getitem__))
            self._fast_sorted = True
        return now - self.stamps[next(iter(order))]
