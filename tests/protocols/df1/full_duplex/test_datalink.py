"""DF1 full-duplex link: two Df1DataLink instances paired in memory with a fake clock and faults."""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import InvalidRequest
from gateway.protocols.df1.framing import ACK_SYMBOL, ENQ_SYMBOL, NAK_SYMBOL, NEED_DATA, Checksum, encode_frame
from gateway.protocols.df1.full_duplex.datalink import (
    BadFrameAnswer,
    DataLinkEvent,
    Df1DataLink,
    EnqAnswer,
    MessageReceived,
    SendComplete,
    SendFailed,
    SendFailure,
    TxState,
)

Fault = Callable[[bytes], bytes]


def identity(data: bytes) -> bytes:
    return data


def packet(tns: int, src: int = 0, dst: int = 1) -> bytes:
    """A PCCC-looking message: DST SRC CMD STS TNS FNC data (distinct per TNS)."""
    return bytes((dst, src, 0x0F, 0x00)) + tns.to_bytes(2, "little") + b"\xa2\x02\x07\x89" + bytes((tns & 0xFF,))


@dataclass
class Pair:
    """Two links wired back to back; ``now`` is the fake clock."""

    a: Df1DataLink
    b: Df1DataLink
    a_to_b: Fault = identity
    b_to_a: Fault = identity
    now: float = 0.0
    a_events: list[DataLinkEvent] = field(default_factory=list)
    b_events: list[DataLinkEvent] = field(default_factory=list)

    def collect(self) -> None:
        for link, events in ((self.a, self.a_events), (self.b, self.b_events)):
            while (event := link.next_event()) is not NEED_DATA:
                events.append(event)

    def run(self, max_steps: int = 100_000) -> None:
        for _ in range(max_steps):
            moved = False
            if out := self.a.data_to_send():
                self.b.receive_data(self.a_to_b(out), self.now)
                moved = True
            if out := self.b.data_to_send():
                self.a.receive_data(self.b_to_a(out), self.now)
                moved = True
            self.collect()
            if moved:
                continue
            deadlines = [d for d in (self.a.next_deadline(), self.b.next_deadline()) if d is not None]
            if not deadlines:
                return
            self.now = min(deadlines)
            self.a.handle_timeout(self.now)
            self.b.handle_timeout(self.now)
        raise AssertionError("link pair did not settle")

    def delivered_to_b(self) -> list[bytes]:
        return [e.payload for e in self.b_events if isinstance(e, MessageReceived)]

    def delivered_to_a(self) -> list[bytes]:
        return [e.payload for e in self.a_events if isinstance(e, MessageReceived)]


def make_pair(
    checksum: Checksum = Checksum.CRC, *, nak_limit: int = 3, enq_limit: int = 3, duplicate_detect: bool = True
) -> Pair:
    def link() -> Df1DataLink:
        return Df1DataLink(
            checksum=checksum,
            ack_timeout=0.2,
            nak_limit=nak_limit,
            enq_limit=enq_limit,
            duplicate_detect=duplicate_detect,
        )

    return Pair(link(), link())


class DropFirst:
    """Remove the first ``count`` occurrences of ``pattern`` from the stream."""

    def __init__(self, pattern: bytes, count: int = 1) -> None:
        self.pattern, self.left = pattern, count

    def __call__(self, data: bytes) -> bytes:
        while self.left and self.pattern in data:
            data = data.replace(self.pattern, b"", 1)
            self.left -= 1
        return data


class CorruptFrames:
    """Flip one bit in the first ``count`` chunks that carry a frame."""

    def __init__(self, count: int = 1) -> None:
        self.left = count

    def __call__(self, data: bytes) -> bytes:
        if self.left and b"\x10\x02" in data:
            self.left -= 1
            start = data.index(b"\x10\x02")
            corrupted = bytearray(data)
            corrupted[start + 4] ^= 0x01
            return bytes(corrupted)
        return data


class DuplicateFrames:
    """Send every chunk that carries a frame twice."""

    def __call__(self, data: bytes) -> bytes:
        return data + data if b"\x10\x02" in data else data


# ----------------------------------------------------------------------------------- normal


