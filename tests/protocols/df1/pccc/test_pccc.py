"""PCCC packets: vectors from the S4516-DF1 manual and the SLC 500 command notes."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import ControllerRefused, InvalidRequest, ProtocolError
from gateway.protocols.df1.address import FileType, parse_address
from gateway.protocols.df1.pccc import (
    CmdByte,
    DataType,
    DiagnosticStatus,
    DiagnosticStatusInfo,
    FileInfo,
    Function,
    LogicalBinaryAddress,
    PcccError,
    PcccFormatError,
    PcccHeader,
    ProcessorFamily,
    ProcessorMode,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadFileInfo,
    Request,
    SetProcessorMode,
    SizeLimits,
    Sts,
    TnsAllocator,
    TypeData,
    TypedData,
    TypedRead,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
    decode_command,
    decode_reply,
    decode_type_data,
    decode_typed_data,
    describe_status,
    encode_command,
    encode_reply,
    encode_type_data,
    encode_typed_data,
    reply_matches,
    slc_read_request,
    slc_write_request,
)

H = bytes.fromhex

# ------------------------------------------------------------------ SLC 500 typed logical


def test_brief_vector_protected_typed_logical_read() -> None:
    request = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 10)
    packet = encode_command(request, dst=1, src=0, tns=1)
    assert packet == H("01 00 0F 00 01 00 A2 0A 07 89 00 00")
    command = decode_command(packet)
    assert command.header == PcccHeader(1, 0, 0x0F, 0, 1)
    assert command.request == request


def test_s4516_sample_slc_read_with_encoded_element() -> None:
    # Appendix B, DF1_AppData block 2: DST 5, SRC 0, TNS 1, 110 elements of N7 from element 40;
    # the sample always encodes the element as FF lo hi; 14 bytes (B3015 = 14).
    packet = H("05 00 0F 00 01 00 A2 DC 07 89 FF 28 00 00")
    command = decode_command(packet)
    assert command.request == ProtectedTypedLogicalRead(0x89, 7, 40, 0, 220)
    assert command.header.dst == 5 and command.header.tns == 1
    # File type of the sample: file number + 0x82 -> N7 = 0x89.
    assert 7 + 0x82 == FileType.INTEGER
    # We encode the element in one byte (0-254).
    assert encode_command(command.request, dst=5, src=0, tns=1) == H("05 00 0F 00 01 00 A2 DC 07 89 28 00")


def test_s4516_sample_slc_write() -> None:
    data = bytes(range(220))
    packet = H("05 00 0F 00 01 00 AA DC 07 89 FF 28 00 00") + data
    assert len(packet) == 2 * 110 + 14  # B3015 = 2*B3010 + 14
    command = decode_command(packet)
    assert command.request == ProtectedTypedLogicalWrite(0x89, 7, 40, 0, data)


def test_three_byte_fields_low_byte_first() -> None:
    # Notes §7.3: "257 decimal expands to FF hex, 01 hex, 01 hex (low byte then high byte)".
    request = ProtectedTypedLogicalRead(FileType.INTEGER, 257, 300, 255, 2)
    packet = encode_command(request, dst=1, src=0, tns=0x1234)
    assert packet == H("01 00 0F 00 34 12 A2 02 FF 01 01 89 FF 2C 01 FF FF 00")
    assert decode_command(packet).request == request
    assert request.expanded_fields == 3
    assert ProtectedTypedLogicalRead(FileType.INTEGER, 254, 254, 0, 2).expanded_fields == 0


def test_masked_write_layout() -> None:
    # Notes §4.36: FNC AB, size, file, type, element, sub-element, mask lo/hi, data lo/hi.
    request = ProtectedTypedLogicalMaskedWrite(FileType.BIT, 3, 2, 0, 0x0200, H("00 02"))
    packet = encode_command(request, dst=1, src=0, tns=2)
    assert packet == H("01 00 0F 00 02 00 AB 02 03 85 02 00 00 02 00 02")
    assert decode_command(packet).request == request


def test_slc_request_for_address() -> None:
    timer = parse_address("T4:3")
    assert slc_read_request(timer) == ProtectedTypedLogicalRead(FileType.TIMER, 4, 3, 0, 6)
    acc = parse_address("T4:3.ACC")
    assert slc_read_request(acc) == ProtectedTypedLogicalRead(FileType.TIMER, 4, 3, 2, 2)
    assert slc_read_request(parse_address("N7:10"), size=20).size == 20
    assert slc_write_request(parse_address("O:5.1"), H("01 00")) == ProtectedTypedLogicalWrite(
        FileType.OUTPUT, 0, 5, 1, H("01 00")
    )


# --------------------------------------------------------------------- PLC-5 word range


def test_s4516_sample_plc5_word_range_read() -> None:
    # Appendix B block 1: DST 3, mask 0F, level 1 = 0, file 7, element FF 28 00, level 4 = 0,
    # 110 elements, size 220 bytes; 19 bytes (B3015 = 19).
    packet = H("03 00 0F 00 01 00 01 00 00 6E 00 0F 00 07 FF 28 00 00 DC")
    request = decode_command(packet).request
    assert request == WordRangeRead(LogicalBinaryAddress(0x0F, (0, 7, 40, 0)), 220, 0, 110)
    assert encode_command(request, dst=3, src=0, tns=1) == H("03 00 0F 00 01 00 01 00 00 6E 00 0F 00 07 28 00 DC")


def test_s4516_sample_plc5_word_range_write() -> None:
    data = bytes(220)
    packet = H("03 00 0F 00 01 00 00 00 00 6E 00 0F 00 07 FF 28 00 00") + data
    assert len(packet) == 2 * 110 + 18  # B3002 = 2*B3010 + 18
    request = decode_command(packet).request
    assert request == WordRangeWrite(LogicalBinaryAddress.for_element(7, 40), data, 0, 110)


def test_logical_binary_address_notes_vector() -> None:
    # Notes §6.0: T4:2.ACC for a PLC-5 = 00001111 / 0 / 4 / 2 / 2.
    assert LogicalBinaryAddress.of(0, 4, 2, 2).encode() == H("0F 00 04 02 02")
    assert LogicalBinaryAddress.from_slc(parse_address("T4:2.ACC")).encode() == H("0F 00 04 02 02")
    assert LogicalBinaryAddress.for_element(300, 1000).encode() == H("0F 00 FF 2C 01 FF E8 03 00")
    with pytest.raises(InvalidRequest):
        LogicalBinaryAddress(0x0F, (0, 1))


def test_word_range_read_defaults_and_validation() -> None:
    request = WordRangeRead(LogicalBinaryAddress.for_element(7, 0), 20)
    assert request.total == 10
    with pytest.raises(InvalidRequest):
        WordRangeRead(LogicalBinaryAddress.for_element(7, 0), 0)
    with pytest.raises(InvalidRequest):
        WordRangeWrite(LogicalBinaryAddress.for_element(7, 0), b"\x01")


# ---------------------------------------------------------------------- other commands


def test_read_file_info_vector() -> None:
    # Notes §7.5: cmd, sts, tnsw, fnc, 06h, 80h, xxh.
    packet = encode_command(ReadFileInfo(7), dst=1, src=0, tns=3)
    assert packet == H("01 00 0F 00 03 00 94 06 80 07")
    assert decode_command(packet).request == ReadFileInfo(7)
    info = FileInfo(size_bytes=512, element_count=256, file_type=FileType.INTEGER)
    assert info.encode() == H("00 02 00 00 00 01 00 89")
    assert FileInfo.decode(info.encode()) == info
    assert info.known_type is FileType.INTEGER
    assert FileInfo(0, 0, 0x8F).known_type is None
    with pytest.raises(PcccFormatError):
        FileInfo.decode(b"\x00")


def test_set_processor_mode_vector() -> None:
    # Notes §7.6: one parameter, the mode byte; 01 program, 06 run, 07-09 test.
    packet = encode_command(SetProcessorMode(ProcessorMode.RUN), dst=1, src=0, tns=4)
    assert packet == H("01 00 0F 00 04 00 80 06")
    assert decode_command(packet).request == SetProcessorMode(6)
    assert [int(m) for m in ProcessorMode] == [0x01, 0x06, 0x07, 0x08, 0x09]


def test_diagnostic_status() -> None:
    packet = encode_command(DiagnosticStatus(), dst=1, src=0, tns=5)
    assert packet == H("01 00 06 00 05 00 03")
    assert decode_command(packet).request == DiagnosticStatus()
    info = DiagnosticStatusInfo.build(processor_type=0x5B, series="C", frn=4, catalog="1747-L541")
    assert info.processor_type == 0x5B
    assert info.family is ProcessorFamily.SLC5_04
    assert info.series == "C" and info.frn == 4
    assert info.catalog == "1747-L541"
    # Notes §6.0: bits 0-4 = 0 for FRN1, bits 5-7 = 0 for series A.
    assert DiagnosticStatusInfo(bytes((0, 0xEE, 0, 0x49, 0x21))).series == "B"
    assert DiagnosticStatusInfo(bytes((0, 0xEE, 0, 0x49, 0x21))).frn == 2
    assert DiagnosticStatusInfo(b"").family is None


# --------------------------------------------------------------- type/data parameters


@pytest.mark.parametrize("encoded", [H("43"), H("49 03"), H("4A 03 00")])
def test_type_data_three_equivalent_encodings(encoded: bytes) -> None:
    # Notes, "Important type/data parameter note": ID 4, size 3 in all three cases.
    assert decode_type_data(encoded) == (TypeData(4, 3), len(encoded))


def test_type_data_encoding() -> None:
    assert encode_type_data(4, 3) == H("43")
    assert encode_type_data(DataType.INTEGER, 2) == H("42")
    assert encode_type_data(DataType.ARRAY, 5) == H("95 09")  # ID 9 > 7 needs a byte
    assert decode_type_data(H("99 09 05")) == (TypeData(DataType.ARRAY, 5), 3)
    assert encode_type_data(DataType.STRING, 84) == H("99 1E 54")
    assert encode_type_data(4, 300) == H("4A 2C 01")
    assert decode_type_data(H("FF 00") + encode_type_data(0x1E, 84), 2) == (TypeData(0x1E, 84), 5)
    with pytest.raises(PcccFormatError):
        decode_type_data(H("4A 03"))


def test_typed_data_array_and_bare() -> None:
    data = H("01 00 02 00")
    encoded = encode_typed_data(DataType.INTEGER, 2, data)
    assert encoded == H("95 09 42") + data
    assert decode_typed_data(encoded) == TypedData(DataType.INTEGER, 2, data)
    assert decode_typed_data(H("99 09 05 42") + data) == TypedData(DataType.INTEGER, 2, data)
    assert decode_typed_data(encode_typed_data(DataType.INTEGER, 2, H("07 00"))) == TypedData(4, 2, H("07 00"))
    assert encode_typed_data(DataType.INTEGER, 2, H("07 00")) == H("42 07 00")
    # The element descriptor inside an array in its padded forms.
    assert decode_typed_data(H("99 09 06 49 02") + data) == TypedData(4, 2, data)
    assert decode_typed_data(H("99 09 07 4A 02 00") + data) == TypedData(4, 2, data)
    assert decode_typed_data(H("9A 09 06 00 49 02") + data).count == 2
    with pytest.raises(PcccFormatError):
        decode_typed_data(H("99 09 09 42") + data)  # array longer than the bytes
    with pytest.raises(PcccFormatError):
        decode_typed_data(H("99 09 04 42 01 00 02"))


def test_typed_read_and_write_packets() -> None:
    address = LogicalBinaryAddress.for_element(7, 0)
    read = TypedRead(address, 2)
    packet = encode_command(read, dst=1, src=0, tns=6)
    assert packet == H("01 00 0F 00 06 00 68 00 00 02 00 0F 00 07 00 00 02 00")
    assert decode_command(packet).request == read
    write = TypedWrite(address, DataType.INTEGER, 2, H("01 00 02 00"))
    packet = encode_command(write, dst=1, src=0, tns=7)
    assert packet == H("01 00 0F 00 07 00 67 00 00 02 00 0F 00 07 00 00 95 09 42 01 00 02 00")
    assert decode_command(packet).request == write
    # Typed write accepts any equivalent type/data encoding.
    padded = H("01 00 0F 00 07 00 67 00 00 02 00 0F 00 07 00 00 9A 09 07 00 4A 02 00 01 00 02 00")
    assert decode_command(padded).request == write
    with pytest.raises(InvalidRequest):
        TypedWrite(address, DataType.INTEGER, 2, H("01"))


# ------------------------------------------------------------------------------ replies


def test_reply_to_sample_command_with_ext_sts() -> None:
    # Appendix B block 2: address out of range -> STS F0, EXT STS 06, 7 bytes.
    command = decode_command(H("05 00 0F 00 2A 00 A2 DC 07 89 FF 28 00 00")).header
    reply_packet = encode_reply(command, sts=0xF0, ext_sts=0x06)
    assert reply_packet == H("00 05 4F F0 2A 00 06")
    reply = decode_reply(reply_packet)
    assert reply.sts == Sts.EXTENDED and reply.ext_sts == 0x06 and reply.data == b""
    assert reply_matches(command, reply)
    error = reply.error(command="N7:40")
    assert isinstance(error, PcccError) and isinstance(error, ControllerRefused)
    assert error.description == "Address doesn't point to something usable"
    assert error.reason == error.description
    assert error.sts == 0xF0 and error.ext_sts == 0x06 and error.code == 0xF0
    assert "N7:40" in str(error) and "EXT STS 0x06" in str(error)
    with pytest.raises(PcccError):
        reply.raise_for_status()


def test_successful_read_reply() -> None:
    command = PcccHeader(1, 0, 0x0F, 0, 0x0102)
    packet = encode_reply(command, data=H("34 12 78 56"))
    assert packet == H("00 01 4F 00 02 01 34 12 78 56")
    reply = decode_reply(packet)
    assert reply.ok and reply.data == H("34 12 78 56") and reply.command == 0x0F
    assert reply.error() is None
    reply.raise_for_status()
    assert not reply_matches(PcccHeader(1, 0, 0x0F, 0, 0x0103), reply)
    assert not reply_matches(PcccHeader(1, 0, 0x06, 0, 0x0102), reply)
    assert reply_matches(encode_command(ReadFileInfo(7), dst=1, src=0, tns=0x0102), reply)


def test_owner_node_after_ext_sts_1a() -> None:
    # Notes §4.36: F0 1A = file already open + node address of file owner (1 byte).
    reply = decode_reply(H("00 01 4F F0 09 00 1A 05"))
    assert reply.ext_sts == 0x1A and reply.owner_node == 5
    error = reply.error()
    assert error is not None and error.owner_node == 5
    assert "owner node 5" in str(error)
    assert encode_reply(PcccHeader(1, 0, 0x0F, 0, 9), sts=0xF0, ext_sts=0x1A, owner_node=5) == H(
        "00 01 4F F0 09 00 1A 05"
    )


def test_remote_sts_without_ext_sts() -> None:
    reply = decode_reply(H("00 01 4F 10 01 00"))
    assert reply.ext_sts is None
    error = reply.error()
    assert error is not None and error.description == "Illegal command or format"


@pytest.mark.parametrize(
    ("sts", "ext", "text"),
    [
        (0x00, None, "Success - no error"),
        (0x02, None, "Cannot guarantee delivery: link layer"),
        (0x05, None, "Application layer timed out waiting for a response"),
        (0x10, None, "Illegal command or format"),
        (0x50, None, "Addressing problem or memory protect rungs"),
        (0x70, None, "Processor is in program mode"),
        (0xF0, 0x0B, "Access denied, improper privilege"),
        (0xF0, 0x11, "Illegal data type"),
        (0xF0, 0x1B, "Another node is the program owner"),
        (0xF0, 0x7E, "Unknown extended status 0x7E"),
    ],
)
def test_status_descriptions(sts: int, ext: int | None, text: str) -> None:
    assert describe_status(sts, ext) == text


def test_status_descriptions_per_command() -> None:
    assert describe_status(0xF0, 0x07, cmd=0x0E) == "Invalid address"
    assert describe_status(0xF0, 0x07, cmd=0x4F) == "File is wrong size"
    keyswitch = describe_status(0xF0, 0x0C, fnc=Function.SET_PROCESSOR_MODE)
    assert keyswitch.startswith("Condition cannot be generated")
    assert describe_status(0x50, fnc=Function.READ_FILE_INFO) == "Bad address; file doesn't exist"
    assert describe_status(0x12) == "Cannot guarantee delivery: link layer; Illegal command or format"
    assert "missing" in describe_status(0xF0)


def test_reply_format_errors() -> None:
    with pytest.raises(PcccFormatError):
        decode_reply(H("00 01 4F 00 01"))
    with pytest.raises(PcccFormatError):
        decode_reply(H("00 01 0F 00 01 00"))  # a command
    with pytest.raises(PcccFormatError):
        decode_reply(H("00 01 4F F0 01 00"))  # EXT STS missing
    with pytest.raises(InvalidRequest):
        encode_reply(PcccHeader(1, 0, 0x0F, 0, 1), sts=0xF0)


# --------------------------------------------------------------------- controller side


def test_decode_command_errors_carry_the_header() -> None:
    with pytest.raises(PcccFormatError) as info:
        decode_command(H("01 00 0F 00 01 00 55"))
    assert info.value.header == PcccHeader(1, 0, 0x0F, 0, 1)
    assert isinstance(info.value, ProtocolError)
    with pytest.raises(PcccFormatError) as info:
        decode_command(H("01 00 0F 00 01 00 A2 0A 07"))  # truncated
    assert info.value.header is not None
    with pytest.raises(PcccFormatError):
        decode_command(H("01 00 0F 00 01 00 A2 0A 07 89 00 00 99"))  # trailing byte
    with pytest.raises(PcccFormatError):
        decode_command(H("01 00 0F 00 01 00 A2 00 07 89 00 00"))  # size 0
    with pytest.raises(PcccFormatError):
        decode_command(H("01 00 4F 00 01 00"))  # a reply
    with pytest.raises(PcccFormatError) as info:
        decode_command(H("01 00"))
    assert info.value.header is None
    with pytest.raises(PcccFormatError):
        decode_command(H("01 00 0F 00 01 00 AA 04 07 89 00 00 01 00"))  # fewer data bytes than size


def test_controller_answers_a_read() -> None:
    packet = encode_command(ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 4), dst=1, src=0, tns=77)
    command = decode_command(packet)
    reply = decode_reply(encode_reply(command.header, data=H("01 00 02 00")))
    assert (reply.dst, reply.src, reply.cmd, reply.tns) == (0, 1, 0x4F, 77)
    assert reply_matches(packet, reply)


requests = st.one_of(
    st.builds(
        ProtectedTypedLogicalRead,
        st.sampled_from(list(FileType)),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.integers(1, 255),
    ),
    st.builds(
        ProtectedTypedLogicalWrite,
        st.sampled_from(list(FileType)),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.binary(min_size=1, max_size=255),
    ),
    st.builds(
        ProtectedTypedLogicalMaskedWrite,
        st.sampled_from(list(FileType)),
        st.integers(0, 300),
        st.integers(0, 300),
        st.integers(0, 2),
        st.integers(0, 0xFFFF),
        st.binary(max_size=82),
    ),
    st.builds(ReadFileInfo, st.integers(0, 0xFFFF)),
    st.builds(SetProcessorMode, st.sampled_from(list(ProcessorMode))),
    st.just(DiagnosticStatus()),
    st.builds(
        WordRangeRead,
        st.builds(LogicalBinaryAddress.for_element, st.integers(0, 999), st.integers(0, 999)),
        st.integers(1, 244),  # pccc.limits.PLC5_WORD_RANGE
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
    ),
    st.builds(
        WordRangeWrite,
        st.builds(LogicalBinaryAddress.for_element, st.integers(0, 999), st.integers(0, 999)),
        st.binary(min_size=1, max_size=100).map(lambda b: b + b),
    ),
    st.builds(
        TypedRead,
        st.builds(LogicalBinaryAddress.for_element, st.integers(0, 999), st.integers(0, 999)),
        st.integers(1, 1000),
    ),
    st.builds(
        TypedWrite,
        st.builds(LogicalBinaryAddress.for_element, st.integers(0, 999), st.integers(0, 999)),
        st.sampled_from(list(DataType)).filter(lambda t: t != DataType.ARRAY),
        st.just(2),
        st.binary(min_size=1, max_size=60).map(lambda b: b + b),
    ),
)


@settings(max_examples=300, deadline=None)
@given(requests, st.integers(0, 255), st.integers(0, 255), st.integers(0, 0xFFFF))
def test_every_request_round_trips(request: Request, dst: int, src: int, tns: int) -> None:
    packet = encode_command(request, dst=dst, src=src, tns=tns)
    command = decode_command(packet)
    assert command.request == request
    assert command.header == PcccHeader(dst, src, request.CMD, 0, tns)
    assert packet[2] in (CmdByte.DIAGNOSTIC, CmdByte.EXTENDED)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40))
def test_decode_command_never_raises_anything_else(packet: bytes) -> None:
    try:
        decode_command(packet)
    except PcccFormatError:
        pass


# ---------------------------------------------------------------------------- TNS, limits


def test_tns_allocator() -> None:
    tns = TnsAllocator(start=0xFFFE)
    first, second, third = tns.allocate(), tns.allocate(), tns.allocate()
    assert (first, second, third) == (0xFFFE, 0xFFFF, 0x0000)
    tns.release(0xFFFF)
    assert tns.outstanding == {0xFFFE, 0x0000}
    allocator = TnsAllocator(start=5)
    a = allocator.allocate()
    for _ in range(0xFFFF):
        allocator.release(allocator.allocate())
    assert a == 5 and allocator.allocate() != 5  # the outstanding TNS is skipped on wrap-around


def test_tns_0_is_a_transaction_number_like_any_other() -> None:
    """A core's ``first_tns`` is taken modulo 0x10000 (0x10000 gives 0): numbering may start at 0."""
    allocator = TnsAllocator(start=0)
    assert (allocator.allocate(), allocator.allocate()) == (0, 1)


