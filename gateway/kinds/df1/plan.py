"""DF1 / SLC 500 map entries -> Modbus points and an optimal read plan.  Pure: no I/O.

A map entry (``table``, ``start``, ``address``, ``count``, ``type``, ``word_order``, ``scan``)
is expanded into points: one register per word (``int16``/``uint16``), two per float
(``float32``, F files), one bit per coil/discrete input.  Structured elements (``T4:0.ACC``,
``C5:2/DN``) step through consecutive elements; bit addresses in word files (``B3:0/0``)
step through consecutive bits; I/O words (``I:1.0``) step through the words of the slot.

**Read plan.** Per data file (per slot for I/O) the needed words are covered with reads of
whole elements, each within the processor's read size limit, choosing the blocks that put
the fewest bytes on the wire: dynamic programming over the sorted word positions, with a
block's cost = fixed transaction overhead + 2 bytes per word read (gaps included).  That is
the optimum for this cost model; merging neighbours and splitting long runs both fall out.
"""

from __future__ import annotations

import functools
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import TypeAlias

from gateway.frozen import frozen
from gateway.modbus.mapping import (
    BitPoint,
    BitWrite,
    Block,
    Codec,
    Half,
    Plan,
    PointLabel,
    RegisterPoint,
    Scan,
    Table,
    WordWrite,
)
from gateway.protocols.df1.address import STRUCTURE_FILE_TYPES, FileType, SlcAddress, element_words, parse_address
from gateway.protocols.df1.plc5_address import Plc5Address

__all__ = [
    "F32_HIGH",
    "F32_LOW",
    "READ_OVERHEAD_BYTES",
    "U16_LE",
    "Df1BitWrite",
    "Df1Plan",
    "Df1Read",
    "Df1WordWrite",
    "MapItem",
    "Plc5BitWrite",
    "Plc5WordWrite",
    "block_cost",
    "optimal_blocks",
    "plan_df1",
    "point_labels_df1",
    "shared_plan_df1",
]

#: Bytes on the wire of one protected typed logical read besides its data: command frame
#: (DLE STX, 6 header, FNC, size, file, type, element, sub-element, DLE ETX, CRC = 18), its
#: DLE ACK (2), the reply frame's framing and header (2 + 6 + 2 + 2 = 12) and our DLE ACK (2).
READ_OVERHEAD_BYTES = 34

#: A PCCC word: little-endian (int16 is the same bits).
U16_LE = Codec("u16le", 1, 0)
#: A PCCC float is 4 bytes little-endian b0 b1 b2 b3: its high half is b3 b2, its low half b1 b0.
F32_HIGH = Codec("f32-high", 3, 2, half=Half.HIGH)
F32_LOW = Codec("f32-low", 1, 0, half=Half.LOW)

_IO = (FileType.INPUT, FileType.OUTPUT)


@frozen
class Df1Read:
    """A protected typed logical read of ``size`` bytes."""

    file_type: int
    file_number: int
    element: int
    sub_element: int
    size: int


@frozen
class MapItem:
    """One ``[[link.map]]`` entry, as the planner needs it."""

    table: str  # holding | input | coil | discrete
    start: int
    address: str
    count: int
    type: str = "int16"  # int16 | uint16 | float32 | bool
    word_order: str = "high-first"
    scan: str = "fast"


#: The write targets of an SLC 500: a typed logical write of the word (or the float) at the
#: address for a holding register, a masked write of the word for a coil (``gateway.kinds.df1.unit``).
Df1WordWrite: TypeAlias = WordWrite[SlcAddress]
Df1BitWrite: TypeAlias = BitWrite[SlcAddress]
#: The write targets of a PLC-5: a word range write, a read-modify-write (``gateway.kinds.df1.plc5_unit``).
Plc5WordWrite: TypeAlias = WordWrite[Plc5Address]
Plc5BitWrite: TypeAlias = BitWrite[Plc5Address]
#: The plan of a DF1 link: typed word writes to holding registers, masked bit writes to coils.
Df1Plan: TypeAlias = Plan[Df1WordWrite, Df1BitWrite]


# --- word positions ------------------------------------------------------------------------

Key = tuple[int, int, int]  # file type, file number, slot (-1 for data files)


