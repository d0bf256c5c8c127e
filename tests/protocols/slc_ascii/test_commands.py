"""Tests of gateway.protocols.slc_ascii.commands against shared/docs/slc100-150-ascii-protocol.md."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import ControllerFault, InvalidRequest, ProtocolError
from gateway.protocols.slc_ascii.commands import (
    BLOCK_SIZE,
    ERROR_BITS,
    Command,
    CommandCode,
    ControllerType,
    FrnInfo,
    Mode,
    ReplyKind,
    TimeoutClass,
    UploadBlock,
    WordReply,
    answers,
    controller_fault,
    decode_error_bits,
    download_block,
    error_description,
    parse_frn_reply,
    parse_read_reply,
    parse_reply,
    parse_upload_reply,
    parse_word_reply,
    read_bytes,
    read_frn,
    read_reset_accumulator,
    read_sequencer_preset,
    set_mode,
    upload_block,
    write_byte,
    write_reset_accumulator,
    write_sequencer_preset,
    write_word,
)
from gateway.protocols.slc_ascii.memory_map import is_readable


def wire(command: Command) -> str:
    """<byte count> <command code> <parameters> as the manual writes them (without # ID CRC)."""
    return f"{command.byte_count:02X}{command.code:02X}{command.params.hex().upper()}"


BLOCK = bytes(range(1, 16))

# ---------------------------------------------------------------------------------------------
# Builders: exact bytes against the manual's formats


@pytest.mark.parametrize(
    ("command", "expected", "reply", "timeout_class", "is_write"),
    [
        # "#0502 <number of bytes> <address>", e.g. #0502 0001 0084
        (read_bytes(0x0084), "0502" "0001" "0084", ReplyKind.DATA, TimeoutClass.NORMAL, False),
        (read_bytes(0x0000, 2), "0502" "0002" "0000", ReplyKind.DATA, TimeoutClass.NORMAL, False),
        (read_bytes(0x0112, 1), "0502" "0001" "0112", ReplyKind.DATA, TimeoutClass.NORMAL, False),
        # "#0503 <address> <data word>"
        (write_word(0x0040, 9999), "0503" "0040" "270F", ReplyKind.ACK, TimeoutClass.NORMAL, True),
        (write_word(0x003E, 0), "0503" "003E" "0000", ReplyKind.ACK, TimeoutClass.NORMAL, True),
        # "#0403 <address> <data byte>"
        (write_byte(0x00A6, 0x55), "0403" "00A6" "55", ReplyKind.ACK, TimeoutClass.NORMAL, True),
        (write_byte(0x00B4, 0xFF), "0403" "00B4" "FF", ReplyKind.ACK, TimeoutClass.NORMAL, True),
        # "#04030101 <data byte>"
        (set_mode(Mode.RUN), "04030101" "80", ReplyKind.ACK, TimeoutClass.SLOW, True),
        (set_mode(Mode.SAVE_TO_EEPROM), "04030101" "8C", ReplyKind.ACK, TimeoutClass.SLOW, True),
        (set_mode(Mode.CONTINUOUS_TEST), "04030101" "82", ReplyKind.ACK, TimeoutClass.SLOW, True),
        (set_mode(Mode.PROGRAM), "04030101" "06", ReplyKind.ACK, TimeoutClass.SLOW, True),
        # "#0108"
        (read_frn(), "0108", ReplyKind.DATA, TimeoutClass.NORMAL, False),
        # "#0100"
        (upload_block(), "0100", ReplyKind.DATA, TimeoutClass.SLOW, False),
        # "#1101 <block number> <15 bytes>"
        (download_block(0x05, BLOCK, controller=ControllerType.SLC100), "1101" "05" + BLOCK.hex().upper(),
         ReplyKind.ACK, TimeoutClass.SLOW, True),
        # "#0404 <rung number> <step number>"
        (read_sequencer_preset(0x0123, 0x04), "0404" "0123" "04", ReplyKind.DATA, TimeoutClass.NORMAL, False),
        # "#0305 <rung number>"
        (read_reset_accumulator(0xFFFF), "0305" "FFFF", ReplyKind.DATA, TimeoutClass.NORMAL, False),
        # "#0606 <rung number> <step number> <preset word>"
        (write_sequencer_preset(0x0010, 0xFF, 1), "0606" "0010" "FF" "0001",
         ReplyKind.ACK, TimeoutClass.NORMAL, True),
        # "#0507 <rung number> <accumulator word>"
        (write_reset_accumulator(0, 9999), "0507" "0000" "270F", ReplyKind.ACK, TimeoutClass.NORMAL, True),
    ],
)
def test_builders_match_the_manual(
    command: Command, expected: str, reply: ReplyKind, timeout_class: TimeoutClass, is_write: bool
) -> None:
    assert wire(command) == expected
    assert command.byte_count == 1 + len(command.params)
    assert command.reply is reply
    assert command.timeout_class is timeout_class
    assert command.is_write is is_write
    assert command.name


def test_command_codes() -> None:
    assert [c.value for c in CommandCode] == [0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08]
    assert read_bytes(0x84).code == CommandCode.READ
    assert int(CommandCode.READ) == 0x02
    assert set_mode(Mode.RUN).code == write_byte(0xA6, 0).code == write_word(0, 0).code == CommandCode.WRITE


def test_names() -> None:
    assert read_bytes(0x84, 2).name == "read 2 bytes at 0x0084"
    assert read_bytes(0x84).name == "read 1 byte at 0x0084"
    assert set_mode(Mode.RUN).name == "set mode RUN (0x80)"
    assert download_block(0x7A, bytes(15), controller=ControllerType.SLC100).name == "download block 0x7A"


def test_program_transfers_wait_the_slow_reply_time() -> None:
    """Upload and download blocks are answered in program mode, as slowly as a mode change."""
    assert upload_block().timeout_class is TimeoutClass.SLOW
    assert download_block(0, BLOCK, controller=ControllerType.SLC100).timeout_class is TimeoutClass.SLOW
    assert set_mode(Mode.PROGRAM).timeout_class is TimeoutClass.SLOW


def test_set_mode_accepts_the_int_value() -> None:
    assert set_mode(0x06) == set_mode(Mode.PROGRAM)  # type: ignore[arg-type]


def test_commands_are_frozen() -> None:
    command = read_frn()
    with pytest.raises(AttributeError):
        command.code = 3  # type: ignore[misc]


# ---------------------------------------------------------------------------------------------
# Builders: every rule rejected


@pytest.mark.parametrize(
    ("address", "count", "message"),
    [
        (0x0081, 1, r"address 0x0081 is in a no-access \(\*\*\) cell: checksum of last ladder diagram"),
        (0x00F8, 1, r"no-access \(\*\*\) cell: flags to identify sequencer instructions"),
        (0x0082, 2, "not in the manual's list of readable addresses"),
        (0x0101, 1, r"controller mode byte\) is not in the manual's list"),
        (0x0200, 1, "outside the described memory map"),
        (0x003F, 1, "LSB of the last word"),
        (0x00E3, 2, "would also read 0x00E4"),
        (0x0084, 3, "byte count 3 is not allowed: command 02 reads 1 or 2 bytes"),
        (-1, 1, "out of range"),
    ],
)
def test_read_bytes_rejects(address: int, count: int, message: str) -> None:
    with pytest.raises(InvalidRequest, match=message):
        read_bytes(address, count)


@pytest.mark.parametrize(
    ("address", "value", "message"),
    [
        (0x0001, 0, "0x0001 is odd: the word write needs an even address"),
        (0x0080, 0, r"0x0080 is not word-writable: the word write takes 0x0000-0x003E .* or 0x0040-0x007E"),
        (0x0084, 0, "not word-writable"),
        (0x0000, 10000, "value 10000 is out of range: data words must be less than 2710H"),
        (0x0000, -1, "value -1 is out of range"),
        (0x0000, True, "value True is not an integer"),
        (0x0000, 1.0, "value 1.0 is not an integer"),
    ],
)
def test_write_word_rejects(address: int, value: int, message: str) -> None:
    with pytest.raises(InvalidRequest, match=message):
        write_word(address, value)


@pytest.mark.parametrize(
    ("address", "value", "message"),
    [
        (0x00A5, 0, r"0x00A5 is not byte-writable: the byte write takes only 0x00A6-0x00B4"),
        (0x00B5, 0, "0x00B5 is not byte-writable"),
        (0x0101, 0x80, "0x0101 is not byte-writable"),
        (0x00A6, 256, "value 256 is out of range: a data byte is 0-255"),
        (0x00A6, -1, "value -1 is out of range"),
    ],
)
def test_write_byte_rejects(address: int, value: int, message: str) -> None:
    with pytest.raises(InvalidRequest, match=message):
        write_byte(address, value)


@pytest.mark.parametrize("mode", [0x81, 0x00, 0x8C + 1, True, "RUN", None])
def test_set_mode_rejects(mode: object) -> None:
    with pytest.raises(InvalidRequest, match=r"is not allowed: the data byte is limited to ") as refused:
        set_mode(mode)  # type: ignore[arg-type]
    # the refusal lists the manual's four data bytes, each with its mode
    assert str(refused.value).endswith(
        "RUN (0x80), SAVE_TO_EEPROM (0x8C), CONTINUOUS_TEST (0x82), PROGRAM (0x06)")


def test_download_block_ranges() -> None:
    assert download_block(0x7A, bytes(7) + bytes(8), controller=ControllerType.SLC100).params[0] == 0x7A
    last = download_block(0xA4, bytes(range(7)) + bytes(8), controller=ControllerType.SLC150)
    assert last.params[0] == 0xA4
    assert download_block(0x7B, BLOCK, controller=ControllerType.SLC150).params[0] == 0x7B
    assert download_block(0, bytearray(BLOCK), controller=ControllerType.SLC100).params[1:] == BLOCK


@pytest.mark.parametrize(
    ("block", "data", "controller", "message"),
    [
        (0x7B, BLOCK, ControllerType.SLC100, "block 123 is out of range: SLC100 blocks are 0x00-0x7A"),
        (0xA5, BLOCK, ControllerType.SLC150, "block 165 is out of range: SLC150 blocks are 0x00-0xA4"),
        (-1, BLOCK, ControllerType.SLC100, "block -1 is out of range"),
        (0, BLOCK[:14], ControllerType.SLC100, "block data is 14 bytes: each block carries exactly 15 bytes"),
        (0, BLOCK + b"\x00", ControllerType.SLC100, "block data is 16 bytes"),
        (0, "00" * 15, ControllerType.SLC100, "block data must be bytes"),
        (0x7A, bytes(14) + b"\x01", ControllerType.SLC100,
         "block 0x7A is the last SLC100 block: its last 8 bytes are fill and must be zero"),
        (0xA4, bytes(7) + b"\x01" + bytes(7), ControllerType.SLC150, "last SLC150 block"),
        (0, BLOCK, 0x10, "controller 16 is not a ControllerType"),
    ],
)
def test_download_block_rejects(block: int, data: bytes, controller: ControllerType, message: str) -> None:
    with pytest.raises(InvalidRequest, match=message):
        download_block(block, data, controller=controller)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: read_sequencer_preset(0x10000, 0), "rung 65536 is out of range: rung numbers are 0-65535"),
        (lambda: read_sequencer_preset(-1, 0), "rung -1 is out of range"),
        (lambda: read_sequencer_preset(0, 0x100), "step 256 is out of range: step numbers are 0-255"),
        (lambda: read_sequencer_preset(0, -1), "step -1 is out of range"),
        (lambda: read_reset_accumulator(0x10000), "rung 65536 is out of range"),
        (lambda: read_reset_accumulator("1"), "rung '1' is not an integer"),  # type: ignore[arg-type]
        (lambda: write_sequencer_preset(0, 0, 0), "preset 0 is out of range: a sequencer preset is non-zero"),
        (lambda: write_sequencer_preset(0, 0, 10000), "preset 10000 is out of range"),
        (lambda: write_sequencer_preset(0, 256, 1), "step 256 is out of range"),
        (lambda: write_sequencer_preset(70000, 0, 1), "rung 70000 is out of range"),
        (lambda: write_reset_accumulator(0, 10000), "accumulator 10000 is out of range: .* less than 2710H"),
        (lambda: write_reset_accumulator(0, -1), "accumulator -1 is out of range"),
        (lambda: write_reset_accumulator(-5, 0), "rung -5 is out of range"),
    ],
)
def test_rung_commands_reject(build: object, message: str) -> None:
    assert callable(build)
    with pytest.raises(InvalidRequest, match=message):
        build()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"code": 0x100}, "command code 256 is not a byte"),
        ({"code": -1}, "command code -1 is not a byte"),
        ({"params": "0084"}, "params must be bytes, not str"),
        ({"params": bytes(255)}, "byte count 256 does not fit two hex characters"),
        ({"name": ""}, "a command needs a name"),
    ],
)
def test_command_validates_itself(kwargs: dict[str, object], message: str) -> None:
    fields: dict[str, object] = {
        "code": 0x02, "params": b"", "name": "x", "reply": ReplyKind.ACK,
        "timeout_class": TimeoutClass.NORMAL,
    }
    fields.update(kwargs)
    with pytest.raises(InvalidRequest, match=message):
        Command(**fields)  # type: ignore[arg-type]


