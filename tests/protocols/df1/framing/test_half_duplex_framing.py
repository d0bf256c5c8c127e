"""DF1 half-duplex framing: printed vectors, check coverage, STN doubling, the streaming decoder.

Page numbers are those of A-B 1770-6.5.16 (DF1) and the 1770-KF2 user manual (KF2); the reading is
in docs/develop/df1-half-duplex-notes.md.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.protocols.df1.checks import bcc, crc16
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    EOT_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    BadFrameReason,
    Checksum,
    DecoderEvent,
    EotReceived,
    Frame,
    MasterMessage,
    NakReceived,
    Poll,
    encode_frame,
    encode_master_message,
    encode_poll,
    master_check,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder

DATA = bytes.fromhex("08 09 06 00 02 04 03")


def drain(decoder: FrameDecoder) -> list[DecoderEvent]:
    events: list[DecoderEvent] = []
    while (event := decoder.next_event()) is not NEED_DATA:
        assert not isinstance(event, type(NEED_DATA))
        events.append(event)
    return events


def decode(data: bytes, checksum: Checksum = Checksum.BCC, *, chunk: int | None = None) -> list[DecoderEvent]:
    decoder = FrameDecoder(checksum, half_duplex=True)
    if chunk is None:
        decoder.feed(data)
        return drain(decoder)
    events: list[DecoderEvent] = []
    for start in range(0, len(data), chunk):
        decoder.feed(data[start : start + chunk])
        events += drain(decoder)
    return events


def all_ways(data: bytes, checksum: Checksum = Checksum.BCC) -> list[DecoderEvent]:
    """Decode whole, byte by byte and in 3-byte pieces; all must agree."""
    whole = decode(data, checksum)
    assert decode(data, checksum, chunk=1) == whole
    assert decode(data, checksum, chunk=3) == whole
    return whole


# ------------------------------------------------------------------------------ printed vectors


def test_kf2_4_25_example_1_master_message_bcc_includes_stn() -> None:
    """KF2 p. 4-25 Example 1: master to station 20 hex; STN + data sum to 40 hex, BCC C0."""
    frame = bytes.fromhex("10 01 20 10 02 08 09 06 00 02 04 03 10 03 C0")
    assert encode_master_message(0x20, DATA, Checksum.BCC) == frame
    assert all_ways(frame) == [MasterMessage(0x20, DATA)]


def test_df1_5_5_slave_frame_bcc() -> None:
    """1770-6.5.16 p. 5-5: 10 02 08 09 06 00 02 04 03 10 03 E0."""
    frame = bytes.fromhex("10 02 08 09 06 00 02 04 03 10 03 E0")
    assert encode_frame(DATA, Checksum.BCC) == frame
    assert all_ways(frame) == [Frame(DATA)]


def test_df1_5_5_and_kf2_4_25_example_2_doubled_dle_counts_once() -> None:
    """1770-6.5.16 p. 5-5 and KF2 p. 4-25 Example 2: data 10 sent as DLE DLE, BCC D2."""
    data = bytes.fromhex("08 09 06 00 10 04 03")
    frame = bytes.fromhex("10 02 08 09 06 00 10 10 04 03 10 03 D2")
    assert encode_frame(data, Checksum.BCC) == frame
    assert all_ways(frame) == [Frame(data)]


def test_df1_5_7_crc_validation_frame() -> None:
    """1770-6.5.16 p. 5-7: "an actual frame that you can use to validate your CRC routine"."""
    data = bytes.fromhex("07 11 41 00 53 B9") + bytes(12)
    frame = b"\x10\x02" + data + bytes.fromhex("10 03 6B 4C")
    assert encode_frame(data, Checksum.CRC) == frame
    assert all_ways(frame, Checksum.CRC) == [Frame(data)]


def test_df1_5_2_poll_bcc_is_complement_of_stn_even_on_crc() -> None:
    """p. 5-2: the poll BCC is the 2's complement of STN, one byte even on a CRC link."""
    assert encode_poll(0x01) == bytes.fromhex("10 05 01 FF")
    assert encode_poll(0x00) == bytes.fromhex("10 05 00 00")
    for checksum in Checksum:
        assert all_ways(encode_poll(0x20), checksum) == [Poll(0x20)]


def test_station_10_doubled_in_poll_and_header() -> None:
    """Table 2.C (p. 2-7): DLE DLE is the data or STN value 10 hex; the check counts it once."""
    assert encode_poll(0x10) == bytes.fromhex("10 05 10 10 F0")
    frame = encode_master_message(0x10, b"\x01\x02", Checksum.BCC)
    assert frame == bytes.fromhex("10 01 10 10 10 02 01 02 10 03") + bytes((-(0x10 + 3) & 0xFF,))
    assert all_ways(encode_poll(0x10)) == [Poll(0x10)]
    assert all_ways(frame) == [MasterMessage(0x10, b"\x01\x02")]


