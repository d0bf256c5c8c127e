"""The DF1 transaction core (``gateway.protocols.df1.full_duplex.transaction``): byte scripts, a fake clock.

Part 1 plays the controller by hand: scripted bytes fed whole, byte by byte and with trailing
garbage, the clock moved by the test.  Part 2 (hypothesis) drives the core against the
sans-I/O simulated SLC 5/04 under every variant, through a wire that loses or damages what a
random fault script says, and checks the exactly-once properties.  No real timers anywhere.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.kinds.df1.sim.slc500 import Slc500Options, Slc500Simulator
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import ACK_SYMBOL, ENQ_SYMBOL, NAK_SYMBOL, NEED_DATA, Checksum, encode_frame
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import (
    Df1Transactions,
    OutcomeUnknown,
    TransactionDone,
    TransactionEvent,
    TransactionFailed,
    TransactionRefused,
    TxnState,
    read_back_for,
)
from gateway.protocols.df1.pccc import (
    PcccHeader,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    Request,
    decode_command,
    encode_reply,
)
from gateway.sim.variants import variant_matrix

N, B = FileType.INTEGER, FileType.BIT
CRC = Checksum.CRC
ACK_TIMEOUT, REPLY_TIMEOUT = 0.2, 0.5


def read(element: int, size: int = 2) -> ProtectedTypedLogicalRead:
    return ProtectedTypedLogicalRead(N, 7, element, 0, size)


def write(element: int, value: int) -> ProtectedTypedLogicalWrite:
    return ProtectedTypedLogicalWrite(N, 7, element, 0, value.to_bytes(2, "little"))


# ------------------------------------------------------------------------------ scripted peer


class Host:
    """The core with a fake clock; ``peer`` bytes are fed as the test says."""

    def __init__(self, *, retries: int = 2, chunk: int | None = None) -> None:
        self.now = 0.0
        self.chunk = chunk
        link = Df1DataLink(checksum=CRC, ack_timeout=ACK_TIMEOUT, enq_limit=retries, nak_limit=retries)
        self.core = Df1Transactions(link, station=1, source=0, reply_timeout=REPLY_TIMEOUT, retries=retries,
                                    first_tns=0x1234)
        self.events: list[TransactionEvent] = []

    def start(self, request: Request, *, is_write: bool) -> tuple[int, bytes]:
        handle = self.core.start(request, self.now, write=is_write)
        return handle, self.sent()

    def sent(self) -> bytes:
        return self.core.data_to_send()

    def feed(self, data: bytes) -> bytes:
        step = self.chunk or len(data) or 1
        for i in range(0, len(data), step):
            self.core.receive_data(data[i : i + step], self.now)
        self._collect()
        return self.sent()

    def wait(self, seconds: float) -> bytes:
        """Move the clock, firing every deadline passed on the way (in order)."""
        end = self.now + seconds
        while (deadline := self.core.next_deadline()) is not None and deadline <= end:
            self.now = max(self.now, deadline)
            self.core.handle_timeout(self.now)
        self.now = end
        self._collect()
        return self.sent()

    def _collect(self) -> None:
        while (event := self.core.next_event()) is not NEED_DATA:
            self.events.append(event)


def message_of(frame: bytes) -> bytes:
    """The message of one CRC frame we sent (no DLE doubling in these tests' packets)."""
    assert frame.startswith(b"\x10\x02") and frame[-4:-2] == b"\x10\x03", frame.hex(" ")
    return frame[2:-4].replace(b"\x10\x10", b"\x10")


def reply_to(frame: bytes, data: bytes = b"", sts: int = 0, ext_sts: int | None = None) -> bytes:
    header = PcccHeader.decode(message_of(frame))
    return encode_frame(encode_reply(header, sts=sts, ext_sts=ext_sts, data=data), CRC)


CHUNKS = pytest.mark.parametrize("chunk", [None, 1], ids=["whole", "byte-by-byte"])


@CHUNKS
def test_a_read_is_answered_by_its_reply(chunk: int | None) -> None:
    host = Host(chunk=chunk)
    handle, frame = host.start(read(5), is_write=False)
    command = decode_command(message_of(frame))
    assert command.header.tns == 0x1234 and command.request == read(5)
    assert host.feed(ACK_SYMBOL) == b""
    assert host.feed(reply_to(frame, b"\x05\x00") + b"\x00\xff\x7e") == ACK_SYMBOL  # trailing garbage
    [done] = host.events
    assert isinstance(done, TransactionDone) and done.handle == handle
    assert done.reply.data == b"\x05\x00" and not done.verified
    assert host.core.state is TxnState.IDLE and host.core.next_deadline() is None


@CHUNKS
def test_a_read_without_reply_is_sent_again_with_a_new_tns_and_a_late_reply_counts(chunk: int | None) -> None:
    host = Host(chunk=chunk)
    _, first = host.start(read(5), is_write=False)
    host.feed(ACK_SYMBOL)
    second = host.wait(REPLY_TIMEOUT)
    assert second.startswith(b"\x10\x02")
    assert decode_command(message_of(second)).header.tns == 0x1235
    assert host.core.counters.reply_timeouts == 1
    # the reply to the first attempt comes late: it is a valid answer to the same read
    host.feed(reply_to(first, b"\x07\x00"))
    [done] = host.events
    assert isinstance(done, TransactionDone) and done.reply.data == b"\x07\x00"
    assert host.core.counters.late_replies == 1


def test_a_read_fails_after_every_try() -> None:
    host = Host(retries=1)
    host.start(read(5), is_write=False)
    host.feed(ACK_SYMBOL)
    host.wait(REPLY_TIMEOUT)
    host.feed(ACK_SYMBOL)
    host.wait(REPLY_TIMEOUT)
    [failed] = host.events
    assert isinstance(failed, TransactionFailed)
    assert "after 2 tries" in failed.reason
    assert host.core.counters.attempts == 2


def test_a_refusal_is_reported_with_its_status() -> None:
    host = Host()
    _, frame = host.start(write(900, 1), is_write=True)
    host.feed(ACK_SYMBOL + reply_to(frame, sts=0xF0, ext_sts=0x06))
    [refused] = host.events
    assert isinstance(refused, TransactionRefused)
    assert (refused.reply.sts, refused.reply.ext_sts) == (0xF0, 0x06)


@CHUNKS
def test_a_write_whose_reply_is_lost_is_read_back_and_done_when_it_holds(chunk: int | None) -> None:
    host = Host(chunk=chunk)
    _, frame = host.start(write(3, 0x1234), is_write=True)
    host.feed(ACK_SYMBOL)
    readback = host.wait(REPLY_TIMEOUT)
    assert frame not in readback
    command = decode_command(message_of(readback))
    assert command.request == read(3)  # the same two bytes, read back; the write is not resent
    host.feed(ACK_SYMBOL + reply_to(readback, b"\x34\x12"))
    [done] = host.events
    assert isinstance(done, TransactionDone) and done.verified
    assert host.core.counters.verified == 1 and host.core.counters.attempts == 1


@CHUNKS
def test_a_write_whose_read_back_shows_another_value_is_outcome_unknown(chunk: int | None) -> None:
    host = Host(chunk=chunk)
    host.start(write(3, 0x1234), is_write=True)
    host.feed(ACK_SYMBOL)
    readback = host.wait(REPLY_TIMEOUT)
    host.feed(ACK_SYMBOL + reply_to(readback, b"\x03\x00"))
    [unknown] = host.events
    assert isinstance(unknown, OutcomeUnknown)
    assert "03 00" in unknown.reason and "may or may not" in unknown.reason


def test_a_refused_read_back_is_outcome_unknown() -> None:
    host = Host()
    host.start(write(3, 0x1234), is_write=True)
    host.feed(ACK_SYMBOL)
    readback = host.wait(REPLY_TIMEOUT)
    host.feed(ACK_SYMBOL + reply_to(readback, sts=0x10))
    [unknown] = host.events
    assert isinstance(unknown, OutcomeUnknown)


def test_a_late_write_reply_during_the_read_back_settles_it() -> None:
    host = Host()
    _, frame = host.start(write(3, 0x1234), is_write=True)
    host.feed(ACK_SYMBOL)
    host.wait(REPLY_TIMEOUT)  # the read-back goes out
    host.feed(reply_to(frame))
    [done] = host.events
    assert isinstance(done, TransactionDone) and not done.verified


@pytest.mark.parametrize("when", ["at once", "after our ENQ"])
def test_a_nak_never_makes_a_write_go_out_twice(when: str) -> None:
    host = Host()
    _, frame = host.start(write(3, 0x1234), is_write=True)
    if when == "after our ENQ":
        assert host.wait(ACK_TIMEOUT) == ENQ_SYMBOL
    readback = host.feed(NAK_SYMBOL)
    assert frame not in readback  # not retransmitted: the NAK is no proof the write was discarded
    assert decode_command(message_of(readback)).request == read(3)
    host.feed(ACK_SYMBOL + reply_to(readback, b"\x34\x12"))
    [done] = host.events
    assert isinstance(done, TransactionDone) and done.verified


def test_a_nak_makes_a_read_go_out_again() -> None:
    host = Host()
    _, frame = host.start(read(3), is_write=False)
    assert host.feed(NAK_SYMBOL) == frame


def test_a_reply_before_its_ack_completes_the_frame_and_a_late_nak_is_not_the_next_frames() -> None:
    host = Host()
    _, frame = host.start(write(3, 1), is_write=True)
    host.wait(ACK_TIMEOUT)  # ENQ out, then the reply comes, then the answer to our ENQ: a NAK
    host.feed(reply_to(frame))
    [done] = host.events
    assert isinstance(done, TransactionDone)
    _, second = host.start(write(4, 2), is_write=True)
    assert host.feed(NAK_SYMBOL) == b""  # owed to the ENQ: neither a retransmission nor a read-back
    host.feed(ACK_SYMBOL + reply_to(second))
    assert isinstance(host.events[-1], TransactionDone)
    assert host.core.link.counters.frames_sent == 2


def test_no_ack_at_all_then_read_back() -> None:
    host = Host(retries=1)
    host.start(write(3, 9), is_write=True)
    assert host.wait(ACK_TIMEOUT) == ENQ_SYMBOL
    readback = host.wait(ACK_TIMEOUT)  # the ENQ limit: the link gives up, the core reads back
    assert decode_command(message_of(readback)).request == read(3)
    host.wait(ACK_TIMEOUT * 10)  # nothing answers the read-backs either
    [unknown] = host.events
    assert isinstance(unknown, OutcomeUnknown)
    assert host.core.counters.read_backs == 2 and host.core.counters.attempts == 1


def test_read_back_of_a_masked_write_compares_only_the_masked_bits() -> None:
    masked = ProtectedTypedLogicalMaskedWrite(B, 3, 1, 0, 0x0102, b"\x00\x01")
    check = read_back_for(masked)
    assert check is not None and check.request == ProtectedTypedLogicalRead(B, 3, 1, 0, 2)
    # mask bytes 02 01: bit 1 of the low byte must be 0, bit 0 of the high byte 1; others are free
    assert check.holds(b"\xfd\xff") and check.holds(b"\x00\x01")
    assert not check.holds(b"\x02\x01") and not check.holds(b"\x00\x00") and not check.holds(b"\x00")
    plain = read_back_for(write(1, 0x0102))
    assert plain is not None and plain.holds(b"\x02\x01") and not plain.holds(b"\x02\x00")


def test_one_transaction_at_a_time_and_bad_settings() -> None:
    host = Host()
    host.start(read(1), is_write=False)
    with pytest.raises(Exception, match="already running"):
        host.core.start(read(2), 0.0, write=False)
    with pytest.raises(ValueError):
        Df1Transactions(Df1DataLink(), station=1, source=0, reply_timeout=0)
    with pytest.raises(ValueError):
        Df1Transactions(Df1DataLink(), station=1, source=0, reply_timeout=1.0, retries=-1)


def test_with_no_retries_a_read_is_sent_once() -> None:
    host = Host(retries=0)
    host.start(read(1), is_write=False)
    host.feed(ACK_SYMBOL)
    assert host.wait(REPLY_TIMEOUT) == b""
    [event] = host.events
    assert isinstance(event, TransactionFailed) and event.reason.endswith("(after 1 tries)")
    assert host.core.counters.attempts == 1


def test_by_default_the_first_command_has_tns_1() -> None:
    core = Df1Transactions(Df1DataLink(checksum=CRC), station=1, source=0, reply_timeout=1.0)
    core.start(read(1), 0.0, write=False)
    header = PcccHeader.decode(message_of(core.data_to_send()))
    assert header.tns == 1


# -------------------------------------------------------------- property: against the simulator

VARIANTS = list(variant_matrix(Slc500Simulator.VARIANTS))
_DELIVER, _LOSE, _DAMAGE = 0, 1, 2
LINE_DELAY = 0.002  # seconds each chunk spends on the wire


@dataclass
class Wire:
    """Chunks in flight, in order; each gets its fate from the fault script as it is sent."""

    script: Iterator[int]
    damage_at: Iterator[int]
    queue: list[tuple[float, str, bytes]] = field(default_factory=list)

    def put(self, now: float, to: str, data: bytes) -> None:
        if not data:
            return
        fate = next(self.script, _DELIVER)
        if fate == _LOSE:
            return
        if fate == _DAMAGE:
            buf = bytearray(data)
            i = next(self.damage_at, 0) % len(buf)
            buf[i] ^= 0x5A  # any change: a check catches it in a frame, a symbol becomes another
            data = bytes(buf)
        arrive = max([now + LINE_DELAY] + [t for t, d, _ in self.queue if d == to])
        self.queue.append((arrive, to, data))
        self.queue.sort(key=lambda item: item[0])


def run_against_simulator(
    variants: dict[str, str], fates: list[int], damage_at: list[int], ops: list[tuple[str, int, int]], sim_faults: int
) -> None:
    sim = Slc500Simulator(
        Slc500Options(checksum=CRC, link_ack_timeout=0.05, drop=sim_faults, withhold_ack=sim_faults,
                      corrupt=sim_faults, seed=sim_faults),
        ladder=False,
        variants=variants,
    )
    link = Df1DataLink(checksum=CRC, ack_timeout=0.05, enq_limit=2, nak_limit=2)
    core = Df1Transactions(link, station=1, source=0, reply_timeout=0.1, retries=2, first_tns=7)
    wire = Wire(iter(fates), iter(damage_at))
    now = 0.0
    history: dict[int, set[int]] = {k: {sim.word("N7", k)} for k in range(8)}  # values each word has held
    written: list[tuple[int, bytes, TransactionEvent]] = []
    value = 1000

    for kind, element, _ in ops:
        value += 1
        is_write = kind == "write"
        request: Request = write(element, value) if is_write else read(element, 4)
        handle = core.start(request, now, write=is_write)
        if is_write:
            history[element].add(value)
        wire.put(now, "sim", core.data_to_send())
        verdict: TransactionEvent | None = None
        for _ in range(10_000):
            event = core.next_event()
            if event is not NEED_DATA:
                assert event.handle == handle
                verdict = event
                break
            # the next thing to happen: a chunk arriving, the core's timer, the simulator's timer
            times = [t for t, _, _ in wire.queue[:1]]
            times += [d for d in (core.next_deadline(), sim.next_deadline()) if d is not None]
            assert times, "nothing left to happen and no verdict"
            now = max(now, min(times))
            while wire.queue and wire.queue[0][0] <= now:
                _, to, data = wire.queue.pop(0)
                if to == "sim":
                    for output in sim.receive(data, now):
                        wire.put(now, "host", output.data)
                else:
                    core.receive_data(data, now)
                    wire.put(now, "sim", core.data_to_send())
            core.handle_timeout(now)
            wire.put(now, "sim", core.data_to_send())
            for output in sim.poll(now):
                wire.put(now, "host", output.data)
        assert verdict is not None, "no verdict"
        if is_write:
            written.append((element, value.to_bytes(2, "little"), verdict))
        elif isinstance(verdict, TransactionDone):
            # no value the controller never held
            got = verdict.reply.data
            assert len(got) == 4
            for i in range(2):
                assert int.from_bytes(got[2 * i : 2 * i + 2], "little") in history[element + i]
        else:
            assert isinstance(verdict, TransactionFailed), verdict

    applied = Counter((address, data) for kind, address, data in sim.applied_writes if kind == "write")
    for element, data, verdict in written:
        count = applied[(f"N7:{element}", data)]
        if isinstance(verdict, TransactionDone):
            assert count == 1, ("acknowledged write not applied exactly once", element, data, count, verdict)
        elif isinstance(verdict, TransactionRefused):
            assert count == 0
        else:
            assert isinstance(verdict, OutcomeUnknown), verdict  # a write never simply "fails"
            assert count <= 1, ("unacknowledged write applied twice", element, data, count)
    assert sum(applied.values()) == len(sim.applied_writes)


ops_strategy = st.lists(
    st.tuples(st.sampled_from(["write", "write", "read"]), st.integers(0, 6), st.just(0)), min_size=1, max_size=12
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    variants=st.sampled_from(VARIANTS),
    fates=st.lists(st.sampled_from([_DELIVER] * 6 + [_LOSE, _DAMAGE]), max_size=200),
    damage_at=st.lists(st.integers(0, 300), max_size=50),
    ops=ops_strategy,
    sim_faults=st.sampled_from([0, 3, 5]),
)
def test_exactly_once_under_every_variant_and_any_fault_script(
    variants: dict[str, str], fates: list[int], damage_at: list[int], ops: list[tuple[str, int, int]],
    sim_faults: int,
) -> None:
    run_against_simulator(variants, fates, damage_at, ops, sim_faults)


@pytest.mark.parametrize("variants", VARIANTS, ids=lambda v: ",".join(f"{k}={x}" for k, x in sorted(v.items())))
def test_exactly_once_per_variant_on_a_bad_line(variants: dict[str, str]) -> None:
    """Every variant, a fixed harsh script: 1 in 5 chunks lost or damaged, simulator faults on."""
    fates = [(_LOSE if i % 10 == 3 else _DAMAGE if i % 10 == 7 else _DELIVER) for i in range(3000)]
    ops = [("write" if i % 3 else "read", i % 7, 0) for i in range(60)]
    run_against_simulator(variants, fates, list(range(0, 3000, 7)), ops, 5)



# ------------------------------------------------------------------ the link going away, the clock


def test_a_read_cut_short_by_the_link_going_away_fails_with_the_reason() -> None:
    host = Host()
    handle, _ = host.start(read(5), is_write=False)
    host.feed(ACK_SYMBOL)
    host.core.abandon("port lost", host.now)
    host.wait(0.0)
    assert host.events == [TransactionFailed(handle, "port lost")]
    assert host.core.state is TxnState.IDLE and host.core.next_deadline() is None
    host.core.abandon("again", host.now)  # nothing runs: nothing to settle
    host.wait(REPLY_TIMEOUT * 4)
    assert len(host.events) == 1


@pytest.mark.parametrize("when", ["on the link", "awaiting its reply", "being read back"])
def test_a_write_cut_short_by_the_link_going_away_is_outcome_unknown(when: str) -> None:
    host = Host()
    handle, _ = host.start(write(3, 0x1234), is_write=True)
    if when != "on the link":
        host.feed(ACK_SYMBOL)
    if when == "being read back":
        host.wait(REPLY_TIMEOUT)
        assert host.core.state is TxnState.VERIFY_SENDING
    host.now += 0.25
    host.core.abandon("port lost", host.now)
    host.wait(0.0)
    [unknown] = host.events
    assert isinstance(unknown, OutcomeUnknown) and unknown.handle == handle
    assert unknown.reason.startswith("port lost; ") and "may or may not" in unknown.reason
    assert host.core.counters.unknown == 1 and host.core.state is TxnState.IDLE


def test_an_early_timeout_call_does_nothing() -> None:
    host = Host()
    host.start(read(5), is_write=False)
    host.feed(ACK_SYMBOL)
    deadline = host.core.next_deadline()
    assert deadline is not None and deadline == pytest.approx(REPLY_TIMEOUT)
    host.core.handle_timeout(deadline - 0.01)
    assert host.sent() == b"" and host.core.state is TxnState.READ_AWAIT_REPLY
    assert host.core.counters.reply_timeouts == 0
    host.core.handle_timeout(deadline)  # at the deadline: the read goes again
    assert decode_command(message_of(host.sent())).header.tns == 0x1235
    assert host.core.counters.reply_timeouts == 1


def test_the_tns_runs_on_across_transactions_and_a_successors_tns_is_skipped() -> None:
    link = Df1DataLink(checksum=CRC)
    core = Df1Transactions(link, station=3, source=9, reply_timeout=1.0, first_tns=0x1FFFE)  # 16 bits: 0xFFFE
    core.start(read(1), 0.0, write=False)
    frame = core.data_to_send()
    first = decode_command(message_of(frame))
    assert (first.header.tns, first.header.dst, first.header.src) == (0xFFFE, 3, 9)
    core.receive_data(ACK_SYMBOL + reply_to(frame), 0.0)
    assert isinstance(core.next_event(), TransactionDone)
    assert core.allocate_tns() == 0xFFFF  # for a successor: never used here
    core.start(read(1), 0.0, write=False)
    assert decode_command(message_of(core.data_to_send().removeprefix(ACK_SYMBOL))).header.tns == 0


# ---------------------------------------------------------------------------- the adaptive reply wait


def answered_reads(host: Host, count: int, after: float) -> None:
    """``count`` reads, each acknowledged at once and answered ``after`` seconds later."""
    for _ in range(count):
        _, frame = host.start(read(1), is_write=False)
        host.feed(ACK_SYMBOL)
        host.now += after
        host.feed(reply_to(frame, b"\x00\x00"))
        assert isinstance(host.events[-1], TransactionDone)


def reply_wait_of_next_read(host: Host) -> float:
    host.start(read(1), is_write=False)
    host.feed(ACK_SYMBOL)
    deadline = host.core.next_deadline()
    assert deadline is not None
    return deadline - host.now


@pytest.mark.parametrize(
    ("replies", "after", "wait"),
    [
        (7, 0.03, REPLY_TIMEOUT),  # fewer than 8 replies measured: the full reply timeout
        (8, 0.03, 0.1),  # 2 x 0.03 s, raised to the floor (0.1 s)
        (8, 0.2, 0.4),  # 2 x the slowest reply
        (8, 0.3, REPLY_TIMEOUT),  # 2 x 0.3 s, capped at the reply timeout
    ],
)
def test_the_reply_wait_adapts_to_the_measured_reply_times(replies: int, after: float, wait: float) -> None:
    host = Host()
    answered_reads(host, replies, after)
    assert reply_wait_of_next_read(host) == pytest.approx(wait)


@pytest.mark.parametrize(("fast", "wait"), [(31, 0.4), (32, 0.1)])
def test_the_reply_wait_counts_the_slowest_of_the_last_32_replies(fast: int, wait: float) -> None:
    """A slow reply (0.2 s) sets the wait (2 x 0.2 s) until 32 newer replies push it out."""
    host = Host()
    answered_reads(host, 1, 0.2)
    answered_reads(host, fast, 0.03)
    assert reply_wait_of_next_read(host) == pytest.approx(wait)


def test_the_reply_wait_floor_is_the_reply_timeout_when_that_is_shorter() -> None:
    host = Host()
    host.core = Df1Transactions(Df1DataLink(checksum=CRC), station=1, source=0, reply_timeout=0.05, first_tns=1)
    assert host.core.min_reply_timeout == 0.05
    answered_reads(host, 8, 0.001)
    assert reply_wait_of_next_read(host) == pytest.approx(0.05)


def test_a_reply_before_the_ack_is_not_a_reply_time() -> None:
    host = Host()
    for _ in range(8):
        _, frame = host.start(read(1), is_write=False)
        host.now += 0.3
        host.feed(reply_to(frame, b"\x00\x00") + ACK_SYMBOL)  # the reply overtakes the ACK
    assert reply_wait_of_next_read(host) == pytest.approx(REPLY_TIMEOUT)


def test_a_late_reply_of_an_earlier_try_is_not_a_reply_time() -> None:
    host = Host()
    for _ in range(8):
        _, first = host.start(read(1), is_write=False)
        host.feed(ACK_SYMBOL)
        host.wait(REPLY_TIMEOUT)  # the read goes again
        host.feed(ACK_SYMBOL)
        host.now += 0.01
        host.feed(reply_to(first, b"\x00\x00"))  # the first try's reply, late
        assert isinstance(host.events[-1], TransactionDone)
    assert host.core.counters.late_replies == 8
    assert reply_wait_of_next_read(host) == pytest.approx(REPLY_TIMEOUT)


def test_a_writes_last_read_back_waits_the_full_reply_timeout() -> None:
    """The silence of the last read-back decides the write's verdict: it is not cut short by the
    adaptive wait; the write and the read-backs before it are."""
    host = Host(retries=2)
    answered_reads(host, 8, 0.01)
    host.start(write(3, 7), is_write=True)
    host.feed(ACK_SYMBOL)
    waits = []
    while not host.events[8:]:
        deadline = host.core.next_deadline()
        assert deadline is not None
        waits.append(round(deadline - host.now, 6))
        host.wait(deadline - host.now)
        if host.core.state is TxnState.VERIFY_SENDING:
            host.feed(ACK_SYMBOL)
    assert waits == [0.1, 0.1, 0.1, REPLY_TIMEOUT]  # the write, read-backs 1 and 2, the last read-back
    [unknown] = host.events[8:]
    assert isinstance(unknown, OutcomeUnknown)
    assert "no reply within 0.5 s of the DLE ACK" in unknown.reason
    assert host.core.counters.read_backs == 3 and host.core.counters.reply_timeouts == 4


# ------------------------------------------------------------------------------ what is not ours


def test_what_answers_nothing_of_ours_is_ignored() -> None:
    host = Host()
    handle, frame = host.start(read(5), is_write=False)
    host.feed(ACK_SYMBOL)
    other = PcccHeader.decode(message_of(frame))
    stray = [
        encode_frame(encode_reply(PcccHeader(0, 1, 0x0F, 0, other.tns + 1), sts=0, data=b"\x01\x00"), CRC),
        encode_frame(encode_reply(PcccHeader(0, 1, 0x06, 0, other.tns), sts=0, data=b"\x01\x00"), CRC),  # CMD
        encode_frame(message_of(frame), CRC),  # a command, not a reply
        encode_frame(b"\x00\x01", CRC),  # too short for a PCCC header
    ]
    for data in stray:
        host.feed(data)
    assert host.events == [] and host.core.state is TxnState.READ_AWAIT_REPLY
    assert host.core.counters.late_replies == 0
    host.feed(reply_to(frame, b"\x05\x00"))
    [done] = host.events
    assert isinstance(done, TransactionDone) and done.handle == handle and done.reply.data == b"\x05\x00"
    host.feed(reply_to(frame, b"\x06\x00"))  # its duplicate, once settled
    assert len(host.events) == 1 and host.core.counters.late_replies == 0


def test_counters_count_each_thing_once() -> None:
    host = Host(retries=1)
    _, frame = host.start(read(5), is_write=False)
    host.feed(ACK_SYMBOL)
    host.wait(REPLY_TIMEOUT)  # a second try
    host.feed(ACK_SYMBOL + reply_to(frame, b"\x05\x00"))  # the first try's reply
    _, wframe = host.start(write(3, 1), is_write=True)
    host.feed(ACK_SYMBOL)
    readback = host.wait(REPLY_TIMEOUT)
    host.feed(ACK_SYMBOL + reply_to(readback, b"\x01\x00"))
    c = host.core.counters
    assert (c.started, c.attempts, c.reply_timeouts, c.read_backs, c.verified, c.unknown, c.late_replies) == (
        2, 3, 2, 1, 1, 0, 1
    )
    assert [type(e) for e in host.events] == [TransactionDone, TransactionDone]
    assert wframe not in readback


def test_the_verified_and_unknown_counters_are_totals_over_every_write() -> None:
    """A write proved by its read-back adds one to ``verified``, a write left unknown one to
    ``unknown``; both are metrics, so two of each count two."""
    host = Host()
    for held in (b"\x01\x00", b"\x01\x00", b"\x02\x00", b"\x02\x00"):
        host.start(write(3, 1), is_write=True)
        host.feed(ACK_SYMBOL)
        readback = host.wait(REPLY_TIMEOUT)
        host.feed(ACK_SYMBOL + reply_to(readback, held))
    assert [type(e) for e in host.events] == [TransactionDone, TransactionDone, OutcomeUnknown, OutcomeUnknown]
    assert (host.core.counters.verified, host.core.counters.unknown) == (2, 2)


def test_a_read_the_controller_refuses_is_refused_with_its_status() -> None:
    host = Host()
    handle, frame = host.start(read(900), is_write=False)
    host.feed(ACK_SYMBOL + reply_to(frame, sts=0x10))
    [refused] = host.events
    assert isinstance(refused, TransactionRefused) and refused.handle == handle and refused.reply.sts == 0x10


def test_every_transaction_has_its_own_handle_and_its_verdict_carries_it() -> None:
    host = Host()
    handles = []
    for element in (1, 2, 3):
        handle, frame = host.start(read(element), is_write=False)
        host.feed(ACK_SYMBOL + reply_to(frame, b"\x00\x00"))
        handles.append(handle)
    assert len(set(handles)) == 3
    assert [event.handle for event in host.events] == handles


@CHUNKS
def test_a_read_back_reply_before_its_ack_settles_the_write_and_completes_the_frame(chunk: int | None) -> None:
    host = Host(chunk=chunk)
    host.start(write(3, 0x1234), is_write=True)
    host.feed(ACK_SYMBOL)
    readback = host.wait(REPLY_TIMEOUT)
    assert host.feed(reply_to(readback, b"\x34\x12")) == ACK_SYMBOL  # no DLE ACK of the read-back first
    [done] = host.events
    assert isinstance(done, TransactionDone) and done.verified
    assert host.wait(ACK_TIMEOUT * 4) == b""  # the frame is complete: no DLE ENQ for its ACK
    assert host.core.link.counters.frames_sent == 2


def test_a_late_write_reply_during_the_read_back_is_counted_late() -> None:
    host = Host()
    _, frame = host.start(write(3, 0x1234), is_write=True)
    host.feed(ACK_SYMBOL)
    host.wait(REPLY_TIMEOUT)
    host.feed(ACK_SYMBOL + reply_to(frame))
    assert host.core.counters.late_replies == 1 and isinstance(host.events[-1], TransactionDone)


def test_a_settled_transactions_tns_are_free_again_so_the_core_never_runs_out() -> None:
    """Every TNS a transaction used - each try of a read, the write, each read-back - is free once
    it settles.  With all but four TNS taken (by successors), rounds of retried reads and of writes
    read back three times run on for ever; a TNS kept would exhaust the four in a few rounds."""
    host = Host(retries=2)
    for _ in range(0x10000 - 4):
        host.core.allocate_tns()
    for _ in range(6):
        _, first = host.start(read(1), is_write=False)
        host.feed(ACK_SYMBOL)
        host.wait(REPLY_TIMEOUT)  # a second try, a new TNS
        host.feed(ACK_SYMBOL + reply_to(first, b"\x01\x00"))  # the first try's reply settles it
        host.start(write(3, 5), is_write=True)
        host.feed(ACK_SYMBOL)
        for _ in range(3):  # three read-backs, each with a new TNS, none answered
            host.wait(REPLY_TIMEOUT)
            host.feed(ACK_SYMBOL)
        host.wait(REPLY_TIMEOUT)
    assert [type(e) for e in host.events] == [TransactionDone, OutcomeUnknown] * 6