def test_largest_command_fits() -> None:
    assert Command(0x01, bytes(254), "x", ReplyKind.ACK, TimeoutClass.NORMAL).byte_count == 0xFF


@given(st.integers(min_value=0, max_value=0x120), st.sampled_from([1, 2]))
def test_read_bytes_follows_the_memory_map(address: int, count: int) -> None:
    if is_readable(address, count):
        command = read_bytes(address, count)
        assert command.params == count.to_bytes(2, "big") + address.to_bytes(2, "big")
        assert command.byte_count == 5
    else:
        with pytest.raises(InvalidRequest):
            read_bytes(address, count)


@given(st.integers(min_value=0, max_value=0xFFFF), st.integers(min_value=0, max_value=0xFF),
       st.integers(min_value=1, max_value=9999))
def test_rung_commands_encode_msb_first(rung: int, step: int, value: int) -> None:
    assert write_sequencer_preset(rung, step, value).params == (
        rung.to_bytes(2, "big") + bytes([step]) + value.to_bytes(2, "big"))
    assert write_reset_accumulator(rung, value).params == rung.to_bytes(2, "big") + value.to_bytes(2, "big")
    assert read_sequencer_preset(rung, step).params == rung.to_bytes(2, "big") + bytes([step])
    assert read_reset_accumulator(rung).params == rung.to_bytes(2, "big")


