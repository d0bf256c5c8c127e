"""One write verdict for both duplex modes (``gateway.protocols.df1.write_verdict``).

The table is checked for completeness, then the same controller behaviour is played as byte
scripts with a fake clock to the full-duplex core (``Df1Transactions``) and to the half-duplex
transaction layer (``HalfDuplexTransactions`` over ``HalfDuplexMaster``), each built with its
defaults: both must give the same verdict after the same number of read-backs.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import ACK_SYMBOL, EOT_SYMBOL, Checksum, NeedData, encode_frame, encode_poll
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import (
    Df1Transactions,
    OutcomeUnknown,
    TransactionDone,
    TransactionEvent,
)
from gateway.protocols.df1.half_duplex.events import LineConfig, StationConfig
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster
from gateway.protocols.df1.half_duplex.transactions import HalfDuplexTransactions
from gateway.protocols.df1.pccc import (
    DataType,
    LogicalBinaryAddress,
    PcccHeader,
    PcccReply,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadModifyWriteRequest,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
    decode_command,
    decode_reply,
    encode_reply,
)
from gateway.protocols.df1.write_verdict import (
    DEFAULT_RETRIES,
    TRANSITIONS,
    SendReadBack,
    Verdict,
    VerdictAction,
    VerdictKind,
    VerdictState,
    WriteInput,
    WriteVerdict,
    read_back_for,
    read_back_tries,
)

WRITE = ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 10, 0, b"\x34\x12")
READ_BACK = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 10, 0, 2)

#: What the controller does with each command: ``"ack"`` (ACK, never a reply), ``"silent"`` (never
#: heard), or the data of its reply.
Behaviour = Callable[[object], "str | bytes"]


def reply_lost_read_back_unanswered(request: object) -> str | bytes:
    return "ack" if request == WRITE else "silent"


def reply_lost_read_back_holds(request: object) -> str | bytes:
    return "ack" if request == WRITE else b"\x34\x12"


def reply_lost_read_back_differs(request: object) -> str | bytes:
    return "ack" if request == WRITE else b"\x00\x00"


# -------------------------------------------------------------------------------------- the table


def test_every_state_and_input_is_a_transition_or_listed_as_ignored() -> None:
    pairs = {(state, what) for state in VerdictState for what in WriteInput}
    assert set(TRANSITIONS) == pairs
    ignored = {pair for pair, entry in TRANSITIONS.items() if entry.action is VerdictAction.IGNORE}
    assert all(TRANSITIONS[pair].next_state is pair[0] for pair in ignored)
    assert all(entry.next_state is VerdictState.SETTLED for pair, entry in TRANSITIONS.items()
               if entry.action not in (VerdictAction.IGNORE, VerdictAction.READ_BACK))


def test_read_backs_follow_the_one_rule() -> None:
    verdict = WriteVerdict(WRITE, retries=2, now=10.0)
    step = verdict.lost("no reply", 10.5)
    steps = [step]
    while isinstance(step, SendReadBack):
        step = verdict.read_back_lost("no reply", 11.0)
        steps.append(step)
    assert [s.attempt for s in steps if isinstance(s, SendReadBack)] == list(range(1, read_back_tries(2) + 1))
    assert isinstance(step, Verdict) and step.kind is VerdictKind.UNKNOWN and step.seconds == pytest.approx(1.0)
    late = decode_reply(encode_reply(PcccHeader(0, 1, 0x0F, 0, 1), sts=0, data=b""))
    assert verdict.settled and verdict.reply(late, 12.0) is None  # settled: later inputs change nothing


# ------------------------------------------------------------------------------ the two duplex paths


def full_duplex(behaviour: Behaviour) -> tuple[TransactionEvent, int]:
    """Df1Transactions with its defaults, CRC, against ``behaviour``; the clock moves to each deadline."""
    core = Df1Transactions(Df1DataLink(checksum=Checksum.CRC), station=1, source=0, reply_timeout=1.0, first_tns=0x100)
    now = 0.0
    core.start(WRITE, now, write=True)
    for _ in range(1000):
        out = core.data_to_send()
        if out.startswith(b"\x10\x02"):
            message = out[2:out.index(b"\x10\x03")].replace(b"\x10\x10", b"\x10")
            command = decode_command(message)
            what = behaviour(command.request)
            if what != "silent":
                answer = ACK_SYMBOL
                if isinstance(what, bytes):
                    answer += encode_frame(encode_reply(command.header, sts=0, data=what), Checksum.CRC)
                core.receive_data(answer, now)
        event = core.next_event()
        if isinstance(event, TransactionDone | OutcomeUnknown):
            return event, core.counters.read_backs
        deadline = core.next_deadline()
        assert deadline is not None
        now = max(now, deadline)
        core.handle_timeout(now)
    raise AssertionError("no verdict")


def half_duplex(behaviour: Behaviour) -> tuple[TransactionEvent, int]:
    """HalfDuplexTransactions with its defaults over a one-station BCC line against ``behaviour``:
    polls are answered with the reply when there is one, else DLE EOT."""
    master = HalfDuplexMaster(LineConfig(Checksum.BCC), [StationConfig(1)])
    txns = HalfDuplexTransactions()
    txns.attach(master, 0.0, reason="")
    master.start(0.0)
    now = 0.0
    pending: list[bytes] = []
    handle = txns.start(1, WRITE, now, write=True)
    for _ in range(5000):
        out = master.data_to_send()
        if out.startswith(ACK_SYMBOL):  # our ACK of the slave's reply
            pending.pop(0)
            out = out[len(ACK_SYMBOL):]
        if out.startswith(b"\x10\x01"):  # a master message: DLE SOH STN DLE STX ... DLE ETX BCC
            command = decode_command(out[5:out.index(b"\x10\x03")].replace(b"\x10\x10", b"\x10"))
            what = behaviour(command.request)
            if what != "silent":
                if isinstance(what, bytes):
                    pending.append(encode_reply(command.header, sts=0, data=what))
                txns.receive_data(ACK_SYMBOL, now)
        elif out == encode_poll(1):
            txns.receive_data(encode_frame(pending[0], Checksum.BCC) if pending else EOT_SYMBOL, now)
        while not isinstance(event := txns.next_event(), NeedData):
            if isinstance(event, TransactionDone | OutcomeUnknown) and event.handle == handle:
                return event, txns.counters(1).read_backs
        if not out and (deadline := master.next_deadline()) is not None:
            now = max(now, deadline)
            txns.handle_timeout(now)
    raise AssertionError("no verdict")


@pytest.mark.parametrize("behaviour", [
    reply_lost_read_back_unanswered, reply_lost_read_back_holds, reply_lost_read_back_differs,
], ids=["read-back unanswered", "read-back holds", "read-back differs"])
def test_both_duplex_modes_give_one_verdict_after_the_same_read_backs(behaviour: Behaviour) -> None:
    full_event, full_read_backs = full_duplex(behaviour)
    half_event, half_read_backs = half_duplex(behaviour)
    assert type(full_event) is type(half_event)
    assert full_read_backs == half_read_backs
    if behaviour is reply_lost_read_back_unanswered:
        assert full_read_backs == read_back_tries(DEFAULT_RETRIES)
    if isinstance(full_event, TransactionDone):
        assert full_event.verified and isinstance(half_event, TransactionDone) and half_event.verified


# ------------------------------------------------------------------- the verdict, input by input
#
# Each test feeds one WriteVerdict what a caller saw, on a fake clock (``now`` passed in), and
# checks the step it answers with: the read-back to send, or the verdict.  The exactly-once rules:
# a write is never sent again (no step resends it), DONE only on its STS 0 reply or a read-back
# that shows the written value, FAILED only when it provably never left.


def reply(sts: int = 0, data: bytes = b"", ext_sts: int | None = None) -> PcccReply:
    return decode_reply(encode_reply(PcccHeader(0, 1, 0x0F, 0, 1), sts=sts, ext_sts=ext_sts, data=data))


def settled_ignores_everything(verdict: WriteVerdict) -> None:
    """A settled verdict answers no later input: it is given once."""
    assert verdict.settled and verdict.state is VerdictState.SETTLED
    assert verdict.reply(reply(), 99.0) is None
    assert verdict.reply(reply(sts=0x10), 99.0) is None
    assert verdict.lost("x", 99.0) is None
    assert verdict.lost("x", 99.0, may_have_executed=False) is None
    assert verdict.read_back_reply(reply(data=b"\x34\x12"), 99.0) is None
    assert verdict.read_back_lost("x", 99.0) is None
    assert verdict.abandon("x", 99.0) is None
    assert verdict.settled


def test_read_back_tries_are_the_tries_of_a_read() -> None:
    assert [read_back_tries(r) for r in (0, 1, 3)] == [1, 2, 4]
    assert DEFAULT_RETRIES == 3


def test_a_write_answered_sts_0_is_done_with_its_reply_and_the_time_it_took() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=10.0)
    assert verdict.state is VerdictState.SENT and not verdict.settled
    ok = reply()
    step = verdict.reply(ok, 10.25)
    assert step == Verdict(VerdictKind.DONE, "", ok, False, 0.25)
    assert verdict.read_backs == 0
    settled_ignores_everything(verdict)


def test_a_write_answered_sts_not_0_is_refused_with_its_reply() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=1.0)
    refusal = reply(sts=0xF0, ext_sts=0x06)
    assert verdict.reply(refusal, 1.5) == Verdict(VerdictKind.REFUSED, "", refusal, False, 0.5)
    settled_ignores_everything(verdict)


def test_a_write_that_never_left_failed_and_says_why() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=2.0)
    step = verdict.lost("every copy was NAKed", 3.5, may_have_executed=False)
    assert isinstance(step, Verdict) and step.kind is VerdictKind.FAILED
    assert step.reply is None and not step.verified and step.seconds == pytest.approx(1.5)
    assert step.reason == "every copy was NAKed; the write was never sent (after 1.5 s)"
    assert verdict.read_backs == 0
    settled_ignores_everything(verdict)


def test_a_lost_answer_asks_for_the_read_back_never_the_write_again() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=0.0)
    assert verdict.lost("no reply", 1.0) == SendReadBack(READ_BACK, 1)
    assert verdict.state is VerdictState.VERIFYING and not verdict.settled and verdict.read_backs == 1
    # the write's own loss reported again, or "never arrived" now: nothing changes
    assert verdict.lost("no reply", 1.1) is None
    assert verdict.lost("no reply", 1.1, may_have_executed=False) is None
    assert verdict.state is VerdictState.VERIFYING and verdict.read_backs == 1


def test_a_read_back_showing_the_written_value_is_done_and_verified() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=0.0)
    verdict.lost("no reply", 1.0)
    shown = reply(data=b"\x34\x12")
    assert verdict.read_back_reply(shown, 1.75) == Verdict(VerdictKind.DONE, "", shown, True, 1.75)
    settled_ignores_everything(verdict)


def test_a_read_back_showing_another_value_is_unknown_and_names_it() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=0.0)
    verdict.lost("no reply", 1.0)
    step = verdict.read_back_reply(reply(data=b"\x00\x12"), 2.0)
    assert isinstance(step, Verdict) and step.kind is VerdictKind.UNKNOWN and not step.verified
    assert step.reason == (
        "the read-back gave 00 12, not the value written; the read-back did not prove it applied: "
        "the write may or may not have been applied (after 2 s)"
    )
    settled_ignores_everything(verdict)


def test_a_refused_read_back_is_unknown_and_names_the_refusal() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=0.0)
    verdict.lost("no reply", 1.0)
    step = verdict.read_back_reply(reply(sts=0x10, data=b"\x34\x12"), 2.0)  # refused, even with the data
    assert isinstance(step, Verdict) and step.kind is VerdictKind.UNKNOWN
    assert step.reason.startswith("the read-back was refused (")
    assert "STS 0x10" in step.reason and "may or may not have been applied" in step.reason
    settled_ignores_everything(verdict)


@pytest.mark.parametrize("retries", [0, 1, 3])
def test_unanswered_read_backs_end_unknown_after_retries_plus_one(retries: int) -> None:
    verdict = WriteVerdict(WRITE, retries=retries, now=0.0)
    steps = [verdict.lost("no reply", 1.0)]
    for i in range(retries + 1):
        steps.append(verdict.read_back_lost(f"read-back {i + 1} unanswered", 2.0 + i))
    assert steps[:-1] == [SendReadBack(READ_BACK, n) for n in range(1, retries + 2)]
    last = steps[-1]
    assert isinstance(last, Verdict) and last.kind is VerdictKind.UNKNOWN
    assert verdict.read_backs == read_back_tries(retries) == verdict.max_read_backs
    assert last.reason == (
        f"read-back {retries + 1} unanswered; {retries + 1} read-backs got no answer: "
        f"the write may or may not have been applied (after {retries + 2} s)"
    )
    settled_ignores_everything(verdict)


def test_a_late_reply_to_the_write_during_the_read_back_settles_it() -> None:
    for late, kind in ((reply(), VerdictKind.DONE), (reply(sts=0x10), VerdictKind.REFUSED)):
        verdict = WriteVerdict(WRITE, retries=3, now=0.0)
        verdict.lost("no reply", 1.0)
        assert verdict.read_back_lost("no reply", 2.0) == SendReadBack(READ_BACK, 2)
        assert verdict.reply(late, 2.5) == Verdict(kind, "", late, False, 2.5)
        settled_ignores_everything(verdict)


@pytest.mark.parametrize("verifying", [False, True], ids=["sent", "verifying"])
def test_an_abandoned_write_is_unknown_never_failed(verifying: bool) -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=0.0)
    if verifying:
        verdict.lost("no reply", 1.0)
    step = verdict.abandon("the port is gone", 4.0)
    assert isinstance(step, Verdict) and step.kind is VerdictKind.UNKNOWN and step.seconds == 4.0
    proof = "; the read-back did not prove it applied"
    assert step.reason == f"the port is gone{proof}: the write may or may not have been applied (after 4 s)"
    settled_ignores_everything(verdict)


@pytest.mark.parametrize("end", ["read-back differs", "abandoned"])
def test_the_last_read_back_answered_or_cut_short_is_not_reported_unanswered(end: str) -> None:
    """Only read-backs that all went unanswered are reported so; the last one's answer (another
    value) or the link going away while it is out is "did not prove it applied"."""
    verdict = WriteVerdict(WRITE, retries=0, now=0.0)
    assert verdict.lost("no reply", 1.0) == SendReadBack(READ_BACK, 1)
    if end == "abandoned":
        step = verdict.abandon("the port is gone", 2.0)
    else:
        step = verdict.read_back_reply(reply(data=b"\x00\x00"), 2.0)
    assert isinstance(step, Verdict) and step.kind is VerdictKind.UNKNOWN
    assert "; the read-back did not prove it applied: " in step.reason
    assert "got no answer" not in step.reason


def test_read_back_inputs_before_any_read_back_change_nothing() -> None:
    verdict = WriteVerdict(WRITE, retries=3, now=0.0)
    assert verdict.read_back_reply(reply(data=b"\x34\x12"), 1.0) is None
    assert verdict.read_back_lost("no reply", 1.0) is None
    assert verdict.state is VerdictState.SENT and verdict.read_backs == 0
    ok = reply()
    assert verdict.reply(ok, 2.0) == Verdict(VerdictKind.DONE, "", ok, False, 2.0)


def test_a_write_without_a_read_back_is_unknown_at_once_when_its_answer_is_lost() -> None:
    request = TypedWrite(LogicalBinaryAddress.of(0, 7, 0), DataType.INTEGER, 2, b"\x01\x00")
    assert read_back_for(request) is None
    verdict = WriteVerdict(request, retries=3, now=0.0)
    step = verdict.lost("no reply", 0.5)
    assert isinstance(step, Verdict) and step.kind is VerdictKind.UNKNOWN and verdict.read_backs == 0
    assert step.reason == "no reply: the write may or may not have been applied (after 0.5 s)"
    settled_ignores_everything(verdict)


def test_negative_retries_are_refused() -> None:
    with pytest.raises(ValueError, match="negative"):
        WriteVerdict(WRITE, retries=-1, now=0.0)
    assert WriteVerdict(WRITE, retries=0, now=0.0).max_read_backs == 1


# ----------------------------------------------------------------------------- the read-backs


def test_a_typed_logical_write_is_read_back_from_the_same_place() -> None:
    write = ProtectedTypedLogicalWrite(FileType.INTEGER, 9, 300, 2, b"\x01\x02\x03\x04")
    check = read_back_for(write)
    assert check is not None
    assert check.request == ProtectedTypedLogicalRead(FileType.INTEGER, 9, 300, 2, 4)
    assert check.holds(b"\x01\x02\x03\x04")
    assert not check.holds(b"\x01\x02\x03\x05") and not check.holds(b"\x01\x02\x03")


def test_a_masked_write_is_read_back_from_the_same_place_and_compares_the_masked_bits() -> None:
    write = ProtectedTypedLogicalMaskedWrite(FileType.BIT, 3, 20, 1, 0x8001, b"\x01\x80\x00\x00")
    check = read_back_for(write)
    assert check is not None
    assert check.request == ProtectedTypedLogicalRead(FileType.BIT, 3, 20, 1, 4)
    # mask 0x8001: bit 0 of each even byte, bit 7 of each odd byte; the rest is free
    assert check.holds(b"\x01\x80\x00\x00") and check.holds(b"\xff\xff\xfe\x7f")
    assert not check.holds(b"\x00\x80\x00\x00")  # even byte 0, bit 0
    assert not check.holds(b"\x01\x00\x00\x00")  # odd byte 1, bit 7
    assert not check.holds(b"\x01\x80\x01\x00")  # even byte 2
    assert not check.holds(b"\x01\x80\x00\x80")  # odd byte 3
    assert not check.holds(b"\x01\x80\x00") and not check.holds(b"\x01\x80\x00\x00\x00")


def test_a_word_range_write_is_read_back_word_for_word() -> None:
    address = LogicalBinaryAddress.of(0, 7, 12)
    check = read_back_for(WordRangeWrite(address, b"\x01\x00\x02\x00\x03\x00"))
    assert check is not None and check.request == WordRangeRead(address, 6)  # its size in bytes
    assert check.holds(b"\x01\x00\x02\x00\x03\x00") and not check.holds(b"\x01\x00\x02\x00\x03\x01")
    # a later packet of a multi-packet write has no read-back of its own
    assert read_back_for(WordRangeWrite(address, b"\x01\x00", packet_offset=1, total=2)) is None


def test_a_one_word_read_modify_write_is_read_back_and_only_its_forced_bits_compared() -> None:
    address = LogicalBinaryAddress.of(0, 3, 4)
    # bit 2 forced to 1 (OR), bit 9 forced to 0 (AND 0), every other bit left alone
    and_mask, or_mask = 0xFFFF & ~(1 << 9), 1 << 2
    check = read_back_for(ReadModifyWriteRequest(((address, and_mask, or_mask),)))
    assert check is not None and check.request == WordRangeRead(address, 2)
    assert check.holds((1 << 2).to_bytes(2, "little"))
    assert check.holds((0xFFFF & ~(1 << 9)).to_bytes(2, "little"))
    assert not check.holds(b"\x00\x00")  # bit 2 clear
    assert not check.holds((1 << 2 | 1 << 9).to_bytes(2, "little"))  # bit 9 set
    assert not check.holds(b"\x04") and not check.holds(b"\x04\x00\x00")
    # the forced bits are those the masks force: a bit the AND mask keeps and the OR mask sets
    high = read_back_for(ReadModifyWriteRequest(((address, 0xFFFF, 0x8000),)))
    assert high is not None and high.holds(b"\x00\x80") and not high.holds(b"\xff\x7f")
    # two words in one command: no single read-back
    assert read_back_for(ReadModifyWriteRequest(((address, 0, 1), (address, 0, 2)))) is None


def test_reads_and_other_commands_have_no_read_back() -> None:
    assert read_back_for(READ_BACK) is None
    assert read_back_for(WordRangeRead(LogicalBinaryAddress.of(0, 7, 0), 2)) is None
    assert read_back_for(object()) is None