def _locate(address: SlcAddress) -> tuple[Key, int]:
    """(group key, word position in the group) of the word ``address`` names."""
    if address.file_type in _IO:
        return (int(address.file_type), address.file_number, address.element), address.sub_element
    size = address.element_size_words
    return (int(address.file_type), address.file_number, -1), address.element * size + address.sub_element


def _element_words(key: Key) -> int:
    return element_words(FileType(key[0]))


def block_cost(words: int, overhead: int = READ_OVERHEAD_BYTES) -> int:
    """Bytes on the wire of one read of ``words`` words."""
    return overhead + 2 * words


def optimal_blocks(
    needed: Iterable[tuple[int, int]], element_words: int, max_words: int, overhead: int = READ_OVERHEAD_BYTES
) -> list[tuple[int, int]]:
    """Cover ``needed`` spans ``(first word, word count)`` with (start, words) reads, fewest bytes.

    Reads start on an element boundary and hold at most ``max_words`` words.  Dynamic
    programming over the spans sorted by first word: O(n^2) in the worst case, cut short
    where a block would exceed the size limit.
    """
    spans = sorted(set(needed))
    n = len(spans)
    best = [0] + [1 << 60] * n
    choice = [0] * (n + 1)
    for j in range(1, n + 1):
        last_end = 0
        for i in range(j, 0, -1):
            first, count = spans[i - 1]
            last_end = max(last_end, first + count)
            start = first - first % element_words
            words = last_end - start
            if words > max_words:
                break
            cost = best[i - 1] + block_cost(words, overhead)
            if cost < best[j]:
                best[j], choice[j] = cost, i
        if best[j] >= 1 << 60:
            raise ValueError(f"a value of {spans[j - 1][1]} words does not fit a read of {max_words} words")
    blocks: list[tuple[int, int]] = []
    j = n
    while j > 0:
        i = choice[j]
        first = spans[i - 1][0]
        start = first - first % element_words
        end = max(f + c for f, c in spans[i - 1 : j])
        blocks.append((start, end - start))
        j = i - 1
    blocks.reverse()
    return blocks


# --- expansion -----------------------------------------------------------------------------


@frozen
class _SlcCell:
    table: Table
    modbus: int
    address: SlcAddress  # the word (for bits: the word holding the bit)
    codec: Codec | None  # None for bits
    bit: int | None
    scan: Scan


