"""DF1 map entries -> Modbus points, and the read planner (``gateway.kinds.df1.plan``).

Expected word positions are worked out here from the SLC 500 addressing reference (one word per
N/B/S element, two per float, three per timer/counter/control structure; I/O words by slot), not
from the planner.  ``optimal_blocks`` is checked against an independent exhaustive search.
"""

from __future__ import annotations

import functools
import itertools
import struct
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.kinds.df1.plan import (
    F32_HIGH,
    F32_LOW,
    READ_OVERHEAD_BYTES,
    U16_LE,
    Df1BitWrite,
    Df1Read,
    Df1WordWrite,
    MapItem,
    block_cost,
    optimal_blocks,
    plan_df1,
    point_labels_df1,
)
from gateway.modbus.mapping import Plan, Scan, Table
from gateway.protocols.df1.address import FileType, SlcAddress, parse_address

INTEGER, FLOAT, TIMER, BIT, INPUT = FileType.INTEGER, FileType.FLOAT, FileType.TIMER, FileType.BIT, FileType.INPUT

#: Words per element, from the addressing reference.
ELEMENT_WORDS = {INTEGER: 1, BIT: 1, FLOAT: 2, TIMER: 3, FileType.COUNTER: 3, FileType.CONTROL: 3}


def read_of(plan: Plan, index: int) -> Df1Read:
    request = plan.blocks[index].request
    assert isinstance(request, Df1Read)
    return request


def all_reads(plan: Plan) -> list[Df1Read]:
    """The plan's reads, by file type, file, element, sub-element."""
    reads = [read_of(plan, i) for i in range(len(plan.blocks))]
    return sorted(reads, key=lambda r: (r.file_type, r.file_number, r.element, r.sub_element))


def first_byte(read: Df1Read) -> int:
    """Byte offset of a read's first byte in its file image (for I/O: in its slot)."""
    if read.file_type in (FileType.INPUT, FileType.OUTPUT):
        return 2 * read.sub_element
    return (read.element * ELEMENT_WORDS[FileType(read.file_type)] + read.sub_element) * 2


def word_byte(file_type: FileType, element: int, sub_element: int = 0) -> int:
    """Byte offset of a word in its file image, by the reference's element sizes."""
    return (element * ELEMENT_WORDS[file_type] + sub_element) * 2


def register_location(plan: Plan, table: Table, address: int) -> tuple[Df1Read, int]:
    """(read, byte offset in the file image) of the word a register is decoded from."""
    point = plan.registers(table)[address]
    read = read_of(plan, point.block)
    assert point.offset + 2 <= read.size
    return read, first_byte(read) + point.offset


def bit_location(plan: Plan, table: Table, address: int) -> tuple[Df1Read, int, int]:
    """(read, byte offset of the word in the file image, bit in the word) of a bit point."""
    point = plan.bits(table)[address]
    read = read_of(plan, point.block)
    assert point.offset < read.size
    word_offset = point.offset - point.offset % 2
    return read, first_byte(read) + word_offset, (point.offset % 2) * 8 + point.bit


def assert_within_limit(plan: Plan, max_read_bytes: int) -> None:
    for block in plan.blocks:
        read = block.request
        assert isinstance(read, Df1Read)
        assert 0 < read.size <= max_read_bytes, block
        assert block.size == read.size


def assert_element_aligned(plan: Plan) -> None:
    """Data file reads start on an element (sub-element 0): a float or structure is never cut at the front."""
    for block in plan.blocks:
        read = block.request
        assert isinstance(read, Df1Read)
        if read.file_type not in (FileType.INPUT, FileType.OUTPUT):
            assert read.sub_element == 0, block


DEMO_MAP = [
    MapItem("holding", 0, "N7:0", 100),
    MapItem("holding", 100, "T4:0.ACC", 10),
    MapItem("holding", 110, "T4:0.PRE", 10),
    MapItem("holding", 200, "F8:0", 10, "float32"),
    MapItem("coil", 0, "B3:0/0", 64, "bool"),
    MapItem("discrete", 0, "T4:0/DN", 10, "bool"),
    MapItem("input", 0, "I:1.0", 8, scan="slow"),
]