@pytest.mark.parametrize("checksum", list(Checksum))
def test_messages_delivered_in_order(checksum: Checksum) -> None:
    pair = make_pair(checksum)
    messages = [packet(tns) for tns in range(1, 6)]
    handles = [pair.a.send(m, pair.now) for m in messages]
    pair.run()
    assert pair.delivered_to_b() == messages
    assert pair.a_events == [SendComplete(h) for h in handles]
    assert pair.a.counters.frames_sent == 5
    assert pair.a.counters.acks_received == 5
    assert pair.b.counters.acks_sent == 5
    assert pair.b.counters.messages_delivered == 5
    assert pair.a.tx_state is TxState.IDLE
    assert pair.a.next_deadline() is None


def test_one_frame_outstanding_at_a_time() -> None:
    link = Df1DataLink(checksum=Checksum.BCC)
    link.send(packet(1), 0.0)
    link.send(packet(2), 0.0)
    assert link.data_to_send() == encode_frame(packet(1), Checksum.BCC)
    assert link.pending == 2
    assert link.next_deadline() == pytest.approx(1.0)  # default ACK timeout
    link.receive_data(ACK_SYMBOL, 0.5)
    assert link.next_event() == SendComplete(1)
    assert link.data_to_send() == encode_frame(packet(2), Checksum.BCC)
    assert link.next_deadline() == pytest.approx(1.5)


def test_full_duplex_both_directions_at_once() -> None:
    pair = make_pair()
    to_b = [packet(tns, src=0, dst=1) for tns in range(1, 8)]
    to_a = [packet(tns, src=1, dst=0) for tns in range(100, 107)]
    for x, y in zip(to_b, to_a, strict=True):
        pair.a.send(x, pair.now)
        pair.b.send(y, pair.now)
    pair.run()
    assert pair.delivered_to_b() == to_b
    assert pair.delivered_to_a() == to_a
    assert sum(isinstance(e, SendComplete) for e in pair.a_events) == 7
    assert sum(isinstance(e, SendComplete) for e in pair.b_events) == 7


def test_frame_with_byte_10_in_payload() -> None:
    pair = make_pair(Checksum.BCC)
    message = bytes.fromhex("10 10 0F 00 10 10 10")
    pair.a.send(message, pair.now)
    pair.run()
    assert pair.delivered_to_b() == [message]


# ------------------------------------------------------------------------------- receiver


def test_receiver_acks_and_naks() -> None:
    link = Df1DataLink(checksum=Checksum.BCC)
    link.receive_data(encode_frame(packet(1), Checksum.BCC), 0.0)
    assert link.data_to_send() == ACK_SYMBOL
    assert link.next_event() == MessageReceived(packet(1))
    bad = bytearray(encode_frame(packet(2), Checksum.BCC))
    bad[-1] ^= 0xFF
    link.receive_data(bytes(bad), 0.0)
    assert link.data_to_send() == NAK_SYMBOL
    assert link.next_event() is NEED_DATA
    assert link.counters.bad_frames == 1


def test_enq_answered_with_last_response() -> None:
    link = Df1DataLink(checksum=Checksum.BCC)
    link.receive_data(ENQ_SYMBOL, 0.0)
    assert link.data_to_send() == NAK_SYMBOL  # nothing answered yet
    link.receive_data(encode_frame(packet(1), Checksum.BCC), 0.0)
    assert link.data_to_send() == ACK_SYMBOL
    link.receive_data(ENQ_SYMBOL + ENQ_SYMBOL, 0.0)
    assert link.data_to_send() == ACK_SYMBOL + ACK_SYMBOL
    link.receive_data(b"\x10\x02\x01\x02\x10\x03\x00", 0.0)  # bad BCC
    assert link.data_to_send() == NAK_SYMBOL
    link.receive_data(ENQ_SYMBOL, 0.0)
    assert link.data_to_send() == NAK_SYMBOL
    assert link.counters.enqs_received == 4