def test_tns_allocator_exhausted() -> None:
    allocator = TnsAllocator(start=1)
    for _ in range(0x10000):
        allocator.allocate()
    with pytest.raises(InvalidRequest):
        allocator.allocate()


def test_processor_family_limits() -> None:
    for family in (ProcessorFamily.SLC500_FIXED, ProcessorFamily.SLC5_01, ProcessorFamily.SLC5_02):
        assert (family.max_read_bytes, family.max_write_bytes) == (82, 82)
    for family in (ProcessorFamily.SLC5_03, ProcessorFamily.SLC5_04, ProcessorFamily.SLC5_05):
        assert (family.max_read_bytes, family.max_write_bytes) == (236, 228)
    assert (ProcessorFamily.PLC5.max_read_bytes, ProcessorFamily.PLC5.max_write_bytes) == (230, 222)
    # Notes §4.36 example: 5/03 without Internet field, file and sub-element in 3-byte form -> 224.
    assert ProcessorFamily.SLC5_03.limits.write_limit(expanded_fields=2) == 224
    assert ProcessorFamily.SLC5_04.limits.max_read_elements(6) == 39  # timers: 39 (read table)
    assert ProcessorFamily.SLC5_04.limits.max_write_elements(2) == 114
    assert ProcessorFamily.from_processor_type(0x49) is ProcessorFamily.SLC5_03
    assert ProcessorFamily.from_processor_type(0x18) is ProcessorFamily.SLC5_01
    assert ProcessorFamily.from_processor_type(0x77) is None
    custom = SizeLimits(max_read_bytes=120, max_write_bytes=100)
    assert custom.max_read_elements(2) == 60
    with pytest.raises(ValueError):
        SizeLimits(0, 10)


