"""DF1 application layer: one PCCC transaction at a time over a :class:`Df1DataLink`, sans-I/O.

What it owns: the TNS of each command, matching replies (``pccc.reply_matches``: same TNS,
CMD | 0x40; DST / SRC not compared), retries, and the exactly-once verdict of
a write.  The data link below it owns DLE ACK / NAK / ENQ (``datalink.py``).

Verdicts (events, one per transaction)::

    TransactionDone     the controller answered STS 0 - or, for a write whose answer was lost,
                        a read-back proved the controller holds the written value
    TransactionRefused  the controller answered STS != 0 (nothing was written)
    OutcomeUnknown      a write the controller may have executed: its frame may have arrived
                        but no answer came, and no read-back proved it applied
    TransactionFailed   a read got no valid answer after every try

The rules, under every reading of the manuals in docs/develop/controller-variants.md:

* A read is idempotent: on a lost frame or a missing reply it is sent again with a new TNS
  (at most ``retries`` more times).  A late reply to any of its TNS is still a valid answer.
* A write is sent once and never resent.  Its verdict - done, refused, read it back, outcome
  unknown - is :class:`~gateway.protocols.df1.write_verdict.WriteVerdict`'s, shared with half
  duplex: without its reply (no DLE ACK, a DLE NAK - no proof, see ``datalink.py`` - an ACK but no
  reply) the core reads the target back (protected typed logical read of the same bytes) at most
  ``retries + 1`` times; a late reply to the write itself during the read-back settles it.
* A reply that arrives before the frame's DLE ACK completes the frame at the link
  (:meth:`Df1DataLink.confirm`), so it is never retransmitted after its answer is in.

States and transitions (:data:`TRANSITIONS`; inputs are classified before the look-up; a read and
a write have their own states, the read-back of a write the VERIFY ones)::

    IDLE --start a read / a write--> READ_SENDING / WRITE_SENDING
    *_SENDING --link ACK----> *_AWAIT_REPLY (reply timer)
    *_SENDING / *_AWAIT_REPLY --reply STS 0--> IDLE (Done)        --reply STS!=0--> IDLE (Refused)
    *_SENDING --link gave up (NAKs, no ACK) / *_AWAIT_REPLY --timeout:
          read:  READ_SENDING new TNS (retries left) | IDLE (Failed)
          write: the verdict's step: VERIFY_SENDING (read-back) | IDLE (OutcomeUnknown)
    VERIFY_SENDING --link ACK--> VERIFY_AWAIT_REPLY
    VERIFY_* --read-back reply / no answer / late reply to the write--> the verdict's step

Usage (the caller owns the port and the clock; one transaction at a time)::

    tx = Df1Transactions(Df1DataLink(...), station=1, source=0, reply_timeout=1.0, first_tns=tns)
    handle = tx.start(request, now, write=True)
    port.write(tx.data_to_send()); tx.receive_data(port.read(), now); tx.handle_timeout(now)
    while (event := tx.next_event()) is not NEED_DATA: ...

This module does no I/O.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Final

from gateway.errors import InvalidRequest, format_seconds
from gateway.frozen import frozen
from gateway.protocols.df1.framing import NEED_DATA, NeedData
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink, MessageReceived, SendComplete, SendFailed
from gateway.protocols.df1.pccc import (
    PcccFormatError,
    PcccHeader,
    PcccReply,
    Request,
    TnsAllocator,
    decode_reply,
    encode_command,
    reply_matches,
)
from gateway.protocols.df1.write_verdict import (
    DEFAULT_RETRIES,
    ReadBack,
    SendReadBack,
    Verdict,
    VerdictKind,
    VerdictStep,
    WriteVerdict,
    read_back_for,
)
from gateway.protocols.transitions import Table, TableEnum, Transition, require_complete, stay

__all__ = [
    "TRANSITIONS",
    "Df1Transactions",
    "OutcomeUnknown",
    "ReadBack",
    "TransactionCounters",
    "TransactionDone",
    "TransactionEvent",
    "TransactionFailed",
    "TransactionRefused",
    "TxnAction",
    "TxnInput",
    "TxnState",
    "read_back_for",
]


# --------------------------------------------------------------------------------------- events


@frozen
class TransactionDone:
    """STS 0 (``reply``); ``verified`` when a read-back, not the reply, proved a write applied."""

    handle: int
    reply: PcccReply
    verified: bool = False


@frozen
class TransactionRefused:
    """The controller refused the command (STS != 0); nothing was written."""

    handle: int
    reply: PcccReply


@frozen
class OutcomeUnknown:
    """A write that may or may not have been applied; ``reason`` says what was seen.  ``shown``: the
    data of a read-back that answered with another value than the one written (full duplex: the
    read-back ran after the write, so what it shows is what the controller held after it)."""

    handle: int
    reason: str
    shown: bytes | None = None


@frozen
class TransactionFailed:
    """No valid answer; for a write, it provably never ran."""

    handle: int
    reason: str


TransactionEvent = TransactionDone | TransactionRefused | OutcomeUnknown | TransactionFailed


@dataclass(slots=True)
class TransactionCounters:
    started: int = 0
    attempts: int = 0  #: commands sent (retries included, read-backs excluded)
    reply_timeouts: int = 0
    read_backs: int = 0  #: read-back commands sent
    verified: int = 0  #: writes proved applied by a read-back
    unknown: int = 0
    late_replies: int = 0  #: replies to an earlier attempt of the same transaction, accepted


# ---------------------------------------------------------------------------------------- table


class TxnState(TableEnum):
    IDLE = "idle"
    READ_SENDING = "a read's frame on the link, waiting for DLE ACK"
    READ_AWAIT_REPLY = "a read acknowledged, waiting for its reply"
    WRITE_SENDING = "a write's frame on the link, waiting for DLE ACK"
    WRITE_AWAIT_REPLY = "a write acknowledged, waiting for its reply"
    VERIFY_SENDING = "read-back frame on the link"
    VERIFY_AWAIT_REPLY = "read-back acknowledged, waiting for its reply"


class TxnInput(TableEnum):
    START_READ = "start a read"
    START_WRITE = "start a write"
    LINK_ACKED = "the link has the ACK of our frame"
    LINK_LOST = "the link gave up on our frame (NAKs, or no ACK): the peer may have it"
    TIMEOUT = "no reply within the reply timeout"
    REPLY = "the reply to our command (any STS)"
    READBACK_REPLY = "the reply to the read-back (any STS)"
    ABANDON = "the link is gone (port lost)"


class TxnAction(TableEnum):
    SEND = "send the command with a new TNS"
    AWAIT = "start the reply timer"
    RETRY = "send the command again with a new TNS if tries are left, else fail"
    ANSWERED = "report TransactionDone (STS 0) or TransactionRefused"
    WRITE_REPLY = "the write's reply: the verdict's step"
    WRITE_LOST = "no answer to the write: the verdict's step"
    READBACK_LOST = "no answer to the read-back: the verdict's step"
    READBACK_REPLY = "the read-back's reply: the verdict's step"
    ABANDON = "settle without a reply: a read fails, a write gets the verdict's step"
    IGNORE = "nothing"


_Table = Table[TxnState, TxnInput, TxnAction]

#: The states in which the command itself is in flight (its reply may complete the frame at the link).
_COMMAND_IN_FLIGHT: Final = frozenset(
    {TxnState.READ_SENDING, TxnState.READ_AWAIT_REPLY, TxnState.WRITE_SENDING, TxnState.WRITE_AWAIT_REPLY}
)


def _build_table() -> _Table:
    T, S, K, A = Transition, TxnState, TxnInput, TxnAction
    idle = frozenset({S.IDLE})
    starts = (K.START_READ, K.START_WRITE)
    links = (K.LINK_ACKED, K.LINK_LOST)

    def exchange(
        sending: TxnState, awaiting: TxnState, reply: TxnInput, answered: TxnAction, lost: TxnAction, again: TxnState
    ) -> _Table:
        """The rows of one frame on the link (``sending``), then acknowledged and waiting for its
        ``reply`` (``awaiting``): the reply runs ``answered``; a frame the link gave up on, or no
        reply in time, runs ``lost``, which sends a frame again (``again``) or settles."""
        return {
            (sending, K.LINK_ACKED): T(A.AWAIT, awaiting),
            (sending, reply): T(answered, S.IDLE),
            (sending, K.LINK_LOST): T(lost, again, idle),
            **stay(A.IGNORE, sending, *starts, K.TIMEOUT),  # no reply timer yet
            (awaiting, reply): T(answered, S.IDLE),
            (awaiting, K.TIMEOUT): T(lost, again, idle),
            **stay(A.IGNORE, awaiting, *starts, *links),  # the link is done with the frame
        }

    return {
        (S.IDLE, K.START_READ): T(A.SEND, S.READ_SENDING),
        (S.IDLE, K.START_WRITE): T(A.SEND, S.WRITE_SENDING),
        # no transaction: a late answer of a settled one
        **stay(A.IGNORE, S.IDLE, *links, K.TIMEOUT, K.REPLY, K.READBACK_REPLY, K.ABANDON),
        # the link is gone: whatever runs is settled
        **{(state, K.ABANDON): T(A.ABANDON, S.IDLE) for state in TxnState if state is not S.IDLE},
        # reads: idempotent, simply sent again
        **exchange(S.READ_SENDING, S.READ_AWAIT_REPLY, K.REPLY, A.ANSWERED, A.RETRY, S.READ_SENDING),
        # writes: the verdict decides (write_verdict.py); never sent again
        **exchange(S.WRITE_SENDING, S.WRITE_AWAIT_REPLY, K.REPLY, A.WRITE_REPLY, A.WRITE_LOST, S.VERIFY_SENDING),
        # no read-back runs while the command itself is in flight
        **{(state, K.READBACK_REPLY): T(A.IGNORE, state) for state in _COMMAND_IN_FLIGHT},
        # the read-back of a write whose answer was lost; a late reply to the write itself settles it
        **exchange(S.VERIFY_SENDING, S.VERIFY_AWAIT_REPLY, K.READBACK_REPLY,
                   A.READBACK_REPLY, A.READBACK_LOST, S.VERIFY_SENDING),
        **{(state, K.REPLY): T(A.WRITE_REPLY, S.IDLE) for state in (S.VERIFY_SENDING, S.VERIFY_AWAIT_REPLY)},
    }


#: The transaction core's state machine: (state, input) -> (action, next state, or the states the
#: action may choose instead: a retry or a read-back, or the verdict).
TRANSITIONS: Final = _build_table()
require_complete(TRANSITIONS, TxnState, TxnInput, "DF1 transactions")


# ---------------------------------------------------------------------------------------- core


@dataclass(slots=True)
class _Txn:
    handle: int
    request: Request
    verdict: WriteVerdict | None  #: a write's verdict; None for a read
    tries: int = 0  #: command frames sent
    tns: set[int] = field(default_factory=set)  #: every TNS the command was sent with
    sent: list[PcccHeader] = field(default_factory=list)  #: the header of every copy sent
    frame: int = 0  #: link handle of the frame in flight
    verify_tns: int | None = None
    verify: PcccHeader | None = None  #: header of the read-back in flight
    why: str = ""  #: what went wrong last (for the verdict's message)

    @property
    def write(self) -> bool:
        return self.verdict is not None

    @property
    def read_back(self) -> ReadBack | None:
        return None if self.verdict is None else self.verdict.read_back


class Df1Transactions:
    """Sans-I/O PCCC transactions over a DF1 full-duplex link (module docstring)."""

    def __init__(
        self,
        link: Df1DataLink,
        *,
        station: int,
        source: int,
        reply_timeout: float,
        retries: int = DEFAULT_RETRIES,
        first_tns: int = 1,
    ) -> None:
        if reply_timeout <= 0:
            raise ValueError("reply_timeout must be positive")
        #: the adaptive reply wait's floor (see _reply_wait)
        self.min_reply_timeout = min(0.1, reply_timeout)
        self._reply_times: deque[float] = deque(maxlen=32)
        self._awaiting_since = 0.0
        self._wait = reply_timeout
        if retries < 0:
            raise ValueError("retries must not be negative")
        self.link: Final = link
        self.station = station
        self.source = source
        self.reply_timeout = reply_timeout
        self.retries = retries
        self.counters = TransactionCounters()
        self._tns = TnsAllocator(first_tns & 0xFFFF)
        self._state = TxnState.IDLE
        self._txn: _Txn | None = None
        self._deadline: float | None = None
        self._events: deque[TransactionEvent] = deque()
        self._next_handle = 1
        self._reply: PcccReply | None = None  # the reply an input is about
        self._current_tns = -1  # TNS of the latest command frame

    # ------------------------------------------------------------------------------ public API

    @property
    def state(self) -> TxnState:
        return self._state

    def allocate_tns(self) -> int:
        """Allocate a TNS to start a successor with (a new data link after a reconnect)."""
        return self._tns.allocate()

    def start(self, request: Request, now: float, *, write: bool) -> int:
        """Begin a transaction; returns its handle.  One at a time."""
        if self._state is not TxnState.IDLE:
            raise InvalidRequest("DF1: a transaction is already running")
        handle = self._next_handle
        self._next_handle += 1
        verdict = WriteVerdict(request, retries=self.retries, now=now) if write else None
        self._txn = _Txn(handle, request, verdict)
        self.counters.started += 1
        self._input(TxnInput.START_WRITE if write else TxnInput.START_READ, now)
        return handle

    def receive_data(self, data: bytes, now: float) -> None:
        self.link.receive_data(data, now)
        self._drain_link(now)

    def data_to_send(self) -> bytes:
        return self.link.data_to_send()

    def next_event(self) -> TransactionEvent | NeedData:
        if self._events:
            return self._events.popleft()
        return NEED_DATA

    def next_deadline(self) -> float | None:
        deadlines = [d for d in (self.link.next_deadline(), self._deadline) if d is not None]
        return min(deadlines) if deadlines else None

    def handle_timeout(self, now: float) -> None:
        """Call at or after :meth:`next_deadline`; early calls do nothing."""
        link_deadline = self.link.next_deadline()
        if link_deadline is not None and now >= link_deadline:
            self.link.handle_timeout(now)
            self._drain_link(now)
        if self._deadline is not None and now >= self._deadline:
            self._deadline = None
            self.counters.reply_timeouts += 1
            if self._txn is not None:
                self._txn.why = f"no reply within {format_seconds(self._wait)} s of the DLE ACK"
            self._input(TxnInput.TIMEOUT, now)

    def abandon(self, reason: str, now: float) -> None:
        """The link is gone (port lost): settle the running transaction without a reply."""
        if self._txn is not None:
            self._txn.why = reason
        self._input(TxnInput.ABANDON, now)

    # ------------------------------------------------------------------------------- internals

    def _drain_link(self, now: float) -> None:
        while (event := self.link.next_event()) is not NEED_DATA:
            txn = self._txn
            match event:
                case MessageReceived(payload=payload):
                    self._on_message(payload, now)
                case SendComplete(handle=handle):
                    if txn is not None and handle == txn.frame:
                        self._input(TxnInput.LINK_ACKED, now)
                case SendFailed(handle=handle, reason=reason):
                    # every NAK or no ACK at all: no proof the frame never arrived (datalink.py)
                    if txn is not None and handle == txn.frame:
                        txn.why = reason.value
                        self._input(TxnInput.LINK_LOST, now)

    def _on_message(self, payload: bytes, now: float) -> None:
        try:
            reply = decode_reply(payload)
        except PcccFormatError:
            return  # a command addressed to us, or junk that passed the check: not ours to answer
        txn = self._txn
        if txn is None:
            return  # a reply to a transaction already settled (late, or the reply to a duplicate)
        if txn.verify is not None and reply_matches(txn.verify, reply):
            self.link.confirm(txn.frame, now)
            self._reply = reply
            self._input(TxnInput.READBACK_REPLY, now)
            return
        if not any(reply_matches(sent, reply) for sent in txn.sent):
            return
        if reply.tns != self._current_tns or self._state not in _COMMAND_IN_FLIGHT:
            self.counters.late_replies += 1  # answers an earlier frame, not the one in flight
        else:
            self.link.confirm(txn.frame, now)
            if self._state in (TxnState.READ_AWAIT_REPLY, TxnState.WRITE_AWAIT_REPLY):
                self._reply_times.append(now - self._awaiting_since)
        self._reply = reply
        self._input(TxnInput.REPLY, now)

    def _reply_wait(self) -> float:
        """How long to wait for a command's reply after its ACK: 2 x the slowest of the last 32
        replies (at least ``min_reply_timeout``), at most ``reply_timeout``.  A reply later than
        that is not lost: a read asks again (its late reply is ignored), a write is read back
        (its late reply still settles it)."""
        if len(self._reply_times) < 8:
            return self.reply_timeout
        return min(self.reply_timeout, max(self.min_reply_timeout, 2 * max(self._reply_times)))

    def _input(self, what: TxnInput, now: float) -> None:
        entry = TRANSITIONS[self._state, what]
        if entry.action is TxnAction.IGNORE:
            return
        txn = self._txn
        assert txn is not None, f"{entry.action.name} without a transaction"
        action, next_state, _ = entry
        self._state = next_state
        self._act(txn, action, next_state, now)
        assert entry.allows(self._state), f"{action.name} ended in {self._state.name}"

    def _act(self, txn: _Txn, action: TxnAction, next_state: TxnState, now: float) -> None:
        reply, self._reply = self._reply, None
        verdict = txn.verdict
        match action:
            case TxnAction.SEND:
                self._send_command(txn, now)
            case TxnAction.AWAIT:
                self._awaiting_since = now
                # the wait for a reply adapts to the controller's measured reply times; the last
                # read-back's wait (its silence decides a write's verdict) keeps the full time
                last = (next_state is TxnState.VERIFY_AWAIT_REPLY and verdict is not None
                        and verdict.read_backs >= verdict.max_read_backs)
                self._wait = self.reply_timeout if last else self._reply_wait()
                self._deadline = now + self._wait
            case TxnAction.RETRY:
                if txn.tries <= self.retries:
                    self._send_command(txn, now)
                else:
                    tries = txn.tries
                    self._settle(TransactionFailed(txn.handle, f"{txn.why} (after {tries} tries)"))
            case TxnAction.ANSWERED:
                assert reply is not None
                self._settle(TransactionDone(txn.handle, reply) if reply.ok else TransactionRefused(txn.handle, reply))
            case TxnAction.WRITE_REPLY:
                assert reply is not None and verdict is not None
                self._follow(txn, verdict.reply(reply, now), now)
            case TxnAction.WRITE_LOST:
                assert verdict is not None
                self._follow(txn, verdict.lost(txn.why, now), now)
            case TxnAction.READBACK_LOST:
                assert verdict is not None
                self._follow(txn, verdict.read_back_lost(txn.why, now), now)
            case TxnAction.READBACK_REPLY:
                assert reply is not None and verdict is not None
                self._follow(txn, verdict.read_back_reply(reply, now), now)
            case TxnAction.ABANDON:
                if verdict is not None:
                    self._follow(txn, verdict.abandon(txn.why, now), now)
                else:
                    self._settle(TransactionFailed(txn.handle, txn.why))

    def _follow(self, txn: _Txn, step: VerdictStep, now: float) -> None:
        """Carry out the verdict's step: a read-back to send, or the verdict as an event."""
        match step:  # None: the input changed nothing
            case SendReadBack(request=request):
                self._state = TxnState.VERIFY_SENDING
                self._send_read_back(txn, request, now)
            case Verdict(kind=VerdictKind.DONE, reply=reply, verified=verified):
                assert reply is not None
                self.counters.verified += verified
                self._settle(TransactionDone(txn.handle, reply, verified=verified))
            case Verdict(kind=VerdictKind.REFUSED, reply=reply):
                assert reply is not None
                self._settle(TransactionRefused(txn.handle, reply))
            case Verdict(kind=VerdictKind.FAILED, reason=reason):
                self._settle(TransactionFailed(txn.handle, reason))
            case Verdict(reason=reason, shown=shown):
                self.counters.unknown += 1
                self._settle(OutcomeUnknown(txn.handle, reason, shown))

    def _send_command(self, txn: _Txn, now: float) -> None:
        tns = self._tns.allocate()
        txn.tns.add(tns)
        self._current_tns = tns
        txn.tries += 1
        self.counters.attempts += 1
        self._deadline = None
        packet = encode_command(txn.request, dst=self.station, src=self.source, tns=tns)
        txn.sent.append(PcccHeader.decode(packet))
        txn.frame = self.link.send(packet, now, idempotent=not txn.write)

    def _send_read_back(self, txn: _Txn, request: Request, now: float) -> None:
        if txn.verify_tns is not None:
            self._tns.release(txn.verify_tns)
        tns = self._tns.allocate()
        txn.verify_tns = tns
        self.counters.read_backs += 1
        self._deadline = None
        packet = encode_command(request, dst=self.station, src=self.source, tns=tns)
        txn.verify = PcccHeader.decode(packet)
        txn.frame = self.link.send(packet, now)

    def _finish_ids(self, txn: _Txn) -> None:
        for tns in txn.tns:
            self._tns.release(tns)
        if txn.verify_tns is not None:
            self._tns.release(txn.verify_tns)

    def _settle(self, event: TransactionEvent) -> None:
        txn = self._txn
        assert txn is not None
        self._deadline = None
        self._state = TxnState.IDLE
        self._finish_ids(txn)
        self._txn = None
        self._events.append(event)