@pytest.mark.parametrize(("answer", "at_once", "on_enq"), [
    (BadFrameAnswer.NAK, NAK_SYMBOL, NAK_SYMBOL),
    (BadFrameAnswer.SILENCE, b"", NAK_SYMBOL),
    (BadFrameAnswer.IGNORE, b"", ACK_SYMBOL),
])
def test_a_damaged_frame_is_answered_as_the_link_is_configured(
    answer: BadFrameAnswer, at_once: bytes, on_enq: bytes
) -> None:
    link = Df1DataLink(checksum=Checksum.BCC, bad_frame=answer)
    link.receive_data(encode_frame(packet(1), Checksum.BCC), 0.0)
    assert link.data_to_send() == ACK_SYMBOL
    bad = b"\x10\x02\x01\x02\x10\x03\x00"  # bad BCC
    link.receive_data(bad, 0.0)
    assert link.data_to_send() == at_once
    link.receive_data(ENQ_SYMBOL, 0.0)
    assert link.data_to_send() == on_enq
    link.receive_data(bad, 0.0)
    assert link.counters.bad_frames == 2 and link.next_event() == MessageReceived(packet(1))


def test_enq_answered_nak_whatever_the_last_response() -> None:
    link = Df1DataLink(checksum=Checksum.BCC, enq_answer=EnqAnswer.NAK)
    link.receive_data(encode_frame(packet(1), Checksum.BCC) + ENQ_SYMBOL, 0.0)
    assert link.data_to_send() == ACK_SYMBOL + NAK_SYMBOL


def test_enq_during_a_truncated_frame_is_answered_nak() -> None:
    link = Df1DataLink(checksum=Checksum.BCC)
    link.receive_data(encode_frame(packet(1), Checksum.BCC), 0.0)
    assert link.data_to_send() == ACK_SYMBOL
    # Frame 2 loses its DLE ETX; the sender's ENQ must not be answered with frame 1's ACK.
    frame = encode_frame(packet(2), Checksum.BCC)
    link.receive_data(frame[:-3] + ENQ_SYMBOL, 0.0)
    assert link.data_to_send() == NAK_SYMBOL
    link.receive_data(frame[:-3] + ENQ_SYMBOL, 0.0)
    assert link.counters.bad_frames == 2  # each truncated frame counts


def test_duplicate_frame_acked_not_delivered_twice() -> None:
    link = Df1DataLink(checksum=Checksum.CRC)
    frame = encode_frame(packet(7), Checksum.CRC)
    link.receive_data(frame + frame, 0.0)
    assert link.data_to_send() == ACK_SYMBOL + ACK_SYMBOL
    assert link.next_event() == MessageReceived(packet(7))
    assert link.next_event() is NEED_DATA
    assert link.counters.duplicates == 1
    # Same SRC/CMD/TNS is a duplicate even if another byte differs (1770-6.5.16 rule).
    other = bytearray(packet(7))
    other[-1] ^= 0xFF
    link.receive_data(encode_frame(bytes(other), Checksum.CRC), 0.0)
    assert link.next_event() is NEED_DATA
    # A new TNS is a new message, and the old one is no longer "the last".
    link.receive_data(encode_frame(packet(8), Checksum.CRC) + frame, 0.0)
    assert link.next_event() == MessageReceived(packet(8))
    assert link.next_event() == MessageReceived(packet(7))


def test_a_header_only_message_is_a_duplicate_by_src_cmd_and_tns() -> None:
    """A 6-byte packet is a whole PCCC header: DST and STS are no part of the comparison."""
    link = Df1DataLink(checksum=Checksum.CRC)
    header = packet(7)[:6]
    other_dst_sts = b"\x09" + header[1:3] + b"\x55" + header[4:6]
    link.receive_data(encode_frame(header, Checksum.CRC) + encode_frame(other_dst_sts, Checksum.CRC), 0.0)
    assert link.next_event() == MessageReceived(header)
    assert link.next_event() is NEED_DATA
    link.receive_data(encode_frame(packet(7), Checksum.CRC) + encode_frame(header, Checksum.CRC), 0.0)
    assert link.next_event() is NEED_DATA  # the longer one, and the header after it: the same message


def test_messages_shorter_than_a_header_are_naked() -> None:
    """1770-6.5.16 p. 4-8: "else if message is too small then send DLE NAK" (a packet has at least
    DST SRC CMD STS TNS, 6 bytes)."""
    link = Df1DataLink(checksum=Checksum.CRC)
    link.receive_data(b"".join(encode_frame(m, Checksum.CRC) for m in (b"\x01\x02", b"\x01\x02\x03\x04\x05")), 0.0)
    assert link.next_event() is NEED_DATA
    assert link.data_to_send() == NAK_SYMBOL + NAK_SYMBOL
    assert link.counters.bad_frames == 2 and link.counters.messages_delivered == 0


