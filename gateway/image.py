"""The Modbus tables of one unit as images, decoded when a block is stored: a read is a slice.

Each table is kept per *segment* (a maximal run of consecutive mapped addresses; a read that
leaves its segment meets an unmapped address):

* register tables: the big-endian bytes of every register, exactly as a FC3/FC4 reply carries
  them (codecs are applied once, when the block arrives: masked presets, little-endian PCCC
  words, the halves of a float, single bytes);
* bit tables: one Python int whose bit ``k`` is the segment's ``k``-th point, so a FC1/FC2
  reply is a shift, a mask and ``to_bytes(..., "little")``;
* beside each image, per point, its *deadline*: the time after which its block's value is
  stale, as the one verdict gives it (``gateway.freshness``: the read time plus the largest age
  at which that block is served).  A read is fresh when ``min(deadlines[i:j])`` is not
  before ``now`` (one C loop, no Python loop per register); only on a miss does a Python loop
  look for the first stale point, to answer with that point's block.

What goes where (the *layout*) is computed once per plan and shared by the units of that plan:
per block, *strided copies* (``image[a:b:s] =
data[c:d:t]``) that cover its registers in as few operations as the map allows, and *bit
runs* that move many bits with one shift.  A confirmed write patches the block's raw bytes and
re-decodes that block into the images; the deadlines are untouched, so a write never makes
stale data look fresh (``BlockCache.patch``).

Generic: knows blocks, points and codecs, no protocol.
"""

from __future__ import annotations

import weakref
from array import array
from bisect import bisect_right
from collections.abc import Callable, Sequence
from typing import Any

from gateway.frozen import frozen
from gateway.modbus.mapping import BitPoint, Plan, RegisterPoint, Table
from gateway.schedule import NEVER

__all__ = ["BIT_TABLES", "REGISTER_TABLES", "ImageMiss", "Images"]

REGISTER_TABLES = (Table.HOLDING, Table.INPUT)
BIT_TABLES = (Table.COIL, Table.DISCRETE)

#: bytes.translate table clearing bit 7 of a register's MSB (a codec's ``mask``)
_MASK_7F = bytes(b & 0x7F for b in range(256))


class ImageMiss(Exception):
    """A read cannot be served: ``address`` is unmapped (``block`` None) or its block is stale."""

    def __init__(self, address: int, block: int | None) -> None:
        super().__init__(address, block)
        self.address = address
        self.block = block


class _Segment:
    """Consecutive mapped addresses ``first``..``last`` of one table, in one unit."""

    __slots__ = ("bits", "blocks", "deadlines", "first", "image", "last")

    def __init__(self, first: int, last: int, registers: bool, blocks: array[int]) -> None:
        n = last - first + 1
        self.first = first
        self.last = last
        #: registers: 2 bytes per address, big-endian (bit tables: empty)
        self.image = bytearray(2 * n if registers else 0)
        #: bit tables: bit k = address first + k
        self.bits = 0
        #: per address: the time after which its value is stale
        self.deadlines: list[float] = [NEVER] * n
        #: per address: its block (to name the block of a stale read; shared by units of one plan)
        self.blocks = blocks


@frozen
class _Copy:
    """Registers at image bytes ``hi`` (MSB) and ``hi + 1`` (LSB), every ``step`` bytes, ``n`` of them.

    Their MSBs come from block bytes ``src_hi`` (every ``src_step``; -1: always 0), their LSBs
    from ``src_lo``; ``mask``: the MSBs pass through ``_MASK_7F``.  ``segment``: index in the
    unit's segments.
    """

    segment: int
    hi: int
    step: int
    n: int
    src_hi: int
    src_lo: int
    src_step: int
    mask: bool

    def apply(self, data: bytes | bytearray, segments: list[_Segment]) -> None:
        image = segments[self.segment].image
        n, step, src_step = self.n, self.step, self.src_step
        span, src_span = step * (n - 1) + 1, src_step * (n - 1) + 1
        if self.src_hi >= 0:
            msb = data[self.src_hi : self.src_hi + src_span : src_step]
            if self.mask:
                msb = msb.translate(_MASK_7F)
            image[self.hi : self.hi + span : step] = msb
        lo = self.hi + 1
        image[lo : lo + span : step] = data[self.src_lo : self.src_lo + src_span : src_step]


