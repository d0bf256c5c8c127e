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
from gateway.protocols.df1.datalink import Df1DataLink
from gateway.protocols.df1.framing import ACK_SYMBOL, EOT_SYMBOL, Checksum, NeedData, encode_frame, encode_poll
from gateway.protocols.df1.half_duplex import HalfDuplexMaster
from gateway.protocols.df1.half_duplex_events import LineConfig, StationConfig
from gateway.protocols.df1.half_duplex_transactions import HalfDuplexTransactions
from gateway.protocols.df1.pccc import (
    PcccHeader,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    decode_command,
    decode_reply,
    encode_reply,
)
from gateway.protocols.df1.transaction import (
    Df1Transactions,
    OutcomeUnknown,
    TransactionDone,
    TransactionEvent,
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
    core = Df1Transactions(Df1DataLink(checksum=Checksum.CRC), station=1, first_tns=0x100)
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