def test_duplicate_detection_can_be_disabled() -> None:
    pair = make_pair(duplicate_detect=False)
    pair.a_to_b = DuplicateFrames()
    pair.a.send(packet(1), pair.now)
    pair.run()
    assert pair.delivered_to_b() == [packet(1), packet(1)]


def test_garbage_between_frames() -> None:
    link = Df1DataLink(checksum=Checksum.CRC)
    frame = encode_frame(packet(1), Checksum.CRC)
    second = encode_frame(packet(2), Checksum.CRC)
    link.receive_data(b"\x00\x55\x10\x33garbage" + frame + b"\xff\xfe" + second, 0)
    assert link.next_event() == MessageReceived(packet(1))
    assert link.next_event() == MessageReceived(packet(2))
    assert link.data_to_send() == ACK_SYMBOL + ACK_SYMBOL


def test_receive_byte_by_byte() -> None:
    link = Df1DataLink(checksum=Checksum.CRC)
    for byte in encode_frame(packet(1), Checksum.CRC) + ACK_SYMBOL:
        link.receive_data(bytes((byte,)), 0.0)
    assert link.next_event() == MessageReceived(packet(1))
    assert link.counters.acks_received == 1  # stray ACK while idle: counted, ignored
    assert link.next_event() is NEED_DATA


# ---------------------------------------------------------------------------- transmitter


def test_corrupted_frame_is_nakked_and_resent_unchanged() -> None:
    pair = make_pair(Checksum.BCC)
    pair.a_to_b = CorruptFrames(1)
    handle = pair.a.send(packet(1), pair.now)
    pair.run()
    assert pair.delivered_to_b() == [packet(1)]
    assert pair.a_events == [SendComplete(handle)]
    assert pair.b.counters.naks_sent == 1
    assert pair.a.counters.naks_received == 1
    assert pair.a.counters.retransmissions == 1
    assert pair.a.counters.frames_sent == 2


def test_answer_before_the_frame_left_is_stale() -> None:
    link = Df1DataLink(checksum=Checksum.BCC)
    link.send(packet(1), 0.0)
    link.receive_data(ACK_SYMBOL + NAK_SYMBOL, 0.0)  # frame still in the output buffer
    assert link.next_event() is NEED_DATA
    assert link.data_to_send() == encode_frame(packet(1), Checksum.BCC)
    link.receive_data(ACK_SYMBOL, 0.1)
    assert link.next_event() == SendComplete(1)


def test_nak_retransmits_the_same_bytes() -> None:
    link = Df1DataLink(checksum=Checksum.CRC)
    link.send(packet(1), 0.0)
    first = link.data_to_send()
    link.receive_data(NAK_SYMBOL, 0.1)
    assert link.data_to_send() == first  # same frame, same TNS


def test_lost_ack_recovered_by_enq_without_resending() -> None:
    pair = make_pair()
    pair.b_to_a = DropFirst(ACK_SYMBOL)
    handle = pair.a.send(packet(1), pair.now)
    pair.run()
    assert pair.a_events == [SendComplete(handle)]
    assert pair.delivered_to_b() == [packet(1)]
    assert pair.a.counters.enqs_sent == 1
    assert pair.a.counters.frames_sent == 1  # exactly once on the wire
    assert pair.now == pytest.approx(0.2)


def test_lost_frame_before_any_response_is_resent_after_enq() -> None:
    pair = make_pair()
    frame = encode_frame(packet(1), Checksum.CRC)
    pair.a_to_b = DropFirst(frame)
    pair.a.send(packet(1), pair.now)
    pair.run()
    assert pair.delivered_to_b() == [packet(1)]
    assert pair.a.counters.enqs_sent == 1
    assert pair.a.counters.retransmissions == 1


def test_lost_start_of_frame_makes_the_last_response_nak() -> None:
    """1770-6.5.16 p. 4-8: DLE ETX without DLE STX is outside a frame: "else LAST-RESPONSE = NAK", no
    symbol sent; the sender's DLE ENQ gets the DLE NAK and it sends the frame again."""
    pair = make_pair()
    pair.a.send(packet(1), pair.now)
    pair.run()
    pair.a_to_b = DropFirst(b"\x10\x02")
    pair.a.send(packet(2), pair.now)
    pair.run()
    assert pair.delivered_to_b() == [packet(1), packet(2)]
    assert pair.b.counters.bad_frames == 0 and pair.b.counters.noise >= 1
    assert (pair.a.counters.enqs_sent, pair.a.counters.naks_received, pair.a.counters.retransmissions) == (1, 1, 1)


