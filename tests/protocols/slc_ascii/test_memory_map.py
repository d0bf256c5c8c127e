"""Tests of gateway.protocols.slc_ascii.memory_map against shared/docs/slc100-150-ascii-protocol.md."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import InvalidRequest, ProtocolError
from gateway.protocols.slc_ascii.commands import CommandCode, write_item, write_item_bit
from gateway.protocols.slc_ascii.memory_map import (
    BYTE_WRITE_RANGE,
    MEMORY_MAP,
    READ_RANGES,
    Access,
    AddressRange,
    Item,
    ItemKind,
    Region,
    accumulator_address,
    all_user_bits,
    byte_to_user_bit,
    check_byte_writable,
    check_readable,
    check_word_writable,
    is_byte_writable,
    is_readable,
    is_word_writable,
    is_writable_user_bit,
    parse_item,
    preset_address,
    region_of,
    step_counter_address,
    user_bit_to_byte,
)

# "User Program Addresses", copied row by row from the manual: hex address, then bits 7..0.
MANUAL_USER_TABLE = """
    96   18  17  16  15  14  13  12  11
    97  118 117 116 115 114 113 112 111
    98  218 217 216 215 214 213 212 211
    99  318 317 316 315 314 313 312 311
    9A  418 417 416 415 414 413 412 411
    9B  518 517 516 515 514 513 512 511
    9C  618 617 616 615 614 613 612 611
    9D    8   7   6   5   4   3   2   1
    9E  108 107 106 105 104 103 102 101
    9F  208 207 206 205 204 203 202 201
    A0  308 307 306 305 304 303 302 301
    A1  408 407 406 405 404 403 402 401
    A2  508 507 506 505 504 503 502 501
    A3  608 607 606 605 604 603 602 601
    A4  210 209 110 109  10   9   X   X
    A5  610 609 510 509 410 409 310 309
    A6  708 707 706 705 704 703 702 701
    A7  716 715 714 713 712 711 710 709
    A8  724 723 722 721 720 719 718 717
    A9  732 731 730 729 728 727 726 725
    AA  740 739 738 737 736 735 734 733
    AB  748 747 746 745 744 743 742 741
    AC  756 755 754 753 752 751 750 749
    AD  764 763 762 761 760 759 758 757
    AE  772 771 770 769 768 767 766 765
    AF  780 779 778 777 776 775 774 773
    B0  788 787 786 785 784 783 782 781
    B1  796 795 794 793 792 791 790 789
    B2  804 803 802 801 800 799 798 797
    B3  812 811 810 809 808 807 806 805
    B4  820 819 818 817 816 815 814 813
    B5  828 827 826 825 824 823 822 821
    B6  836 835 834 833 832 831 830 829
    B7  844 843 842 841 840 839 838 837
    B8  852 851 850 849 848 847 846 845
    B9  860 859 858 857 856 855 854 853
    BA  868 867 866 865 864 863 862 861
    BB  876 875 874 873 872 871 870 869
    DC  908 907 906 905 904 903 902 901
    DD  916 915 914 913 912 911 910 909
    DE  924 923 922 921 920 919 918 917
    DF  932 931 930 929 928 927 926 925
    E0  958 957 956 955 954 953 952 951
    E1  966 965 964 963 962 961 960 959
    E2  974 973 972 971 970 969 968 967
    E3  982 981 980 979 978 977 976 975