def test_request_validation() -> None:
    with pytest.raises(InvalidRequest):
        ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 256)
    with pytest.raises(InvalidRequest):
        ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 0, 0, b"")
    with pytest.raises(InvalidRequest):
        ProtectedTypedLogicalRead(FileType.INTEGER, 0x10000, 0, 0, 2)
    with pytest.raises(InvalidRequest):
        encode_command(DiagnosticStatus(), dst=256, src=0, tns=0)


# --- the refusal as the gateway reports it (survivors of a mutation run) ------------


def test_a_refusal_names_the_command_its_codes_and_the_manuals_text_for_that_function() -> None:
    reply = decode_reply(H("00 01 4F F0 09 00 0C"))  # SET PROCESSOR MODE refused: keyswitch not in REM
    error = reply.error(command="set mode RUN", fnc=Function.SET_PROCESSOR_MODE)
    assert error is not None
    assert error.command == "set mode RUN" and error.code == 0xF0 and error.sts == 0xF0 and error.ext_sts == 0x0C
    assert error.reason == error.description == "Condition cannot be generated (keyswitch not in REM)"
    assert str(error) == ("set mode RUN: controller refused: STS 0xF0 EXT STS 0x0C: "
                          "Condition cannot be generated (keyswitch not in REM)")
    with pytest.raises(ControllerRefused) as raised:
        reply.raise_for_status(command="set mode RUN", fnc=Function.SET_PROCESSOR_MODE)
    assert str(raised.value) == str(error)