def test_duplicated_frames_delivered_once() -> None:
    pair = make_pair()
    pair.a_to_b = DuplicateFrames()
    messages = [packet(tns) for tns in range(1, 4)]
    for m in messages:
        pair.a.send(m, pair.now)
    pair.run()
    assert pair.delivered_to_b() == messages
    assert pair.b.counters.duplicates == 3
    assert [type(e) for e in pair.a_events] == [SendComplete] * 3


def test_nak_limit_reports_failure() -> None:
    pair = make_pair(nak_limit=3)
    pair.a_to_b = CorruptFrames(100)
    handle = pair.a.send(packet(1), pair.now)
    second = pair.a.send(packet(2), pair.now)
    pair.a_to_b = CorruptFrames(4)  # first frame + its 3 retransmissions
    pair.run()
    assert pair.a_events == [SendFailed(handle, SendFailure.NAK_LIMIT), SendComplete(second)]
    assert pair.delivered_to_b() == [packet(2)]
    assert pair.a.counters.retransmissions == 3
    assert pair.a.counters.send_failures == 1


def test_no_response_reports_failure_after_enq_limit() -> None:
    pair = make_pair(enq_limit=3)
    pair.a_to_b = lambda data: b""
    handle = pair.a.send(packet(1), pair.now)
    pair.run()
    assert pair.a_events == [SendFailed(handle, SendFailure.NO_RESPONSE)]
    assert pair.a.counters.enqs_sent == 3
    assert pair.now == pytest.approx(0.8)  # 1 + 3 timeouts of 0.2 s
    assert pair.a.next_deadline() is None


def test_timeout_is_configurable_and_early_calls_do_nothing() -> None:
    link = Df1DataLink(checksum=Checksum.BCC, ack_timeout=0.3)
    link.send(packet(1), 10.0)
    link.data_to_send()
    assert link.next_deadline() == pytest.approx(10.3)
    link.handle_timeout(10.1)
    assert link.data_to_send() == b""
    link.handle_timeout(10.3)
    assert link.data_to_send() == ENQ_SYMBOL
    assert link.next_deadline() == pytest.approx(10.6)


def test_ack_after_enq_completes() -> None:
    link = Df1DataLink(checksum=Checksum.BCC, ack_timeout=0.1)
    link.send(packet(1), 0.0)
    link.data_to_send()
    link.handle_timeout(0.1)
    assert link.data_to_send() == ENQ_SYMBOL
    link.receive_data(ACK_SYMBOL, 0.15)
    assert link.next_event() == SendComplete(1)
    assert link.next_deadline() is None


def test_zero_retries() -> None:
    link = Df1DataLink(checksum=Checksum.BCC, nak_limit=0, enq_limit=0, ack_timeout=0.1)
    link.send(packet(1), 0.0)
    link.data_to_send()
    link.receive_data(NAK_SYMBOL, 0.0)
    assert link.next_event() == SendFailed(1, SendFailure.NAK_LIMIT)
    link.send(packet(2), 0.0)
    link.handle_timeout(0.1)
    assert link.next_event() == SendFailed(2, SendFailure.NO_RESPONSE)
    assert link.counters.send_failures == 2


def test_reset_fails_everything_pending() -> None:
    link = Df1DataLink(checksum=Checksum.BCC)
    link.send(packet(1), 0.0)
    link.send(packet(2), 0.0)
    link.receive_data(b"\x10\x02\x01", 0.0)  # partial frame
    link.reset()
    assert link.next_event() == SendFailed(1, SendFailure.LINK_RESET)
    assert link.next_event() == SendFailed(2, SendFailure.LINK_RESET)
    assert link.data_to_send() == b""
    assert link.next_deadline() is None
    assert link.counters.send_failures == 2
    link.receive_data(encode_frame(packet(3), Checksum.BCC), 0.0)
    assert link.next_event() == MessageReceived(packet(3))