# ---------------------------------------------------------------------------------------------
# Controller types


def test_controller_types() -> None:
    assert ControllerType.SLC100.device_type == 0x10
    assert ControllerType.SLC150.device_type == 0x15
    assert ControllerType.SLC100.block_count == 0x7B
    assert ControllerType.SLC150.block_count == 0xA5
    assert ControllerType.SLC100.last_block == 0x7A
    assert ControllerType.SLC150.last_block == 0xA4
    # "1770 for SLC 100, 2400 for SLC 150": the program blocks before the end/preset blocks
    assert ControllerType.SLC100.program_bytes == (0x76 * BLOCK_SIZE)
    assert ControllerType.SLC150.program_bytes == (0xA0 * BLOCK_SIZE)
    assert ControllerType.from_device_type(0x15) is ControllerType.SLC150
    assert ControllerType.from_device_type(0x20) is None


# ---------------------------------------------------------------------------------------------
# Reply bodies


@pytest.mark.parametrize(
    ("address", "count", "body_hex", "data"),
    [
        (0x0084, 1, "01" "0084" "81", b"\x81"),  # 2-digit count
        (0x0084, 1, "0001" "0084" "81", b"\x81"),  # 4-digit count
        (0x0084, 2, "02" "0084" "8105", b"\x81\x05"),
        (0x0084, 2, "0002" "0084" "8105", b"\x81\x05"),
        (0x0040, 2, "0002" "0040" "A70F", b"\xa7\x0f"),
        (0x00a6, 1, "0100a6ff", b"\xff"),  # lower case is accepted
    ],
)
def test_parse_read_reply(address: int, count: int, body_hex: str, data: bytes) -> None:
    assert parse_read_reply(address, count, body_hex) == data