# --------------------------------------------------------------------------------------------
# Expansion: which word each Modbus address reads and writes


@pytest.mark.parametrize("max_read_bytes", [82, 236])
def test_n7_words_one_register_each(max_read_bytes: int) -> None:
    plan = plan_df1([MapItem("holding", 10, "N7:5", 100)], max_read_bytes)
    assert sorted(plan.holding) == list(range(10, 110))
    for k in range(100):
        read, offset = register_location(plan, Table.HOLDING, 10 + k)
        assert (read.file_type, read.file_number) == (INTEGER, 7)
        assert offset == word_byte(INTEGER, 5 + k)
        point = plan.holding[10 + k]
        assert point.codec is U16_LE
        assert point.write == Df1WordWrite(SlcAddress(INTEGER, 7, 5 + k, 0))
    assert_within_limit(plan, max_read_bytes)


@pytest.mark.parametrize("max_read_bytes", [82, 236])
def test_timer_accumulators_step_through_elements(max_read_bytes: int) -> None:
    plan = plan_df1([MapItem("holding", 100, "T4:0.ACC", 10)], max_read_bytes)
    offsets = []
    for k in range(10):
        read, offset = register_location(plan, Table.HOLDING, 100 + k)
        assert (read.file_type, read.file_number) == (TIMER, 4)
        assert offset == word_byte(TIMER, k, 2)  # .ACC is word 2 of the timer
        offsets.append(offset)
        assert plan.holding[100 + k].write == Df1WordWrite(parse_address(f"T4:{k}.ACC"))
    assert [b - a for a, b in itertools.pairwise(offsets)] == [6] * 9  # one element: 3 words
    assert_within_limit(plan, max_read_bytes)
    assert_element_aligned(plan)


def test_timer_presets_and_accumulators_share_reads() -> None:
    plan = plan_df1([MapItem("holding", 100, "T4:0.ACC", 10), MapItem("holding", 110, "T4:0.PRE", 10)], 236)
    assert len(plan.blocks) == 1
    for k in range(10):
        assert register_location(plan, Table.HOLDING, 110 + k)[1] == word_byte(TIMER, k, 1)
        assert register_location(plan, Table.HOLDING, 100 + k)[1] == word_byte(TIMER, k, 2)


@pytest.mark.parametrize(("word_order", "high", "low"), [("high-first", 0, 1), ("low-first", 1, 0)])
def test_float32_two_registers_in_either_order(word_order: str, high: int, low: int) -> None:
    plan = plan_df1([MapItem("holding", 200, "F8:3", 5, "float32", word_order)], 236)
    assert sorted(plan.holding) == list(range(200, 210))
    # A block image with F8:3..7 = 1.5, -2.25, 1e6, 0.1, 3e-5 (PCCC float: 4 bytes little-endian).
    values = [1.5, -2.25, 1e6, 0.1, 3e-5]
    (read,) = [read_of(plan, i) for i in range(len(plan.blocks))]
    assert (read.file_type, read.file_number) == (FLOAT, 8)
    image = bytearray(read.size)
    for k, value in enumerate(values):
        struct.pack_into("<f", image, word_byte(FLOAT, 3 + k) - first_byte(read), value)
    for k, value in enumerate(values):
        raw = struct.unpack("<I", struct.pack("<f", value))[0]
        hi_point, lo_point = plan.holding[200 + 2 * k + high], plan.holding[200 + 2 * k + low]
        assert (hi_point.codec, lo_point.codec) == (F32_HIGH, F32_LOW)
        assert hi_point.offset == lo_point.offset == word_byte(FLOAT, 3 + k) - first_byte(read)
        assert hi_point.write == lo_point.write == Df1WordWrite(parse_address(f"F8:{3 + k}"))
        # decoded as the unit does: the float's 32 bits, high half and low half
        bits = struct.unpack_from("<I", image, hi_point.offset)[0]
        assert (bits >> 16, bits & 0xFFFF) == (raw >> 16, raw & 0xFFFF)
    assert_element_aligned(plan)


