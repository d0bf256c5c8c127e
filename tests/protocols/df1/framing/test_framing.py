"""DF1 framing: BCC / CRC-16 vectors, DLE doubling, the streaming decoder."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.protocols.df1.checks import bcc, crc16
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    ENQ_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    BadFrameReason,
    Checksum,
    DecoderEvent,
    EnqReceived,
    Frame,
    NakReceived,
    encode_frame,
    frame_check,
    master_check,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder

# The brief's vector: an SLC 500 protected typed logical read of N7:0, 10 bytes, DST 1, TNS 1.
VECTOR = bytes.fromhex("01 00 0F 00 01 00 A2 0A 07 89 00 00")


def drain(decoder: FrameDecoder) -> list[DecoderEvent]:
    events: list[DecoderEvent] = []
    while (event := decoder.next_event()) is not NEED_DATA:
        events.append(event)
    return events


def decode(data: bytes, checksum: Checksum = Checksum.BCC, *, chunk: int | None = None) -> list[DecoderEvent]:
    decoder = FrameDecoder(checksum)
    events: list[DecoderEvent] = []
    if chunk is None:
        decoder.feed(data)
        return drain(decoder)
    for start in range(0, len(data), chunk):
        decoder.feed(data[start : start + chunk])
        events += drain(decoder)
    return events


def test_bcc_vector() -> None:
    assert bcc(VECTOR) == 0xB3


def test_crc_vector() -> None:
    """CRC-16 over the message and ETX (1770-6.5.16 p. 5-6): the caller passes the ETX."""
    assert crc16(VECTOR + b"\x03") == 0xF863
    assert encode_frame(VECTOR, Checksum.CRC)[-2:] == (0xF863).to_bytes(2, "little")


def test_one_check_contract_for_every_frame() -> None:
    """One CRC function with one contract (exactly the bytes given) serves every frame: a DLE STX
    frame's check covers the message and ETX, a half-duplex master message's STN STX message ETX."""
    assert crc16(b"\x03", crc16(VECTOR)) == crc16(VECTOR + b"\x03") == 0xF863
    assert frame_check(VECTOR, Checksum.CRC) == (0xF863).to_bytes(2, "little")
    assert frame_check(VECTOR, Checksum.BCC) == bytes((bcc(VECTOR),))
    assert master_check(1, VECTOR, Checksum.CRC) == crc16(b"\x01\x02" + VECTOR + b"\x03").to_bytes(2, "little")
    assert master_check(1, VECTOR, Checksum.BCC) == bytes((bcc(b"\x01" + VECTOR),))


def test_frame_vectors() -> None:
    assert encode_frame(VECTOR, Checksum.BCC) == b"\x10\x02" + VECTOR + b"\x10\x03\xb3"
    assert encode_frame(VECTOR, Checksum.CRC) == b"\x10\x02" + VECTOR + b"\x10\x03\x63\xf8"


def test_dle_doubling_vector() -> None:
    # TNS 0x1010 and a data byte 0x10: every 0x10 is sent twice, the checks count it once.
    message = bytes.fromhex("01 00 0F 00 10 10 A2 02 07 89 10 00")
    frame = encode_frame(message, Checksum.BCC)
    # sum = 0x174 -> low byte 0x74 -> two's complement 0x8C (each 0x10 counted once)
    assert frame == bytes.fromhex("10 02 01 00 0F 00 10 10 10 10 A2 02 07 89 10 10 00 10 03 8C")
    assert decode(frame) == [Frame(message)]
    crc_frame = encode_frame(message, Checksum.CRC)
    assert crc_frame[:-2] == frame[:-1]
    assert decode(crc_frame, Checksum.CRC) == [Frame(message)]


def test_bcc_is_not_xor() -> None:
    message = bytes((0x01, 0x02, 0x04))
    assert bcc(message) == 0xF9  # XOR would give 0x07


def test_empty_message_cannot_be_encoded() -> None:
    with pytest.raises(ValueError):
        encode_frame(b"", Checksum.BCC)


@pytest.mark.parametrize("checksum", list(Checksum))
@pytest.mark.parametrize("chunk", [None, 1, 2, 5])
def test_decoder_whole_bytewise_and_trailing(checksum: Checksum, chunk: int | None) -> None:
    frame = encode_frame(VECTOR, checksum)
    assert decode(frame, checksum, chunk=chunk) == [Frame(VECTOR)]
    # With trailing bytes: the next frame's beginning only.
    decoder = FrameDecoder(checksum)
    decoder.feed(frame + frame[:5])
    assert drain(decoder) == [Frame(VECTOR)]
    decoder.feed(frame[5:])
    assert drain(decoder) == [Frame(VECTOR)]


def test_need_data_shows_as_its_name() -> None:
    """What a driver logs or an assertion prints when a core has nothing to report."""
    assert repr(FrameDecoder(Checksum.BCC).next_event()) == "NEED_DATA"


@pytest.mark.parametrize("buffer", [bytearray, memoryview])
def test_any_bytes_like_read_decodes_as_bytes(buffer: type[bytearray] | type[memoryview]) -> None:
    """A read handed over as a bytearray or a memoryview (a buffered protocol's) decodes the same."""
    decoder = FrameDecoder(Checksum.CRC)
    frame = encode_frame(b"\x01\x10\x02", Checksum.CRC)
    for part in (frame[:4], frame[4:] + ACK_SYMBOL):
        decoder.feed(buffer(part))
    assert drain(decoder) == [Frame(b"\x01\x10\x02"), AckReceived()]


def test_link_symbols() -> None:
    assert decode(ACK_SYMBOL + NAK_SYMBOL + ENQ_SYMBOL) == [AckReceived(), NakReceived(), EnqReceived()]
    assert decode(ACK_SYMBOL + NAK_SYMBOL + ENQ_SYMBOL, chunk=1) == [
        AckReceived(),
        NakReceived(),
        EnqReceived(),
    ]


def test_ack_embedded_in_a_frame() -> None:
    frame = encode_frame(VECTOR, Checksum.BCC)
    mixed = frame[:6] + ACK_SYMBOL + frame[6:9] + NAK_SYMBOL + frame[9:]
    assert decode(mixed) == [AckReceived(), NakReceived(), Frame(VECTOR)]


def test_enq_inside_a_frame_aborts_it() -> None:
    frame = encode_frame(VECTOR, Checksum.BCC)
    assert decode(frame[:7] + ENQ_SYMBOL + frame) == [EnqReceived(aborted_frame=True), Frame(VECTOR)]


@pytest.mark.parametrize("checksum", list(Checksum))
def test_bad_checksum_is_reported(checksum: Checksum) -> None:
    frame = bytearray(encode_frame(VECTOR, checksum))
    frame[-1] ^= 0x01
    assert decode(bytes(frame), checksum) == [BadFrame(BadFrameReason.CHECKSUM)]


def test_corrupted_message_byte() -> None:
    frame = bytearray(encode_frame(VECTOR, Checksum.CRC))
    frame[5] ^= 0x40
    assert decode(bytes(frame), Checksum.CRC) == [BadFrame(BadFrameReason.CHECKSUM)]


def test_invalid_dle_sequence_inside_frame() -> None:
    frame = encode_frame(VECTOR, Checksum.BCC)
    bad = frame[:5] + b"\x10\x41" + frame[5:]
    assert decode(bad) == [BadFrame(BadFrameReason.INVALID_DLE_SEQUENCE)]


def test_empty_frame_is_bad() -> None:
    assert decode(b"\x10\x02\x10\x03\x00") == [BadFrame(BadFrameReason.EMPTY)]


def test_etx_without_stx_is_bad() -> None:
    frame = encode_frame(VECTOR, Checksum.BCC)
    assert decode(frame[2:]) == [BadFrame(BadFrameReason.MISSING_START)]


def test_garbage_between_frames_is_discarded() -> None:
    frame = encode_frame(VECTOR, Checksum.BCC)
    garbage = b"\x00\xff\x41\x10\x41\x10\x10\x02\x03\x99"
    assert decode(garbage + frame + garbage + frame) == [Frame(VECTOR), Frame(VECTOR)]


def test_stx_inside_a_frame_restarts() -> None:
    frame = encode_frame(VECTOR, Checksum.BCC)
    assert decode(frame[:8] + frame) == [Frame(VECTOR)]


def test_too_long_frame_is_bounded_and_bad() -> None:
    decoder = FrameDecoder(Checksum.BCC, max_message=16)
    long_message = bytes(range(32, 32 + 40))
    decoder.feed(encode_frame(long_message, Checksum.BCC))
    assert drain(decoder) == [BadFrame(BadFrameReason.TOO_LONG)]
    assert len(decoder._message) == 0  # nothing kept
    decoder.feed(encode_frame(VECTOR, Checksum.BCC))
    assert drain(decoder) == [Frame(VECTOR)]


def test_endless_frame_keeps_memory_bounded() -> None:
    decoder = FrameDecoder(Checksum.BCC, max_message=64)
    decoder.feed(b"\x10\x02" + b"\x55" * 100_000)
    assert len(decoder._message) <= 64
    assert drain(decoder) == []
    decoder.feed(encode_frame(VECTOR, Checksum.BCC))
    assert drain(decoder) == [Frame(VECTOR)]


def test_check_byte_equal_to_dle_is_not_doubled() -> None:
    # Find a message whose BCC is 0x10.
    message = bytes((0x01, 0x00, 0x0F, 0x00, 0x01, 0x00, 0xDF))
    assert bcc(message) == 0x10
    frame = encode_frame(message, Checksum.BCC)
    assert frame.endswith(b"\x10\x03\x10")
    assert decode(frame + encode_frame(VECTOR, Checksum.BCC)) == [Frame(message), Frame(VECTOR)]


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400), st.sampled_from(list(Checksum)))
def test_never_wedged_by_any_byte_stream(noise: bytes, checksum: Checksum) -> None:
    decoder = FrameDecoder(checksum, max_message=128)
    decoder.feed(noise)
    drain(decoder)
    # Whatever came before, the decoder is back in step within one frame: of three copies of a
    # frame the last two decode, and the first either decodes too or is judged bad (the noise
    # had opened a frame, or left a DLE that pairs with the frame's first one) - never lost
    # silently, never taken for something else.
    frame = encode_frame(VECTOR, checksum)
    decoder.feed(frame * 3)
    events = drain(decoder)
    assert events[-2:] == [Frame(VECTOR), Frame(VECTOR)]
    first = events[:-2]
    assert first == [Frame(VECTOR)] or (1 <= len(first) <= 2 and all(isinstance(e, BadFrame) for e in first)), first


@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(min_size=1, max_size=60), min_size=1, max_size=5), st.sampled_from(list(Checksum)))
def test_round_trip_any_messages(messages: list[bytes], checksum: Checksum) -> None:
    stream = b"".join(encode_frame(m, checksum) for m in messages)
    assert decode(stream, checksum) == [Frame(m) for m in messages]
    assert decode(stream, checksum, chunk=1) == [Frame(m) for m in messages]