"""


def manual_user_table() -> dict[int, tuple[int, int]]:
    table: dict[int, tuple[int, int]] = {}
    for line in MANUAL_USER_TABLE.strip().splitlines():
        address, *cells = line.split()
        for bit, cell in zip(range(7, -1, -1), cells, strict=True):
            if cell != "X":
                table[int(cell)] = (int(address, 16), bit)
    return table


# ---------------------------------------------------------------------------------------------
# The memory map


def test_memory_map_is_contiguous_from_0000_to_0112() -> None:
    assert MEMORY_MAP[0].start == 0x0000
    assert MEMORY_MAP[-1].end == 0x0112
    for before, after in itertools.pairwise(MEMORY_MAP):
        assert after.start == before.end + 1


def test_memory_map_bytes_used_column() -> None:
    # "Bytes Used" column of "The Memory Map", both pages.
    assert [r.size for r in MEMORY_MAP] == [
        64, 64, 2, 2, 2, 16, 7, 9, 21, 1, 32, 4, 4, 4, 4, 4, 4, 4, 4, 4, 1, 1, 16, 1,
    ]


def test_no_access_cells_are_the_double_star_rows() -> None:
    no_access = {a for r in MEMORY_MAP if r.access is Access.NO_ACCESS for a in range(r.start, r.end + 1)}
    assert no_access == {0x80, 0x81, *range(0xEC, 0x100)}


def test_read_only_cells_are_the_star_rows() -> None:
    read_only = {a for r in MEMORY_MAP if r.access is Access.READ_ONLY for a in range(r.start, r.end + 1)}
    assert read_only == {0x82, 0x83, *range(0x96, 0xEC), 0x100}


@pytest.mark.parametrize("kind", ["range", "region"])
def test_ranges_and_regions_lie_in_the_16_bit_address_space(kind: str) -> None:
    """Both are inclusive ``start``-``end`` spans of four-hex-digit addresses; one address is a span too."""

    def build(start: int, end: int) -> AddressRange | Region:
        if kind == "range":
            return AddressRange(start, end, "test")
        return Region("test", start, end, Access.READ_WRITE)

    assert 0xFFFF in build(0x0000, 0xFFFF)
    assert 0x0000 in build(0x0000, 0x0000)
    assert 0x0113 not in build(0x0000, 0x0112)
    for start, end in [(-1, 0), (0x0000, 0x10000), (0x0085, 0x0084)]:
        with pytest.raises(ValueError, match=f"0x{start:04X}-0x{end:04X}"):
            build(start, end)


def test_read_ranges_verbatim() -> None:
    assert [(r.start, r.end) for r in READ_RANGES] == [
        (0x0000, 0x003E), (0x0040, 0x007E), (0x0084, 0x0085), (0x0086, 0x0095), (0x0096, 0x009C),
        (0x009D, 0x00A5), (0x00A6, 0x00BA), (0x00BB, 0x00BB), (0x00BC, 0x00DB), (0x00DC, 0x00DF),
        (0x00E0, 0x00E3), (0x0102, 0x0111), (0x0112, 0x0112),
    ]


@pytest.mark.parametrize(
    ("address", "name"),
    [
        (0x00, "timer/counter/sequencer accumulators"),
        (0x7F, "timer/counter presets"),
        (0x81, "checksum of last ladder diagram"),
        (0x85, "controller error mode bits"),
        (0xA5, "input state table"),
        (0xBB, "fine timer bits, AUTO/MAN switch"),
        (0x101, "controller mode byte"),
        (0x112, "access code byte"),
    ],
)
def test_region_of(address: int, name: str) -> None:
    region = region_of(address)
    assert region is not None
    assert region.name == name
    assert address in region


def test_region_of_beyond_map_is_none() -> None:
    assert region_of(0x0113) is None
    assert region_of(0xFFFF) is None


@pytest.mark.parametrize("address", [-1, 0x10000, True, "0x84", 1.0])
def test_region_of_rejects_bad_addresses(address: object) -> None:
    with pytest.raises(InvalidRequest, match="address"):
        region_of(address)  # type: ignore[arg-type]


def test_no_double_star_cell_is_ever_readable() -> None:
    for address in range(0x0000, 0x0400):
        for count in (1, 2):
            if is_readable(address, count):
                for byte in range(address, address + count):
                    region = region_of(byte)
                    assert region is not None
                    assert region.access is not Access.NO_ACCESS
                    assert region.readable


def test_every_byte_of_a_readable_region_can_be_read() -> None:
    covered = {
        byte
        for address in range(0x0000, 0x0400)
        for count in (1, 2)
        if is_readable(address, count)
        for byte in range(address, address + count)
    }
    readable = {a for r in MEMORY_MAP if r.readable for a in range(r.start, r.end + 1)}
    assert covered == readable


@pytest.mark.parametrize(
    ("address", "count"),
    [(0x0000, 2), (0x003E, 2), (0x0001, 1), (0x007E, 2), (0x0084, 2), (0x0085, 2), (0x00A5, 1), (0x00E3, 1),
     (0x0112, 1), (0x0111, 2)],
)
def test_readable(address: int, count: int) -> None:
    assert is_readable(address, count)
    check_readable(address, count)
    if count == 1:  # one byte unless told otherwise, as command 02 is built
        assert is_readable(address)
        check_readable(address)


@pytest.mark.parametrize(
    ("address", "count", "message"),
    [
        (0x0080, 1, r"address 0x0080 is in a no-access \(\*\*\) cell: checksum of last ladder diagram"),
        (0x0081, 2, r"address 0x0081 is in a no-access \(\*\*\) cell: checksum of last ladder diagram"),
        (0x00EC, 1, r"no-access \(\*\*\) cell: up counter/timer/sequencer last state bits"),
        (0x00FF, 1, r"no-access \(\*\*\) cell: RTF instruction identifier bits"),
        (0x0082, 1, r"0x0082 \(current rung number\) is not in the manual's list of readable addresses"),
        (0x00E4, 1, r"immediate rung bits\) is not in the manual's list"),
        (0x0100, 1, r"0x0100 .* is not in the manual's list"),
        (0x0101, 1, r"0x0101 \(controller mode byte\) is not in the manual's list"),
        (0x0113, 1, r"0x0113 is outside the described memory map"),
        (0x003F, 1, r"0x003F is the LSB of the last word .* start at 0x0000-0x003E"),
        (0x007F, 2, r"0x007F is the LSB of the last word .* start at 0x0040-0x007E"),
        (0x00E3, 2, r"reading 2 bytes at 0x00E3 would also read 0x00E4"),
        (0x0112, 2, r"reading 2 bytes at 0x0112 would also read 0x0113, which is outside"),
        (0xFFFF, 1, r"outside the described memory map"),
        (0x0084, 3, r"byte count 3 is not allowed: command 02 reads 1 or 2 bytes"),
        (0x0084, 0, r"byte count 0 is not allowed"),
        (0x0084, True, r"byte count True is not allowed"),
        (0x0084, 1.0, r"byte count 1.0 is not allowed"),
        (True, 1, r"address True is not an integer"),
        (-1, 1, r"address -1 is out of range"),
        (0x10000, 1, r"out of range 0x0000-0xFFFF"),
    ],
)
def test_unreadable(address: int, count: int, message: str) -> None:
    assert not is_readable(address, count)
    with pytest.raises(InvalidRequest, match=message):
        check_readable(address, count)


#: the "Reading Data" list as the refusals of an unreadable address quote it
MANUAL_READ_LIST = (
    "0x0000-0x003E (timer/counter/sequencer accumulator), 0x0040-0x007E (timer/counter presets), "
    "0x0084-0x0085 (error bits), 0x0086-0x0095 (force select table), 0x0096-0x009C (output state table), "
    "0x009D-0x00A5 (input state table), 0x00A6-0x00BA (internal relay table), "
    "0x00BB (fine timer bits, auto/man switch), 0x00BC-0x00DB (sequencer step counters), "
    "0x00DC-0x00DF (timer/counter/sequencer output table), 0x00E0-0x00E3 (timer/counter/sequencer overflow table), "
    "0x0102-0x0111 (force state table), 0x0112 (access code byte)"
)


@pytest.mark.parametrize("address", [0x0082, 0x0101, 0x0113])
def test_an_unlisted_address_is_refused_with_the_manuals_read_list(address: int) -> None:
    """The refusal tells the user every start address command 02 takes, as the manual lists them."""
    with pytest.raises(InvalidRequest) as refused:
        check_readable(address)
    assert str(refused.value).endswith(f"readable: {MANUAL_READ_LIST}")


def test_word_writable() -> None:
    writable = {a for a in range(0x0200) if is_word_writable(a)}
    assert writable == set(range(0x00, 0x80, 2))
    check_word_writable(0x007E)
    with pytest.raises(InvalidRequest, match="0x0041 is odd"):
        check_word_writable(0x41)
    with pytest.raises(InvalidRequest, match="0x0080 is not word-writable"):
        check_word_writable(0x80)


def test_byte_writable() -> None:
    writable = {a for a in range(0x0200) if is_byte_writable(a)}
    assert writable == set(range(0xA6, 0xB5))
    assert not is_byte_writable(True)
    with pytest.raises(InvalidRequest, match=r"0x00B5 is not byte-writable: .*0x00A6-0x00B4"):
        check_byte_writable(0xB5)
    with pytest.raises(InvalidRequest, match="0x0101 is not byte-writable"):
        check_byte_writable(0x101)


# ---------------------------------------------------------------------------------------------
# User address table


@pytest.mark.parametrize(
    ("user_address", "cell"),
    [
        (701, (0xA6, 0)), (11, (0x96, 0)), (1, (0x9D, 0)), (9, (0xA4, 2)), (10, (0xA4, 3)), (210, (0xA4, 7)),
        (309, (0xA5, 0)), (610, (0xA5, 7)), (909, (0xDD, 0)), (951, (0xE0, 0)), (868, (0xBA, 7)),
        (18, (0x96, 7)), (618, (0x9C, 7)), (608, (0x9D + 6, 7)), (820, (0xB4, 7)), (869, (0xBB, 0)),
        (876, (0xBB, 7)), (932, (0xDF, 7)), (982, (0xE3, 7)), (800, (0xB2, 3)),
    ],
)
def test_user_bit_cells_from_the_manual(user_address: int, cell: tuple[int, int]) -> None:
    assert user_bit_to_byte(user_address) == cell
    assert byte_to_user_bit(*cell) == user_address


def test_whole_user_table_matches_the_manual() -> None:
    manual = manual_user_table()
    assert list(all_user_bits()) == sorted(manual)
    for user_address, cell in manual.items():
        assert user_bit_to_byte(user_address) == cell
        assert byte_to_user_bit(*cell) == user_address


def test_user_bits_count() -> None:
    # outputs 7*8, inputs 7*8 + 14, relays 168, fine timer 8, outputs 32, overflow 32
    assert len(list(all_user_bits())) == 56 + 70 + 168 + 8 + 32 + 32


def test_round_trip_over_all_user_bits() -> None:
    for user_address in all_user_bits():
        assert byte_to_user_bit(*user_bit_to_byte(user_address)) == user_address


def test_reverse_round_trip_over_all_cells() -> None:
    hits = 0
    for byte_address in range(0x0000, 0x0200):
        for bit in range(8):
            user_address = byte_to_user_bit(byte_address, bit)
            if user_address is not None:
                hits += 1
                assert user_bit_to_byte(user_address) == (byte_address, bit)
    assert hits == len(list(all_user_bits()))


@pytest.mark.parametrize(
    ("byte_address", "bit"),
    [(0xA4, 0), (0xA4, 1), (0xE4, 0), (0xE8, 0), (0xBC, 0), (0x00, 0), (0x84, 7), (0x112, 0)],
)
def test_cells_without_user_address(byte_address: int, bit: int) -> None:
    assert byte_to_user_bit(byte_address, bit) is None


@pytest.mark.parametrize("bit", [-1, 8, True, "1"])
def test_byte_to_user_bit_rejects_bad_bits(bit: object) -> None:
    with pytest.raises(InvalidRequest, match="is not a bit number 0-7"):
        byte_to_user_bit(0x96, bit)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "user_address", [0, 19, 20, 99, 100, 119, 200, 611 + 8, 699, 700, 877, 900, 933, 950, 983, 1000, -1]
)
def test_invalid_user_addresses(user_address: int) -> None:
    with pytest.raises(InvalidRequest, match=rf"user address {user_address} is not a bit address; valid"):
        user_bit_to_byte(user_address)


def test_user_address_must_be_int() -> None:
    with pytest.raises(InvalidRequest, match="is not an integer"):
        user_bit_to_byte("701")  # type: ignore[arg-type]
    with pytest.raises(InvalidRequest, match="is not an integer"):
        user_bit_to_byte(True)


def test_writable_user_bits_are_relays_701_to_820() -> None:
    assert {n for n in all_user_bits() if is_writable_user_bit(n)} == set(range(701, 821))
    assert not is_writable_user_bit(19)


@given(st.sampled_from(sorted(manual_user_table())))
def test_user_bit_round_trip_property(user_address: int) -> None:
    byte_address, bit = user_bit_to_byte(user_address)
    assert 0 <= bit <= 7
    assert byte_to_user_bit(byte_address, bit) == user_address
    assert is_readable(byte_address, 1)


@given(st.integers(min_value=-10, max_value=1100))
def test_user_bit_to_byte_is_total_on_integers(user_address: int) -> None:
    if user_address in manual_user_table():
        assert user_bit_to_byte(user_address) == manual_user_table()[user_address]
    else:
        with pytest.raises(InvalidRequest):
            user_bit_to_byte(user_address)


# ---------------------------------------------------------------------------------------------
# Timer / counter / sequencer numbers


def test_timer_addresses() -> None:
    assert accumulator_address(901) == 0x00
    assert accumulator_address(932) == 0x3E
    assert preset_address(901) == 0x40
    assert preset_address(932) == 0x7E
    assert step_counter_address(901) == 0xBC
    assert step_counter_address(932) == 0xDB
    for n in range(901, 933):
        assert is_word_writable(accumulator_address(n))
        assert is_word_writable(preset_address(n))
        assert is_readable(accumulator_address(n), 2)
        assert is_readable(preset_address(n), 2)
        assert is_readable(step_counter_address(n), 1)


@pytest.mark.parametrize("number", [900, 933, 0, True, 901.0, "901"])
def test_timer_numbers_are_901_to_932(number: int) -> None:
    for function in (accumulator_address, preset_address, step_counter_address):
        with pytest.raises(InvalidRequest, match="is not in 901-932"):
            function(number)


# ---------------------------------------------------------------------------------------------
# Items


def test_item_accumulator() -> None:
    item = parse_item("902.ACC")
    assert (item.text, item.kind, item.read_address, item.read_count, item.number) == (
        "902.ACC", ItemKind.ACCUMULATOR, 0x02, 2, 902)
    assert item.decode(b"\x27\x0f") == 9999
    assert item.decode(b"\x80\x05") == 5  # bit 15 is the protect bit, never data
    assert item.writable
    assert not item.read_modify_write
    command = write_item(item, 1234)
    assert (command.code, command.params) == (CommandCode.WRITE, b"\x00\x02\x04\xd2")


def test_item_preset_masks_protect_bit() -> None:
    item = parse_item(" 932.pre ")
    assert (item.text, item.read_address, item.read_count, item.number) == ("932.PRE", 0x7E, 2, 932)
    assert item.decode(b"\x83\xe8") == 1000
    assert write_item(item, 0).params == b"\x00\x7e\x00\x00"
    with pytest.raises(InvalidRequest, match="less than 2710H"):
        write_item(item, 10000)


def test_item_protected() -> None:
    item = parse_item("901.Protected")
    assert (item.text, item.kind, item.read_address, item.read_count, item.number) == (
        "901.PROTECTED", ItemKind.PROTECTED, 0x40, 1, 901)
    assert item.decode(b"\x80") is True
    assert item.decode(b"\x7f") is False
    assert not item.writable
    with pytest.raises(InvalidRequest, match=r"901\.PROTECTED is read only"):
        write_item(item, 1)


def test_item_step() -> None:
    item = parse_item("905.STEP")
    assert (item.text, item.kind, item.read_address, item.read_count, item.number) == (
        "905.STEP", ItemKind.STEP, 0xC0, 1, 905)
    assert item.decode(b"\x07") == 7
    with pytest.raises(InvalidRequest, match="read only"):
        write_item(item, 1)


@pytest.mark.parametrize(
    ("text", "address", "bit"),
    [("701", 0xA6, 0), ("11", 0x96, 0), ("1", 0x9D, 0), ("909", 0xDD, 0), ("951", 0xE0, 0), ("210", 0xA4, 7)],
)
def test_item_user_bits(text: str, address: int, bit: int) -> None:
    item = parse_item(text)
    assert (item.text, item.kind, item.read_address, item.read_count, item.bit, item.number) == (
        text, ItemKind.BIT, address, 1, bit, int(text))
    assert item.decode(bytes([1 << bit])) is True
    assert item.decode(bytes([0xFF ^ (1 << bit)])) is False
    assert item.read_modify_write


def test_item_bit_write_is_read_modify_write() -> None:
    item = parse_item("703")
    assert item.writable
    with pytest.raises(InvalidRequest, match="703 is a bit: read byte 0x00A6 and use write_item_bit"):
        write_item(item, 1)
    on = write_item_bit(item, 0b1000_0001, True)
    assert (on.code, on.params) == (CommandCode.WRITE, b"\x00\xa6\x85")
    off = write_item_bit(item, 0xFF, False)
    assert off.params == b"\x00\xa6\xfb"
    with pytest.raises(InvalidRequest, match="current byte 256 is not in 0-255"):
        write_item_bit(item, 256, True)


@pytest.mark.parametrize("text", ["821", "11", "1", "909", "951", "869"])
def test_item_read_only_bits(text: str) -> None:
    item = parse_item(text)
    assert not item.writable
    with pytest.raises(InvalidRequest, match="is read only"):
        write_item_bit(item, 0, True)
    with pytest.raises(InvalidRequest, match="is read only"):
        write_item(item, 1)


def test_item_raw_byte() -> None:
    for text in ("@0x84", "@84", "@0X0084", "@0084"):
        item = parse_item(text)
        assert (item.text, item.kind, item.read_address, item.read_count) == (
            "@0x0084", ItemKind.BYTE, 0x84, 1)
        assert item.number is None
        assert item.decode(b"\x81") == 0x81
        assert not item.writable
    relay = parse_item("@a6")
    assert relay.writable
    assert write_item(relay, 0x55).params == b"\x00\xa6\x55"
    with pytest.raises(InvalidRequest, match="value 256 is out of range"):
        write_item(relay, 256)
    with pytest.raises(InvalidRequest, match="not a bit item"):
        write_item_bit(relay, 0, True)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (("@0x00E3", ItemKind.BYTE, 0x00E3, 2), "would also read 0x00E4"),  # 1 byte there is readable
        (("@0x0080", ItemKind.BYTE, 0x0080, 1), "no-access"),
        (("@0x0084", ItemKind.BYTE, 0x0084, 3), "byte count 3 is not allowed"),
    ],
)
def test_an_item_names_only_a_read_command_02_may_make(fields: tuple[str, ItemKind, int, int], message: str) -> None:
    with pytest.raises(InvalidRequest, match=message):
        Item(*fields)


@pytest.mark.parametrize("bit", [-1, 8])
def test_a_bit_item_names_a_bit_0_to_7(bit: int) -> None:
    assert Item("701", ItemKind.BIT, 0x00A6, 1, bit=7).bit == 7
    with pytest.raises(ValueError, match=f"bad bit {bit}"):
        Item("701", ItemKind.BIT, 0x00A6, 1, bit=bit)


def test_item_decode_checks_length() -> None:
    with pytest.raises(ProtocolError, match=r"901.ACC: expected 2 byte\(s\), got 1"):
        parse_item("901.ACC").decode(b"\x00")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("900.ACC", "900 is not a timer/counter/sequencer number 901-932"),
        ("933.PRE", "933 is not a timer/counter/sequencer number 901-932"),
        ("901.DN", "unknown suffix 'DN'; use NNN.ACC, NNN.PRE, NNN.PROTECTED or NNN.STEP"),
        ("19", "is not a user bit address; valid bit addresses are inputs 1-10"),
        ("0", "is not a user bit address"),
        ("@0x81", r"item '@0x81': address 0x0081 is in a no-access \(\*\*\) cell: checksum of last ladder diagram"),
        ("@82", "item '@82': address 0x0082 .* not in the manual's list of readable addresses"),
        ("@0x3F", "item '@0x3F': address 0x003F is the LSB of the last word"),
        ("@12345", "is not valid; use NNN.ACC"),
        ("@", "is not valid"),
        ("@0xZZ", "is not valid"),
        ("", "is not valid"),
        ("T4:0.ACC", "is not valid"),
        ("-1", "is not valid"),
        ("1.5", "is not valid"),
    ],
)
def test_parse_item_rejects(text: str, message: str) -> None:
    with pytest.raises(InvalidRequest, match=message):
        parse_item(text)


def test_parse_item_rejects_non_text() -> None:
    with pytest.raises(InvalidRequest, match="is not text"):
        parse_item(701)  # type: ignore[arg-type]


def test_every_user_bit_is_an_item() -> None:
    for user_address in all_user_bits():
        item = parse_item(str(user_address))
        assert (item.read_address, item.bit) == user_bit_to_byte(user_address)
        assert item.writable == (item.read_address in BYTE_WRITE_RANGE)


@given(st.sampled_from(range(901, 933)), st.sampled_from(["ACC", "PRE", "PROTECTED", "STEP"]))
def test_timer_items_are_readable(number: int, suffix: str) -> None:
    item = parse_item(f"{number}.{suffix.lower()}")
    assert item.text == f"{number}.{suffix}"
    assert is_readable(item.read_address, item.read_count)
    assert parse_item(item.text) == item


def test_a_raw_byte_item_names_exactly_the_bytes_command_02_reads_alone() -> None:
    """``@ADDR`` reads one byte: every address the manual lets command 02 read, and no other.

    The byte before a readable one (0x00E3, 0x0111) is an item though a 2-byte read there is not.
    """
    items = set()
    for address in range(0x0120):
        try:
            item = parse_item(f"@{address:X}")
        except InvalidRequest:
            continue
        assert (item.read_address, item.read_count) == (address, 1)
        items.add(address)
    assert items == {a for a in range(0x0120) if is_readable(a, 1)}
    assert {0x00E3, 0x0111, 0x0112} <= items


@given(st.integers(min_value=0, max_value=0xFFFF))
def test_raw_byte_items_follow_is_readable(address: int) -> None:
    if is_readable(address, 1):
        assert parse_item(f"@{address:x}").read_address == address
    else:
        with pytest.raises(InvalidRequest):
            parse_item(f"@0x{address:04X}")
