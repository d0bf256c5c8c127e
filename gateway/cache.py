"""The memory image of one controller: the raw bytes of each read block and when it was read.

A block that fails to read keeps its last bytes and ages; readers decide from the age whether
a value is fresh enough to serve.  A confirmed write patches the bytes it changed (the time
stays the time of the last read, so a write never makes stale data look fresh).
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["BlockCache"]

NEVER = float("-inf")


class BlockCache:
    """Bytes and read times of the blocks of a read plan, by block index."""

    __slots__ = ("data", "newest", "stamps")

    def __init__(self, sizes: Sequence[int]) -> None:
        self.data = [bytearray(size) for size in sizes]
        #: loop time of the last successful read of each block; NEVER before the first
        self.stamps = [NEVER] * len(sizes)
        #: loop time of the last successful read of any block (the controller last answered)
        self.newest = NEVER

    def store(self, block: int, data: bytes, now: float) -> None:
        target = self.data[block]
        if len(data) != len(target):
            raise ValueError(f"block {block}: {len(data)} bytes read, {len(target)} expected")
        target[:] = data
        self.stamps[block] = now
        self.newest = max(self.newest, now)

    def patch(self, block: int, offset: int, data: bytes) -> None:
        """Apply a write the controller confirmed."""
        self.data[block][offset : offset + len(data)] = data

    def age(self, block: int, now: float) -> float:
        return now - self.stamps[block]

    def oldest_age(self, blocks: Sequence[int], now: float) -> float:
        if not blocks:
            return 0.0
        return now - min(self.stamps[i] for i in blocks)
