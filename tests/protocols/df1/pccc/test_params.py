"""The PCCC parameter fields (``pccc/params.py``) and the commands they added: typed logical read /
write with two address fields (0F A1 / A9) and echo (06 00)."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import InvalidRequest
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import (
    Echo,
    PcccFormatError,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalTwoFieldRead,
    ProtectedTypedLogicalTwoFieldWrite,
    Request,
    decode_command,
    encode_command,
    is_write,
)
from gateway.protocols.df1.pccc.codec import Reader, encode_field
from gateway.protocols.df1.pccc.params import Byte, Decoded, Word


def H(text: str) -> bytes:
    return bytes.fromhex(text)


def test_two_address_field_read_is_size_file_type_element() -> None:
    """1756-PM020F p. 91: [byte size][file number][file type][element number]."""
    request = ProtectedTypedLogicalTwoFieldRead(FileType.INTEGER, 7, 3, 4)
    assert encode_command(request, dst=1, src=0, tns=5) == H("01 00 0F 00 05 00 A1 04 07 89 03")
    assert decode_command(H("01 00 0F 00 05 00 A1 04 07 89 03")).request == request
    expanded = ProtectedTypedLogicalTwoFieldRead(FileType.INTEGER, 300, 256, 2)
    assert expanded.encode_params() == H("02 FF 2C 01 89 FF 00 01")
    assert expanded.expanded_fields == 2


def test_two_address_field_write_carries_its_byte_size_ahead_of_the_address() -> None:
    """1756-PM020F p. 92: [byte size][file number][file type][element number][data]."""
    request = ProtectedTypedLogicalTwoFieldWrite(FileType.INTEGER, 7, 1, H("01 00 02 00"))
    assert encode_command(request, dst=1, src=0, tns=5) == H("01 00 0F 00 05 00 A9 04 07 89 01 01 00 02 00")
    assert decode_command(H("01 00 0F 00 05 00 A9 04 07 89 01 01 00 02 00")).request == request
    assert is_write(request)
    with pytest.raises(PcccFormatError):
        decode_command(H("01 00 0F 00 05 00 A9 04 07 89 01 01 00 02"))  # fewer data bytes than the size


def test_echo_sends_its_data_and_nothing_else() -> None:
    request = Echo(H("DE AD 10"))
    assert encode_command(request, dst=1, src=0, tns=9) == H("01 00 06 00 09 00 00 DE AD 10")
    assert decode_command(H("01 00 06 00 09 00 00")).request == Echo(b"")
    assert not is_write(request)
    Echo(bytes(243))
    with pytest.raises(InvalidRequest, match="PCCC: echo data bytes 244 out of range 0-243"):
        Echo(bytes(244))


def test_every_field_of_the_two_field_commands_is_range_checked_and_named() -> None:
    for field, name in (("file_type", "file type"), ("file_number", "file number"), ("element", "element"),
                        ("size", "byte size")):
        valid: dict[str, Any] = dict(file_type=0x89, file_number=7, element=0, size=2)
        with pytest.raises(InvalidRequest, match=f"PCCC: {name} 1000000 out of range"):
            ProtectedTypedLogicalTwoFieldRead(**{**valid, field: 10**6})
    with pytest.raises(InvalidRequest, match="PCCC: byte size 0 out of range 1-255"):
        ProtectedTypedLogicalTwoFieldWrite(0x89, 7, 0, b"")


def test_a_field_reads_and_writes_its_width_low_byte_first() -> None:
    class Holder:
        value = 0x1234

    assert Word("value", "value").encode(Holder()) == H("34 12")
    assert Byte("value", "value", high=0xFFFF, low=0).check(Holder()) is None
    with pytest.raises(InvalidRequest, match="PCCC: value 4660 out of range 0-255"):
        Byte("value", "value").check(Holder())
    reader = Reader(H("34"))
    with pytest.raises(PcccFormatError, match="too short for value"):
        Word("value", "value").decode(reader, Decoded())


def test_a_reader_starts_at_the_packets_first_byte_unless_given_an_offset() -> None:
    decoded = Decoded()
    Word("value", "value").decode(Reader(H("34 12")), decoded)
    assert decoded.values["value"] == 0x1234
    assert Reader(H("00 34 12"), 1).u16("value") == 0x1234


def test_an_address_fields_three_byte_form_holds_at_most_ffff() -> None:
    """notes §7.3: ``FF lo hi`` carries 255-0xFFFF; a larger value is refused as out of range."""
    assert encode_field("element", 0xFFFF) == H("FF FF FF")
    with pytest.raises(InvalidRequest, match="PCCC: element 65536 out of range 0-65535"):
        encode_field("element", 0x10000)


def test_nothing_may_follow_the_parameters() -> None:
    with pytest.raises(PcccFormatError, match="unexpected bytes after the parameters"):
        decode_command(H("01 00 0F 00 05 00 A1 04 07 89 03 00"))
    assert ProtectedTypedLogicalRead(0x89, 7, 0, 0, 2).encode_params() == H("02 07 89 00 00")


_NEW = st.one_of(
    st.builds(ProtectedTypedLogicalTwoFieldRead, st.sampled_from(list(FileType)), st.integers(0, 0xFFFF),
              st.integers(0, 0xFFFF), st.integers(1, 255)),
    st.builds(ProtectedTypedLogicalTwoFieldWrite, st.sampled_from(list(FileType)), st.integers(0, 0xFFFF),
              st.integers(0, 0xFFFF), st.binary(min_size=1, max_size=255)),
    st.builds(Echo, st.binary(max_size=243)),
)


@settings(max_examples=200, deadline=None)
@given(_NEW, st.integers(0, 255), st.integers(0, 0xFFFF))
def test_the_new_requests_round_trip(request: Request, dst: int, tns: int) -> None:
    assert decode_command(encode_command(request, dst=dst, src=0, tns=tns)).request == request