@frozen
class _BitRun:
    """``n`` bits of a block from bit ``shift`` (of the block as a little-endian int) to segment bit ``at``."""

    segment: int
    shift: int
    at: int
    mask: int  # (1 << n) - 1
    keep: int  # ~(mask << at)


@frozen
class _Stamp:
    """Points ``first``, ``first + step`` ... (``n`` of them) of a segment's deadlines."""

    segment: int
    first: int
    step: int
    n: int


def _register_bytes(point: RegisterPoint[Any]) -> tuple[int, int, bool]:
    """(MSB source or -1, LSB source, mask) of a register in its block, from its codec."""
    o = point.offset
    codec = point.codec
    return (-1 if codec.msb is None else o + codec.msb), o + codec.lsb, codec.mask


def _strided_runs(items: Sequence[tuple[int, tuple[int, ...]]]) -> list[tuple[int, int, int, tuple[int, ...], int]]:
    """Group (index, sources) sorted by index into runs where index and every source advance evenly.

    Returns (first index, index step, n, first sources, source step); steps are positive.
    """
    runs: list[tuple[int, int, int, tuple[int, ...], int]] = []
    for index, sources in items:
        if runs:
            first, step, n, src, src_step = runs[-1]
            last_index = first + step * (n - 1)
            last_src = tuple(s + src_step * (n - 1) if s >= 0 else s for s in src)
            d_index = index - last_index
            deltas = {s - ls for s, ls in zip(sources, last_src, strict=True) if s >= 0 or ls >= 0}
            negative_match = all((s < 0) == (ls < 0) for s, ls in zip(sources, last_src, strict=True))
            if negative_match and len(deltas) == 1:
                d_src = deltas.pop()
                if n == 1 and d_index > 0 and d_src > 0:
                    runs[-1] = (first, d_index, 2, src, d_src)
                    continue
                if n > 1 and d_index == step and d_src == src_step:
                    runs[-1] = (first, step, n + 1, src, src_step)
                    continue
        runs.append((index, 1, 1, sources, 1))
    return runs


class _Layout:
    """What goes where, per plan (shared by every unit of that plan): segments and per-block recipes."""

    __slots__ = ("bit_runs", "blocks_of", "bounds", "copies", "stamps", "tables")

    def __init__(self, plan: Plan[Any, Any]) -> None:
        #: per table: (first addresses of its segments, index of its first segment)
        self.tables: dict[Table, tuple[list[int], int]] = {}
        #: per segment: first, last, is a register segment
        self.bounds: list[tuple[int, int, bool]] = []
        #: per segment: the block of each of its points
        self.blocks_of: list[array[int]] = []
        n_blocks = len(plan.blocks)
        copies: list[list[_Copy]] = [[] for _ in range(n_blocks)]
        bit_runs: list[list[_BitRun]] = [[] for _ in range(n_blocks)]
        stamps: list[list[_Stamp]] = [[] for _ in range(n_blocks)]
        for table in REGISTER_TABLES + BIT_TABLES:
            registers = table in REGISTER_TABLES
            points: dict[int, RegisterPoint[Any]] | dict[int, BitPoint[Any]] = (
                plan.registers(table) if registers else plan.bits(table)
            )
            ranges = plan.ranges(table)
            self.tables[table] = ([first for first, _ in ranges], len(self.bounds))
            for first, last in ranges:
                segment = len(self.bounds)
                self.bounds.append((first, last, registers))
                self.blocks_of.append(array("I", [points[a].block for a in range(first, last + 1)]))
                groups: dict[tuple[int, object], list[int]] = {}
                for a in range(first, last + 1):
                    point = points[a]
                    key = (point.codec, point.word_order_low_first) if isinstance(point, RegisterPoint) else None
                    groups.setdefault((point.block, key), []).append(a)
                for (block, _), addresses in groups.items():
                    if registers:
                        copies[block].extend(self._copies(segment, first, addresses, plan.holding
                                                          if table is Table.HOLDING else plan.input))
                    else:
                        bit_runs[block].extend(self._bit_runs(segment, first, addresses, plan.bits(table)))
                    for k, step, n, _, _ in _strided_runs([(a - first, (a - first,)) for a in addresses]):
                        stamps[block].append(_Stamp(segment, k, step, n))
        self.copies = [tuple(c) for c in copies]
        self.bit_runs = [tuple(r) for r in bit_runs]
        self.stamps = [tuple(s) for s in stamps]

    @staticmethod
    def _copies(segment: int, first: int, addresses: list[int], points: dict[int, RegisterPoint[Any]]) -> list[_Copy]:
        items: list[tuple[int, tuple[int, ...]]] = []
        masks = set()
        for a in addresses:
            src_hi, src_lo, mask = _register_bytes(points[a])
            masks.add(mask)
            items.append((a - first, (src_hi, src_lo)))
        (mask,) = masks  # one codec per group
        return [
            _Copy(segment, 2 * k, 2 * step, n, src_hi, src_lo, src_step, mask)
            for k, step, n, (src_hi, src_lo), src_step in _strided_runs(items)
        ]

    @staticmethod
    def _bit_runs(segment: int, first: int, addresses: list[int], points: dict[int, BitPoint[Any]]) -> list[_BitRun]:
        runs: list[_BitRun] = []
        items = [(a - first, (8 * points[a].offset + points[a].bit,)) for a in addresses]
        for k, step, n, (shift,), src_step in _strided_runs(items):
            if step == 1 and src_step == 1:
                mask = (1 << n) - 1
                runs.append(_BitRun(segment, shift, k, mask, ~(mask << k)))
            else:
                for m in range(n):
                    at = k + m * step
                    runs.append(_BitRun(segment, shift + m * src_step, at, 1, ~(1 << at)))
        return runs