def test_after_a_reset_the_first_ack_completes_the_next_frame() -> None:
    """A confirm() before the reset leaves no answer owed: the line was forgotten with it."""
    link = Df1DataLink(checksum=Checksum.BCC)
    handle = link.send(packet(1), 0.0)
    link.data_to_send()
    link.confirm(handle, 0.0)
    assert link.next_event() == SendComplete(handle)
    link.reset()
    handle = link.send(packet(2), 0.0)
    link.data_to_send()
    link.receive_data(ACK_SYMBOL, 0.0)
    assert link.next_event() == SendComplete(handle)


def test_send_validation() -> None:
    link = Df1DataLink(checksum=Checksum.BCC, max_message=16)
    with pytest.raises(InvalidRequest):
        link.send(b"", 0.0)
    with pytest.raises(InvalidRequest):
        link.send(bytes(17), 0.0)
    assert link.send(bytes(16), 0.0) == 1  # as long as max_message: sent
    assert link.data_to_send() == encode_frame(bytes(16), Checksum.BCC)
    with pytest.raises(ValueError):
        Df1DataLink(ack_timeout=0)


def test_the_limits_reject_a_negative_count_of_either_kind() -> None:
    with pytest.raises(ValueError):
        Df1DataLink(enq_limit=-1)
    with pytest.raises(ValueError):
        Df1DataLink(nak_limit=-1)


def test_by_default_a_frame_is_sent_again_on_3_naks_and_enquired_3_times() -> None:
    """The DF1 manuals' default retry counts (3 DLE NAKs, 3 DLE ENQs), which the simulated
    controllers' links run with."""
    link = Df1DataLink(checksum=Checksum.BCC, ack_timeout=0.1)
    frame = encode_frame(packet(1), Checksum.BCC)
    link.send(packet(1), 0.0)
    assert link.data_to_send() == frame
    for _ in range(3):
        link.receive_data(NAK_SYMBOL, 0.0)
        assert link.data_to_send() == frame
    link.receive_data(NAK_SYMBOL, 0.0)
    assert link.next_event() == SendFailed(1, SendFailure.NAK_LIMIT)
    link.send(packet(2), 0.0)
    link.data_to_send()
    now = 0.0
    for _ in range(3):
        now += 0.1
        link.handle_timeout(now)
        assert link.data_to_send() == ENQ_SYMBOL
    link.handle_timeout(now + 0.1)
    assert link.next_event() == SendFailed(2, SendFailure.NO_RESPONSE)


def test_by_default_the_ack_wait_does_not_allow_for_character_times() -> None:
    """``char_time`` 0 by default: the measured ACK times are the whole wait after writing."""
    link = Df1DataLink(ack_timeout=1.0)
    now = 0.0
    for n in range(8):
        link.send(packet(n + 1), now)
        link.data_to_send()
        link.receive_data(ACK_SYMBOL, now + 0.01)
        assert link.next_event() == SendComplete(n + 1)
        now += 0.1
    link.send(packet(9), now)
    link.data_to_send()
    assert link.next_deadline() == pytest.approx(now + 0.05)  # 2 x 10 ms, raised to the floor


def test_a_frame_longer_than_max_message_is_nakked_not_delivered() -> None:
    link = Df1DataLink(checksum=Checksum.BCC, max_message=16)
    link.receive_data(encode_frame(bytes(range(1, 18)), Checksum.BCC), 0.0)
    assert link.data_to_send() == NAK_SYMBOL
    assert link.next_event() is NEED_DATA
    link.receive_data(encode_frame(bytes(range(1, 17)), Checksum.BCC), 0.0)
    assert link.data_to_send() == ACK_SYMBOL
    assert link.next_event() == MessageReceived(bytes(range(1, 17)))


# ---------------------------------------------------------------------------------- soak


class RandomFaults:
    """Drop bytes and flip single bits at random; at most ``per_chunk`` faults per write."""

    def __init__(self, rng: random.Random, drop: float, flip: float, per_chunk: int = 1_000_000) -> None:
        self.rng, self.drop, self.flip, self.per_chunk = rng, drop, flip, per_chunk

    def __call__(self, data: bytes) -> bytes:
        out = bytearray()
        faults = 0
        for byte in data:
            roll = self.rng.random() if faults < self.per_chunk else 1.0
            if roll < self.drop:
                faults += 1
                continue
            if roll < self.drop + self.flip:
                faults += 1
                byte ^= 1 << self.rng.randrange(8)
            out.append(byte)
        return bytes(out)


