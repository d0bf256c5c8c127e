"""SLC 100/150 ASCII framing: CRC vectors from the manual, frame encoding, the streaming decoders.

Source: shared/docs/slc100-150-ascii-protocol.md, "Format of Transmission".  The CRC is cross-checked
against a literal transcription of the manual's BASIC program, written here independently of the
implementation's byte table.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command, ReplyKind, TimeoutClass
from gateway.protocols.slc_ascii.framing import (
    MAX_FRAME,
    MAX_ID,
    NEED_DATA,
    Ack,
    CommandDecoder,
    CommandFrame,
    DataReply,
    Fault,
    Garbled,
    HostEvent,
    IdMismatch,
    Refused,
    ReplyDecoder,
    ReplyEvent,
    RetransmitRequest,
    crc,
    encode_ack,
    encode_data_reply,
    encode_fault,
    encode_id_mismatch,
    encode_refused,
    encode_retransmit,
    frame_command,
)

# ---------------------------------------------------------------------------------------------
# The manual's BASIC program, transcribed line by line (IBM BASIC: INT(x / 16) on a non-negative
# number is an integer division; XOR and AND are bitwise).
#
#   10 DIM G(16) / 20-40 READ G(I) / 180-190 DATA ...
#   60 CHECKSUM=0
#   70 FOR COUNT=1 TO LEN(A$)
#   80 CHAR=ASC (MID$(A$, COUNT, 1))
#   90 FOR J=1 TO 2
#   100 INDEX=(CHECKSUM XOR CHAR) AND &HF
#   110 CHECKSUM=INT (CHECKSUM / 16)
#   120 CHECKSUM=CHECKSUM XOR G (INDEX)
#   130 CHAR=INT (CHAR / 16)
#   140 NEXT J
#   150 NEXT COUNT

BASIC_DATA = [0, 23, 46, 57, 92, 75, 114, 101, 184, 175, 150, 129, 228, 243, 202, 221]


def basic_crc(a_string: str) -> int:
    g = list(BASIC_DATA)  # 10-40, 180-190
    checksum = 0  # 60
    for count in range(1, len(a_string) + 1):  # 70
        char = ord(a_string[count - 1 : count])  # 80
        for _j in range(1, 3):  # 90
            index = (checksum ^ char) & 0xF  # 100
            checksum = int(checksum / 16)  # 110
            checksum = checksum ^ g[index]  # 120
            char = int(char / 16)  # 130
    return checksum  # 160 PRINT HEX$(CHECKSUM)


def msb_first_polynomial_crc(data: bytes) -> int:
    """The printed polynomial X^8+X^6+X^5+X^4+1 done the 'obvious' way (MSB first, init 0)."""
    checksum = 0
    for byte in data:
        checksum ^= byte
        for _ in range(8):
            checksum = ((checksum << 1) ^ 0x171) & 0xFF if checksum & 0x80 else (checksum << 1) & 0xFF
    return checksum


# ---------------------------------------------------------------------------------------------
# helpers


def drain(decoder: ReplyDecoder | CommandDecoder) -> list[ReplyEvent | HostEvent]:
    events: list[ReplyEvent | HostEvent] = []
    while (event := decoder.next_event()) is not NEED_DATA:
        events.append(event)
    return events


Feeder = Callable[[ReplyDecoder | CommandDecoder, bytes], list[ReplyEvent | HostEvent]]


def feed_whole(decoder: ReplyDecoder | CommandDecoder, data: bytes) -> list[ReplyEvent | HostEvent]:
    decoder.receive_data(data)
    return drain(decoder)


def feed_bytewise(decoder: ReplyDecoder | CommandDecoder, data: bytes) -> list[ReplyEvent | HostEvent]:
    events: list[ReplyEvent | HostEvent] = []
    for i in range(len(data)):
        decoder.receive_data(data[i : i + 1])
        events += drain(decoder)
    return events


def feed_chunks_of_3(decoder: ReplyDecoder | CommandDecoder, data: bytes) -> list[ReplyEvent | HostEvent]:
    events: list[ReplyEvent | HostEvent] = []
    for i in range(0, len(data), 3):
        decoder.receive_data(data[i : i + 3])
        events += drain(decoder)
    return events


FEEDERS: Sequence[Feeder] = (feed_whole, feed_bytewise, feed_chunks_of_3)
FEEDER_IDS = ("whole", "byte-by-byte", "chunks-of-3")

#: Trailing bytes after a frame: the start of the next frame, line noise, a stray CR/LF.
TRAILERS = (b"", b";R0", b":0002", b"\n", b"\r", b"\x00\x7f", b"\r\n;E")


def decode_replies(data: bytes, feeder: Feeder = feed_whole) -> list[ReplyEvent]:
    events = feeder(ReplyDecoder(), data)
    return [e for e in events if not isinstance(e, (CommandFrame, RetransmitRequest))]


def decode_commands(data: bytes, feeder: Feeder = feed_whole) -> list[HostEvent]:
    events = feeder(CommandDecoder(), data)
    return [e for e in events if isinstance(e, (CommandFrame, RetransmitRequest, Garbled))]


def set_bit7(data: bytes) -> bytes:
    return bytes(b | 0x80 for b in data)


# ---------------------------------------------------------------------------------------------
# CRC


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("010800", 0xA3),  # #0108 with ID 00 (read FRN)
        ("R03", 0x8D),  # ;R acknowledge with ID 03
    ],
)
def test_crc_manual_vectors(text: str, expected: int) -> None:
    assert basic_crc(text) == expected
    assert crc(text.encode("ascii")) == expected


@pytest.mark.parametrize(
    "text",
    ["", "0", "Z09", "E07", "T00", "I12", "0502000200840102", "04030101067F", "021FFE154700",
     "1101" + "00" + "0F" * 15 + "7F", "000200400064", "abcdef", "~!\x7f\x00"],
)
def test_crc_agrees_with_the_basic_program(text: str) -> None:
    assert crc(text.encode("latin-1")) == basic_crc(text)


@given(st.text(alphabet=st.characters(min_codepoint=0, max_codepoint=127), max_size=60))
def test_crc_agrees_with_the_basic_program_on_any_ascii(text: str) -> None:
    assert crc(text.encode("ascii")) == basic_crc(text)


def test_crc_is_not_the_naive_msb_first_polynomial() -> None:
    # docs/develop/ARCHITECTURE.md: the BASIC table is normative; the printed polynomial done MSB-first differs.
    assert msb_first_polynomial_crc(b"010800") != 0xA3
    assert msb_first_polynomial_crc(b"R03") != 0x8D


def test_crc_is_always_one_byte() -> None:
    for value in range(256):
        assert 0 <= crc(bytes([value]) * 3) <= 0xFF


# ---------------------------------------------------------------------------------------------
# Encoding: full frames, each checked against the BASIC CRC


def frame_of(lead: str, text: str) -> bytes:
    return f"{lead}{text}{basic_crc(text):02X}\r".encode("ascii")


@pytest.mark.parametrize(
    ("encoded", "lead", "text"),
    [
        (frame_command(cmds.read_frn(), 0), "#", "010800"),
        (frame_command(cmds.read_bytes(0x84, 2), 1), "#", "0502" "0002" "0084" "01"),
        (frame_command(cmds.write_word(0x40, 1234), 2), "#", "0503" "0040" "04D2" "02"),
        (frame_command(cmds.write_byte(0xA6, 0x55), 0x7F), "#", "0403" "00A6" "55" "7F"),
        (frame_command(cmds.set_mode(cmds.Mode.PROGRAM), 0x10), "#", "04030101" "06" "10"),
        (frame_command(cmds.upload_block(), 5), "#", "0100" "05"),
        (frame_command(cmds.download_block(3, bytes(range(15)), controller=cmds.ControllerType.SLC150), 6),
         "#", "1101" "03" + bytes(range(15)).hex().upper() + "06"),
        (encode_retransmit(9), ";", "Z09"),
        (encode_ack(3), ";", "R03"),
        (encode_refused(7), ";", "E07"),
        (encode_fault(), ";", "T00"),
        (encode_id_mismatch(0x12), ";", "I12"),
        (encode_data_reply("021FFE1547", 0), ":", "021FFE1547" "00"),
        (encode_data_reply("000200400064", 0x7F), ":", "000200400064" "7F"),
        (encode_data_reply("0aff", 1), ":", "0AFF" "01"),  # upper case on the wire
    ],
)
def test_encoded_frames(encoded: bytes, lead: str, text: str) -> None:
    assert encoded == frame_of(lead, text)


def test_manual_frames_literally() -> None:
    assert frame_command(cmds.read_frn(), 0) == b"#010800A3\r"
    assert encode_ack(3) == b";R038D\r"


@pytest.mark.parametrize(
    "encode",
    [
        lambda i: encode_ack(i),
        lambda i: encode_refused(i),
        lambda i: encode_fault(i),
        lambda i: encode_id_mismatch(i),
        lambda i: encode_retransmit(i),
        lambda i: encode_data_reply("00", i),
        lambda i: frame_command(cmds.read_frn(), i),
    ],
)
@pytest.mark.parametrize("bad_id", [-1, MAX_ID + 1, 0xFF])
def test_encoders_refuse_ids_out_of_range(encode: Callable[[int], bytes], bad_id: int) -> None:
    with pytest.raises(ValueError):
        encode(bad_id)


# ---------------------------------------------------------------------------------------------
# Reply decoding: every kind, fed whole, byte by byte and with trailing bytes

REPLY_SAMPLES: list[tuple[bytes, ReplyEvent]] = [
    (b";R038D\r", Ack(3)),
    (frame_of(";", "R00"), Ack(0)),
    (frame_of(";", "R7F"), Ack(0x7F)),
    (frame_of(";", "E07"), Refused(7)),
    (frame_of(";", "T00"), Fault(0)),
    (frame_of(";", "T5A"), Fault(0x5A)),
    (frame_of(";", "I12"), IdMismatch(0x12)),
    (frame_of(";", "I00"), IdMismatch(0)),
    # FRN reply: 2-digit byte count, device type 15 (SLC 150), FRN 47
    (frame_of(":", "021FFE1547" "00"), DataReply("021FFE1547", 0)),
    # read reply with a 4-digit count (as the read command sends it) and with a 2-digit count
    (frame_of(":", "0002" "0040" "0064" "05"), DataReply("000200400064", 5)),
    (frame_of(":", "02" "0040" "0064" "05"), DataReply("0200400064", 5)),
    (frame_of(":", "0001" "0084" "08" "2A"), DataReply("0001008408", 0x2A)),
    # upload block: <block #> <15 bytes>
    (frame_of(":", "A4" + "11" * 7 + "00" * 8 + "33"), DataReply("A4" + "11" * 7 + "00" * 8, 0x33)),
]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
@pytest.mark.parametrize("trailer", TRAILERS)
@pytest.mark.parametrize(("frame", "expected"), REPLY_SAMPLES)
def test_reply_kinds(frame: bytes, expected: ReplyEvent, trailer: bytes, feeder: Feeder) -> None:
    assert decode_replies(frame + trailer, feeder) == [expected]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
@pytest.mark.parametrize(("frame", "expected"), REPLY_SAMPLES)
def test_reply_with_bit7_set_on_every_byte(frame: bytes, expected: ReplyEvent, feeder: Feeder) -> None:
    # Even parity read by a port set to 8 data bits: bit 7 is the parity bit, masked away.
    assert decode_replies(set_bit7(frame), feeder) == [expected]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_stray_line_feeds_are_ignored(feeder: Feeder) -> None:
    data = b"\n;R0\n38D\r\n\n" + frame_of(":", "021FFE1547" "01").replace(b"FE", b"F\nE") + b"\n"
    assert decode_replies(data, feeder) == [Ack(3), DataReply("021FFE1547", 1)]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_noise_before_a_frame_is_discarded(feeder: Feeder) -> None:
    assert decode_replies(b"\x00\x07garbage 123\r\r" + b";R038D\r", feeder) == [Ack(3)]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_a_stream_of_replies(feeder: Feeder) -> None:
    data = b"".join(frame for frame, _ in REPLY_SAMPLES)
    assert decode_replies(data, feeder) == [event for _, event in REPLY_SAMPLES]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_lower_case_hex_is_accepted(feeder: Feeder) -> None:
    text = "021ffe1547" "0a"
    frame = f":{text}{crc(text.encode()):02x}\r".encode()
    assert decode_replies(frame, feeder) == [DataReply("021FFE1547", 0x0A)]
    # a sender that computes the CRC over the upper-case text and then sends it in lower case
    over_upper = f":{text}{crc(text.upper().encode()):02X}\r".encode()
    assert crc(text.upper().encode()) != crc(text.encode())
    assert decode_replies(over_upper, feeder) == [DataReply("021FFE1547", 0x0A)]


def test_two_and_four_digit_counts_parse_to_the_same_data() -> None:
    four = decode_replies(frame_of(":", "0002" "0040" "0064" "05"))
    two = decode_replies(frame_of(":", "02" "0040" "0064" "05"))
    assert isinstance(four[0], DataReply)
    assert isinstance(two[0], DataReply)
    assert cmds.parse_read_reply(0x40, 2, four[0].body_hex) == b"\x00\x64"
    assert cmds.parse_read_reply(0x40, 2, two[0].body_hex) == b"\x00\x64"
    frn = decode_replies(frame_of(":", "021FFE1547" "00"))[0]
    assert isinstance(frn, DataReply)
    info = cmds.parse_frn_reply(frn.body_hex)
    assert (info.controller, info.frn) == (cmds.ControllerType.SLC150, 47)
    frn4 = decode_replies(frame_of(":", "00021FFE1005" "00"))[0]
    assert isinstance(frn4, DataReply)
    assert cmds.parse_frn_reply(frn4.body_hex).controller is cmds.ControllerType.SLC100


# ---------------------------------------------------------------------------------------------
# Garbled replies, and recovery for the next frame

GOOD = b";R04C0\r"
assert GOOD == frame_of(";", "R04")

GARBLED_SAMPLES: list[tuple[str, bytes]] = [
    ("bad CRC", b";R038E\r"),
    ("CRC not hex", b";R03X8\r"),
    ("data reply bad CRC", frame_of(":", "021FFE1547" "00").replace(b"47", b"46")),
    ("truncated with CR", b";R0\r"),
    ("only the lead", b":\r"),
    ("data reply odd body", frame_of(":", "021FFE154" "00")),
    ("data reply empty body", frame_of(":", "00")),
    ("data reply non-hex body", frame_of(":", "02GG" "00")),
    ("reply too long", frame_of(";", "R0300")),
    ("unknown reply letter", frame_of(";", "X03")),
    ("ID not hex", frame_of(";", "RZZ")),
    ("ID out of range", frame_of(";", "R80")),
    ("too long", b":" + b"0" * (MAX_FRAME + 10) + b"\r"),
]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
@pytest.mark.parametrize(("name", "bad"), GARBLED_SAMPLES, ids=[name for name, _ in GARBLED_SAMPLES])
def test_garbled_reply_then_recovery(name: str, bad: bytes, feeder: Feeder) -> None:
    events = decode_replies(bad + GOOD, feeder)
    assert len(events) == 2, events
    assert isinstance(events[0], Garbled)
    assert events[0].reason
    assert events[1] == Ack(4)


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_frame_interrupted_by_a_new_leading_character(feeder: Feeder) -> None:
    # The CR of the first reply was lost: the next leading character ends it.
    events = decode_replies(b";R03" + b":021FFE" + GOOD, feeder)
    assert [type(e) for e in events] == [Garbled, Garbled, Ack]
    assert isinstance(events[0], Garbled)
    assert events[0].raw == b";R03"
    assert events[-1] == Ack(4)


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_long_garbage_without_cr_is_dropped_and_the_next_frame_decodes(feeder: Feeder) -> None:
    events = decode_replies(b";" + b"5" * (3 * MAX_FRAME) + GOOD, feeder)
    assert all(isinstance(e, Garbled) for e in events[:-1])
    assert len(events) >= 2
    assert events[-1] == Ack(4)


def test_a_line_of_max_frame_characters_waits_for_its_cr_and_one_more_is_too_long() -> None:
    decoder = ReplyDecoder()
    decoder.receive_data(b";" + b"0" * (MAX_FRAME - 1))
    assert decoder.next_event() is NEED_DATA
    assert decoder.partial
    decoder.receive_data(b"0")
    garbled = decoder.next_event()
    assert isinstance(garbled, Garbled)
    assert garbled.raw == b";" + b"0" * (MAX_FRAME - 1)
    assert not decoder.partial


def test_longest_real_frame_fits() -> None:
    block = cmds.download_block(0xA4, bytes(7) + bytes(8), controller=cmds.ControllerType.SLC150)
    frame = frame_command(block, 0x7F)
    assert len(frame) - 1 <= MAX_FRAME
    assert decode_commands(frame) == [CommandFrame(block.code, block.params, 0x7F)]


def test_a_partial_frame_is_need_data() -> None:
    decoder = ReplyDecoder()
    decoder.receive_data(b";R038")
    assert decoder.next_event() is NEED_DATA
    decoder.receive_data(b"D")
    assert decoder.next_event() is NEED_DATA
    decoder.receive_data(b"\r")
    assert decoder.next_event() == Ack(3)
    assert decoder.next_event() is NEED_DATA


def test_a_partial_frame_given_up_is_reported_garbled_once() -> None:
    """The inter-character timeout gives up on a frame without CR: it is one Garbled line, its bytes
    forgotten; with nothing partial there is nothing to report, and the next frame decodes."""
    decoder = ReplyDecoder()
    assert decoder.flush_partial() is None
    decoder.receive_data(b"noise;R03")
    assert decoder.partial
    garbled = decoder.flush_partial()
    assert isinstance(garbled, Garbled)
    assert garbled.raw == b";R03"
    assert not decoder.partial
    assert decoder.flush_partial() is None
    decoder.receive_data(GOOD)
    assert decoder.next_event() == Ack(4)
    assert decoder.next_event() is NEED_DATA


def test_reply_decoder_ignores_host_frames_leading_character() -> None:
    # '#' is not a reply leading character: an echoed command is line noise to the host.
    assert decode_replies(b"#010800A3\r" + GOOD) == [Ack(4)]


# ---------------------------------------------------------------------------------------------
# Command decoding (the simulator's side)

COMMAND_SAMPLES: list[tuple[bytes, HostEvent]] = [
    (b"#010800A3\r", CommandFrame(0x08, b"", 0)),
    (frame_command(cmds.read_bytes(0x84, 2), 1), CommandFrame(0x02, bytes.fromhex("00020084"), 1)),
    (frame_command(cmds.write_word(0x40, 1234), 0x7F), CommandFrame(0x03, bytes.fromhex("004004D2"), 0x7F)),
    (frame_command(cmds.set_mode(cmds.Mode.RUN), 2), CommandFrame(0x03, bytes.fromhex("010180"), 2)),
    (encode_retransmit(9), RetransmitRequest(9)),
]


@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
@pytest.mark.parametrize("trailer", (b"", b"#01", b"\n", b"\x00", b";Z"))
@pytest.mark.parametrize(("frame", "expected"), COMMAND_SAMPLES)
def test_command_frames(frame: bytes, expected: HostEvent, trailer: bytes, feeder: Feeder) -> None:
    assert decode_commands(frame + trailer, feeder) == [expected]
    assert decode_commands(set_bit7(frame), feeder) == [expected]


@pytest.mark.parametrize(
    "bad",
    [
        frame_of("#", "0208" "00"),  # byte count 2, but only the code follows
        frame_of("#", "0108" "AA" "00"),  # byte count 1, one parameter byte too many
        frame_of("#", "01" "00"),  # no command code
        frame_of("#", "010" "00"),  # odd number of hex digits
        frame_of("#", "01" "GG" "00"),  # whole bytes, but not hex
        frame_of(";", "Q01"),  # unknown ; command
        frame_of(";", "Z0101"),  # ;Z too long
        b"#010800A4\r",  # bad CRC
    ],
)
@pytest.mark.parametrize("feeder", FEEDERS, ids=FEEDER_IDS)
def test_garbled_commands_then_recovery(bad: bytes, feeder: Feeder) -> None:
    events = decode_commands(bad + b"#010800A3\r", feeder)
    assert len(events) == 2
    assert isinstance(events[0], Garbled)
    assert events[1] == CommandFrame(0x08, b"", 0)


# ---------------------------------------------------------------------------------------------
# Properties

ids_strategy = st.integers(min_value=0, max_value=MAX_ID)

reply_strategy = st.one_of(
    st.builds(Ack, ids_strategy),
    st.builds(Refused, ids_strategy),
    st.builds(Fault, ids_strategy),
    st.builds(IdMismatch, ids_strategy),
    st.builds(
        DataReply,
        st.binary(min_size=1, max_size=(MAX_FRAME - 5) // 2).map(lambda b: b.hex().upper()),
        ids_strategy,
    ),
)


def encode_reply(event: ReplyEvent) -> bytes:
    if isinstance(event, Ack):
        return encode_ack(event.msg_id)
    if isinstance(event, Refused):
        return encode_refused(event.msg_id)
    if isinstance(event, Fault):
        return encode_fault(event.msg_id)
    if isinstance(event, IdMismatch):
        return encode_id_mismatch(event.last_valid_id)
    assert isinstance(event, DataReply)
    return encode_data_reply(event.body_hex, event.msg_id)


@settings(max_examples=200)
@given(st.lists(reply_strategy, min_size=1, max_size=8), st.integers(min_value=1, max_value=7), st.booleans())
def test_reply_round_trip(events: list[ReplyEvent], chunk: int, parity_bit: bool) -> None:
    data = b"".join(encode_reply(e) for e in events)
    if parity_bit:
        data = set_bit7(data)
    decoder = ReplyDecoder()
    decoded: list[ReplyEvent | HostEvent] = []
    for i in range(0, len(data), chunk):
        decoder.receive_data(data[i : i + chunk])
        decoded += drain(decoder)
    assert decoded == events


command_strategy = st.builds(
    lambda code, params: Command(code, params, "test", ReplyKind.ACK, TimeoutClass.NORMAL),
    st.integers(min_value=0, max_value=0xFF),
    st.binary(max_size=(MAX_FRAME - 9) // 2),
)


@settings(max_examples=200)
@given(command_strategy, ids_strategy, st.integers(min_value=1, max_value=7))
def test_command_round_trip(command: Command, msg_id: int, chunk: int) -> None:
    data = frame_command(command, msg_id) + encode_retransmit(msg_id)
    decoder = CommandDecoder()
    decoded: list[ReplyEvent | HostEvent] = []
    for i in range(0, len(data), chunk):
        decoder.receive_data(data[i : i + chunk])
        decoded += drain(decoder)
    assert decoded == [CommandFrame(command.code, command.params, msg_id), RetransmitRequest(msg_id)]


@settings(max_examples=300)
@given(st.binary(max_size=300), reply_strategy)
def test_random_bytes_never_raise_and_the_next_frame_decodes(noise: bytes, event: ReplyEvent) -> None:
    decoder = ReplyDecoder()
    decoder.receive_data(noise)
    for item in drain(decoder):
        assert isinstance(item, (DataReply, Ack, Refused, Fault, IdMismatch, Garbled))
    decoder.receive_data(encode_reply(event))
    assert drain(decoder)[-1] == event


@settings(max_examples=300)
@given(st.binary(max_size=300))
def test_random_bytes_never_raise_in_the_command_decoder(noise: bytes) -> None:
    decoder = CommandDecoder()
    decoder.receive_data(noise)
    for item in drain(decoder):
        assert isinstance(item, (CommandFrame, RetransmitRequest, Garbled))
    decoder.receive_data(b"#010800A3\r")
    assert drain(decoder)[-1] == CommandFrame(0x08, b"", 0)


@settings(max_examples=200)
@given(st.lists(st.sampled_from(b"#;:RETIZ0123456789ABCDEF\r\n"), max_size=200).map(bytes))
def test_protocol_alphabet_soup_never_raises(soup: bytes) -> None:
    for decoder in (ReplyDecoder(), CommandDecoder()):
        decoder.receive_data(soup)
        drain(decoder)


class _ByteByByteSplitter:
    """The first, byte-at-a-time line splitter, kept as the reference for the run-copying one."""

    def __init__(self, leads: bytes) -> None:
        self.leads = frozenset(leads)
        self.buffer = bytearray()
        self.pending: list[tuple[bytes, str]] = []

    def feed(self, data: bytes) -> None:
        from gateway.protocols.slc_ascii.framing import MAX_FRAME

        for byte in data:
            byte &= 0x7F
            if byte == 0x0A:
                continue
            if byte in self.leads:
                if self.buffer:
                    self.pending.append((bytes(self.buffer), "frame interrupted by a new leading character"))
                self.buffer.clear()
                self.buffer.append(byte)
            elif byte == 0x0D:
                if self.buffer:
                    self.pending.append((bytes(self.buffer), ""))
                    self.buffer.clear()
            elif self.buffer:
                if len(self.buffer) >= MAX_FRAME:
                    self.pending.append((bytes(self.buffer), "line too long"))
                    self.buffer.clear()
                else:
                    self.buffer.append(byte)


_LINE_BYTES = st.lists(
    st.one_of(
        st.sampled_from([b"#", b":", b";", b"\r", b"\n", b"\x8d", b"\xa3", b";R038D\r", b":0002008412340A"]),
        st.binary(min_size=0, max_size=120),
        st.just(b"A" * 100),
    ),
    max_size=12,
)


@given(_LINE_BYTES, st.integers(min_value=1, max_value=17))
@settings(max_examples=400)
def test_line_splitter_matches_the_byte_by_byte_reference(chunks: list[bytes], size: int) -> None:
    from gateway.protocols.slc_ascii.framing import _LineSplitter

    stream = b"".join(chunks)
    for leads in (b":;", b"#;"):
        fast, reference = _LineSplitter(leads), _ByteByByteSplitter(leads)
        for i in range(0, len(stream), size):
            fast.feed(stream[i : i + size])
            reference.feed(stream[i : i + size])
        lines = []
        while (line := fast.next_line()) is not None:
            lines.append((line.raw, line.reason) if isinstance(line, Garbled) else (line, ""))
        assert lines == reference.pending
        assert fast.buffered == len(reference.buffer)


# ---------------------------------------------------------------------------------------------
# What goes on the wire is upper-case hex, as every frame the manual prints (a mutation run: the decoders
# accept lower case, so a round trip cannot tell; a controller may not).


@given(msg_id=st.integers(0, MAX_ID), address=st.sampled_from([0x00AA, 0x00FE, 0x0040]),
       value=st.integers(0, 9999))
def test_every_frame_the_host_sends_is_upper_case_hex(msg_id: int, address: int, value: int) -> None:
    import re

    command = cmds.write_word(address & 0x7E, value) if address != 0x00AA else cmds.write_byte(0xAA, value & 0xFF)
    frame = frame_command(command, msg_id)
    assert re.fullmatch(rb"#[0-9A-F]+\r", frame), frame
    text = frame[1:-3]
    assert text == b"%02X%02X%s%02X" % (command.byte_count, command.code, command.params.hex().upper().encode(),
                                        msg_id)
    assert frame[-3:-1] == b"%02X" % crc(text)
    z = encode_retransmit(msg_id)
    assert z == b";Z%02X%02X\r" % (msg_id, crc(b"Z%02X" % msg_id))


@pytest.mark.parametrize(("encode", "letter"), [(encode_ack, b"R"), (encode_refused, b"E"), (encode_fault, b"T"),
                                                (encode_id_mismatch, b"I")])
def test_the_controllers_frames_are_upper_case(encode: Callable[[int], bytes], letter: bytes) -> None:
    for msg_id in (0x0A, 0x7F, 0x3C):
        assert encode(msg_id) == b";%s%02X%02X\r" % (letter, msg_id, crc(letter + b"%02X" % msg_id))
    reply = encode_data_reply("021ffe15ab", 0x7E)
    assert reply == b":021FFE15AB7E%02X\r" % crc(b"021FFE15AB7E")


def test_a_fault_report_carries_id_00_unless_told() -> None:
    assert encode_fault() == encode_fault(0)