#: layouts by id(plan), dropped with their plan
_LAYOUTS: dict[int, _Layout] = {}


def _layout(plan: Plan[Any, Any]) -> _Layout:
    layout = _LAYOUTS.get(id(plan))
    if layout is None:
        layout = _LAYOUTS[id(plan)] = _Layout(plan)
        weakref.finalize(plan, _LAYOUTS.pop, id(plan), None)
    return layout


class Images:
    """The four tables of a plan as images with per-point deadlines (module docstring).

    The layout (what goes where) is computed once per plan and shared by the units of that plan.
    """

    __slots__ = ("_bit_runs", "_copies", "_deadline", "_stamps", "_tables", "block_deadline", "segments")

    def __init__(self, plan: Plan[Any, Any], deadline: Callable[[int, float], float]) -> None:
        layout = _layout(plan)
        #: (block, read time) -> the time its value is stale after (``gateway.freshness.Freshness.deadline``)
        self._deadline = deadline
        #: per block: the deadline stamped on its points (NEVER: never read, or expired)
        self.block_deadline = [NEVER] * len(plan.blocks)
        self._copies = layout.copies
        self._bit_runs = layout.bit_runs
        self._stamps = layout.stamps
        self.segments = [
            _Segment(first, last, registers, blocks)
            for (first, last, registers), blocks in zip(layout.bounds, layout.blocks_of, strict=True)
        ]
        self._tables = layout.tables

    # --- stores -------------------------------------------------------------------------

    def decode(self, block: int, data: bytes | bytearray) -> None:
        """Write the values of ``block`` (its raw bytes ``data``) into the images."""
        segments = self.segments
        for copy in self._copies[block]:
            copy.apply(data, segments)
        runs = self._bit_runs[block]
        if runs:
            value = int.from_bytes(data, "little")
            for run in runs:
                segment = segments[run.segment]
                segment.bits = (segment.bits & run.keep) | (((value >> run.shift) & run.mask) << run.at)

    def stamp(self, block: int, now: float) -> None:
        """The points of ``block`` were read at ``now``: fresh until the deadline the verdict gives."""
        deadline = self.block_deadline[block] = self._deadline(block, now)
        segments = self.segments
        for s in self._stamps[block]:
            deadlines = segments[s.segment].deadlines
            if s.n == 1:
                deadlines[s.first] = deadline
            else:
                deadlines[s.first : s.first + s.step * (s.n - 1) + 1 : s.step] = [deadline] * s.n

    def expire(self, block: int) -> None:
        """The points of ``block`` are stale until it is stored again."""
        self.block_deadline[block] = NEVER
        segments = self.segments
        for s in self._stamps[block]:
            deadlines = segments[s.segment].deadlines
            deadlines[s.first : s.first + s.step * (s.n - 1) + 1 : s.step] = [NEVER] * s.n

    def blocks_in(self, table: Table, address: int, count: int) -> tuple[int, ...]:
        """The blocks holding the mapped addresses of ``address``.. (``count``), in address order,
        each once (what a read of them makes demanded)."""
        segment = self._find(table, address)
        if segment is None:
            return ()
        i = address - segment.first
        j = min(address + count - 1, segment.last) - segment.first + 1
        return tuple(dict.fromkeys(segment.blocks[i:j]))

    def stale_blocks(self, table: Table, address: int, count: int, now: float) -> tuple[int, ...]:
        """The blocks of ``address``.. (``count``) whose points are stale at ``now``, each once."""
        segment = self._find(table, address)
        if segment is None:
            return ()
        i = address - segment.first
        j = min(address + count - 1, segment.last) - segment.first + 1
        deadlines, blocks = segment.deadlines, segment.blocks
        return tuple(dict.fromkeys(blocks[k] for k in range(i, j) if deadlines[k] < now))

    # --- reads --------------------------------------------------------------------------

    def _find(self, table: Table, address: int) -> _Segment | None:
        firsts, base = self._tables[table]
        i = bisect_right(firsts, address) - 1
        if i < 0:
            return None
        segment = self.segments[base + i]
        return segment if address <= segment.last else None

    def mapped(self, table: Table, address: int, count: int) -> bool:
        segment = self._find(table, address)
        return segment is not None and address + count - 1 <= segment.last

    def peek(self, table: Table, address: int) -> tuple[int, int] | None:
        """``(value, block)`` of one mapped address as last stored, fresh or not; None if unmapped.

        For diagnostics (the status page shows a stale value marked stale); reads use :meth:`registers`
        and :meth:`bits`, which check freshness.
        """
        segment = self._find(table, address)
        if segment is None:
            return None
        i = address - segment.first
        if segment.image:
            value = segment.image[2 * i] << 8 | segment.image[2 * i + 1]
        else:
            value = segment.bits >> i & 1
        return value, segment.blocks[i]

    def _segment(self, table: Table, address: int, count: int, now: float) -> tuple[_Segment, int, int]:
        segment = self._find(table, address)
        if segment is None:
            raise ImageMiss(address, None)
        i = address - segment.first
        j = min(address + count - 1, segment.last) - segment.first + 1
        deadlines = segment.deadlines
        if min(deadlines[i:j]) < now:
            for k in range(i, j):
                if deadlines[k] < now:
                    raise ImageMiss(segment.first + k, segment.blocks[k])
        if j - i < count:
            raise ImageMiss(segment.last + 1, None)
        return segment, i, j

    def registers(self, table: Table, address: int, count: int, now: float) -> bytes:
        """The big-endian bytes of registers ``address``.. (``count``); ImageMiss at the first failing one."""
        segment, i, j = self._segment(table, address, count, now)
        return bytes(segment.image[2 * i : 2 * j])

    def bits(self, table: Table, address: int, count: int, now: float) -> bytes:
        """Bits ``address``.. packed LSB first, as a FC1/FC2 reply; ImageMiss at the first failing one."""
        segment, i, _ = self._segment(table, address, count, now)
        return ((segment.bits >> i) & ((1 << count) - 1)).to_bytes((count + 7) // 8, "little")

    def held(self, table: Table, address: int, count: int, now: float | None) -> bytes:
        """As :meth:`registers` or :meth:`bits` whatever the freshness (a link's ``offline`` policy):
        the values last stored; with ``now``, every point stale at ``now`` as 0.  The range must be
        mapped (ImageMiss at the first unmapped address)."""
        segment = self._find(table, address)
        if segment is None:
            raise ImageMiss(address, None)
        i = address - segment.first
        if address + count - 1 > segment.last:
            raise ImageMiss(segment.last + 1, None)
        deadlines = segment.deadlines
        stale = [] if now is None else [k for k in range(count) if deadlines[i + k] < now]
        if table in REGISTER_TABLES:
            data = bytearray(segment.image[2 * i : 2 * (i + count)])
            for k in stale:
                data[2 * k : 2 * k + 2] = b"\0\0"
            return bytes(data)
        bits = (segment.bits >> i) & ((1 << count) - 1)
        for k in stale:
            bits &= ~(1 << k)
        return bits.to_bytes((count + 7) // 8, "little")