def test_a_refusal_without_a_command_name_or_ext_sts_or_owner_has_no_empty_parts() -> None:
    error = decode_reply(H("00 01 4F 10 01 00")).error()
    assert error is not None and error.command == "" and error.owner_node is None
    assert str(error).startswith("controller refused: STS 0x10: ")
    assert "EXT STS" not in str(error) and "owner" not in str(error) and "XX" not in str(error)


def test_an_unknown_local_error_names_its_low_nibble() -> None:
    assert describe_status(0x0C) == "Unknown local error 0x0C"
    assert describe_status(0x1C) == "Unknown local error 0x0C; Illegal command or format"


# --- range checks of the SLC 500 PCCC commands: each field's range, and the error names it -------

_SLC_COMMANDS: list[tuple[type, dict[str, object], dict[str, str]]] = [
    (ProtectedTypedLogicalRead, dict(file_type=0x89, file_number=7, element=0, sub_element=0, size=2),
     {"file_type": "file type", "size": "byte size", "file_number": "file number", "element": "element",
      "sub_element": "sub element"}),
    (ProtectedTypedLogicalWrite, dict(file_type=0x89, file_number=7, element=0, sub_element=0, data=b"\x00\x01"),
     {"file_type": "file type", "file_number": "file number", "element": "element", "sub_element": "sub element"}),
    (ProtectedTypedLogicalMaskedWrite,
     dict(file_type=0x85, file_number=3, element=0, sub_element=0, mask=0x0004, data=b"\x00\x04"),
     {"file_type": "file type", "mask": "bit mask", "file_number": "file number", "element": "element",
      "sub_element": "sub element"}),
    (ReadFileInfo, dict(file_number=7), {"file_number": "file number"}),
    (SetProcessorMode, dict(mode=1), {"mode": "mode"}),
]