def _slc_cells(item: MapItem, words: dict[SlcAddress, SlcAddress]) -> list[_SlcCell]:
    """The cells of one map entry.  ``words`` interns word addresses across the plan: the 16
    coils of one word share one address object (a plan lives as long as its links)."""
    base = parse_address(item.address)
    table = Table(item.table)
    scan = Scan(item.scan)
    cells: list[_SlcCell] = []
    if table in (Table.COIL, Table.DISCRETE):
        step_elements = base.file_type in STRUCTURE_FILE_TYPES
        first_bit = base.bit or 0
        for k in range(item.count):
            if step_elements:
                word, bit = base.offset(k), first_bit
            else:
                absolute = first_bit + k
                word, bit = base.offset(absolute // 16), absolute % 16
            word = SlcAddress(word.file_type, word.file_number, word.element, word.sub_element, None)
            word = words.setdefault(word, word)
            cells.append(_SlcCell(table, item.start + k, word, None, bit, scan))
        return cells
    if item.type == "float32":
        high, low = (0, 1) if item.word_order == "high-first" else (1, 0)
        for k in range(item.count):
            address = base.offset(k)
            cells.append(_SlcCell(table, item.start + 2 * k + high, address, F32_HIGH, None, scan))
            cells.append(_SlcCell(table, item.start + 2 * k + low, address, F32_LOW, None, scan))
        return cells
    for k in range(item.count):
        address = base.offset(k)
        cells.append(_SlcCell(table, item.start + k, address, U16_LE, None, scan))
    return cells


def plan_df1(items: Sequence[MapItem], max_read_bytes: int, overhead: int = READ_OVERHEAD_BYTES) -> Df1Plan:
    """The read plan and Modbus points of a DF1 link's map."""
    interned: dict[SlcAddress, SlcAddress] = {}
    cells = [cell for item in items for cell in _slc_cells(item, interned)]
    max_words = max_read_bytes // 2
    # Needed spans per (scan, key); a word read by the fast class is not read again by the slow.
    fast_words: set[tuple[Key, int]] = set()
    for cell in cells:
        if cell.scan is Scan.FAST:
            key, position = _locate(cell.address)
            fast_words.add((key, position))
    needed: dict[tuple[Scan, Key], set[tuple[int, int]]] = defaultdict(set)
    for cell in cells:
        key, position = _locate(cell.address)
        words = 2 if cell.codec is not None and cell.codec.half is not None else 1
        scan = Scan.FAST if (key, position) in fast_words else cell.scan
        needed[scan, key].add((position, words))
    plan: Df1Plan = Plan()
    where: dict[tuple[Scan, Key], list[tuple[int, int, int]]] = {}  # -> [(start, words, block index)]
    for (scan, key), spans in sorted(needed.items(), key=lambda kv: (kv[0][0].value, kv[0][1])):
        file_type, file_number, slot = key
        element_words = _element_words(key)
        entries = []
        for start, words in optimal_blocks(spans, element_words, max_words, overhead):
            if slot >= 0:
                element, sub = slot, start
                label = f"{FileType(file_type).letter}:{slot}.{start}"
            else:
                element, sub = divmod(start, element_words)
                label = f"{FileType(file_type).letter}{file_number}:{element}" + (f".{sub}" if sub else "")
            index = len(plan.blocks)
            request = Df1Read(file_type, file_number, element, sub, 2 * words)
            plan.blocks.append(Block(request, 2 * words, scan, f"{label} ({words} words)"))
            entries.append((start, words, index))
        where[scan, key] = entries

    def find(cell: _SlcCell) -> tuple[int, int]:
        key, position = _locate(cell.address)
        scan = Scan.FAST if (key, position) in fast_words else cell.scan
        for start, words, index in where[scan, key]:
            if start <= position < start + words:
                return index, 2 * (position - start)
        raise AssertionError(f"{cell.address} not covered by the read plan")

    word_writes: dict[SlcAddress, Df1WordWrite] = {}  # one per word or float (both halves share it)
    for cell in cells:
        block, offset = find(cell)
        writable = cell.table.writable
        if cell.bit is not None:
            write = Df1BitWrite(cell.address, cell.bit) if writable else None
            point = BitPoint(block, offset + cell.bit // 8, cell.bit % 8, write)
            plan.bits(cell.table)[cell.modbus] = point
        else:
            assert cell.codec is not None
            word_write = word_writes.setdefault(cell.address, Df1WordWrite(cell.address)) if writable else None
            plan.registers(cell.table)[cell.modbus] = RegisterPoint(block, offset, cell.codec, word_write)
    return plan


def entry_description(item: MapItem) -> str:
    """A point's description in tag lists: the map entry it comes from."""
    return f"map entry {item.address} x{item.count}, {item.type}, {item.scan} scan"


def point_labels_df1(items: Sequence[MapItem]) -> dict[tuple[Table, int], PointLabel]:
    """What each point of :func:`plan_df1` is: its SLC 500 address (``N7:10``, ``B3:0/5``, ``F8:2``)."""
    labels: dict[tuple[Table, int], PointLabel] = {}
    interned: dict[SlcAddress, SlcAddress] = {}
    for item in items:
        description = entry_description(item)
        for cell in _slc_cells(item, interned):
            address = cell.address if cell.bit is None else replace(cell.address, bit=cell.bit)
            labels[cell.table, cell.modbus] = PointLabel(str(address), item.type, description)
    return labels


@functools.lru_cache(maxsize=256)
def _shared_plan(items: tuple[MapItem, ...], max_read_bytes: int) -> Df1Plan:
    return plan_df1(items, max_read_bytes)


def shared_plan_df1(items: Sequence[MapItem], max_read_bytes: int) -> Df1Plan:
    """:func:`plan_df1`, built once per distinct map: links with the same map (a plant's
    identical machines) share one plan and one image layout, as every SLC 100/150 link shares
    ``slc_ascii_plan()``.  A plan is never changed once built."""
    return _shared_plan(tuple(items), max_read_bytes)
