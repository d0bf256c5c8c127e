"""PCCC transactions over a DF1 half-duplex line master (sans-I/O).

:class:`HalfDuplexTransactions` sits on a :class:`~gateway.protocols.df1.half_duplex.master.HalfDuplexMaster`
and turns a PCCC request for a station into one verdict event, the same events as the full-duplex
core (``transaction.py``): :class:`TransactionDone`, :class:`TransactionRefused`,
:class:`OutcomeUnknown`, :class:`TransactionFailed`.  It owns the TNS (one allocator per line: the
master refuses a TNS already in use on the line) and:

* a read without an answer is submitted again with a new TNS, at most ``retries`` more times; a
  station demoted to slow poll fails it at once;
* a write is submitted once, ``urgent`` (the master serves it before other stations' work), and
  its verdict is :class:`~gateway.protocols.df1.write_verdict.WriteVerdict`'s, as on full duplex:
  the read-backs it asks for are submitted urgent too, at most ``retries + 1`` of them;
* a reply whose PCCC packet does not decode is no answer (as on full duplex, where it is ignored).

Every other master event (station demoted / restored, a slave's own message, the fate of a reply
to it) is passed on through :meth:`next_event`.  The master is replaced on a reconnect
(:meth:`attach`): the transactions on the old one are settled as the link going away settles them.

This module does no I/O.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import ClassVar, Protocol

from gateway.protocols.df1.framing import NEED_DATA, NeedData
from gateway.protocols.df1.full_duplex.transaction import (
    OutcomeUnknown,
    TransactionDone,
    TransactionEvent,
    TransactionFailed,
    TransactionRefused,
)
from gateway.protocols.df1.half_duplex.events import FailReason, MasterEvent, ReplyReceived, RequestFailed
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster
from gateway.protocols.df1.pccc import PcccFormatError, PcccHeader, PcccReply, TnsAllocator, decode_reply
from gateway.protocols.df1.write_verdict import (
    DEFAULT_RETRIES,
    SendReadBack,
    Verdict,
    VerdictKind,
    VerdictStep,
    WriteVerdict,
)

__all__ = ["HalfDuplexTransactions", "PcccRequestLike", "TxnCounters", "encode_packet"]


class PcccRequestLike(Protocol):
    """Any PCCC request: ``CMD`` / ``FNC`` and the parameters after FNC (the pccc request classes)."""

    CMD: ClassVar[int]
    FNC: ClassVar[int]

    def encode_params(self) -> bytes: ...


def encode_packet(request: PcccRequestLike, *, dst: int, src: int, tns: int) -> bytes:
    """``DST SRC CMD 00 TNS FNC params``."""
    return PcccHeader(dst, src, request.CMD, 0, tns).encode() + bytes((request.FNC,)) + request.encode_params()


@dataclass(slots=True)
class TxnCounters:
    """Per station, since the line was created."""

    read_retries: int = 0  #: reads submitted again with a new TNS
    read_backs: int = 0  #: read-backs submitted for writes whose answer was lost


@dataclass(slots=True)
class _HalfDuplexTxn:
    handle: int
    station: int
    request: PcccRequestLike
    verdict: WriteVerdict | None  #: a write's; None for a read
    tries: int = 0  #: submissions of the request itself
    request_id: int = 0  #: the master's id of what is in flight
    tns: int = -1
    read_back: bool = False  #: what is in flight is a read-back


class HalfDuplexTransactions:
    """Sans-I/O PCCC transactions over a half-duplex master (module docstring)."""

    def __init__(self, *, source: int = 0, retries: int = DEFAULT_RETRIES, first_tns: int = 1) -> None:
        if retries < 0:
            raise ValueError("retries must not be negative")
        self.source = source
        self.retries = retries
        self.master: HalfDuplexMaster | None = None
        self._tns = TnsAllocator(first_tns & 0xFFFF)
        self._txns: dict[int, _HalfDuplexTxn] = {}  #: by handle
        self._by_request: dict[int, _HalfDuplexTxn] = {}  #: by the master's request id in flight
        self._events: deque[TransactionEvent | MasterEvent] = deque()
        self._next_handle = 1
        self._counters: dict[int, TxnCounters] = {}

    def counters(self, station: int) -> TxnCounters:
        return self._counters.setdefault(station, TxnCounters())

    def attach(self, master: HalfDuplexMaster, now: float, *, reason: str) -> None:
        """A new master (a new connection): settle every transaction of the old one."""
        for txn in list(self._txns.values()):
            self._release(txn)
            if txn.verdict is not None:
                self._follow(txn, txn.verdict.abandon(reason, now), now)
            else:
                self._settle(txn, TransactionFailed(txn.handle, reason))
        self.master = master

    def start(self, station: int, request: PcccRequestLike, now: float, *, write: bool) -> int:
        """Begin a transaction for ``station``; returns its handle (events carry it)."""
        handle = self._next_handle
        self._next_handle += 1
        verdict = WriteVerdict(request, retries=self.retries, now=now) if write else None
        txn = _HalfDuplexTxn(handle, station, request, verdict)
        self._txns[handle] = txn
        self._submit(txn, request, now, read_back=False)
        return handle

    # --- the master's loop, passed through ------------------------------------------------------

    def receive_data(self, data: bytes, now: float) -> None:
        assert self.master is not None
        self.master.receive_data(data, now)
        self._drain(now)

    def handle_timeout(self, now: float) -> None:
        assert self.master is not None
        self.master.handle_timeout(now)
        self._drain(now)

    def next_event(self) -> TransactionEvent | MasterEvent | NeedData:
        return self._events.popleft() if self._events else NEED_DATA

    # --- internals ------------------------------------------------------------------------------

    def _submit(self, txn: _HalfDuplexTxn, request: PcccRequestLike, now: float, *, read_back: bool) -> None:
        master = self.master
        assert master is not None
        txn.tns = self._tns.allocate()
        txn.read_back = read_back
        if not read_back:
            txn.tries += 1
        packet = encode_packet(request, dst=txn.station, src=self.source, tns=txn.tns)
        txn.request_id = master.submit(txn.station, packet, now, urgent=txn.verdict is not None)
        self._by_request[txn.request_id] = txn
        self._drain(now)

    def _drain(self, now: float) -> None:
        master = self.master
        assert master is not None
        while (event := master.next_event()) is not NEED_DATA:
            if (isinstance(event, ReplyReceived | RequestFailed)
                    and (txn := self._by_request.pop(event.request_id, None)) is not None):
                self._tns.release(txn.tns)
                self._outcome(txn, event, now)
            else:
                self._events.append(event)  # not a transaction's (a reply to a slave's MSG too): the driver's

    def _outcome(self, txn: _HalfDuplexTxn, event: ReplyReceived | RequestFailed, now: float) -> None:
        """What the master reports of the request ``txn`` has in flight."""
        match event:
            case RequestFailed(reason=reason, may_have_executed=may_have_executed):
                self._lost(txn, reason.value, may_have_executed, reason is FailReason.STATION_DEMOTED, now)
            case ReplyReceived(message=message):
                try:
                    reply = decode_reply(message)
                except PcccFormatError as exc:
                    self._lost(txn, f"the reply does not decode: {exc}", True, False, now)
                else:
                    self._answered(txn, reply, now)

    def _answered(self, txn: _HalfDuplexTxn, reply: PcccReply, now: float) -> None:
        if txn.verdict is None:
            self._settle(txn, TransactionDone(txn.handle, reply) if reply.ok else TransactionRefused(txn.handle, reply))
        elif txn.read_back:
            self._follow(txn, txn.verdict.read_back_reply(reply, now), now)
        else:
            self._follow(txn, txn.verdict.reply(reply, now), now)

    def _lost(self, txn: _HalfDuplexTxn, why: str, may_have_executed: bool, demoted: bool, now: float) -> None:
        if txn.verdict is None:
            if demoted or txn.tries > self.retries:
                self._settle(txn, TransactionFailed(txn.handle, f"{why} (after {txn.tries} tries)"))
            else:
                self.counters(txn.station).read_retries += 1
                self._submit(txn, txn.request, now, read_back=False)
        elif txn.read_back:
            self._follow(txn, txn.verdict.read_back_lost(why, now), now)
        else:
            self._follow(txn, txn.verdict.lost(why, now, may_have_executed=may_have_executed), now)

    def _follow(self, txn: _HalfDuplexTxn, step: VerdictStep, now: float) -> None:
        match step:  # None: the input changed nothing
            case SendReadBack(request=request):
                self.counters(txn.station).read_backs += 1
                self._submit(txn, request, now, read_back=True)
            case Verdict(kind=VerdictKind.DONE, reply=reply, verified=verified):
                assert reply is not None
                self._settle(txn, TransactionDone(txn.handle, reply, verified=verified))
            case Verdict(kind=VerdictKind.REFUSED, reply=reply):
                assert reply is not None
                self._settle(txn, TransactionRefused(txn.handle, reply))
            case Verdict(kind=VerdictKind.FAILED, reason=reason):
                self._settle(txn, TransactionFailed(txn.handle, reason))
            case Verdict(reason=reason):
                self._settle(txn, OutcomeUnknown(txn.handle, reason))

    def _release(self, txn: _HalfDuplexTxn) -> None:
        """Forget the request ``txn`` has in flight (every running transaction has one)."""
        del self._by_request[txn.request_id]
        self._tns.release(txn.tns)

    def _settle(self, txn: _HalfDuplexTxn, event: TransactionEvent) -> None:
        del self._txns[txn.handle]
        self._events.append(event)

