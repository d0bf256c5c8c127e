"""PLC-5 addresses, word range read/write and read-modify-write packets.

Vectors are the ones printed in A-B 1770-6.5.16 (DF1) chapter 13 and the 1770-KF2 manual (KF2);
see docs/develop/df1-half-duplex-notes.md section 6.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.protocols.df1 import pccc
from gateway.protocols.df1.framing import Checksum, encode_frame
from gateway.protocols.df1.pccc.plc5 import ReadModifyWrite, WordRangeReadParams, WordRangeWriteParams
from gateway.protocols.df1.plc5_address import (
    AddressError,
    Plc5Address,
    decode_logical_ascii,
    decode_logical_binary,
    encode_logical_ascii,
    encode_logical_binary,
    parse_plc5_address,
)

# ------------------------------------------------------------------------- printed vectors


def test_df1_13_12_n7_30() -> None:
    """DF1 p. 13-12: N7:30 -> mask (3 levels) 00 07 1E."""
    address = parse_plc5_address("N7:30")
    assert encode_logical_binary(address) == bytes.fromhex("07 00 07 1E")
    assert decode_logical_binary(bytes.fromhex("07 00 07 1E")) == ((0, 7, 30), 4)


def test_df1_13_12_b3_300() -> None:
    """DF1 p. 13-12: B3:300 -> mask 06 (level 1 defaulted), 03, FF 2C 01."""
    address = parse_plc5_address("B3:300")
    assert encode_logical_binary(address, compact=True) == bytes.fromhex("06 03 FF 2C 01")
    assert decode_logical_binary(bytes.fromhex("06 03 FF 2C 01")) == ((0, 3, 300), 5)
    assert encode_logical_binary(address) == bytes.fromhex("07 00 03 FF 2C 01")


def test_df1_13_12_t4_2_acc() -> None:
    """DF1 p. 13-12: T4:2.ACC -> mask 0F, 00 04 02 02 (sub-element 2 = accumulated)."""
    address = parse_plc5_address("T4:2.ACC")
    assert encode_logical_binary(address) == bytes.fromhex("0F 00 04 02 02")
    assert decode_logical_binary(bytes.fromhex("0F 00 04 02 02")) == ((0, 4, 2, 2), 5)


def test_df1_13_12_pd12_10_sp_decodes() -> None:
    """DF1 p. 13-12: PD12:10.SP -> 0F 00 0C 0A 02 (PD files are not served; the bytes decode)."""
    assert decode_logical_binary(bytes.fromhex("0F 00 0C 0A 02")) == ((0, 12, 10, 2), 5)


def test_df1_13_15_logical_ascii_n10_360() -> None:
    """DF1 p. 13-15 and KF2 p. 6-13 Figure 6.9: NUL $ N10:360 NUL."""
    wire = bytes.fromhex("00 24 4E 31 30 3A 33 36 30 00")
    assert encode_logical_ascii(parse_plc5_address("N10:360")) == wire
    assert decode_logical_ascii(wire + b"\x99") == ("N10:360", 10)


def test_df1_13_11_levels_of_255_and_more_use_ff() -> None:
    """p. 13-11: "greater than or equal to 255" -> FF lo hi; 254 is still one byte."""
    assert encode_logical_binary(Plc5Address("N", 7, 254)) == bytes.fromhex("07 00 07 FE")
    assert encode_logical_binary(Plc5Address("N", 7, 255)) == bytes.fromhex("07 00 07 FF FF 00")
    assert encode_logical_binary(Plc5Address("N", 300, 0)) == bytes.fromhex("07 00 FF 2C 01 00")


def test_s4516_sample_mask_0f_decodes_to_the_same_word() -> None:
    """S4516 §2.6.1 sample: mask 0F with level 4 = 0 addresses the same word as mask 07."""
    assert decode_logical_binary(bytes.fromhex("0F 00 07 1E 00"))[0][:3] == (0, 7, 30)


# ------------------------------------------------------------------------------ parsing


@pytest.mark.parametrize(
    ("text", "expected", "words"),
    [
        ("N7:0", Plc5Address("N", 7, 0), 1),
        ("F8:2", Plc5Address("F", 8, 2), 2),
        ("B3:300", Plc5Address("B", 3, 300), 1),
        ("B3/5", Plc5Address("B", 3, 0, bit=5), 1),
        ("B3/37", Plc5Address("B", 3, 2, bit=5), 1),
        ("N7:0/3", Plc5Address("N", 7, 0, bit=3), 1),
        ("T4:1.ACC", Plc5Address("T", 4, 1, 2), 1),
        ("T4:2.PRE", Plc5Address("T", 4, 2, 1), 1),
        ("T4:1", Plc5Address("T", 4, 1), 3),
        ("T4:1/DN", Plc5Address("T", 4, 1, 0, 13), 1),
        ("T4:1.DN", Plc5Address("T", 4, 1, 0, 13), 1),
        ("C5:0.ACC", Plc5Address("C", 5, 0, 2), 1),
        ("C5:0/CU", Plc5Address("C", 5, 0, 0, 15), 1),
        ("R6:0.POS", Plc5Address("R", 6, 0, 2), 1),
        ("S:3", Plc5Address("S", 2, 3), 1),
        ("O:0", Plc5Address("O", 0, 0), 1),
        ("I:017/17", Plc5Address("I", 1, 0o17, bit=0o17), 1),
        ("n7:30", Plc5Address("N", 7, 30), 1),
        ("$N7:30", Plc5Address("N", 7, 30), 1),
    ],
)
def test_parse_the_forms_users_type(text: str, expected: Plc5Address, words: int) -> None:
    address = parse_plc5_address(text)
    assert address == expected
    assert address.words == words
    assert parse_plc5_address(str(address)) == address


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("N:0", "file number"),
        ("X7:0", "unknown file type"),
        ("N7/5", "only for binary"),
        ("I:018", "octal"),
        ("T4:1.LEN", "no member"),
        ("T4:1/3", "name the word"),
        ("N7:0/16", "out of range"),
        ("N7", "not a PLC-5 address"),
        ("B3/16000", "beyond 15999"),
        ("C5:0/EN", "no status bit"),
    ],
)
def test_bad_addresses_say_what_is_wrong(text: str, message: str) -> None:
    with pytest.raises(AddressError, match=message):
        parse_plc5_address(text)


def test_truncated_and_invalid_binary_addresses() -> None:
    for data in (b"", b"\x07\x00", b"\x07\x00\x07\xff\x01", b"\x00", b"\x1f\x00"):
        with pytest.raises(AddressError):
            decode_logical_binary(data)
    with pytest.raises(AddressError, match="NUL"):
        decode_logical_ascii(b"\x00$N7:0")


@given(
    file_number=st.integers(0, 999),
    element=st.integers(0, 0xFFFF),
    sub=st.none() | st.integers(0, 0xFFFF),
    compact=st.booleans(),
)
def test_logical_binary_round_trip(file_number: int, element: int, sub: int | None, compact: bool) -> None:
    address = Plc5Address("N", file_number, element, sub)
    wire = encode_logical_binary(address, compact=compact)
    assert decode_logical_binary(wire + b"\xaa") == (address.levels, len(wire))


# ------------------------------------------------------------------------------ packets


def test_word_range_read_layout_matches_kf2_5_57_and_the_pccc_codec() -> None:
    """KF2 p. 5-57: PACKET OFFSET(2) TOTAL TRANS(2) ADDRESS SIZE(1), low byte first."""
    address = encode_logical_binary(parse_plc5_address("N7:30"))
    read = WordRangeReadParams(address, size=20)
    assert read.encode() == bytes.fromhex("00 00 0A 00 07 00 07 1E 14")
    assert WordRangeReadParams.decode(read.encode()) == WordRangeReadParams(address, 20, 0, 10)
    typed_address = pccc.WordRangeRead(pccc.LogicalBinaryAddress.of(0, 7, 30), 20)
    assert typed_address.encode_params() == read.encode()  # one layout: pccc.plc5.word_range_params


def test_word_range_write_layout() -> None:
    address = encode_logical_binary(parse_plc5_address("B3:300"), compact=True)
    write = WordRangeWriteParams(address, bytes.fromhex("34 12 78 56"), packet_offset=0)
    assert write.encode() == bytes.fromhex("00 00 02 00 06 03 FF 2C 01 34 12 78 56")
    assert WordRangeWriteParams.decode(write.encode()) == WordRangeWriteParams(
        address, bytes.fromhex("34 12 78 56"), 0, 2
    )
    ascii_address = encode_logical_ascii("N7:0")
    assert (
        WordRangeWriteParams.decode(WordRangeWriteParams(ascii_address, b"\x01\x00").encode()).address == ascii_address
    )


def test_read_modify_write_is_the_coil_write() -> None:
    """p. 7-20: AND mask 0 resets a bit, OR mask 1 sets it; masks low byte first."""
    address = encode_logical_binary(parse_plc5_address("B3:0"))
    on = ReadModifyWrite.set_bit(address, 5)
    assert on.encode() == address + bytes.fromhex("FF FF 20 00")
    off = ReadModifyWrite.reset_bit(address, 15)
    assert off.encode() == address + bytes.fromhex("FF 7F 00 00")
    assert on.apply(0x0000) == 0x0020 and off.apply(0xFFFF) == 0x7FFF
    assert ReadModifyWrite.decode(on.encode() + off.encode()).sets == on.sets + off.sets
    assert ReadModifyWrite(((address, 0x5555, 0xA00F),)).apply(0xF0F0) == 0xF05F  # (F0F0 & 5555) | A00F


def test_packet_limits() -> None:
    address = encode_logical_binary(parse_plc5_address("N7:0"))
    with pytest.raises(AddressError, match="even"):
        WordRangeReadParams(address, 3).encode()
    with pytest.raises(AddressError, match=r"2\.\.244"):
        WordRangeReadParams(address, 246).encode()
    with pytest.raises(AddressError, match="239"):
        WordRangeWriteParams(address, bytes(236)).encode()
    with pytest.raises(AddressError, match="whole number"):
        WordRangeWriteParams(address, b"\x01").encode()
    with pytest.raises(AddressError, match="243"):
        ReadModifyWrite(((address, 0, 0),) * 31).encode()
    with pytest.raises(AddressError, match="truncated"):
        ReadModifyWrite.decode(address + b"\xff")


# ------------------------------------------------------------- 1785-KE printed frames (p. 5-5, 5-6)


def test_1785ke_5_5_word_range_write_logical_binary_n10_15() -> None:
    """1785-KE manual p. 5-5: write 4 words to N10:15 of PLC-5 node 51 (octal), and the reply."""
    frame = bytes.fromhex("10 02 29 20 0F 00 46 01 00 00 00 04 00 0F 00 0A 0F 00 22 11 44 33 66 55 88 77 10 03 D1")
    address = bytes.fromhex("0F 00 0A 0F 00")  # mask 0F: data table 0, file 10, element 15, sub 0
    assert decode_logical_binary(address) == ((0, 10, 15, 0), 5)
    write = WordRangeWriteParams(address, bytes.fromhex("22 11 44 33 66 55 88 77"))
    header = bytes.fromhex("29 20 0F 00 46 01 00")  # DST SRC CMD STS TNS(2) FNC 00
    assert encode_frame(header + write.encode(), Checksum.BCC) == frame
    assert WordRangeWriteParams.decode(write.encode()) == WordRangeWriteParams(address, write.data, 0, 4)
    reply = bytes.fromhex("10 02 20 29 4F 00 46 01 10 03 21")
    assert encode_frame(bytes.fromhex("20 29 4F 00 46 01"), Checksum.BCC) == reply


def test_1785ke_5_6_word_range_read_logical_ascii_n10_15() -> None:
    """1785-KE manual p. 5-6: read the same 4 words by the logical ASCII address $N10:15."""
    frame = bytes.fromhex("10 02 29 20 0F 00 47 01 01 00 00 04 00 00 24 4E 31 30 3A 31 35 00 08 10 03 E0")
    address = encode_logical_ascii(parse_plc5_address("N10:15"))
    assert address == bytes.fromhex("00 24 4E 31 30 3A 31 35 00")
    read = WordRangeReadParams(address, size=8)
    header = bytes.fromhex("29 20 0F 00 47 01 01")
    assert encode_frame(header + read.encode(), Checksum.BCC) == frame
    assert WordRangeReadParams.decode(read.encode()) == WordRangeReadParams(address, 8, 0, 4)
    reply = bytes.fromhex("10 02 20 29 4F 00 47 01 22 11 44 33 66 55 88 77 10 03 BC")
    assert encode_frame(bytes.fromhex("20 29 4F 00 47 01 22 11 44 33 66 55 88 77"), Checksum.BCC) == reply


def test_plc5_address_error_is_the_projects_address_error_answered_0x03() -> None:
    """A bad PLC-5 address is a rule the request broke, as a bad SLC 500 address is: Modbus 0x03."""
    from gateway.errors import InvalidRequest, modbus_exception
    from gateway.protocols.df1 import address, plc5_address

    assert plc5_address.AddressError is address.AddressError
    with pytest.raises(InvalidRequest) as caught:
        parse_plc5_address("Q9:0")
    assert modbus_exception(caught.value).code == 0x03
    assert modbus_exception(plc5_address.AddressError("N7:70000")).code == 0x03


# ---------------------------------------------------------------------------------------------
# Behaviours a mutation run found unchecked


@pytest.mark.parametrize(
    ("address", "text"),
    [
        (Plc5Address("O", 0, 0o17, bit=0o15), "O:17/15"),  # default file numbers are left out
        (Plc5Address("I", 1, 0, bit=7), "I:0/7"),
        (Plc5Address("S", 2, 3), "S:3"),
        (Plc5Address("O", 3, 1), "O3:1"),  # other file numbers of O, I, S are written
        (Plc5Address("I", 0, 1), "I0:1"),
        (Plc5Address("S", 1, 3), "S1:3"),
        (Plc5Address("B", 3, 2, bit=5), "B3:2/5"),
        (Plc5Address("T", 4, 1, sub_element=2), "T4:1.ACC"),
    ],
)
def test_str_is_what_a_programmer_types(address: Plc5Address, text: str) -> None:
    assert str(address) == text
    assert parse_plc5_address(text) == address


def test_str_of_a_sub_element_without_a_name_is_its_number() -> None:
    assert str(Plc5Address("N", 7, 0, sub_element=3)) == "N7:0.3"


@pytest.mark.parametrize(("text", "element", "bit"), [("B3/16", 1, 0), ("B3/300", 18, 12), ("B3/15999", 999, 15)])
def test_direct_bit_addresses_count_16_bits_per_word(text: str, element: int, bit: int) -> None:
    address = parse_plc5_address(text)
    assert (address.element, address.bit) == (element, bit)


def test_a_direct_bit_past_15999_is_refused() -> None:
    with pytest.raises(AddressError, match="beyond 15999"):
        parse_plc5_address("B3/16000")


@pytest.mark.parametrize("text", ["", "   ", "N7:0\u00e9", "N7\x00:0"])
def test_logical_ascii_refuses_what_cannot_be_sent(text: str) -> None:
    with pytest.raises(AddressError, match="cannot be sent"):
        encode_logical_ascii(text)


def test_logical_ascii_sends_a_typed_address_without_its_blanks() -> None:
    assert encode_logical_ascii("  N7:0 ") == b"\x00$N7:0\x00"


def test_logical_ascii_decodes_an_empty_address_and_a_byte_that_is_not_ascii() -> None:
    assert decode_logical_ascii(b"\x00$\x00N7:0\x00") == ("", 3)
    assert decode_logical_ascii(b"xx\x00$N7\xff\x00", 2) == ("N7\ufffd", 8)


def test_file_numbers_run_to_999() -> None:
    assert Plc5Address("N", 999, 0).file_number == 999
    with pytest.raises(AddressError, match="file number 1000 out of range"):
        Plc5Address("N", 1000, 0)


@pytest.mark.parametrize(("text", "what"), [("O:8", "element 8 is octal"), ("O:0/8", "bit 8 is octal"),
                                            ("I:19", "element 19 is octal")])
def test_an_octal_field_with_8_or_9_is_refused_naming_the_field(text: str, what: str) -> None:
    with pytest.raises(AddressError, match=what):
        parse_plc5_address(text)


@pytest.mark.parametrize("mask", [0x00, 0x10, 0x1F])
def test_a_logical_binary_mask_naming_no_level_1_to_4_is_refused(mask: int) -> None:
    with pytest.raises(AddressError, match="names no level"):
        decode_logical_binary(bytes([mask, 0, 7, 0, 0, 0]))


# ------------------------------------------------- the byte-level builders' bounds, field by field


def test_word_range_read_size_is_even_from_2_to_244_bytes() -> None:
    """KF2 p. 5-57 / 1770-6.5.16: a word range read asks for whole words, at most 244 data bytes."""
    address = encode_logical_binary(parse_plc5_address("N7:0"))
    assert WordRangeReadParams(address, 2).encode() == bytes.fromhex("00 00 01 00 07 00 07 00 02")
    assert WordRangeReadParams(address, 244).encode()[-1] == 244
    for size in (0, 1, 245, 246):
        with pytest.raises(AddressError, match=f"size {size}"):
            WordRangeReadParams(address, size).encode()


def test_word_range_write_takes_239_bytes_of_address_and_data() -> None:
    address = encode_logical_binary(parse_plc5_address("N7:0"))  # 4 bytes
    assert WordRangeWriteParams(address, bytes(234)).encode()[8:] == bytes(234)  # 4 + 234 = 238
    with pytest.raises(AddressError, match="239"):
        WordRangeWriteParams(address, bytes(236)).encode()  # 240
    odd_address = encode_logical_binary(parse_plc5_address("N7:0"), compact=True)  # 3 bytes
    WordRangeWriteParams(odd_address, bytes(236)).encode()  # 3 + 236 = 239: the limit itself


def test_word_range_offset_and_total_are_sent_as_given_over_the_whole_16_bits() -> None:
    """PACKET OFFSET and TOTAL TRANS are unsigned words, low byte first; a total given is sent as is."""
    address = encode_logical_binary(parse_plc5_address("N7:0"))
    read = WordRangeReadParams(address, 4, packet_offset=0xFFFF, total_transaction=0x8001)
    assert read.encode() == bytes.fromhex("FF FF 01 80") + address + b"\x04"
    assert WordRangeReadParams.decode(read.encode()) == read
    write = WordRangeWriteParams(address, b"\x01\x00", packet_offset=0x8000, total_transaction=0xFFFF)
    assert write.encode() == bytes.fromhex("00 80 FF FF") + address + b"\x01\x00"
    assert WordRangeWriteParams.decode(write.encode()) == write


@pytest.mark.parametrize(("field", "offset", "total"), [
    ("packet offset", 0x10000, 1), ("total transaction", 0, 0x10000),
    ("packet offset", -1, 1), ("total transaction", 0, -1),
])
def test_word_range_offset_and_total_outside_16_bits_are_refused_and_named(field: str, offset: int, total: int) -> None:
    address = encode_logical_binary(parse_plc5_address("N7:0"))
    value = offset if field == "packet offset" else total
    with pytest.raises(AddressError, match=f"^{field} {value} out of range"):
        WordRangeReadParams(address, 2, offset, total).encode()
    with pytest.raises(AddressError, match=f"^{field} {value} out of range"):
        WordRangeWriteParams(address, b"\x00\x00", offset, total).encode()


@pytest.mark.parametrize("length", [0, 3])
def test_word_range_parameters_cut_before_the_address_are_an_address_error(length: int) -> None:
    params = WordRangeReadParams(encode_logical_binary(parse_plc5_address("N7:0")), 2).encode()
    for decode in (WordRangeReadParams.decode, WordRangeWriteParams.decode):
        with pytest.raises(AddressError, match="truncated"):
            decode(params[:length])


def test_read_modify_write_sets_take_243_bytes() -> None:
    """p. 7-20: the ADDRESS AND OR sets of one command, at most 243 bytes; sets follow one another."""
    address = encode_logical_binary(parse_plc5_address("N7:0"))  # 4 bytes: an 8-byte set
    compact = encode_logical_binary(parse_plc5_address("N7:1"), compact=True)  # 3 bytes: a 7-byte set
    two = ReadModifyWrite(((address, 0x00FF, 0x0100), (compact, 0xFFFF, 0x0000)))
    assert two.encode() == address + bytes.fromhex("FF 00 00 01") + compact + bytes.fromhex("FF FF 00 00")
    assert ReadModifyWrite.decode(two.encode()) == two
    assert len(ReadModifyWrite(((compact, 0, 0),) * 5 + ((address, 0, 0),) * 26).encode()) == 243
    with pytest.raises(AddressError, match="243"):
        ReadModifyWrite(((compact, 0, 0),) * 4 + ((address, 0, 0),) * 27).encode()  # 244
    with pytest.raises(AddressError, match="at least one"):
        ReadModifyWrite(()).encode()


@pytest.mark.parametrize(("sets", "field"), [(((0x10000, 0),), "AND mask"), (((0, 0x10000),), "OR mask"),
                                             (((-1, 0),), "AND mask"), (((0, -1),), "OR mask")])
def test_read_modify_write_masks_outside_16_bits_are_refused_and_named(sets: tuple[tuple[int, int]],
                                                                      field: str) -> None:
    address = encode_logical_binary(parse_plc5_address("N7:0"))
    ReadModifyWrite(((address, 0xFFFF, 0xFFFF),)).encode()
    with pytest.raises(AddressError, match=f"^{field} "):
        ReadModifyWrite(tuple((address, m_and, m_or) for m_and, m_or in sets)).encode()


def test_a_coil_write_addresses_bits_0_to_15_of_the_word() -> None:
    address = encode_logical_binary(parse_plc5_address("B3:0"))
    assert ReadModifyWrite.set_bit(address, 0).sets == ((address, 0xFFFF, 0x0001),)
    assert ReadModifyWrite.reset_bit(address, 0).sets == ((address, 0xFFFE, 0x0000),)
    assert ReadModifyWrite.set_bit(address, 15).sets == ((address, 0xFFFF, 0x8000),)
    for bit in (-1, 16):
        with pytest.raises(AddressError, match=f"bit {bit} out of range"):
            ReadModifyWrite.set_bit(address, bit)
        with pytest.raises(AddressError, match=f"bit {bit} out of range"):
            ReadModifyWrite.reset_bit(address, bit)
