"""One full-duplex receiver for both roles: the host's data link and the target's responder.

Both stations run the receiver of ``gateway.protocols.df1.full_duplex.table`` (A-B 1770-6.5.16
p. 4-8, the RECEIVER program), so to the same bytes they give the same link-layer response (DLE
ACK, DLE NAK or nothing) and accept the same frames.  The responder's sink is made large enough
never to fill (the data link has none): that is a role parameter, not a receiver rule.
"""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.protocols.df1.framing import ACK_SYMBOL, ENQ_SYMBOL, NAK_SYMBOL, NEED_DATA, Checksum, Noise, encode_frame
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink, MessageReceived
from gateway.protocols.df1.full_duplex.responder import Df1Responder
from gateway.protocols.df1.full_duplex.responder_events import CommandReceived, DuplicateReceived
from gateway.protocols.df1.full_duplex.table import (
    RECEIVER,
    BadFrameAnswer,
    EnqAnswer,
    RxAction,
    RxInput,
    receiver_table,
)
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, duplicate_key

Station = Df1DataLink | Df1Responder


def stations(checksum: Checksum) -> tuple[Df1DataLink, Df1Responder]:
    return Df1DataLink(checksum=checksum), Df1Responder(checksum=checksum, max_pending=1 << 30)


def feed(station: Station, data: bytes) -> tuple[bytes, list[bytes]]:
    """What ``station`` sends and the messages it accepts for ``data``."""
    if isinstance(station, Df1DataLink):
        station.receive_data(data, 0.0)
    else:
        station.feed(data, 0.0)
    accepted: list[bytes] = []
    while (event := station.next_event()) is not NEED_DATA:
        if isinstance(event, MessageReceived):
            accepted.append(event.payload)
        elif isinstance(event, CommandReceived):
            accepted.append(event.packet)
        else:
            assert isinstance(event, DuplicateReceived), event
    return station.data_to_send(), accepted


def packet(tns: int, size: int = 11) -> bytes:
    return (bytes((1, 0, 0x0F, 0x00)) + tns.to_bytes(2, "little") + b"\xa2\x02\x07\x89\x00" + b"\x10" * 4)[:size]


# ------------------------------------------------------------------- the p. 4-8 rules, both roles


@pytest.mark.parametrize("role", [0, 1], ids=["data link", "responder"])
def test_dle_etx_without_dle_stx_is_no_frame_the_last_response_becomes_nak(role: int) -> None:
    """p. 4-8: outside a frame, anything but DLE STX / DLE ENQ is "else LAST-RESPONSE = NAK": no
    symbol is sent, and the next DLE ENQ gets DLE NAK."""
    station = stations(Checksum.CRC)[role]
    assert feed(station, encode_frame(packet(1), Checksum.CRC)) == (ACK_SYMBOL, [packet(1)])
    assert feed(station, encode_frame(packet(2), Checksum.CRC)[2:]) == (b"", [])  # its DLE STX lost
    assert feed(station, ENQ_SYMBOL) == (NAK_SYMBOL, [])
    assert station.counters.noise >= 1 and station.counters.bad_frames == 0


@pytest.mark.parametrize("role", [0, 1], ids=["data link", "responder"])
def test_noise_outside_a_frame_makes_the_last_response_nak(role: int) -> None:
    """p. 4-8 "else LAST-RESPONSE = NAK"; p. 4-7 "a false control or data symbol occurs outside a
    message": after noise a DLE ENQ no longer gets the DLE ACK of the last frame."""
    station = stations(Checksum.BCC)[role]
    assert feed(station, encode_frame(packet(1), Checksum.BCC)) == (ACK_SYMBOL, [packet(1)])
    assert feed(station, ENQ_SYMBOL) == (ACK_SYMBOL, [])
    assert feed(station, b"\x55\x00") == (b"", [])
    assert feed(station, ENQ_SYMBOL) == (NAK_SYMBOL, [])


@pytest.mark.parametrize("role", [0, 1], ids=["data link", "responder"])
def test_a_message_shorter_than_a_packet_header_is_naked(role: int) -> None:
    """p. 4-8 "else if message is too small then send DLE NAK": a packet has DST SRC CMD STS TNS."""
    station = stations(Checksum.CRC)[role]
    assert feed(station, encode_frame(packet(1, HEADER_SIZE - 1), Checksum.CRC)) == (NAK_SYMBOL, [])
    assert feed(station, encode_frame(packet(1, HEADER_SIZE), Checksum.CRC)) == (ACK_SYMBOL, [packet(1, HEADER_SIZE)])