@pytest.mark.parametrize(("cls", "valid", "fields"), _SLC_COMMANDS, ids=lambda v: getattr(v, "__name__", ""))
def test_every_field_of_an_slc_command_is_range_checked_and_named(
    cls: type, valid: dict[str, object], fields: dict[str, str]
) -> None:
    import re

    cls(**valid)
    for field, name in fields.items():
        with pytest.raises(InvalidRequest) as info:
            cls(**{**valid, field: 10**6})
        found = re.fullmatch(rf"PCCC: {name} 1000000 out of range (\d+)-(\d+)", str(info.value))
        assert found, (field, str(info.value))
        low, high = int(found[1]), int(found[2])
        # a byte or a word; a word range read's size: 244 data bytes at most (pccc/limits.py)
        assert (low, high) in ((0, 0xFF), (1, 0xFF), (0, 0xFFFF), (1, 0xFFFF), (1, 244)), (field, low, high)
        cls(**{**valid, field: low})
        cls(**{**valid, field: high})
        for outside in (low - 1, high + 1):
            with pytest.raises(InvalidRequest, match=rf"PCCC: {name} {outside} out of range"):
                cls(**{**valid, field: outside})


@pytest.mark.parametrize(("cls", "low"), [(ProtectedTypedLogicalWrite, 1), (ProtectedTypedLogicalMaskedWrite, 0)])
def test_the_data_of_an_slc_write_is_one_size_byte_long(cls: type, low: int) -> None:
    valid = _SLC_COMMANDS[1 if cls is ProtectedTypedLogicalWrite else 2][1]
    cls(**{**valid, "data": bytes(255)})
    cls(**{**valid, "data": bytes(low)})
    with pytest.raises(InvalidRequest, match="PCCC: byte size 256 out of range"):
        cls(**{**valid, "data": bytes(256)})
    if low:
        with pytest.raises(InvalidRequest, match="PCCC: byte size 0 out of range"):
            cls(**{**valid, "data": b""})


