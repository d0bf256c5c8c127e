"""``gateway.image._strided_runs``: the runs the register images decode blocks with.

The image decodes a block with one slice copy per run of registers whose index and source bytes
advance evenly; a wrong run writes a register from the wrong byte.  Its contract (docstring):
the runs, expanded, are exactly the items, with positive steps; an even progression is one run.

Then the images themselves (``gateway.image.Images`` behind a ``BlockCache``) against a naive model
that decodes every point on its own: what SCADA reads must be the bytes the plan says.
"""

from __future__ import annotations

import random
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.cache import BlockCache
from gateway.image import ImageMiss, Images, _strided_runs
from gateway.modbus.mapping import BitPoint, Block, Codec, Plan, RegisterPoint, Scan, Table

Item = tuple[int, tuple[int, ...]]


def expand(runs: list[tuple[int, int, int, tuple[int, ...], int]]) -> list[Item]:
    out: list[Item] = []
    for first, step, n, src, src_step in runs:
        assert step > 0 and src_step > 0 and n >= 1
        out += [(first + k * step, tuple(s + k * src_step if s >= 0 else s for s in src)) for k in range(n)]
    return out


@st.composite
def items(draw: st.DrawFn) -> list[Item]:
    width = draw(st.integers(1, 2))
    indexes = sorted(draw(st.sets(st.integers(0, 60), min_size=1, max_size=25)))
    source = st.sampled_from([-1]) | st.integers(0, 120)
    return [(i, tuple(draw(source) for _ in range(width))) for i in indexes]


@given(items())
def test_the_runs_are_exactly_the_items(given_items: list[Item]) -> None:
    assert expand(_strided_runs(given_items)) == given_items


@given(first=st.integers(0, 20), step=st.integers(1, 5), n=st.integers(2, 20), src=st.integers(0, 50),
       src_step=st.integers(1, 4), msb_missing=st.booleans())
def test_an_even_progression_is_one_run(first: int, step: int, n: int, src: int, src_step: int,
                                        msb_missing: bool) -> None:
    progression = [(first + k * step, (-1 if msb_missing else src + 1 + k * src_step, src + k * src_step))
                   for k in range(n)]
    assert _strided_runs(progression) == [(first, step, n, progression[0][1], src_step)]


def test_a_progression_broken_by_a_step_or_a_missing_byte_starts_a_new_run() -> None:
    assert len(_strided_runs([(0, (0,)), (1, (2,)), (2, (4,)), (4, (6,))])) == 2  # index step changes
    assert len(_strided_runs([(0, (0, 1)), (1, (2, 3)), (2, (-1, 5))])) == 2  # MSB source disappears
    assert len(_strided_runs([(0, (5,)), (1, (4,))])) == 2  # sources go back: no negative steps
    assert len(_strided_runs([(0, (0, 1)), (1, (2, 4))])) == 2  # the two sources advance unevenly
    assert len(_strided_runs([(0, (-1, 0)), (1, (0, 1))])) == 2  # an MSB source appears, at byte 0
    assert len(_strided_runs([(0, (-1, 1)), (1, (1, 2))])) == 2  # an MSB source appears, at byte 1


# --- the images against a naive model of the layout ------------------------------------------
#
# What SCADA reads is a slice of an image; the layout computes once per plan which block bytes go
# to which image bytes (strided copies, bit runs, deadline stamps).  The model below decodes every
# point from its block's bytes on its own, one at a time, from the codec's definition
# (``gateway.modbus.mapping.Codec``), and says which address a read fails at.  The plans are drawn
# so that one block's points in a segment often advance evenly with steps other than 1 (points of
# blocks interleaved, bytes or bits skipped), which is what the strided copies and bit runs
# exist for.

REGISTER_TABLE_LIST = (Table.HOLDING, Table.INPUT)
BIT_TABLE_LIST = (Table.COIL, Table.DISCRETE)
AGES = (0.5, 1.0, 2.0)
TIMES = st.integers(0, 16).map(lambda k: k / 4)  # dyadic: every sum below is exact
LAST_ADDRESS = 90  # past the last address a plan maps
#: offset steps of a lane, in bytes and in bits: mostly the even ones a layout merges
REGISTER_STRIDES = st.sampled_from([2, 2, 1, 3, 4, 0])
BIT_STRIDES = st.sampled_from([1, 1, 1, 2, 3, 8, 9, 0])


def _codec_width(codec: Codec) -> int:
    return max(codec.lsb, -1 if codec.msb is None else codec.msb) + 1


