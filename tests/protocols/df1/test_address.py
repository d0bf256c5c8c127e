"""SLC 500 logical addresses: every form of the addressing reference, errors, round trip."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import InvalidRequest
from gateway.protocols.df1.address import AddressError, FileType, SlcAddress, parse_address

T, C, R = FileType.TIMER, FileType.COUNTER, FileType.CONTROL


@pytest.mark.parametrize(
    ("text", "expected", "canonical"),
    [
        # Table C: I/O element 3 in slot 5 (element = slot, sub-element = word).
        ("O:5.3/6", SlcAddress(FileType.OUTPUT, 0, 5, 3, 6), "O:5.3/6"),
        ("I:5.3", SlcAddress(FileType.INPUT, 1, 5, 3), "I:5.3"),
        ("$I:5.3/6", SlcAddress(FileType.INPUT, 1, 5, 3, 6), "I:5.3/6"),
        ("O:5.3", SlcAddress(FileType.OUTPUT, 0, 5, 3), "O:5.3"),
        ("I:2", SlcAddress(FileType.INPUT, 1, 2, 0), "I:2.0"),
        ("O0:1.0", SlcAddress(FileType.OUTPUT, 0, 1, 0), "O:1.0"),
        ("I1:30.1/15", SlcAddress(FileType.INPUT, 1, 30, 1, 15), "I:30.1/15"),
        # Table E: status element 3.
        ("S:3", SlcAddress(FileType.STATUS, 2, 3), "S:3"),
        ("S2:3", SlcAddress(FileType.STATUS, 2, 3), "S:3"),
        ("S:3/9", SlcAddress(FileType.STATUS, 2, 3, 0, 9), "S:3/9"),
        ("S2:3/9", SlcAddress(FileType.STATUS, 2, 3, 0, 9), "S:3/9"),
        ("S:82", SlcAddress(FileType.STATUS, 2, 82), "S:82"),
        # Table G: integer element 3.
        ("N7:3", SlcAddress(FileType.INTEGER, 7, 3), "N7:3"),
        ("N7:3/9", SlcAddress(FileType.INTEGER, 7, 3, 0, 9), "N7:3/9"),
        ("$N7:3/9", SlcAddress(FileType.INTEGER, 7, 3, 0, 9), "N7:3/9"),
        # Table I: binary element 2; absolute bit addressing.
        ("B3:2", SlcAddress(FileType.BIT, 3, 2), "B3:2"),
        ("B3:2/9", SlcAddress(FileType.BIT, 3, 2, 0, 9), "B3:2/9"),
        ("B3/37", SlcAddress(FileType.BIT, 3, 2, 0, 5), "B3:2/5"),
        ("B3/0", SlcAddress(FileType.BIT, 3, 0, 0, 0), "B3:0/0"),
        ("B3/4095", SlcAddress(FileType.BIT, 3, 255, 0, 15), "B3:255/15"),
        ("N7/17", SlcAddress(FileType.INTEGER, 7, 1, 0, 1), "N7:1/1"),
        ("S/17", SlcAddress(FileType.STATUS, 2, 1, 0, 1), "S:1/1"),
        ("R6/37", SlcAddress(R, 6, 0, 2, 5), "R6:0.POS/5"),
        # Table K: floating point element 9.
        ("F8:9", SlcAddress(FileType.FLOAT, 8, 9), "F8:9"),
        # Table M: timer structure 3.
        ("T4:3", SlcAddress(T, 4, 3), "T4:3"),
        ("T4:3.EN", SlcAddress(T, 4, 3, 0, 15), "T4:3/EN"),
        ("T4:3/EN", SlcAddress(T, 4, 3, 0, 15), "T4:3/EN"),
        ("T4:3.TT", SlcAddress(T, 4, 3, 0, 14), "T4:3/TT"),
        ("T4:3/DN", SlcAddress(T, 4, 3, 0, 13), "T4:3/DN"),
        ("T4:3.PRE", SlcAddress(T, 4, 3, 1), "T4:3.PRE"),
        ("T4:3.ACC", SlcAddress(T, 4, 3, 2), "T4:3.ACC"),
        ("T4:3.ACC/4", SlcAddress(T, 4, 3, 2, 4), "T4:3.ACC/4"),
        # Table O: counter structure 7.
        ("C5:7", SlcAddress(C, 5, 7), "C5:7"),
        ("C5:7.CU", SlcAddress(C, 5, 7, 0, 15), "C5:7/CU"),
        ("C5:7/CD", SlcAddress(C, 5, 7, 0, 14), "C5:7/CD"),
        ("C5:7.DN", SlcAddress(C, 5, 7, 0, 13), "C5:7/DN"),
        ("C5:7/OV", SlcAddress(C, 5, 7, 0, 12), "C5:7/OV"),
        ("C5:7.UN", SlcAddress(C, 5, 7, 0, 11), "C5:7/UN"),
        ("C5:7/UA", SlcAddress(C, 5, 7, 0, 10), "C5:7/UA"),
        ("C5:7.PRE", SlcAddress(C, 5, 7, 1), "C5:7.PRE"),
        ("C5:7.ACC", SlcAddress(C, 5, 7, 2), "C5:7.ACC"),
        # Table Q: control structure 0.
        ("R6:0", SlcAddress(R, 6, 0), "R6:0"),
        ("R6:0.EN", SlcAddress(R, 6, 0, 0, 15), "R6:0/EN"),
        ("R6:0/EU", SlcAddress(R, 6, 0, 0, 14), "R6:0/EU"),
        ("R6:0.DN", SlcAddress(R, 6, 0, 0, 13), "R6:0/DN"),
        ("R6:0/EM", SlcAddress(R, 6, 0, 0, 12), "R6:0/EM"),
        ("R6:0.ER", SlcAddress(R, 6, 0, 0, 11), "R6:0/ER"),
        ("R6:0/UL", SlcAddress(R, 6, 0, 0, 10), "R6:0/UL"),
        ("R6:0.IN", SlcAddress(R, 6, 0, 0, 9), "R6:0/IN"),
        ("R6:0/FD", SlcAddress(R, 6, 0, 0, 8), "R6:0/FD"),
        ("R6:0.LEN", SlcAddress(R, 6, 0, 1), "R6:0.LEN"),
        ("R6:0.POS", SlcAddress(R, 6, 0, 2), "R6:0.POS"),
        ("R6:0/3", SlcAddress(R, 6, 0, 0, 3), "R6:0/3"),
        # User files 9-255 (Table A notes 3 and 4).
        ("N9:0", SlcAddress(FileType.INTEGER, 9, 0), "N9:0"),
        ("B9:1/2", SlcAddress(FileType.BIT, 9, 1, 0, 2), "B9:1/2"),
        ("N10:0", SlcAddress(FileType.INTEGER, 10, 0), "N10:0"),
        ("B12:4", SlcAddress(FileType.BIT, 12, 4), "B12:4"),
        ("T15:0.ACC", SlcAddress(T, 15, 0, 2), "T15:0.ACC"),
        ("C20:255/DN", SlcAddress(C, 20, 255, 0, 13), "C20:255/DN"),
        ("R100:1.LEN", SlcAddress(R, 100, 1, 1), "R100:1.LEN"),
        ("F255:255", SlcAddress(FileType.FLOAT, 255, 255), "F255:255"),
        # Case and whitespace are forgiven.
        ("  n7:0 ", SlcAddress(FileType.INTEGER, 7, 0), "N7:0"),
        ("t4:3.acc", SlcAddress(T, 4, 3, 2), "T4:3.ACC"),
    ],
)
def test_valid_addresses(text: str, expected: SlcAddress, canonical: str) -> None:
    address = parse_address(text)
    assert address == expected
    assert str(address) == canonical
    assert parse_address(canonical) == address


def test_file_type_codes_from_the_notes() -> None:
    assert {t.letter: int(t) for t in FileType} == {
        "S": 0x84,
        "B": 0x85,
        "T": 0x86,
        "C": 0x87,
        "R": 0x88,
        "N": 0x89,
        "F": 0x8A,
        "O": 0x8B,
        "I": 0x8C,
        "ST": 0x8D,
        "A": 0x8E,
    }


def test_sizes() -> None:
    assert parse_address("T4:3").element_size_words == 3
    assert parse_address("T4:3").word_count == 3 and parse_address("T4:3").is_structure
    assert parse_address("T4:3.ACC").word_count == 1 and not parse_address("T4:3.ACC").is_structure
    assert parse_address("T4:3/DN").word_count == 1
    assert parse_address("C5:0").element_size_words == 3
    assert parse_address("R6:0").byte_count == 6
    assert parse_address("F8:0").element_size_words == 2 and parse_address("F8:0").word_count == 2
    assert parse_address("N7:0").element_size_words == 1 and parse_address("N7:0").byte_count == 2
    assert parse_address("O:1.2").element_size_words == 1


def test_stepping() -> None:
    assert parse_address("N7:3").offset(2) == parse_address("N7:5")
    assert parse_address("T4:3.ACC").offset(1) == parse_address("T4:4.ACC")
    assert parse_address("T4:3.ACC").with_element(9) == parse_address("T4:9.ACC")
    assert parse_address("O:5.0").offset(3) == parse_address("O:5.3")  # I/O: words in the slot
    assert parse_address("N7:3/4").offset(1) == parse_address("N7:4/4")
    with pytest.raises(AddressError):
        parse_address("N7:255").offset(1)
    with pytest.raises(AddressError):
        parse_address("N7:0").with_element(-1)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("B3:2/16", "B3:2/16: bit must be 0-15"),
        ("T4:3.XYZ", "T4:3.XYZ: unknown sub-element; timers have ACC, PRE, EN, TT, DN"),
        ("C5:1.XYZ", "C5:1.XYZ: unknown sub-element; counters have ACC, PRE, CU, CD, DN, OV, UN, UA"),
        ("R6:1.ACC", "R6:1.ACC: unknown sub-element; control files have LEN, POS, EN, EU, DN, EM, ER, UL, IN, FD"),
        ("T4:3/XY", "T4:3/XY: unknown bit; timers have EN, TT, DN"),
        ("T4:3/ACC", "T4:3/ACC: /ACC is a word; write .ACC"),
        ("T4:3/5", "T4:3/5: timers have bits EN, TT, DN in word 0 (numbered bits: .PRE/n, .ACC/n)"),
        ("T4:3.DN/2", "T4:3.DN/2: .DN is a bit; it takes no /2"),
        ("T4:3.ACC/DN", "T4:3.ACC/DN: DN is a bit of word 0; write /DN without .ACC"),
        ("N7:256", "N7:256: element 256 out of range 0-255"),
        ("N256:0", "N256:0: file number 256 out of range (SLC 500 files are 0-255)"),
        ("N3:0", "N3:0: file 3 is the bit file (B3)"),
        ("B7:0", "B7:0: file 7 is the integer file (N7)"),
        ("N2:0", "N2:0: file 2 is the status file (S:)"),
        ("F8:0/1", "F8:0/1: floating-point elements are addressed in their entirety"),
        ("F8:0.1", "F8:0.1: floating-point elements are addressed in their entirety"),
        ("N7:0.1", "N7:0.1: integer elements have no sub-elements"),
        ("O1:0", "O1:0: the output file is always file 0"),
        ("I0:0", "I0:0: the input file is always file 1"),
        ("S3:0", "S3:0: the status file is always file 2"),
        ("O:31", "O:31: slot 31 out of range 0-30"),
        ("O:1.ACC", "O:1.ACC: I/O words are numbers (O:slot.word/bit)"),
        ("I:1/16", "I:1/16: bit must be 0-15"),
        ("I/5", "I/5: I/O bits need a slot: I:slot/bit"),
        ("T4/5", "T4/5: timer files cannot be addressed by absolute bit number"),
        ("F8/5", "F8/5: float files cannot be addressed by absolute bit number"),
        ("B3/4096", "B3/4096: absolute bit 4096 out of range 0-4095"),
        ("N:0", "N:0: a file number is required after N"),
        ("ST9:0", "ST9:0: ST files are not supported"),
        ("N7:0/X", "N7:0/X: bit must be a number 0-15"),
    ],
)
def test_invalid_addresses(text: str, message: str) -> None:
    with pytest.raises(AddressError) as info:
        parse_address(text)
    assert str(info.value) == message
    assert isinstance(info.value, InvalidRequest) and isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    "text", ["", "N7", "N7:", "X7:0", "N7:0:1", "N7:-1", "7:0", "N7:0/", "N7:0.", "N 7:0", "T4:3..ACC", "B3//3"]
)
def test_not_an_address(text: str) -> None:
    with pytest.raises(AddressError, match="not an SLC 500 address"):
        parse_address(text)


def test_direct_construction_is_validated() -> None:
    with pytest.raises(AddressError):
        SlcAddress(FileType.TIMER, 4, 0, 3)
    with pytest.raises(AddressError):
        SlcAddress(FileType.INTEGER, 7, 0, 0, 16)
    with pytest.raises(AddressError):
        SlcAddress(FileType.FLOAT, 8, 0, 1)
    with pytest.raises(AddressError):
        SlcAddress(FileType.STATUS, 2, 0, 1)


# ------------------------------------------------------------------------ round trip

_elements = st.integers(0, 255)
_bits = st.none() | st.integers(0, 15)
_user_files = st.integers(9, 255)


def _data_file(letter: str, default: int) -> st.SearchStrategy[str]:
    return st.builds(
        lambda f, e, b: f"{letter}{f}:{e}" + ("" if b is None else f"/{b}"),
        st.just(default) | _user_files,
        _elements,
        _bits,
    )


def _structure(letter: str, default: int, members: list[str]) -> st.SearchStrategy[str]:
    return st.builds(
        lambda f, e, m: f"{letter}{f}:{e}{m}",
        st.just(default) | st.integers(10, 255),
        _elements,
        st.sampled_from(["", *members]),
    )


address_texts = st.one_of(
    _data_file("B", 3),
    _data_file("N", 7),
    st.builds(lambda f, e: f"F{f}:{e}", st.just(8) | st.integers(10, 255), _elements),
    st.builds(lambda e, b: f"S:{e}" + ("" if b is None else f"/{b}"), _elements, _bits),
    st.builds(
        lambda io, s, w, b: f"{io}:{s}.{w}" + ("" if b is None else f"/{b}"),
        st.sampled_from("IO"),
        st.integers(0, 30),
        st.integers(0, 255),
        _bits,
    ),
    st.builds(lambda letter, n: f"{letter}/{n}", st.sampled_from(["B3", "N7", "S", "R6", "B10"]), st.integers(0, 4095)),
    _structure("T", 4, [".ACC", ".PRE", "/EN", ".TT", "/DN", ".ACC/3", ".PRE/15"]),
    _structure("C", 5, [".ACC", ".PRE", ".CU", "/CD", "/DN", ".OV", "/UN", "/UA"]),
    _structure("R", 6, [".LEN", ".POS", "/EN", ".EU", "/DN", ".EM", "/ER", ".UL", "/IN", ".FD", "/7", ".POS/2"]),
)


@given(address_texts)
def test_round_trip(text: str) -> None:
    address = parse_address(text)
    assert parse_address(str(address)) == address
    assert str(parse_address(str(address))) == str(address)


@given(st.text(max_size=20))
def test_parse_never_raises_anything_else(text: str) -> None:
    try:
        parse_address(text)
    except AddressError:
        pass


@pytest.mark.parametrize(("text", "element", "sub_element", "bit"),
                         [("R6/50", 1, 0, 2), ("R6/40", 0, 2, 8), ("R6/47", 0, 2, 15), ("B3/50", 3, 0, 2)])
def test_absolute_bits_of_control_files_count_3_words_per_element(
    text: str, element: int, sub_element: int, bit: int
) -> None:
    address = parse_address(text)
    assert (address.element, address.sub_element, address.bit) == (element, sub_element, bit)


def test_file_numbers_and_io_words_stop_at_255() -> None:
    assert SlcAddress(FileType.INTEGER, 255, 0).file_number == 255
    with pytest.raises(AddressError, match="file number 256 out of range"):
        SlcAddress(FileType.INTEGER, 256, 0)
    assert SlcAddress(FileType.OUTPUT, 0, 1, 255).sub_element == 255
    with pytest.raises(AddressError, match="sub-element 256 out of range"):
        SlcAddress(FileType.OUTPUT, 0, 1, 256)