def check_exactly_once(
    sent: list[bytes], handles: list[int], events: list[DataLinkEvent], delivered: list[bytes]
) -> None:
    # Every send resolves exactly once.
    resolved = [e.handle for e in events if isinstance(e, SendComplete | SendFailed)]
    assert sorted(resolved) == sorted(handles)
    # Delivered messages: no duplicates, in sending order.
    assert len(set(delivered)) == len(delivered)
    positions = [sent.index(m) for m in delivered]
    assert positions == sorted(positions)
    # Everything reported complete was delivered.
    completed = {e.handle for e in events if isinstance(e, SendComplete)}
    for handle, message in zip(handles, sent, strict=True):
        if handle in completed:
            assert message in delivered


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(list(Checksum)))
def test_soak_one_way_exactly_once(seed: int, checksum: Checksum) -> None:
    """One fault per frame or symbol at most: every completed send is delivered exactly once.

    (Two faults in one frame - say both DLE STX and DLE ETX damaged - can make a frame vanish
    without trace; the peer then answers ENQ with the previous ACK.  That is a limit of DF1
    itself, covered by the PCCC reply timeout, and is what the two-way soak below tolerates.)
    """
    rng = random.Random(seed)
    pair = make_pair(checksum)
    # A BCC cannot see a lost 0x00 byte (it adds nothing to the sum): no drops inside BCC frames.
    drop = 0.01 if checksum is Checksum.CRC else 0.0
    pair.a_to_b = RandomFaults(rng, drop=drop, flip=0.01, per_chunk=1)
    pair.b_to_a = RandomFaults(rng, drop=0.05, flip=0.05, per_chunk=1)
    sent = [packet(tns) for tns in range(1, 31)]
    handles = [pair.a.send(m, pair.now) for m in sent]
    pair.run()
    check_exactly_once(sent, handles, pair.a_events, pair.delivered_to_b())
    completed = sum(isinstance(e, SendComplete) for e in pair.a_events)
    assert completed >= 20  # light faults: most get through


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_soak_both_ways_in_order_without_duplicates(seed: int) -> None:
    rng = random.Random(seed)
    pair = make_pair(Checksum.CRC)
    pair.a_to_b = RandomFaults(rng, drop=0.01, flip=0.01)
    pair.b_to_a = RandomFaults(rng, drop=0.01, flip=0.01)
    to_b = [packet(tns, src=0) for tns in range(1, 21)]
    to_a = [packet(tns, src=1) for tns in range(500, 520)]
    a_handles = [pair.a.send(m, pair.now) for m in to_b]
    b_handles = [pair.b.send(m, pair.now) for m in to_a]
    pair.run()
    for sent, handles, events, delivered in (
        (to_b, a_handles, pair.a_events, pair.delivered_to_b()),
        (to_a, b_handles, pair.b_events, pair.delivered_to_a()),
    ):
        resolved = [e.handle for e in events if isinstance(e, SendComplete | SendFailed)]
        assert sorted(resolved) == sorted(handles)
        assert len(set(delivered)) == len(delivered)
        positions = [sent.index(m) for m in delivered]
        assert positions == sorted(positions)


# ------------------------------------------------------- frames that must not run twice (writes)


@pytest.mark.parametrize("enquire_first", [False, True])
def test_a_nak_never_retransmits_a_frame_sent_as_not_idempotent(enquire_first: bool) -> None:
    link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.5, nak_limit=3)
    handle = link.send(packet(1), 0.0, idempotent=False)
    frame = link.data_to_send()
    assert frame == encode_frame(packet(1), Checksum.CRC)
    if enquire_first:
        link.handle_timeout(0.5)
        assert link.data_to_send() == ENQ_SYMBOL
    link.receive_data(NAK_SYMBOL, 0.6)
    assert link.data_to_send() == b""  # not sent again: the NAK is no proof it was discarded
    assert link.next_event() == SendFailed(handle, SendFailure.AMBIGUOUS_NAK)
    assert link.tx_state is TxState.IDLE and link.counters.retransmissions == 0