def test_size_limits_are_one_size_byte_and_writes_lose_two_bytes_per_expanded_field() -> None:
    for read, write in ((1, 1), (255, 255)):
        SizeLimits(read, write)
    for read, write in ((0, 1), (1, 0), (256, 1), (1, 256)):
        with pytest.raises(ValueError, match="1-255"):
            SizeLimits(read, write)
    limits = SizeLimits(200, 3)
    assert limits.write_limit() == 3 and limits.write_limit(1) == 1 and limits.write_limit(2) == 0


_N7 = LogicalBinaryAddress(0x0F, (0, 7, 0, 0))
_PLC5_COMMANDS: list[tuple[type, dict[str, object], dict[str, str]]] = [
    (WordRangeRead, dict(address=_N7, size=4), {"size": "byte size", "packet_offset": "packet offset",
                                                 "total": "total transaction"}),
    (WordRangeWrite, dict(address=_N7, data=b"\x01\x00"), {"packet_offset": "packet offset",
                                                           "total": "total transaction"}),
    (TypedRead, dict(address=_N7, count=2), {"count": "element count", "packet_offset": "packet offset",
                                             "total": "total transaction"}),
    (TypedWrite, dict(address=_N7, data_type=4, element_size=2, data=b"\x01\x00"),
     {"packet_offset": "packet offset", "total": "total transaction"}),
]


@pytest.mark.parametrize(("cls", "valid", "fields"), _PLC5_COMMANDS, ids=lambda v: getattr(v, "__name__", ""))
def test_every_field_of_a_plc5_command_is_range_checked_and_named(
    cls: type, valid: dict[str, object], fields: dict[str, str]
) -> None:
    test_every_field_of_an_slc_command_is_range_checked_and_named(cls, valid, fields)


def test_read_modify_write_masks_are_16_bit_and_named() -> None:
    from gateway.protocols.df1.pccc import ReadModifyWriteRequest

    ReadModifyWriteRequest(((_N7, 0, 0xFFFF), (_N7, 0xFFFF, 0)))
    for sets, name in ((((_N7, 0x10000, 0),), "AND mask"), (((_N7, 0, -1),), "OR mask")):
        with pytest.raises(InvalidRequest, match=f"PCCC: {name} "):
            ReadModifyWriteRequest(sets)


def test_a_remote_error_whose_ext_sts_byte_is_missing_says_so() -> None:
    assert describe_status(0xF0) == "Error code in EXT STS, but the EXT STS byte is missing"


def test_a_pccc_error_without_command_or_description_has_empty_ones() -> None:
    from gateway.protocols.df1.pccc import PcccError

    error = PcccError("refused", sts=0x10)
    assert (error.command, error.description, error.reason, error.code) == ("", "", "", 0x10)


# --- what a simulated SLC answers to diagnostic status, and the reply fields read from it ---------


def test_a_built_diagnostic_status_is_the_slc_layout_byte_for_byte() -> None:
    """mode, EE, 00, processor type, series << 5 | FRN - 1, 11 catalog characters padded with spaces."""
    built = DiagnosticStatusInfo.build(processor_type=0x49, series="b", frn=3, catalog="1747-L532")
    assert built.raw == H("00 EE 00 49 22") + b"1747-L532  "
    assert built.series == "B" and built.frn == 3
    assert DiagnosticStatusInfo.build(processor_type=0x5B).raw == H("00 EE 00 5B 00") + b" " * 11
    assert DiagnosticStatusInfo.build(processor_type=0x5B, catalog="1747-L5430XY").raw[5:] == b"1747-L5430X"


def test_diagnostic_status_fields_past_the_reply_are_none() -> None:
    four = DiagnosticStatusInfo(H("00 EE 00 49"))
    assert four.processor_type == 0x49 and four.family is ProcessorFamily.SLC5_03
    assert four.series is None and four.frn is None and four.catalog is None


# --- refusals and malformed commands: what the error carries ------------------------------------


def test_a_refusal_is_described_by_the_table_of_the_command_it_answers() -> None:
    """EXT STS 07 is "Invalid address" for CMD 0E, "File is wrong size" for CMD 0F (Appendix A)."""
    assert (decode_reply(H("00 01 4E F0 09 00 07")).error() or PcccError("")).description == "Invalid address"
    assert (decode_reply(H("00 01 4F F0 09 00 07")).error() or PcccError("")).description == "File is wrong size"