def test_b3_bits_count_64_across_four_words() -> None:
    plan = plan_df1([MapItem("coil", 0, "B3:0/0", 64, "bool")], 236)
    assert sorted(plan.coils) == list(range(64))
    assert len(plan.blocks) == 1 and read_of(plan, 0) == Df1Read(BIT, 3, 0, 0, 8)
    for n in range(64):
        _, word_offset, bit = bit_location(plan, Table.COIL, n)
        assert (word_offset, bit) == (word_byte(BIT, n // 16), n % 16), n
        assert plan.coils[n].write == Df1BitWrite(SlcAddress(BIT, 3, n // 16, 0), n % 16)


def test_bits_starting_mid_word_carry_into_the_next_word() -> None:
    plan = plan_df1([MapItem("coil", 5, "B3:2/14", 4, "bool")], 236)
    got = [bit_location(plan, Table.COIL, 5 + k)[1:] for k in range(4)]
    assert got == [(word_byte(BIT, 2), 14), (word_byte(BIT, 2), 15), (word_byte(BIT, 3), 0), (word_byte(BIT, 3), 1)]


def test_timer_done_bits_step_through_structures() -> None:
    plan = plan_df1([MapItem("discrete", 0, "T4:0/DN", 10, "bool")], 236)
    assert sorted(plan.discrete) == list(range(10))
    for k in range(10):
        read, word_offset, bit = bit_location(plan, Table.DISCRETE, k)
        assert (read.file_type, read.file_number) == (TIMER, 4)
        assert (word_offset, bit) == (word_byte(TIMER, k, 0), 13)  # DN: bit 13 of the control word
        assert plan.discrete[k].write is None  # discrete inputs are read only
    assert_element_aligned(plan)


def test_input_slot_words() -> None:
    plan = plan_df1([MapItem("input", 0, "I:1.0", 8, scan="slow")], 236)
    assert len(plan.blocks) == 1
    assert plan.blocks[0].scan is Scan.SLOW
    assert read_of(plan, 0) == Df1Read(INPUT, 1, 1, 0, 16)  # slot 1, words 0-7
    for k in range(8):
        point = plan.input[k]
        assert point.offset == 2 * k and point.write is None


def test_input_words_from_the_middle_of_a_slot() -> None:
    plan = plan_df1([MapItem("input", 0, "I:2.3", 2)], 236)
    assert read_of(plan, 0) == Df1Read(INPUT, 1, 2, 3, 4)


def test_demo_map_plan() -> None:
    plan = plan_df1(DEMO_MAP, 236)
    reads = {(read_of(plan, i), plan.blocks[i].scan) for i in range(len(plan.blocks))}
    assert len(reads) == len(plan.blocks)
    assert reads == {
        (Df1Read(BIT, 3, 0, 0, 8), Scan.FAST),
        (Df1Read(TIMER, 4, 0, 0, 60), Scan.FAST),  # ACC, PRE and DN of T4:0-9: ten whole timers
        (Df1Read(INTEGER, 7, 0, 0, 200), Scan.FAST),
        (Df1Read(FLOAT, 8, 0, 0, 40), Scan.FAST),
        (Df1Read(INPUT, 1, 1, 0, 16), Scan.SLOW),
    }
    assert plan.holding[5].write is not None and plan.input[0].write is None


# --------------------------------------------------------------------------------------------
# The plan: size limit, merging, splitting, alignment


@pytest.mark.parametrize("max_read_bytes", [82, 236])
def test_blocks_never_exceed_the_read_limit(max_read_bytes: int) -> None:
    items = [
        MapItem("holding", 0, "N7:0", 256),
        MapItem("holding", 1000, "T4:0.ACC", 20),
        MapItem("holding", 2000, "F8:0", 64, "float32"),
        MapItem("coil", 0, "B3:0/0", 1024, "bool"),
        MapItem("input", 0, "I:1.0", 8),
    ]
    plan = plan_df1(items, max_read_bytes)
    assert_within_limit(plan, max_read_bytes)
    assert_element_aligned(plan)
    # everything is still covered, word by word
    for k in range(256):
        assert register_location(plan, Table.HOLDING, k)[1] == word_byte(INTEGER, k)
    for k in range(20):
        assert register_location(plan, Table.HOLDING, 1000 + k)[1] == word_byte(TIMER, k, 2)
    for k in range(64):
        read, offset = register_location(plan, Table.HOLDING, 2000 + 2 * k)
        assert offset == word_byte(FLOAT, k)
        assert plan.holding[2000 + 2 * k].offset + 4 <= read.size  # a float is never split across reads
    n7_bytes = sum(read_of(plan, i).size for i in range(len(plan.blocks)) if read_of(plan, i).file_number == 7)
    assert n7_bytes == 512  # split, not overlapping
    n7_reads = [read_of(plan, i) for i in range(len(plan.blocks)) if read_of(plan, i).file_number == 7]
    assert len(n7_reads) == -(-512 // (max_read_bytes - max_read_bytes % 2))


def test_near_neighbours_merge_far_ones_split() -> None:
    # Two words 5 apart: one read of 6 words (34 + 12 bytes) beats two reads (2 x 36).
    near = plan_df1([MapItem("holding", 0, "N7:0", 1), MapItem("holding", 1, "N7:5", 1)], 236)
    assert [read_of(near, i) for i in range(len(near.blocks))] == [Df1Read(INTEGER, 7, 0, 0, 12)]
    # 100 words apart: two reads (72 bytes) beat one of 101 words (236).
    far = plan_df1([MapItem("holding", 0, "N7:0", 1), MapItem("holding", 1, "N7:100", 1)], 236)
    assert all_reads(far) == [Df1Read(INTEGER, 7, 0, 0, 2), Df1Read(INTEGER, 7, 100, 0, 2)]
    # The break-even gap: a gap of g words costs 2g bytes merged vs one more overhead split.
    even = READ_OVERHEAD_BYTES // 2  # gap words at which both cost the same
    merged = optimal_blocks([(0, 1), (1 + even - 1, 1)], 1, 118)
    split = optimal_blocks([(0, 1), (1 + even + 1, 1)], 1, 118)
    assert merged == [(0, even + 1)]
    assert split == [(0, 1), (even + 2, 1)]


def test_different_files_are_never_merged() -> None:
    plan = plan_df1([MapItem("holding", 0, "N7:0", 2), MapItem("holding", 2, "N10:0", 2)], 236)
    assert sorted((read_of(plan, i).file_number, read_of(plan, i).size) for i in range(2)) == [(7, 4), (10, 4)]


def test_timer_and_float_reads_start_on_an_element() -> None:
    plan = plan_df1([MapItem("holding", 0, "T4:7.ACC", 1), MapItem("holding", 1, "F8:9", 1, "float32")], 236)
    assert all_reads(plan) == [Df1Read(TIMER, 4, 7, 0, 6), Df1Read(FLOAT, 8, 9, 0, 4)]
    assert register_location(plan, Table.HOLDING, 0)[1] == word_byte(TIMER, 7, 2)


def test_fast_words_are_not_read_again_by_the_slow_class() -> None:
    plan = plan_df1([MapItem("holding", 0, "N7:0", 10), MapItem("input", 0, "N7:0", 10, scan="slow")], 236)
    assert len(plan.blocks) == 1 and plan.blocks[0].scan is Scan.FAST
    assert plan.input[3].block == plan.holding[3].block == 0


def test_a_value_larger_than_a_read_is_refused() -> None:
    with pytest.raises(ValueError, match="does not fit"):
        optimal_blocks([(0, 2)], 2, 1)


# --------------------------------------------------------------------------------------------
# optimal_blocks against an exhaustive search


def brute_force(spans: Sequence[tuple[int, int]], element_words: int, max_words: int, overhead: int) -> int:
    """Fewest bytes covering each span inside one read; reads element aligned, at most max_words.

    Exhaustive: some read holds the leftmost uncovered span; try every read that can, recurse.
    """
    spans = sorted(set(spans))

    @functools.cache
    def best(uncovered: frozenset[tuple[int, int]]) -> int:
        if not uncovered:
            return 0
        first, count = min(uncovered)
        result = 1 << 60
        for start in range(first - first % element_words, -1, -element_words):
            for words in range(first + count - start, max_words + 1):
                rest = frozenset(s for s in uncovered if not (start <= s[0] and s[0] + s[1] <= start + words))
                result = min(result, overhead + 2 * words + best(rest))
        return result

    return best(frozenset(spans))


@st.composite
def planner_inputs(draw: st.DrawFn) -> tuple[list[tuple[int, int]], int, int, int]:
    element_words = draw(st.sampled_from([1, 2, 3]))
    max_words = draw(st.integers(min_value=element_words, max_value=12))
    overhead = draw(st.integers(min_value=0, max_value=12))
    if element_words == 2:  # floats: whole elements of 2 words
        elements = draw(st.lists(st.integers(0, 12), min_size=1, max_size=7))
        spans = [(2 * e, 2) for e in elements]
    else:  # single words (N, B, I/O) or words of structures
        spans = [(p, 1) for p in draw(st.lists(st.integers(0, 30), min_size=1, max_size=7))]
    return spans, element_words, max_words, overhead


@settings(max_examples=300, deadline=None)
@given(planner_inputs())
def test_optimal_blocks_matches_exhaustive_search(case: tuple[list[tuple[int, int]], int, int, int]) -> None:
    spans, element_words, max_words, overhead = case
    blocks = optimal_blocks(spans, element_words, max_words, overhead)
    for start, words in blocks:
        assert start % element_words == 0
        assert 0 < words <= max_words
    for first, count in spans:  # every needed word is covered, each value inside one read
        assert any(start <= first and first + count <= start + words for start, words in blocks), (first, count)
    cost = sum(block_cost(words, overhead) for _, words in blocks)
    assert cost == brute_force(spans, element_words, max_words, overhead)


def test_links_with_the_same_map_share_one_plan() -> None:
    """Identical machines' links hold one plan (and so one image layout); a different map or
    size limit gets its own."""
    from gateway.kinds.df1.plan import shared_plan_df1

    items = [MapItem(table="holding", start=0, address="N7:0", count=10)]
    same = [MapItem(table="holding", start=0, address="N7:0", count=10)]
    other = [MapItem(table="holding", start=0, address="N7:0", count=11)]
    assert shared_plan_df1(items, 236) is shared_plan_df1(same, 236)
    assert shared_plan_df1(items, 236) is not shared_plan_df1(other, 236)
    assert shared_plan_df1(items, 236) is not shared_plan_df1(items, 100)


# --------------------------------------------------------------------------------------------
# What check-config and the tag lists show (docs/guide/df1-full-duplex.md, "Read plan")


def test_block_labels_are_the_check_config_lines_of_the_guide() -> None:
    # the guide's example map is DEMO_MAP; its read plan as check-config prints it
    plan = plan_df1(DEMO_MAP, 236)
    assert {(block.scan, block.label) for block in plan.blocks} == {
        (Scan.FAST, "B3:0 (4 words)"),
        (Scan.FAST, "T4:0 (30 words)"),
        (Scan.FAST, "N7:0 (100 words)"),
        (Scan.FAST, "F8:0 (20 words)"),
        (Scan.SLOW, "I:1.0 (8 words)"),
    }
    # a read from the middle of a file is named by its first element, a read of a slot by slot.word
    far = plan_df1([MapItem("holding", 0, "N7:0", 1), MapItem("holding", 1, "N7:100", 2)], 236)
    assert sorted(block.label for block in far.blocks) == ["N7:0 (1 words)", "N7:100 (2 words)"]
    io = plan_df1([MapItem("input", 0, "I:2.3", 2)], 236)
    assert [block.label for block in io.blocks] == ["I:2.3 (2 words)"]


def test_slot_0_is_an_io_slot_like_any_other() -> None:
    # slot 0 holds the processor's own (fixed controller) I/O: I:0.1 is word 1 of slot 0
    plan = plan_df1([MapItem("input", 0, "I:0.1", 2)], 236)
    assert all_reads(plan) == [Df1Read(INPUT, 1, 0, 1, 4)]
    assert [block.label for block in plan.blocks] == ["I:0.1 (2 words)"]


def test_a_gap_that_costs_as_much_as_another_read_is_not_merged() -> None:
    # The guide: neighbours merge "when reading a gap costs less than another transaction".  A gap of
    # READ_OVERHEAD_BYTES / 2 words costs exactly one more transaction: two reads.
    even = READ_OVERHEAD_BYTES // 2
    assert optimal_blocks([(0, 1), (1 + even, 1)], 1, 118) == [(0, 1), (1 + even, 1)]


def test_the_plan_uses_the_transaction_overhead_it_is_given() -> None:
    items = [MapItem("holding", 0, "N7:0", 1), MapItem("holding", 1, "N7:2", 1)]
    # the default overhead: reading the one-word gap is cheaper than a second read
    assert all_reads(plan_df1(items, 236)) == [Df1Read(INTEGER, 7, 0, 0, 6)]
    # no overhead per read: the gap costs 2 bytes, a second read nothing
    assert all_reads(plan_df1(items, 236, overhead=0)) == [Df1Read(INTEGER, 7, 0, 0, 2), Df1Read(INTEGER, 7, 2, 0, 2)]


def test_point_labels_name_each_point_by_its_slc_500_address() -> None:
    items = [
        MapItem("holding", 0, "N7:10", 2),
        MapItem("holding", 10, "F8:2", 1, "float32"),
        MapItem("coil", 0, "B3:0/14", 4, "bool"),
        MapItem("discrete", 0, "T4:0/DN", 2, "bool"),
    ]
    labels = point_labels_df1(items)
    assert {key: (label.address, label.type) for key, label in labels.items()} == {
        (Table.HOLDING, 0): ("N7:10", "int16"),
        (Table.HOLDING, 1): ("N7:11", "int16"),
        (Table.HOLDING, 10): ("F8:2", "float32"),
        (Table.HOLDING, 11): ("F8:2", "float32"),
        # bits of a word file carry into the next word: B3:0/15, then B3:1/0 (the reference's B3/16)
        (Table.COIL, 0): ("B3:0/14", "bool"),
        (Table.COIL, 1): ("B3:0/15", "bool"),
        (Table.COIL, 2): ("B3:1/0", "bool"),
        (Table.COIL, 3): ("B3:1/1", "bool"),
        (Table.DISCRETE, 0): ("T4:0/DN", "bool"),
        (Table.DISCRETE, 1): ("T4:1/DN", "bool"),
    }
    # each point's description is the map entry it comes from
    n7, f8, b3 = labels[Table.HOLDING, 0], labels[Table.HOLDING, 10], labels[Table.COIL, 0]
    assert labels[Table.HOLDING, 1].description == n7.description
    assert "N7:10" in n7.description and "int16" in n7.description and "fast" in n7.description
    assert "F8:2" in f8.description and "float32" in f8.description
    assert "B3:0/14" in b3.description and "bool" in b3.description