@pytest.mark.parametrize(
    ("address", "count", "body_hex", "message"),
    [
        (0x0084, 1, "01" "0085" "81", r"reply echoes 1 byte\(s\) at 0x0085"),
        (0x0084, 2, "01" "0084" "81", r"reply echoes 1 byte\(s\) at 0x0084"),
        (0x0084, 1, "02" "0084" "8105", r"reply echoes 2 byte\(s\)"),
        (0x0084, 1, "0002" "0084" "8105", r"reply echoes 2 byte\(s\)"),
        (0x0084, 1, "10" "0084" + "00" * 16, r"reply echoes 16 byte\(s\)"),  # the count is hex: 10H
        (0x0084, 1, "01" "0084", "is not <count><address><data>"),
        (0x0084, 1, "01" "0084" "8100", "is not <count><address><data>"),
        (0x0084, 1, "", "is not <count><address><data>"),
        (0x0084, 1, "01" "0084" "8", "not an even number of hex digits"),
        (0x0084, 1, "01 0084 81", "not an even number of hex digits"),
        (0x0084, 1, "01" "0084" "G1", "not an even number of hex digits"),
        (0x0084, 1, "+1" "0084" "81", "not an even number of hex digits"),
        (0x0084, 1, b"01008481", "body must be hex text, not bytes"),
    ],
)
def test_parse_read_reply_rejects(address: int, count: int, body_hex: str, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        parse_read_reply(address, count, body_hex)


def test_parse_read_reply_checks_the_request() -> None:
    with pytest.raises(InvalidRequest, match="no-access"):
        parse_read_reply(0x0080, 1, "01008000")
    # one byte at 00E3H is readable, two are not (00E4H is not in the "Reading Data" list)
    with pytest.raises(InvalidRequest, match="would also read 0x00E4"):
        parse_read_reply(0x00E3, 2, "0200E30102")


@given(
    st.sampled_from([(a, c) for a in range(0x0120) for c in (1, 2) if is_readable(a, c)]),
    st.binary(min_size=2, max_size=2),
    st.sampled_from([2, 4]),
    st.booleans(),
)
def test_read_reply_round_trip(request: tuple[int, int], payload: bytes, digits: int, lower: bool) -> None:
    address, count = request
    data = payload[:count]
    body = f"{count:0{digits}X}{address:04X}{data.hex().upper()}"
    assert parse_read_reply(address, count, body.lower() if lower else body) == data


def test_parse_frn_reply() -> None:
    # ":021FFE <device type> <FRN #>": "10 for SLC", "05 for FRN 5"
    assert parse_frn_reply("021FFE1005") == FrnInfo(0x10, 5, ControllerType.SLC100, 0x05)
    # "15 for SLC 150", "47 for FRN 47"
    assert parse_frn_reply("00021FFE1547") == FrnInfo(0x15, 47, ControllerType.SLC150, 0x47)
    unknown = parse_frn_reply("021FFE204A")
    assert unknown == FrnInfo(0x20, 0x4A, None, 0x4A)


@pytest.mark.parametrize(
    ("body_hex", "message"),
    [
        ("021FFF1005", r"expected 2 bytes at 0x1FFE, got 2 at 0x1FFF"),
        ("011FFE10", r"expected 2 bytes at 0x1FFE, got 1 at 0x1FFE"),
        ("021FFE10", "is not <count><address><data>"),
        ("1005", "is not <count><address><data>"),
        ("001FFE", r"expected 2 bytes at 0x1FFE, got 0 at 0x1FFE"),  # a count with no data
        ("00001FFE", r"expected 2 bytes at 0x1FFE, got 0 at 0x1FFE"),
    ],
)
def test_parse_frn_reply_rejects(body_hex: str, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        parse_frn_reply(body_hex)


def test_parse_upload_reply() -> None:
    body = "7A" + (bytes(range(7)) + bytes(8)).hex().upper()
    block = parse_upload_reply(body)
    assert block == UploadBlock(0x7A, bytes(range(7)) + bytes(8))
    number, data = block
    assert (number, len(data)) == (0x7A, 15)
    assert parse_upload_reply(body, controller=ControllerType.SLC100).block == 0x7A
    assert parse_upload_reply("A4" + "00" * 15, controller=ControllerType.SLC150).block == 0xA4


@pytest.mark.parametrize(
    ("body_hex", "controller", "message"),
    [
        ("7B" + "00" * 15, ControllerType.SLC100, "block 0x7B is beyond the last SLC100 block 0x7A"),
        ("A5" + "00" * 15, ControllerType.SLC150, "block 0xA5 is beyond the last SLC150 block 0xA4"),
        ("00" + "00" * 14, None, "body has 30 hex digits, expected 32"),
        ("00" + "00" * 16, None, "body has 34 hex digits, expected 32"),
        ("00" + "0" * 29, None, "not an even number of hex digits"),
    ],
)
def test_parse_upload_reply_rejects(body_hex: str, controller: ControllerType | None, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        parse_upload_reply(body_hex, controller=controller)


@pytest.mark.parametrize(
    ("body_hex", "expected"),
    [
        ("02" "0385" "03E8", WordReply(0x0385, 1000, False)),
        ("02" "0385" "83E8", WordReply(0x0385, 1000, True)),
        ("0002" "0901" "A70F", WordReply(0x0901, 0x270F, True)),
        ("0002" "0000" "0000", WordReply(0, 0, False)),
    ],
)
def test_parse_word_reply(body_hex: str, expected: WordReply) -> None:
    assert parse_word_reply(body_hex) == expected
    user_address, value, protected = parse_word_reply(body_hex)
    assert (user_address, value, protected) == tuple(expected)


@pytest.mark.parametrize(
    ("body_hex", "message"),
    [
        ("01" "0385" "03", r"expected a 2-byte word, got 1 byte\(s\)"),
        ("00" "0385", r"expected a 2-byte word, got 0 byte\(s\)"),
        ("0000" "0385", r"expected a 2-byte word, got 0 byte\(s\)"),
        ("02" "0385" "03", "is not <count><address><data>"),
        ("", "is not <count><address><data>"),
    ],
)
def test_parse_word_reply_rejects(body_hex: str, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        parse_word_reply(body_hex)


@given(st.integers(min_value=0, max_value=0xFFFF), st.integers(min_value=0, max_value=0xFFFF),
       st.sampled_from([2, 4]))
def test_word_reply_round_trip(user_address: int, word: int, digits: int) -> None:
    reply = parse_word_reply(f"{2:0{digits}X}{user_address:04X}{word:04X}")
    assert reply == WordReply(user_address, word & 0x7FFF, word >= 0x8000)


@pytest.mark.parametrize(
    ("command", "body_hex", "reply"),
    [
        # the manual's one printed data reply, ":021FFE <device type> <FRN #>" ("10 for SLC", "05 for FRN 5")
        (read_frn(), "021FFE1005", FrnInfo(0x10, 5, ControllerType.SLC100, 0x05)),
        (read_frn(), "00021FFE1547", FrnInfo(0x15, 47, ControllerType.SLC150, 0x47)),
        # ":<number of bytes> <address> <data byte(s)>", the count with 2 or 4 digits
        (read_bytes(0x0084), "01008481", b"\x81"),
        (read_bytes(0x0084, 2), "000200848105", b"\x81\x05"),
        (read_bytes(0x0112), "0001011207", b"\x07"),  # an address above 00FFH
        (read_bytes(0x0102, 2), "0201020304", b"\x03\x04"),
        # ":<block #> <15 bytes>"
        (upload_block(), "7A" + "01" * 7 + "00" * 8, UploadBlock(0x7A, b"\x01" * 7 + bytes(8))),
        # ":02 <user address> <preset word>" / "<accumulator word>", protect bit masked out
        (read_sequencer_preset(1, 2), "02" "0385" "83E8", WordReply(0x0385, 1000, True)),
        (read_reset_accumulator(1), "0002" "0901" "270F", WordReply(0x0901, 9999, False)),
    ],
)
def test_parse_reply_parses_each_data_command_s_reply_with_its_own_parser(
    command: Command, body_hex: str, reply: object
) -> None:
    assert parse_reply(command, body_hex) == reply
    assert answers(command, body_hex)


@pytest.mark.parametrize(
    ("command", "body_hex"),
    [
        (read_bytes(0x0112), "01001207"),  # echoes 0012H, not 0112H
        (read_bytes(0x0084), "7A" + "00" * 15),  # an upload block
        (read_frn(), "02038503E8"),  # a word reply
        (upload_block(), "021FFE1005"),  # an FRN reply
        (read_sequencer_preset(1, 2), "7A" + "00" * 15),
        (read_reset_accumulator(1), "021FFE1005" "00"),
        (write_word(0x0040, 1), "02004003E8"),  # a write is answered ;R, never with data
        (download_block(0, BLOCK, controller=ControllerType.SLC100), "7A" + "00" * 15),
    ],
)
def test_a_data_reply_that_does_not_answer_the_command_is_refused(command: Command, body_hex: str) -> None:
    with pytest.raises(ProtocolError):
        parse_reply(command, body_hex)
    assert not answers(command, body_hex)


def test_a_read_whose_count_field_is_not_1_or_2_has_no_answer() -> None:
    """A hand-built read of 0101H bytes: no reply answers it, not even one byte at its address."""
    bad = Command(CommandCode.READ, bytes.fromhex("0101" "0084"), "bad read", ReplyKind.DATA, TimeoutClass.NORMAL)
    with pytest.raises(InvalidRequest, match="byte count 257 is not allowed"):
        parse_reply(bad, "01008481")


@pytest.mark.parametrize("params", ["0001" "0084" "00", "0001" "00"], ids=["a byte too many", "a byte too few"])
def test_a_read_whose_parameters_are_not_a_count_and_an_address_has_no_answer(params: str) -> None:
    """A hand-built read is answered only if its parameters are what ``read_bytes`` builds: a
    2-byte count and a 2-byte address; a byte more or less is refused whatever the reply."""
    bad = Command(CommandCode.READ, bytes.fromhex(params), "bad read", ReplyKind.DATA, TimeoutClass.NORMAL)
    with pytest.raises(InvalidRequest, match="a read's parameters are 4 bytes"):
        parse_reply(bad, "01008481")


# ---------------------------------------------------------------------------------------------
# ;T error bits


@pytest.mark.parametrize(
    ("b84", "b85", "numbers"),
    [
        (0x00, 0x00, ()),
        (0x80, 0x00, (62,)),
        (0x40, 0x00, (4,)),
        (0x20, 0x00, (6,)),
        (0x10, 0x00, (3,)),
        (0x08, 0x00, (8,)),
        (0x04, 0x00, (5,)),
        (0x02, 0x00, (2,)),
        (0x01, 0x00, (1,)),
        (0x00, 0x80, ()),  # 85H bit 7 is unused
        (0x00, 0x40, (26,)),
        (0x00, 0x20, (25,)),
        (0x00, 0x10, (24,)),
        (0x00, 0x08, (9,)),
        (0x00, 0x04, (51,)),
        (0x00, 0x02, (7,)),
        (0x00, 0x01, (51,)),
        (0x00, 0x05, (51,)),
        (0xFF, 0xFF, (1, 2, 3, 4, 5, 6, 7, 8, 9, 24, 25, 26, 51, 62)),
        (0x81, 0x42, (1, 7, 26, 62)),
    ],
)
def test_decode_error_bits(b84: int, b85: int, numbers: tuple[int, ...]) -> None:
    assert decode_error_bits(b84, b85) == numbers


@pytest.mark.parametrize(("b84", "b85"), [(256, 0), (0, -1), (True, 0), (0, "1")])
def test_decode_error_bits_rejects(b84: int, b85: int) -> None:
    with pytest.raises(InvalidRequest, match=r"byte 8[45]H"):
        decode_error_bits(b84, b85)


def test_error_table() -> None:
    assert len(ERROR_BITS) == 15
    cells = {(e.address, e.bit) for e in ERROR_BITS}
    assert cells == {(0x84, b) for b in range(8)} | {(0x85, b) for b in range(7)}
    assert error_description(62) == "error 62 (84H bit 7)"
    assert error_description(51) == "error 51 (85H bit 2, 85H bit 0)"
    assert error_description(99) == "error 99"


@given(st.integers(min_value=0, max_value=0xFF), st.integers(min_value=0, max_value=0xFF))
def test_error_bits_are_the_union_of_single_bits(b84: int, b85: int) -> None:
    expected: set[int] = set()
    for bit in range(8):
        expected.update(decode_error_bits(b84 & (1 << bit), 0))
        expected.update(decode_error_bits(0, b85 & (1 << bit)))
    assert decode_error_bits(b84, b85) == tuple(sorted(expected))


def test_controller_fault() -> None:
    fault = controller_fault(0x80, 0x01)
    assert isinstance(fault, ControllerFault)
    assert fault.errors == (51, 62)
    assert "84H=0x80, 85H=0x01" in str(fault)
    assert "error 62 (84H bit 7)" in str(fault)
    assert controller_fault(0, 0).errors == ()
    assert "no error bit set" in str(controller_fault(0, 0))


# ---------------------------------------------------------------------------------------------
# Which commands are writes: the SLC core resends a write under a new ID only with proof
# that it did not run, and resyncs on a quiet line before it; a write taken for a read could run
# twice.  Built inside the test (not in a parametrize list, which runs at collection).


def test_every_command_that_changes_the_controller_is_a_write_and_no_other() -> None:
    writes = [
        write_word(0x0040, 1), write_byte(0x00A6, 1), set_mode(Mode.RUN), set_mode(Mode.PROGRAM),
        download_block(0, BLOCK, controller=ControllerType.SLC100), write_sequencer_preset(0x10, 0, 5),
        write_reset_accumulator(0x20, 5),
    ]
    reads = [read_bytes(0x0040, 2), read_frn(), upload_block(), read_sequencer_preset(0x10, 0),
             read_reset_accumulator(0x20)]
    assert [c.is_write for c in writes] == [True] * len(writes)
    assert [c.is_write for c in reads] == [False] * len(reads)
    assert [c.reply for c in writes] == [ReplyKind.ACK] * len(writes)
    assert [c.reply for c in reads] == [ReplyKind.DATA] * len(reads)
    assert upload_block().params == b"" and read_frn().params == b""


@pytest.mark.parametrize("value", [1, 9999])
def test_a_sequencer_preset_may_be_1_to_9999(value: int) -> None:
    assert write_sequencer_preset(0x10, 0, value).params[-2:] == value.to_bytes(2, "big")


@pytest.mark.parametrize("value", [0, 9999])
def test_a_reset_accumulator_may_be_0_to_9999(value: int) -> None:
    assert write_reset_accumulator(0x20, value).params[-2:] == value.to_bytes(2, "big")


@pytest.mark.parametrize("value", [-1, 10000])
def test_a_reset_accumulator_out_of_range_is_refused(value: int) -> None:
    with pytest.raises(InvalidRequest, match="out of range"):
        write_reset_accumulator(0x20, value)


def test_a_bit_write_keeps_the_other_bits_of_any_current_byte() -> None:
    from gateway.protocols.slc_ascii.commands import write_item_bit
    from gateway.protocols.slc_ascii.memory_map import parse_item

    item = parse_item("703")  # relay 703: bit 2 of A6H
    assert write_item_bit(item, 0, True).params == b"\x00\xa6\x04"
    assert write_item_bit(item, 0, False).params == b"\x00\xa6\x00"
    assert write_item_bit(item, 0xFF, True).params == b"\x00\xa6\xff"
    for current in (True, False, -1, 256, "0"):
        with pytest.raises(InvalidRequest, match="is not in 0-255"):
            write_item_bit(item, current, True)  # type: ignore[arg-type]


@pytest.mark.parametrize(("b84", "b85"), [(0, 256), (0, True), (-1, 0)])
def test_decode_error_bits_refuses_what_is_not_a_byte(b84: int, b85: int) -> None:
    with pytest.raises(InvalidRequest):
        decode_error_bits(b84, b85)


def test_error_bits_of_both_bytes_are_decoded_at_the_edges() -> None:
    both = set(decode_error_bits(0xFF, 0)) | set(decode_error_bits(0, 0xFF))
    assert decode_error_bits(0xFF, 0xFF) == tuple(sorted(both)) and len(both) == 14
    assert decode_error_bits(0, 0) == ()


def test_a_controller_fault_lists_each_error_or_says_none_is_set() -> None:
    from gateway.protocols.slc_ascii.commands import error_description

    assert str(controller_fault(0, 0)) == "controller fault (84H=0x00, 85H=0x00): no error bit set"
    assert str(controller_fault(0x03, 0)) == (
        f"controller fault (84H=0x03, 85H=0x00): {error_description(1)}; {error_description(2)}")


@pytest.mark.parametrize(("b84", "b85", "named"), [(256, 0, "byte 84H 256"), (0, 256, "byte 85H 256")])
def test_an_error_byte_out_of_range_is_named(b84: int, b85: int, named: str) -> None:
    with pytest.raises(InvalidRequest, match=f"^{named} is out of range: a byte is 0-255$"):
        decode_error_bits(b84, b85)


def test_the_frn_probe_is_named_as_the_manual_names_it() -> None:
    assert read_frn().name == "read FRN"


def test_a_command_code_is_a_byte_and_a_data_word_may_be_9999() -> None:
    assert Command(0xFF, b"", "code FF", ReplyKind.ACK, TimeoutClass.NORMAL).code == 0xFF
    for code in (True, 0x100, -1):
        with pytest.raises(InvalidRequest, match="is not a byte"):
            Command(code, b"", "bad", ReplyKind.ACK, TimeoutClass.NORMAL)
    assert write_word(0x0040, 9999).params == b"\x00\x40\x27\x0f"
    with pytest.raises(InvalidRequest, match="out of range"):
        write_word(0x0040, 10000)
