"""The block cache (``gateway/cache.py``): bytes and read times of a read plan's blocks."""

from __future__ import annotations

import math

import pytest

from gateway.cache import BlockCache


def test_a_block_never_read_is_infinitely_old_and_zeroed() -> None:
    cache = BlockCache([2, 4])
    assert cache.data == [bytearray(2), bytearray(4)]
    assert math.isinf(cache.age(0, 5.0)) and cache.age(0, 5.0) > 0
    assert cache.newest == -math.inf


def test_store_keeps_bytes_and_read_time_and_patch_keeps_the_read_time() -> None:
    cache = BlockCache([2, 4])
    cache.store(1, b"\x01\x02\x03\x04", 10.0)
    assert cache.data[1] == bytearray(b"\x01\x02\x03\x04")
    assert cache.age(1, 12.5) == 2.5 and cache.newest == 10.0
    cache.patch(1, 2, b"\xaa")
    assert cache.data[1] == bytearray(b"\x01\x02\xaa\x04")
    assert cache.age(1, 12.5) == 2.5  # a write never makes the block look fresher
    with pytest.raises(ValueError, match="3 bytes read, 4 expected"):
        cache.store(1, b"\x00\x00\x00", 11.0)
    assert cache.data[1] == bytearray(b"\x01\x02\xaa\x04")


def test_oldest_age_of_some_blocks() -> None:
    cache = BlockCache([1, 1, 1])
    assert cache.oldest_age([], 3.0) == 0.0
    cache.store(0, b"\x00", 1.0)
    cache.store(1, b"\x00", 2.0)
    assert cache.oldest_age([0, 1], 5.0) == 4.0
    assert cache.oldest_age([1], 5.0) == 3.0
    assert math.isinf(cache.oldest_age([1, 2], 5.0))


def test_oldest_fast_age_follows_the_least_recently_read_fast_block() -> None:
    cache = BlockCache([1, 1, 1, 1], fast=[0, 2, 3])
    assert BlockCache([1]).oldest_fast_age(9.0) == 0.0  # no fast blocks
    assert math.isinf(cache.oldest_fast_age(1.0))  # never read
    for block, t in [(0, 1.0), (2, 2.0), (3, 3.0)]:
        cache.store(block, b"\x00", t)
    assert cache.oldest_fast_age(10.0) == 9.0  # block 0
    cache.store(0, b"\x00", 4.0)
    assert cache.oldest_fast_age(10.0) == 8.0  # block 2
    cache.store(1, b"\x00", 0.5)  # not a fast block: no effect
    assert cache.oldest_fast_age(10.0) == 8.0
    # a store that goes back in time (a read whose time was taken before another's)
    cache.store(2, b"\x00", 3.5)
    cache.store(3, b"\x00", 2.5)
    assert cache.oldest_fast_age(10.0) == 7.5  # block 3, though stored last
    cache.store(3, b"\x00", 5.0)
    assert cache.oldest_fast_age(10.0) == 6.5  # block 2
    assert cache.newest == 5.0


def test_listeners_hear_every_store_and_patch_after_the_bytes_changed() -> None:
    cache = BlockCache([2, 2])
    heard: list[tuple[int, float | None, bytes]] = []
    cache.listeners.append(lambda block, now: heard.append((block, now, bytes(cache.data[block]))))
    cache.store(1, b"\x01\x02", 5.0)
    cache.patch(1, 0, b"\x09")
    cache.store(0, b"\x03\x04", 6.0)
    assert heard == [(1, 5.0, b"\x01\x02"), (1, None, b"\x09\x02"), (0, 6.0, b"\x03\x04")]