def test_the_limits_have_one_name_in_both_roles() -> None:
    link, responder = Df1DataLink(nak_limit=2, enq_limit=1), Df1Responder(nak_limit=2, enq_limit=1)
    assert (link.nak_limit, link.enq_limit) == (responder.nak_limit, responder.enq_limit) == (2, 1)


def test_the_duplicate_key_is_src_cmd_tns() -> None:
    """p. 6-3: "The combination of SRC, CMD, and TNS bytes uniquely identifies every message packet"."""
    assert duplicate_key(bytes((9, 2, 0x0F, 0xF0, 0x34, 0x12))) == (2, 0x0F, 0x1234)
    assert duplicate_key(bytes((9, 2, 0x0F, 0xF0, 0x34, 0x12))) == duplicate_key(bytes((7, 2, 0x0F, 0, 0x34, 0x12)))


def test_every_reading_of_the_receiver_has_an_action_for_every_input() -> None:
    for bad_frame in BadFrameAnswer:
        for enq_answer in EnqAnswer:
            assert set(receiver_table(bad_frame, enq_answer)) == set(RxInput)
    assert RECEIVER[RxInput.BAD_FRAME] is RxAction.REJECT and RECEIVER[RxInput.ENQ] is RxAction.ANSWER_ENQ
    assert RECEIVER[RxInput.NOISE] is RxAction.LAST_NAK


# ------------------------------------------------------------------------------- the property


def units(checksum: Checksum) -> st.SearchStrategy[bytes]:
    """Pieces of a line: frames (good, damaged, cut short, too short), symbols, DLE pairs, noise."""
    packets = st.builds(packet, st.integers(0, 3), st.integers(1, 14))
    good = packets.map(lambda p: encode_frame(p, checksum))
    return st.one_of(
        good,
        good,
        st.tuples(good, st.integers(0, 64), st.integers(1, 255)).map(
            lambda t: t[0][: t[1] % len(t[0])] + bytes((t[0][t[1] % len(t[0])] ^ t[2],)) + t[0][t[1] % len(t[0]) + 1 :]
        ),
        st.tuples(good, st.integers(0, 64)).map(lambda t: t[0][t[1] % len(t[0]) :]),
        st.tuples(good, st.integers(0, 64)).map(lambda t: t[0][: t[1] % len(t[0])]),
        st.sampled_from([ENQ_SYMBOL, ACK_SYMBOL, NAK_SYMBOL, b"\x10\x03", b"\x10\x02", b"\x10\x10", b"\x10"]),
        st.binary(max_size=6),
    )


@st.composite
def lines(draw: st.DrawFn) -> tuple[Checksum, list[bytes]]:
    checksum = draw(st.sampled_from(list(Checksum)))
    data = b"".join(draw(st.lists(units(checksum), max_size=12)))
    cuts = sorted(set(draw(st.lists(st.integers(0, len(data)), max_size=6))) | {0, len(data)})
    return checksum, [data[a:b] for a, b in itertools.pairwise(cuts)]


@settings(max_examples=400, deadline=None)
@given(line=lines())
def test_the_data_link_and_the_responder_answer_every_byte_sequence_alike(line: tuple[Checksum, list[bytes]]) -> None:
    checksum, chunks = line
    link, responder = stations(checksum)
    for chunk in chunks:
        assert feed(link, chunk) == feed(responder, chunk)
    for counter in ("frames_received", "bad_frames", "duplicates", "noise", "acks_sent", "naks_sent"):
        assert getattr(link.counters, counter) == getattr(responder.counters, counter), counter
    assert feed(link, ENQ_SYMBOL) == feed(responder, ENQ_SYMBOL)  # the same last response


@settings(max_examples=300, deadline=None)
@given(line=lines())
def test_reporting_noise_changes_no_other_decoder_event(line: tuple[Checksum, list[bytes]]) -> None:
    """``report_noise`` adds Noise events and nothing else; a read without a byte outside a frame
    reports none."""
    checksum, chunks = line
    plain, noisy = FrameDecoder(checksum), FrameDecoder(checksum, report_noise=True)
    seen: list[list[object]] = [[], []]
    for chunk in chunks:
        for decoder, events in zip((plain, noisy), seen, strict=True):
            decoder.feed(chunk)
            while (event := decoder.next_event()) is not NEED_DATA:
                events.append(event)
    assert seen[0] == [event for event in seen[1] if not isinstance(event, Noise)]
    clean = b"".join(encode_frame(packet(tns), checksum) + ENQ_SYMBOL + ACK_SYMBOL for tns in range(3))
    noisy.reset()
    noisy.feed(clean)
    assert not any(isinstance(event, Noise) for event in iter(noisy.next_event, NEED_DATA))