def test_raising_a_refusal_without_a_command_name_has_no_label() -> None:
    with pytest.raises(PcccError) as raised:
        decode_reply(H("00 01 4F 10 01 00")).raise_for_status()
    assert str(raised.value).startswith("controller refused: STS 0x10")


@pytest.mark.parametrize("address", ["94 06 81 07", "94 03 80 07", "94 0A 80 07"])
def test_read_file_info_takes_only_mask_06_major_type_80(address: str) -> None:
    """Notes §7.5: 94 06 80 <file>; another mask or major type is not a data table file."""
    with pytest.raises(PcccFormatError, match="mask 06, major type 80") as raised:
        decode_command(H("01 00 0F 00 01 00") + H(address))
    assert raised.value.header == PcccHeader(1, 0, 0x0F, 0, 1)


def test_typed_data_elements_are_at_least_one_byte() -> None:
    assert encode_typed_data(DataType.BYTE_STRING, 1, b"AB") == H("93 09 31") + b"AB"
    assert TypedWrite(_N7, DataType.BYTE_STRING, 1, b"A").element_size == 1
    for size in (0, -2):
        with pytest.raises(InvalidRequest):
            encode_typed_data(DataType.INTEGER, size, b"\x01\x00")
        with pytest.raises(InvalidRequest):
            TypedWrite(_N7, DataType.INTEGER, size, b"\x01\x00")


def test_a_malformed_typed_write_says_what_is_wrong_with_its_data() -> None:
    with pytest.raises(PcccFormatError, match="3 data bytes are not whole 2-byte elements") as raised:
        decode_command(H("01 00 0F 00 07 00 67 00 00 01 00 0F 00 07 00 00 42 01 00 02"))
    assert raised.value.header is not None
    with pytest.raises(PcccFormatError, match="typed write data"):
        decode_command(H("01 00 0F 00 07 00 67 00 00 01 00 0F 00 07 00 00 42"))  # no data


def test_a_word_range_write_takes_239_bytes_of_address_and_data() -> None:
    """KF2 p. 5-57; the address N7:0 is 0F 00 07 00 00, five bytes."""
    WordRangeWrite(_N7, bytes(234))
    with pytest.raises(InvalidRequest, match="PCCC: address \\+ data bytes 241 out of range 1-239"):
        WordRangeWrite(_N7, bytes(236))


def test_read_modify_write_sends_every_set_and_reads_them_back() -> None:
    """1770-6.5.16 p. 7-20: ADDRESS AND(2) OR(2), repeated to the end of the packet."""
    from gateway.protocols.df1.pccc import ReadModifyWriteRequest

    two = ReadModifyWriteRequest(((_N7, 0xFFFE, 0x0000), (LogicalBinaryAddress.of(0, 7, 1), 0xFFFF, 0x8000)))
    packet = encode_command(two, dst=1, src=0, tns=3)
    assert packet == H("01 00 0F 00 03 00 26 0F 00 07 00 00 FE FF 00 00 07 00 07 01 FF FF 00 80")
    assert decode_command(packet).request == two
    one = ReadModifyWriteRequest(((_N7, 0, 0xFFFF),))
    assert decode_command(encode_command(one, dst=1, src=0, tns=3)).request == one
    with pytest.raises(PcccFormatError, match="at least one address"):
        decode_command(H("01 00 0F 00 03 00 26"))  # no set at all
    for sets in (((_N7, 0x10000, 0),), ((_N7, 0, 0x10000),)):
        with pytest.raises(InvalidRequest, match=r"PCCC: (AND|OR) mask 65536 out of range 0-65535"):
            ReadModifyWriteRequest(sets)


# --- a truncated packet: the error names the field the packet stops in ---------------------------

_CUT = [
    # (the whole command after DST SRC CMD STS TNS, how many of those bytes arrive, the field named)
    ("0F A2 0A 07 89 00 00", 0, "function code"),
    ("0F A2 0A 07 89 00 00", 1, "byte size"),
    ("0F A2 0A 07 89 00 00", 2, "file number"),
    ("0F A2 0A FF 2C 01 89 00 00", 3, "file number"),
    ("0F A2 0A 07 89 00 00", 3, "file type"),
    ("0F A2 0A 07 89 00 00", 4, "element"),
    ("0F A2 0A 07 89 00 00", 5, "sub element"),
    ("0F AB 02 03 85 00 00 0F 0F AA AA", 6, "bit mask"),
    ("0F AA 04 07 89 00 00 01 00 02 00", 9, "write data"),
    ("0F 01 00 00 02 00 0F 00 07 03 00 04", 1, "packet offset"),
    ("0F 01 00 00 02 00 0F 00 07 03 00 04", 3, "total transaction"),
    ("0F 01 00 00 02 00 0F 00 07 03 00 04", 5, "address mask"),
    ("0F 01 00 00 02 00 0F 00 07 03 00 04", 7, "address level"),
    ("0F 01 00 00 02 00 0F 00 07 FF 03 00 00 04", 10, "address level"),
    ("0F 01 00 00 02 00 0F 00 07 03 00 04", 10, "byte size"),
    ("0F 68 00 00 02 00 07 00 07 00 02 00", 10, "element count"),
    ("0F 26 07 00 07 00 FE FF 00 00", 5, "AND mask"),
    ("0F 26 07 00 07 00 FE FF 00 00", 7, "OR mask"),
    ("0F 94 06 80 07", 3, "address level"),
]