@st.composite
def layout_plans(draw: st.DrawFn) -> Plan[None, None]:
    sizes = draw(st.lists(st.integers(1, 24), min_size=1, max_size=4))
    plan: Plan[None, None] = Plan(blocks=[Block(None, size, Scan.FAST) for size in sizes])
    codecs = [Codec(f"c{i}", draw(st.sampled_from([None, 0, 1, 2, 3])), draw(st.integers(0, 3)), draw(st.booleans()))
              for i in range(draw(st.integers(1, 3)))]
    for table in REGISTER_TABLE_LIST:
        points = plan.registers(table)
        for first in draw(st.lists(st.integers(0, 60), max_size=4, unique=True)):
            # the segment's points are dealt to 1..3 lanes in turn; each lane: one block, codec,
            # first offset and offset step (so a lane's points advance evenly, index step = lanes)
            lanes = [(draw(st.integers(0, len(sizes) - 1)), draw(st.sampled_from(codecs)), draw(st.integers(0, 8)),
                      draw(REGISTER_STRIDES), draw(st.booleans())) for _ in range(draw(st.integers(1, 3)))]
            for k in range(draw(st.integers(1, 12))):
                block, codec, start, stride, low_first = lanes[k % len(lanes)]
                offset = start + (k // len(lanes)) * stride
                if draw(st.integers(0, 9)) == 0:  # now and then a point of its own
                    block, codec, offset = (draw(st.integers(0, len(sizes) - 1)), draw(st.sampled_from(codecs)),
                                            draw(st.integers(0, 23)))
                room = sizes[block] - _codec_width(codec) + 1
                if room > 0:
                    points[first + k] = RegisterPoint(block, offset % room, codec, word_order_low_first=low_first)
    for table in BIT_TABLE_LIST:
        bit_points = plan.bits(table)
        for first in draw(st.lists(st.integers(0, 60), max_size=4, unique=True)):
            lanes_b = [(draw(st.integers(0, len(sizes) - 1)), draw(st.integers(0, 191)), draw(BIT_STRIDES))
                       for _ in range(draw(st.integers(1, 3)))]
            for k in range(draw(st.integers(1, 24))):
                block, start, stride = lanes_b[k % len(lanes_b)]
                position = start + (k // len(lanes_b)) * stride
                if draw(st.integers(0, 9)) == 0:
                    block, position = draw(st.integers(0, len(sizes) - 1)), draw(st.integers(0, 191))
                position %= 8 * sizes[block]
                bit_points[first + k] = BitPoint(block, position // 8, position % 8)
    return plan


class NaiveImages:
    """Every point decoded on its own from its block's bytes; a read fails at its first unmapped or stale address."""

    def __init__(self, plan: Plan[None, None], max_age: list[float]) -> None:
        self.plan = plan
        self.max_age = max_age
        self.data = [bytearray(b.size) for b in plan.blocks]
        self.stamps = [float("-inf")] * len(plan.blocks)

    def point(self, table: Table, address: int) -> RegisterPoint[None] | BitPoint[None] | None:
        points = self.plan.registers(table) if table in REGISTER_TABLE_LIST else self.plan.bits(table)
        return points.get(address)

    def value(self, table: Table, address: int) -> int:
        point = self.point(table, address)
        assert point is not None
        data = self.data[point.block]
        if isinstance(point, BitPoint):
            return data[point.offset] >> point.bit & 1
        codec = point.codec
        msb = 0 if codec.msb is None else data[point.offset + codec.msb] & (0x7F if codec.mask else 0xFF)
        return msb << 8 | data[point.offset + codec.lsb]

    def first_failure(self, table: Table, address: int, count: int, now: float) -> tuple[int, int | None] | None:
        for a in range(address, address + count):
            point = self.point(table, a)
            if point is None:
                return a, None
            if self.stamps[point.block] + self.max_age[point.block] < now:
                return a, point.block
        return None


@st.composite
def image_operations(draw: st.DrawFn, plan: Plan[None, None]) -> list[tuple[Any, ...]]:
    """Every block stored once (in a random order, at random times), then stores, patches and reads."""
    # random bytes, not drawn ones: hypothesis draws mostly zeros, which hide a bit in the wrong place
    noise = random.Random(draw(st.integers(0, 2**32)))
    blocks = list(range(len(plan.blocks)))
    ops: list[tuple[Any, ...]] = [("store", block, noise.randbytes(plan.blocks[block].size), draw(TIMES))
                                  for block in draw(st.permutations(blocks))]
    for _ in range(draw(st.integers(0, 8))):
        block = draw(st.sampled_from(blocks))
        size = plan.blocks[block].size
        kind = draw(st.sampled_from(["store", "patch", "read", "read"]))
        if kind == "store":
            ops.append(("store", block, noise.randbytes(size), draw(TIMES)))
        elif kind == "patch":
            offset = draw(st.integers(0, size - 1))
            ops.append(("patch", block, offset, noise.randbytes(draw(st.integers(1, size - offset)))))
        else:
            reads = []
            for _ in range(draw(st.integers(1, 6))):
                table = draw(st.sampled_from(Table))
                mapped = sorted(plan.registers(table) if table in REGISTER_TABLE_LIST else plan.bits(table))
                address = (max(0, draw(st.sampled_from(mapped)) - draw(st.integers(0, 1))) if mapped and draw(
                    st.integers(0, 3)) else draw(st.integers(0, LAST_ADDRESS)))
                reads.append((table, address, draw(st.integers(1, 14))))
            ops.append(("read", draw(TIMES), reads))
    return ops


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_slice_of_the_images_equals_the_points_decoded_one_by_one(data: st.DataObject) -> None:
    plan = data.draw(layout_plans())
    max_age = [data.draw(st.sampled_from(AGES)) for _ in plan.blocks]
    images = Images(plan, lambda block, read_at: read_at + max_age[block])
    cache = BlockCache([b.size for b in plan.blocks], images=images)
    model = NaiveImages(plan, max_age)
    for op in data.draw(image_operations(plan)):
        if op[0] == "store":
            _, block, raw, now = op
            cache.store(block, raw, now)
            model.data[block][:] = raw
            model.stamps[block] = now
        elif op[0] == "patch":
            _, block, offset, raw = op
            cache.patch(block, offset, raw)
            model.data[block][offset : offset + len(raw)] = raw
        else:
            _, now, reads = op
            for table, address, count in reads:
                assert images.mapped(table, address, count) == all(
                    model.point(table, a) is not None for a in range(address, address + count))
                failure = model.first_failure(table, address, count, now)
                read = images.registers if table in REGISTER_TABLE_LIST else images.bits
                if failure is not None:
                    with pytest.raises(ImageMiss) as miss:
                        read(table, address, count, now)
                    assert (miss.value.address, miss.value.block) == failure
                    assert miss.value.args == failure  # what its traceback shows, should it ever escape
                    continue
                values = [model.value(table, a) for a in range(address, address + count)]
                if table in REGISTER_TABLE_LIST:
                    assert read(table, address, count, now) == b"".join(v.to_bytes(2, "big") for v in values)
                else:
                    packed = sum(v << k for k, v in enumerate(values))
                    assert read(table, address, count, now) == packed.to_bytes((count + 7) // 8, "little")
    # at the end, every address as last stored, fresh or not (the status page's view)
    for table in Table:
        for address in range(LAST_ADDRESS + 1):
            point = model.point(table, address)
            expected = None if point is None else (model.value(table, address), point.block)
            assert images.peek(table, address) == expected, (table, address)


def test_a_read_fails_at_its_first_stale_point_not_at_one_exactly_at_its_deadline() -> None:
    """A point is fresh up to and at its deadline: a read whose first point is exactly at its
    deadline and whose second is past its own fails at the second, naming the second's block."""
    plan: Plan[None, None] = Plan(blocks=[Block(None, 2, Scan.FAST), Block(None, 2, Scan.FAST)])
    plan.holding[10] = RegisterPoint(0, 0, Codec("u16", 0, 1))
    plan.holding[11] = RegisterPoint(1, 0, Codec("u16", 0, 1))
    images = Images(plan, lambda block, read_at: read_at + 1.0)
    cache = BlockCache([2, 2], images=images)
    cache.store(0, b"\x12\x34", 5.0)  # deadline 6.0
    cache.store(1, b"\x56\x78", 4.5)  # deadline 5.5
    assert images.registers(Table.HOLDING, 10, 1, 6.0) == b"\x12\x34"
    with pytest.raises(ImageMiss) as miss:
        images.registers(Table.HOLDING, 10, 2, 6.0)
    assert (miss.value.address, miss.value.block) == (11, 1)


def test_a_point_whose_block_was_never_stored_peeks_as_the_caches_zero_bytes() -> None:
    """The images begin as the decoding of the cache's initial data (zero bytes), so the status
    page's view of a point never read is its codec's value of zeros, registers and bits alike,
    also beside a point of another block that was stored."""
    plan: Plan[None, None] = Plan(blocks=[Block(None, 2, Scan.FAST), Block(None, 2, Scan.FAST)])
    plan.holding[10] = RegisterPoint(0, 0, Codec("u16", 0, 1))
    plan.holding[11] = RegisterPoint(1, 0, Codec("u16", 0, 1))
    plan.coils[20] = BitPoint(0, 0, 0)
    plan.coils[21] = BitPoint(1, 0, 0)
    images = Images(plan, lambda block, read_at: read_at + 1.0)
    cache = BlockCache([2, 2], images=images)
    cache.store(1, b"\xff\xff", 5.0)
    assert [images.peek(Table.HOLDING, a) for a in (10, 11)] == [(0, 0), (0xFFFF, 1)]
    assert [images.peek(Table.COIL, a) for a in (20, 21)] == [(0, 0), (1, 1)]


def test_the_layout_is_computed_once_per_plan_and_shared_by_its_images() -> None:
    """Decode once: every ``Images`` of one plan (one per unit that serves it) uses the same
    layout, computed for the first; an equal plan that is another object gets its own."""
    def plan() -> Plan[None, None]:
        made: Plan[None, None] = Plan(blocks=[Block(None, 4, Scan.FAST)])
        made.holding[0] = RegisterPoint(0, 0, Codec("u16", 0, 1))
        made.coils[5] = BitPoint(0, 2, 3)
        return made

    first, other = plan(), plan()
    a, b, c = (Images(first, lambda _, t: t + 1.0), Images(first, lambda _, t: t + 2.0),
               Images(other, lambda _, t: t + 1.0))
    assert a._copies is b._copies and a._bit_runs is b._bit_runs and a._stamps is b._stamps
    assert a._copies is not c._copies and a._copies == c._copies
