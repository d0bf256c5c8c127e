"""DF1 application layer: one PCCC transaction at a time over a :class:`Df1Link`, sans-I/O.

What it owns: the TNS of each command, matching replies (``pccc.reply_matches``: same TNS,
CMD | 0x40; DST / SRC not compared), retries, and the exactly-once verdict of
a write.  The link below it owns DLE ACK / NAK / ENQ (``link.py``).

Verdicts (events, one per transaction)::

    TransactionDone     the controller answered STS 0 - or, for a write whose answer was lost,
                        a read-back proved the controller holds the written value
    TransactionRefused  the controller answered STS != 0 (nothing was written)
    OutcomeUnknown      a write the controller may have executed: its frame may have arrived
                        but no answer came, and no read-back proved it applied
    TransactionFailed   a read got no valid answer after every try

The rules, under every reading of the manuals in docs/controller-variants.md:

* A read is idempotent: on a lost frame or a missing reply it is sent again with a new TNS
  (at most ``retries`` more times).  A late reply to any of its TNS is still a valid answer.
* A write is sent once.  Without its reply - no DLE ACK, a DLE NAK (no proof: see ``link.py``),
  an ACK but no reply - it may have run (with duplicate detection off, S4516-DF1 manual §4.2 /
  §5.2, "Detect Duplicate Messages should be unchecked", a second copy would run again), so it
  is never resent: the core reads the target back (protected typed logical read of the same
  bytes).  If the controller holds the written value (under the write's mask) the write is
  done; if the read-back shows anything else, or cannot be made, the outcome is unknown.
  A late reply to the write itself during the read-back settles it (STS 0: done).
* A reply that arrives before the frame's DLE ACK completes the frame at the link
  (:meth:`Df1Link.confirm`), so it is never retransmitted after its answer is in.

States and transitions (:data:`_TRANSITIONS`; inputs are classified before the look-up)::

    IDLE ------start------> SENDING
    SENDING --link ACK----> AWAIT_REPLY (reply timer)
    SENDING / AWAIT_REPLY --reply STS 0--> IDLE (Done)        --reply STS!=0--> IDLE (Refused)
    SENDING --link gave up (NAKs, no ACK) / AWAIT_REPLY --timeout:
          read:  SENDING new TNS (retries left) | IDLE (Failed)
          write: VERIFY (read-back) if a read-back exists | IDLE (OutcomeUnknown)
    VERIFY --read-back holds--> IDLE (Done, verified)   --differs / refused--> IDLE (OutcomeUnknown)
    VERIFY --no answer--> VERIFY again (retries left) | IDLE (OutcomeUnknown)
    VERIFY --late reply to the write--> IDLE (Done | Refused)

Usage (the caller owns the port and the clock; one transaction at a time)::

    tx = Df1Transactions(Df1Link(...), station=1, source=0, reply_timeout=1.0, first_tns=tns)
    handle = tx.start(request, now, write=True)
    port.write(tx.data_to_send()); tx.receive_data(port.read(), now); tx.handle_timeout(now)
    while (event := tx.next_event()) is not NEED_DATA: ...

This module does no I/O.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from gateway.errors import InvalidRequest, format_seconds
from gateway.protocols.df1.framing import NEED_DATA, NeedData
from gateway.protocols.df1.link import Df1Link, MessageReceived, SendComplete, SendFailed, SendFailure
from gateway.protocols.df1.pccc import (
    PcccFormatError,
    PcccHeader,
    PcccReply,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadModifyWriteRequest,
    Request,
    TnsAllocator,
    WordRangeRead,
    WordRangeWrite,
    decode_reply,
    encode_command,
    reply_matches,
)

__all__ = [
    "Df1Transactions",
    "OutcomeUnknown",
    "ReadBack",
    "TransactionCounters",
    "TransactionDone",
    "TransactionEvent",
    "TransactionFailed",
    "TransactionRefused",
    "TxnState",
    "read_back_for",
]


# --------------------------------------------------------------------------------------- events


@dataclass(frozen=True, slots=True)
class TransactionDone:
    """STS 0 (``reply``); ``verified`` when a read-back, not the reply, proved a write applied."""

    handle: int
    reply: PcccReply
    verified: bool = False


@dataclass(frozen=True, slots=True)
class TransactionRefused:
    """The controller refused the command (STS != 0); nothing was written."""

    handle: int
    reply: PcccReply


@dataclass(frozen=True, slots=True)
class OutcomeUnknown:
    """A write that may or may not have been applied; ``reason`` says what was seen."""

    handle: int
    reason: str


@dataclass(frozen=True, slots=True)
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


# ------------------------------------------------------------------------------------ read-back


@dataclass(frozen=True, slots=True)
class ReadBack:
    """How to verify a write: the read to send and whether its data shows the write applied."""

    request: ProtectedTypedLogicalRead | WordRangeRead
    holds: Callable[[bytes], bool]


def read_back_for(request: Request) -> ReadBack | None:
    """The read-back of a protected typed logical (masked) write, a PLC-5 word range write or a
    one-word read-modify-write; None for other commands."""
    if isinstance(request, ProtectedTypedLogicalWrite):
        data = request.data
        read = ProtectedTypedLogicalRead(
            request.file_type, request.file_number, request.element, request.sub_element, len(data)
        )
        return ReadBack(read, lambda got: got == data)
    if isinstance(request, ProtectedTypedLogicalMaskedWrite):
        data, mask = request.data, request.mask.to_bytes(2, "little")
        read = ProtectedTypedLogicalRead(
            request.file_type, request.file_number, request.element, request.sub_element, len(data)
        )
        # the mask's low byte applies to even bytes, its high byte to odd ones (notes §4.36)

        def holds(got: bytes) -> bool:
            return len(got) == len(data) and all(
                (got[i] & mask[i % 2]) == (data[i] & mask[i % 2]) for i in range(len(data))
            )

        return ReadBack(read, holds)
    if isinstance(request, WordRangeWrite) and request.packet_offset == 0:
        # PLC-5 word range write (issue #12): read the same words back with a word range read
        words = request.data
        return ReadBack(WordRangeRead(request.address, len(words)), lambda got: got == words)
    if isinstance(request, ReadModifyWriteRequest) and len(request.sets) == 1:
        # PLC-5 coil write: the bits the masks force (AND 0 or OR 1) hold the OR mask's value (p. 7-20)
        address, and_mask, or_mask = request.sets[0]
        forced = (~and_mask | or_mask) & 0xFFFF

        def forced_bits_hold(got: bytes) -> bool:
            return len(got) == 2 and int.from_bytes(got, "little") & forced == or_mask & forced

        return ReadBack(WordRangeRead(address, 2), forced_bits_hold)
    return None


# ---------------------------------------------------------------------------------------- table


class TxnState(enum.Enum):
    IDLE = "idle"
    SENDING = "command frame on the link, waiting for DLE ACK"
    AWAIT_REPLY = "command acknowledged, waiting for its reply"
    VERIFY_SENDING = "read-back frame on the link"
    VERIFY_AWAIT_REPLY = "read-back acknowledged, waiting for its reply"

    __hash__ = object.__hash__


class _In(enum.Enum):
    START = "start a transaction"
    LINK_ACKED = "the link has the ACK of our frame"
    LINK_NAKED = "every copy of our frame was NAKed: it never arrived"
    LINK_LOST = "the link gave up on our frame; the peer may have it"
    TIMEOUT = "no reply within the reply timeout"
    REPLY_OK = "the reply to our command, STS 0"
    REPLY_REFUSED = "the reply to our command, STS != 0"
    READBACK_HOLDS = "the read-back shows the written value"
    READBACK_DIFFERS = "the read-back shows another value, or was refused"

    __hash__ = object.__hash__


class _Do(enum.Enum):
    SEND = "send the command with a new TNS"
    AWAIT = "start the reply timer"
    RETRY = "send the command again with a new TNS if tries are left, else fail"
    VERIFY = "send the read-back if the write has one, else outcome unknown"
    VERIFY_AGAIN = "send the read-back again if tries are left, else outcome unknown"
    DONE = "report TransactionDone"
    DONE_VERIFIED = "report TransactionDone(verified=True)"
    REFUSED = "report TransactionRefused"
    UNKNOWN = "report OutcomeUnknown"
    IGNORE = "nothing"

    __hash__ = object.__hash__


S, K = TxnState, _In
_READ, _WRITE = False, True

#: (state, input, is_write) -> (action, next state).  Pairs missing from the table are ignored.
_TRANSITIONS: Final[dict[tuple[TxnState, _In, bool], tuple[_Do, TxnState]]] = {}
for _w in (_READ, _WRITE):
    _TRANSITIONS.update({
        (S.IDLE, K.START, _w): (_Do.SEND, S.SENDING),
        (S.SENDING, K.LINK_ACKED, _w): (_Do.AWAIT, S.AWAIT_REPLY),
        (S.SENDING, K.REPLY_OK, _w): (_Do.DONE, S.IDLE),
        (S.SENDING, K.REPLY_REFUSED, _w): (_Do.REFUSED, S.IDLE),
        (S.AWAIT_REPLY, K.REPLY_OK, _w): (_Do.DONE, S.IDLE),
        (S.AWAIT_REPLY, K.REPLY_REFUSED, _w): (_Do.REFUSED, S.IDLE),
    })
_TRANSITIONS.update({
    # reads: idempotent, simply sent again
    (S.SENDING, K.LINK_NAKED, _READ): (_Do.RETRY, S.SENDING),
    (S.SENDING, K.LINK_LOST, _READ): (_Do.RETRY, S.SENDING),
    (S.AWAIT_REPLY, K.TIMEOUT, _READ): (_Do.RETRY, S.SENDING),
    # writes: may have run; find out, never send again
    (S.SENDING, K.LINK_NAKED, _WRITE): (_Do.VERIFY, S.VERIFY_SENDING),
    (S.SENDING, K.LINK_LOST, _WRITE): (_Do.VERIFY, S.VERIFY_SENDING),
    (S.AWAIT_REPLY, K.TIMEOUT, _WRITE): (_Do.VERIFY, S.VERIFY_SENDING),
    (S.VERIFY_SENDING, K.LINK_ACKED, _WRITE): (_Do.AWAIT, S.VERIFY_AWAIT_REPLY),
    (S.VERIFY_SENDING, K.LINK_NAKED, _WRITE): (_Do.VERIFY_AGAIN, S.VERIFY_SENDING),
    (S.VERIFY_SENDING, K.LINK_LOST, _WRITE): (_Do.VERIFY_AGAIN, S.VERIFY_SENDING),
    (S.VERIFY_AWAIT_REPLY, K.TIMEOUT, _WRITE): (_Do.VERIFY_AGAIN, S.VERIFY_SENDING),
    (S.VERIFY_SENDING, K.READBACK_HOLDS, _WRITE): (_Do.DONE_VERIFIED, S.IDLE),
    (S.VERIFY_AWAIT_REPLY, K.READBACK_HOLDS, _WRITE): (_Do.DONE_VERIFIED, S.IDLE),
    (S.VERIFY_SENDING, K.READBACK_DIFFERS, _WRITE): (_Do.UNKNOWN, S.IDLE),
    (S.VERIFY_AWAIT_REPLY, K.READBACK_DIFFERS, _WRITE): (_Do.UNKNOWN, S.IDLE),
    # a late reply to the write itself settles it
    (S.VERIFY_SENDING, K.REPLY_OK, _WRITE): (_Do.DONE, S.IDLE),
    (S.VERIFY_AWAIT_REPLY, K.REPLY_OK, _WRITE): (_Do.DONE, S.IDLE),
    (S.VERIFY_SENDING, K.REPLY_REFUSED, _WRITE): (_Do.REFUSED, S.IDLE),
    (S.VERIFY_AWAIT_REPLY, K.REPLY_REFUSED, _WRITE): (_Do.REFUSED, S.IDLE),
})
del _w


# ---------------------------------------------------------------------------------------- core


@dataclass(slots=True)
class _Txn:
    handle: int
    request: Request
    write: bool
    read_back: ReadBack | None
    tries: int = 0  #: command frames sent
    verify_tries: int = 0
    tns: set[int] = field(default_factory=set)  #: every TNS the command was sent with
    sent: list[PcccHeader] = field(default_factory=list)  #: the header of every copy sent
    frame: int = 0  #: link handle of the frame in flight
    verify_tns: int | None = None
    verify: PcccHeader | None = None  #: header of the read-back in flight
    why: str = ""  #: what went wrong last (for the verdict's message)


class Df1Transactions:
    """Sans-I/O PCCC transactions over a DF1 full-duplex link (module docstring)."""

    def __init__(
        self,
        link: Df1Link,
        *,
        station: int,
        source: int = 0,
        reply_timeout: float = 1.0,
        retries: int = 3,
        first_tns: int = 1,
    ) -> None:
        if reply_timeout <= 0:
            raise ValueError("reply_timeout must be positive")
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

    @property
    def next_tns(self) -> int:
        """A TNS to start a successor with (a new link after a reconnect)."""
        return self._tns.allocate()

    def start(self, request: Request, now: float, *, write: bool) -> int:
        """Begin a transaction; returns its handle.  One at a time."""
        if self._state is not TxnState.IDLE:
            raise InvalidRequest("DF1: a transaction is already running")
        handle = self._next_handle
        self._next_handle += 1
        self._txn = _Txn(handle, request, write, read_back_for(request) if write else None)
        self.counters.started += 1
        self._input(_In.START, now)
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
                self._txn.why = f"no reply within {format_seconds(self.reply_timeout)} s of the DLE ACK"
            self._input(_In.TIMEOUT, now)

    def abandon(self, reason: str) -> None:
        """The link is gone (port lost): settle the running transaction without a reply."""
        txn = self._txn
        if txn is None:
            return
        self._deadline = None
        self._state = TxnState.IDLE
        self._finish_ids(txn)
        self._txn = None
        if txn.write and (txn.tries > 0):
            self.counters.unknown += 1
            self._events.append(OutcomeUnknown(txn.handle, reason))
        else:
            self._events.append(TransactionFailed(txn.handle, reason))

    # ------------------------------------------------------------------------------- internals

    def _drain_link(self, now: float) -> None:
        while (event := self.link.next_event()) is not NEED_DATA:
            txn = self._txn
            match event:
                case MessageReceived(payload=payload):
                    self._on_message(payload, now)
                case SendComplete(handle=handle):
                    if txn is not None and handle == txn.frame:
                        self._input(_In.LINK_ACKED, now)
                case SendFailed(handle=handle, reason=reason):
                    if txn is not None and handle == txn.frame:
                        txn.why = reason.value
                        naked = reason is SendFailure.NAK_LIMIT
                        self._input(_In.LINK_NAKED if naked else _In.LINK_LOST, now)

    def _on_message(self, payload: bytes, now: float) -> None:
        try:
            reply = decode_reply(payload)
        except PcccFormatError:
            return  # a command addressed to us, or junk that passed the check: not ours to answer
        txn = self._txn
        if txn is None:
            return  # a reply to a transaction already settled (late, or the reply to a duplicate)
        if txn.read_back is not None and txn.verify is not None and reply_matches(txn.verify, reply):
            self.link.confirm(txn.frame, now)
            holds = reply.ok and txn.read_back.holds(reply.data)
            if not holds:
                txn.why = (
                    f"the read-back was refused ({reply.error()})" if not reply.ok
                    else f"the read-back gave {reply.data.hex(' ')}, not the value written"
                )
            self._reply = reply
            self._input(_In.READBACK_HOLDS if holds else _In.READBACK_DIFFERS, now)
            return
        if not any(reply_matches(sent, reply) for sent in txn.sent):
            return
        if reply.tns != self._current_tns or self._state not in (TxnState.SENDING, TxnState.AWAIT_REPLY):
            self.counters.late_replies += 1  # answers an earlier frame, not the one in flight
        else:
            self.link.confirm(txn.frame, now)
        self._reply = reply
        self._input(_In.REPLY_OK if reply.ok else _In.REPLY_REFUSED, now)

    def _input(self, what: _In, now: float) -> None:
        txn = self._txn
        if txn is None:
            return
        entry = _TRANSITIONS.get((self._state, what, txn.write))
        if entry is None:
            return
        action, next_state = entry
        self._state = next_state
        match action:
            case _Do.IGNORE:
                pass
            case _Do.SEND:
                self._send_command(txn, now)
            case _Do.AWAIT:
                self._deadline = now + self.reply_timeout
            case _Do.RETRY:
                if txn.tries <= self.retries:
                    self._send_command(txn, now)
                else:
                    tries = txn.tries
                    self._settle(TransactionFailed(txn.handle, f"{txn.why} (after {tries} tries)"))
            case _Do.VERIFY | _Do.VERIFY_AGAIN:
                if txn.read_back is not None and txn.verify_tries <= self.retries:
                    self._send_read_back(txn, now)
                else:
                    self._unknown(txn)
            case _Do.DONE:
                reply = self._reply
                assert reply is not None
                self._settle(TransactionDone(txn.handle, reply))
            case _Do.DONE_VERIFIED:
                reply = self._reply
                assert reply is not None
                self.counters.verified += 1
                self._settle(TransactionDone(txn.handle, reply, verified=True))
            case _Do.REFUSED:
                reply = self._reply
                assert reply is not None
                self._settle(TransactionRefused(txn.handle, reply))
            case _Do.UNKNOWN:
                self._unknown(txn)
        self._reply = None

    def _unknown(self, txn: _Txn) -> None:
        self.counters.unknown += 1
        verify = "" if txn.read_back is None else "; the read-back did not prove it applied"
        self._settle(OutcomeUnknown(txn.handle, f"{txn.why}{verify}: the write may or may not have been applied"))

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

    def _send_read_back(self, txn: _Txn, now: float) -> None:
        assert txn.read_back is not None
        if txn.verify_tns is not None:
            self._tns.release(txn.verify_tns)
        tns = self._tns.allocate()
        txn.verify_tns = tns
        txn.verify_tries += 1
        self.counters.read_backs += 1
        self._deadline = None
        packet = encode_command(txn.read_back.request, dst=self.station, src=self.source, tns=tns)
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