@pytest.mark.parametrize(("body", "length", "field"), _CUT)
def test_a_truncated_command_names_the_field_it_stops_in(body: str, length: int, field: str) -> None:
    """What a controller (or the DF1 target) can log about a short command: where it ended."""
    cmd, params = H(body)[0], H(body)[1:]
    packet = bytes((1, 0, cmd, 0, 9, 0)) + params[:length]
    with pytest.raises(PcccFormatError, match=f"too short for {field}$") as raised:
        decode_command(packet)
    assert raised.value.header == PcccHeader(1, 0, cmd, 0, 9)


def test_a_reply_cut_before_its_ext_sts_says_so() -> None:
    with pytest.raises(PcccFormatError, match=r"too short for EXT STS$") as raised:
        decode_reply(H("00 01 4F F0 01 00"))
    assert raised.value.header == PcccHeader(0, 1, 0x4F, 0xF0, 1)  # what a controller would answer STS 10 to


def test_a_logical_binary_address_has_a_one_byte_mask_and_16_bit_levels_and_names_them() -> None:
    LogicalBinaryAddress(0xFF, tuple(range(8)))
    LogicalBinaryAddress(0x01, (0xFFFF,))
    with pytest.raises(InvalidRequest, match="PCCC: address mask 256 out of range 1-255"):
        LogicalBinaryAddress(0x100, tuple(range(9)))
    with pytest.raises(InvalidRequest, match="PCCC: address level 65536 out of range 0-65535"):
        LogicalBinaryAddress(0x01, (0x10000,))


# --- header, reply and TNS bounds, and which byte is an owner node -------------------------------


def test_every_header_byte_is_range_checked_and_named() -> None:
    valid = dict(dst=1, src=0, cmd=0x0F, sts=0, tns=1)
    for field, name, high in (("dst", "DST", 0xFF), ("src", "SRC", 0xFF), ("cmd", "CMD", 0xFF),
                              ("sts", "STS", 0xFF), ("tns", "TNS", 0xFFFF)):
        PcccHeader(**{**valid, field: high})
        with pytest.raises(InvalidRequest, match=f"^PCCC: {name} {high + 1} out of range 0-{high}$"):
            PcccHeader(**{**valid, field: high + 1})
    with pytest.raises(InvalidRequest, match=r"^PCCC: TNS 65536 out of range"):
        TnsAllocator(start=0x10000)


def test_only_ext_sts_1a_and_1b_are_followed_by_an_owner_node() -> None:
    """Notes §4.36: F0 1A / 1B carry the owner's node; another EXT STS's next byte is data."""
    assert decode_reply(H("00 01 4F F0 09 00 1A")).owner_node is None  # the owner byte is optional
    other = decode_reply(H("00 01 4F F0 09 00 06 12"))
    assert other.owner_node is None and other.data == H("12")


def test_a_reply_carries_ext_sts_exactly_with_sts_f0_and_both_are_bytes() -> None:
    command = PcccHeader(1, 0, 0x0F, 0, 9)
    with pytest.raises(InvalidRequest):
        encode_reply(command, sts=0x10, ext_sts=0x06)
    with pytest.raises(InvalidRequest, match=r"^PCCC: EXT STS 256 out of range 0-255$"):
        encode_reply(command, sts=0xF0, ext_sts=0x100)
    with pytest.raises(InvalidRequest, match=r"^PCCC: owner node 256 out of range 0-255$"):
        encode_reply(command, sts=0xF0, ext_sts=0x1A, owner_node=0x100)
    assert encode_reply(command, sts=0xF0, ext_sts=0xFF, owner_node=0xFF) == H("00 01 4F F0 09 00 FF FF")


def test_a_reply_matches_a_command_given_as_a_bytearray() -> None:
    packet = encode_command(ReadFileInfo(7), dst=1, src=0, tns=0x0102)
    reply = decode_reply(encode_reply(decode_command(packet).header))
    assert reply_matches(bytearray(packet), reply)


def test_a_command_with_a_field_out_of_range_says_which_field() -> None:
    with pytest.raises(PcccFormatError, match="PCCC: byte size 0 out of range 1-255") as raised:
        decode_command(H("01 00 0F 00 01 00 A2 00 07 89 00 00"))
    assert raised.value.header == PcccHeader(1, 0, 0x0F, 0, 1)


def test_a_type_data_nibble_holds_0_to_7_and_larger_values_take_up_to_7_bytes() -> None:
    """Notes, type/data parameter note: a nibble with bit 3 clear is the value itself (0-7)."""
    assert encode_type_data(DataType.CONTROL, 7) == H("77")
    assert encode_type_data(0, 8) == H("09 08")
    assert encode_type_data(DataType.INTEGER, 0) == H("40")
    most = (1 << 56) - 1
    assert encode_type_data(most, most) == H("FF") + H("FF") * 14
    assert decode_type_data(encode_type_data(most, most)) == (TypeData(most, most), 15)
    for type_id, size, name in ((1 << 56, 0, "type ID"), (0, 1 << 56, "type size"), (-1, 0, "type ID"),
                                (0, -1, "type size")):
        with pytest.raises(InvalidRequest, match=f"^PCCC: {name} {type_id if name == 'type ID' else size} "):
            TypeData(type_id, size)


@pytest.mark.parametrize("encoded", ["", "4A 03", "A2 01"])
def test_a_cut_type_data_parameter_is_named(encoded: str) -> None:
    with pytest.raises(PcccFormatError, match=r"too short for type/data parameter$"):
        decode_type_data(H(encoded))


def test_a_tns_still_outstanding_is_skipped_for_the_next_number_up() -> None:
    """Unique among outstanding commands and incrementing: with 5 held, the wrap-around gives 6."""
    allocator = TnsAllocator(start=5)
    held = allocator.allocate()
    for _ in range(0xFFFF):
        allocator.release(allocator.allocate())
    assert held == 5 and allocator.allocate() == 6