def test_check_byte_of_10_is_not_doubled() -> None:
    """p. 5-5: "If your BCC check sum is 10 hex, send it as 10 and not 10 10"."""
    assert encode_poll(0xF0) == bytes.fromhex("10 05 F0 10")
    assert all_ways(encode_poll(0xF0) + encode_poll(0x01)) == [Poll(0xF0), Poll(0x01)]
    data = bytes((0xF0,))
    frame = encode_frame(data, Checksum.BCC)
    assert frame.endswith(b"\x10\x03\x10")
    assert all_ways(frame + EOT_SYMBOL) == [Frame(data), EotReceived()]


def test_master_crc_covers_stn_stx_data_etx_and_bcc_does_not_cover_stx() -> None:
    """p. 5-6/5-7: master CRC over STN, STX, data, ETX; p. 5-2: master BCC over STN and data."""
    crc = encode_master_message(0x20, DATA, Checksum.CRC)
    assert crc[-2:] == crc16(bytes((0x20, 0x02)) + DATA + b"\x03").to_bytes(2, "little")
    # Not the CRC a slave message would carry for STN+data (ETX only, no STX).
    assert crc[-2:] != crc16(bytes((0x20,)) + DATA + b"\x03").to_bytes(2, "little")
    assert encode_master_message(0x20, DATA, Checksum.BCC)[-1] == bcc(bytes((0x20,)) + DATA)
    assert all_ways(crc, Checksum.CRC) == [MasterMessage(0x20, DATA)]


def test_slave_frame_is_the_full_duplex_frame() -> None:
    """The slave frame is the full-duplex frame (p. 5-2): both decoders read it alike."""
    for data in (DATA, b"\x10\x10\x00", bytes(range(60))):
        for checksum in Checksum:
            full = FrameDecoder(checksum)
            full.feed(encode_frame(data, checksum))
            assert drain(full) == all_ways(encode_frame(data, checksum), checksum) == [Frame(data)]


def test_response_symbols() -> None:
    """Table 2.C: DLE ACK, DLE NAK (15 hex, AG-UM008 B-5), DLE EOT."""
    assert (ACK_SYMBOL, NAK_SYMBOL, EOT_SYMBOL) == (b"\x10\x06", b"\x10\x15", b"\x10\x04")
    assert all_ways(ACK_SYMBOL + NAK_SYMBOL + EOT_SYMBOL) == [AckReceived(), NakReceived(), EotReceived()]


def test_nak_misprint_0f_is_not_nak() -> None:
    """Table 2.A prints NAK as 0F; ANSI X3.4 and AG-UM008 B-5 give 15.  10 0F is noise."""
    assert all_ways(b"\x10\x0f" + ACK_SYMBOL) == [AckReceived()]


# ----------------------------------------------------------------------------------- bad input


def test_bad_checks_are_reported_not_raised() -> None:
    frame = bytearray(encode_master_message(0x20, DATA, Checksum.BCC))
    frame[-1] ^= 0xFF
    assert all_ways(bytes(frame)) == [BadFrame(BadFrameReason.CHECKSUM, master=True)]
    poll = bytearray(encode_poll(3))
    poll[-1] ^= 1
    assert all_ways(bytes(poll)) == [BadFrame(BadFrameReason.CHECKSUM, master=True)]
    slave = bytearray(encode_frame(DATA, Checksum.CRC))
    slave[3] ^= 4
    assert all_ways(bytes(slave), Checksum.CRC) == [BadFrame(BadFrameReason.CHECKSUM, master=False)]


def test_single_byte_station_10_is_a_bad_station() -> None:
    """A slave that does not double STN 10: the poll is rejected, the next symbol still decodes."""
    assert all_ways(bytes.fromhex("10 05 10 F0") + EOT_SYMBOL) == [
        BadFrame(BadFrameReason.BAD_STATION, master=True),
        EotReceived(),
    ]


def test_header_without_stx_is_rejected() -> None:
    assert all_ways(bytes.fromhex("10 01 05 10 03 00") + ACK_SYMBOL) == [
        BadFrame(BadFrameReason.BAD_STATION, master=True),
        AckReceived(),
    ]
    assert all_ways(bytes.fromhex("10 01 05 07")) == [BadFrame(BadFrameReason.BAD_STATION, master=True)]


def test_new_symbol_inside_a_frame_truncates_it() -> None:
    """A collision or a dropout: the frame so far is bad, the new symbol is decoded."""
    partial = encode_frame(DATA, Checksum.BCC)[:6]
    assert all_ways(partial + encode_poll(7)) == [BadFrame(BadFrameReason.TRUNCATED, master=False), Poll(7)]
    header = encode_master_message(9, DATA, Checksum.BCC)[:8]
    assert all_ways(header + EOT_SYMBOL) == [BadFrame(BadFrameReason.TRUNCATED, master=True), EotReceived()]