def test_a_nak_retransmits_an_idempotent_frame() -> None:
    link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.5)
    link.send(packet(1), 0.0)
    frame = link.data_to_send()
    link.receive_data(NAK_SYMBOL, 0.1)
    assert link.data_to_send() == frame


def test_confirm_completes_the_frame_and_the_next_answer_is_owed_to_it() -> None:
    link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.5)
    first = link.send(packet(1), 0.0)
    link.data_to_send()
    link.confirm(first + 100, 0.1)  # not the frame in flight: nothing
    assert link.tx_state is TxState.AWAIT_ACK
    link.confirm(first, 0.1)
    assert link.next_event() == SendComplete(first)
    assert link.next_deadline() is None
    second = link.send(packet(2), 0.2)
    link.data_to_send()
    link.receive_data(ACK_SYMBOL, 0.3)  # the first frame's late ACK
    assert link.tx_state is TxState.AWAIT_ACK and link.next_event() is NEED_DATA
    link.receive_data(ACK_SYMBOL, 0.3)
    assert link.next_event() == SendComplete(second)


def test_the_ack_wait_adapts_to_the_peers_measured_ack_times() -> None:
    """After 8 ACKs that came 10 ms after the frame's last character, a lost ACK is asked for
    with DLE ENQ after 2 x 10 ms plus the frame's time, not after the whole ACK timeout."""
    char_time = 0.001
    link = Df1DataLink(checksum=Checksum.BCC, ack_timeout=1.0, char_time=char_time)
    now = 0.0
    for n in range(8):
        link.send(packet(n + 1), now)
        frame = link.data_to_send()
        assert link.next_deadline() == pytest.approx(now + 1.0)  # too few ACKs seen to adapt
        now += len(frame) * char_time + 0.010
        link.receive_data(ACK_SYMBOL, now)
        assert link.next_event() == SendComplete(n + 1)
        now += 0.1
    link.send(packet(9), now)
    frame = link.data_to_send()
    assert link.next_deadline() == pytest.approx(now + len(frame) * char_time + 0.05)  # the 50 ms floor
    link.handle_timeout(now + len(frame) * char_time + 0.05)
    assert link.data_to_send() == ENQ_SYMBOL
    link.receive_data(ACK_SYMBOL, now + 0.1)  # the ENQ's answer: the frame's ACK
    assert link.next_event() == SendComplete(9)


def test_the_ack_wait_is_twice_the_slowest_of_the_last_32_clean_acks() -> None:
    """Only ACKs of frames sent once, without DLE ENQ, are measured; the slowest of the last 32
    counts twice, above the floor and below ``ack_timeout``."""
    char_time = 0.001
    link = Df1DataLink(checksum=Checksum.BCC, ack_timeout=1.0, char_time=char_time, enq_limit=1, nak_limit=1)
    now = 0.0
    handle = 0

    def exchange(delay: float, *, nak: bool = False, enq: bool = False) -> int:
        """One frame, answered ``delay`` s after its last character; its frame length."""
        nonlocal now, handle
        handle = link.send(packet(handle + 1), now)
        length = len(link.data_to_send())
        if nak:
            link.receive_data(NAK_SYMBOL, now)
            link.data_to_send()
        if enq:
            now = link.next_deadline() or now
            link.handle_timeout(now)
            assert link.data_to_send() == ENQ_SYMBOL
        now += length * char_time + delay
        link.receive_data(ACK_SYMBOL, now)
        assert link.next_event() == SendComplete(handle)
        now += 0.1
        return length

    def wait() -> float:
        link.send(packet(handle + 1), now)
        length = len(link.data_to_send())
        deadline = link.next_deadline()
        assert deadline is not None
        link.reset()
        link.next_event()
        return deadline - now - length * char_time

    exchange(0.3)  # the slowest: measured, until 32 newer ones push it out
    exchange(0.9, nak=True)  # retransmitted, then enquired: not measured
    exchange(0.9, enq=True)
    for _ in range(7):
        exchange(0.04)
    assert wait() == pytest.approx(0.6)  # 8 measured: 2 x 0.3
    for _ in range(24):
        exchange(0.04)
    assert wait() == pytest.approx(0.6)  # 32 measured: the 0.3 s is the oldest one kept
    exchange(0.04)
    assert wait() == pytest.approx(0.08)  # 2 x 0.04, above the 50 ms floor