def test_invalid_dle_sequence_and_empty_and_too_long() -> None:
    assert all_ways(bytes.fromhex("10 02 01 10 07 02 10 03 00")) == [
        BadFrame(BadFrameReason.INVALID_DLE_SEQUENCE, master=False)
    ]
    assert all_ways(bytes.fromhex("10 02 10 03 00")) == [BadFrame(BadFrameReason.EMPTY, master=False)]
    decoder = FrameDecoder(Checksum.BCC, half_duplex=True, max_message=4)
    decoder.feed(encode_frame(b"\x01" * 5, Checksum.BCC) + EOT_SYMBOL)
    assert drain(decoder) == [BadFrame(BadFrameReason.TOO_LONG, master=False), EotReceived()]


def test_noise_outside_frames_and_trailing_garbage() -> None:
    frame = encode_master_message(0x20, DATA, Checksum.CRC)
    events = all_ways(b"\x00\xff\x03\x10\x10" + frame + b"\x10\x02\x01", Checksum.CRC)
    assert events == [MasterMessage(0x20, DATA)]
    decoder = FrameDecoder(Checksum.CRC, half_duplex=True)
    decoder.feed(frame + b"\x10\x02\x01")
    assert drain(decoder) == [MasterMessage(0x20, DATA)]
    assert decoder.in_frame
    decoder.reset()
    assert not decoder.in_frame


def test_a_decoder_tells_which_framing_it_reads() -> None:
    assert FrameDecoder(Checksum.BCC, half_duplex=True).half_duplex is True
    assert FrameDecoder(Checksum.BCC).half_duplex is False


def test_encoder_validation() -> None:
    with pytest.raises(ValueError, match=r"0\.\.255"):
        encode_poll(256)
    with pytest.raises(ValueError, match="at least one"):
        encode_master_message(1, b"", Checksum.BCC)
    with pytest.raises(ValueError, match="at least one"):
        encode_frame(b"", Checksum.BCC)
    with pytest.raises(ValueError, match="max_message"):
        FrameDecoder(Checksum.BCC, half_duplex=True, max_message=0)
    with pytest.raises(ValueError):
        Poll(-1)
    with pytest.raises(ValueError):
        Frame(b"")
    assert master_check(1, b"\x02", Checksum.BCC) == bytes((-(1 + 2) & 0xFF,))


# ------------------------------------------------------------------------------------ property

frames = st.one_of(
    st.integers(0, 255).map(lambda s: (encode_poll(s), Poll(s))),
    st.tuples(st.integers(0, 255), st.binary(min_size=1, max_size=40)),
    st.binary(min_size=1, max_size=40).map(lambda m: (m, None)),
    st.sampled_from([(ACK_SYMBOL, AckReceived()), (NAK_SYMBOL, NakReceived()), (EOT_SYMBOL, EotReceived())]),
)


@settings(max_examples=200, deadline=None)
@given(items=st.lists(frames, max_size=6), checksum=st.sampled_from(list(Checksum)), chunk=st.integers(1, 9))
def test_any_sequence_round_trips_in_any_chunking(
    items: list[tuple[object, object]], checksum: Checksum, chunk: int
) -> None:
    wire = b""
    expected: list[DecoderEvent] = []
    for first, second in items:
        if isinstance(first, int) and isinstance(second, bytes):
            wire += encode_master_message(first, second, checksum)
            expected.append(MasterMessage(first, second))
        elif isinstance(first, bytes) and second is None:
            wire += encode_frame(first, checksum)
            expected.append(Frame(first))
        else:
            assert isinstance(first, bytes)
            wire += first
            assert isinstance(second, Poll | AckReceived | NakReceived | EotReceived)
            expected.append(second)
    assert decode(wire, checksum, chunk=chunk) == expected


@settings(max_examples=300, deadline=None)
@given(noise=st.binary(max_size=60), checksum=st.sampled_from(list(Checksum)))
def test_noise_never_raises_and_never_wedges(noise: bytes, checksum: Checksum) -> None:
    """After any noise, a DLE ACK to flush plus a good frame is always decoded."""
    decoder = FrameDecoder(checksum, half_duplex=True)
    decoder.feed(noise)
    drain(decoder)
    decoder.feed(b"\x00" * 3 + ACK_SYMBOL)  # ends any open poll/header/check; a data state sees ACK truncate
    drain(decoder)
    decoder.feed(encode_poll(0x42))
    assert drain(decoder)[-1] == Poll(0x42)
