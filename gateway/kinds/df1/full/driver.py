"""Asyncio driver for DF1 full duplex + PCCC (SLC 500, PLC-5): a thin loop around the cores.

The sans-I/O cores decide everything: :class:`~gateway.protocols.df1.full_duplex.datalink.Df1DataLink` (DLE ACK /
NAK / ENQ) under :class:`~gateway.protocols.df1.full_duplex.transaction.Df1Transactions` (TNS, reply
matching, retries, the exactly-once verdict of a write and its read-back).  This module moves
bytes, runs the one timer the core asks for (``next_deadline()`` / ``handle_timeout(now)``)
and turns the core's verdicts into results and exceptions:

* done -> the reply (for a write whose reply was lost but whose read-back showed the written
  value: a success too);
* refused -> :class:`~gateway.protocols.df1.pccc.PcccError` with the manual's text;
* outcome unknown -> :class:`~gateway.errors.WriteOutcomeUnknown` (Modbus 0x0B); the write was
  sent once (re-exported here for the modules that import it from this one);
* failed -> :class:`~gateway.errors.LinkTimeout`.
"""

from __future__ import annotations

import asyncio
import random
from typing import Final, Protocol, Unpack

from gateway.config.link import DEFAULT_RETRIES
from gateway.errors import GatewayError, LinkTimeout, ProtocolError, WriteOutcomeUnknown
from gateway.kinds.df1.config import DF1_DEFAULTS
from gateway.line_driver import LineDriver, LineDriverOptions, LineLease, Priority
from gateway.link_health import LineCounters, LineQuality
from gateway.protocols.df1.framing import DEFAULT_CHECKSUM, NEED_DATA, Checksum
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import (
    Df1Transactions,
    OutcomeUnknown,
    TransactionCounters,
    TransactionDone,
    TransactionEvent,
    TransactionFailed,
    TransactionRefused,
)
from gateway.protocols.df1.pccc import (
    DiagnosticStatus,
    DiagnosticStatusInfo,
    PcccReply,
    ProcessorFamily,
    Request,
)
from gateway.protocols.df1.pccc import is_write as pccc_is_write
from gateway.protocols.df1.pccc.codec import HEADER_SIZE
from gateway.protocols.df1.pccc.limits import MAX_DATA_BYTES
from gateway.transport import SerialSettings

__all__ = ["DF1_SETTINGS", "Df1Driver", "PcccLink", "WriteOutcomeUnknown", "transaction_result"]

#: DF1 full duplex default line settings (19200 8N1), kept with the link model's defaults.
DF1_SETTINGS: Final = DF1_DEFAULTS.settings

#: Characters of the longest DF1 frame: the header, 4 bytes of function and address, the most data
#: bytes of any family, DLE STX, DLE ETX and a CRC, and 28 for DLE doubling.
_LONGEST_FRAME: Final = HEADER_SIZE + 4 + MAX_DATA_BYTES + 6 + 28


class Df1Driver(LineDriver):
    """One DF1 full-duplex link to one node."""

    def __init__(
        self,
        url: str,
        *,
        settings: SerialSettings = DF1_SETTINGS,
        station: int = 1,
        source: int = 0,
        checksum: Checksum = DEFAULT_CHECKSUM,
        family: ProcessorFamily = ProcessorFamily.SLC5_04,
        timeout: float = DF1_DEFAULTS.timeout,
        ack_timeout: float | None = None,
        retries: int = DEFAULT_RETRIES,
        first_tns: int | None = None,
        **line: Unpack[LineDriverOptions],
    ) -> None:
        super().__init__(url, settings=settings, **line)
        self.checksum = checksum
        self.station = station
        self.source = source
        self.family = family
        self.timeout = timeout
        self.ack_timeout = ack_timeout or timeout
        self.retries = retries
        self.last_sts = 0
        # A random first TNS: a new session (CLI run, gateway restart) must not repeat the last
        # session's SRC/CMD/TNS, or the controller's duplicate detection would discard it.
        # (``first_tns`` fixes it for replays of recorded traffic.)
        self._core = self._new_core(random.randrange(1, 0x10000) if first_tns is None else first_tns)
        self._link_base = (0, 0, 0)  # enq, nak, bad frames of links before this one
        self._retransmissions_before = 0  # frames sent again after a DLE NAK, on links before this one
        self._waiting: dict[int, asyncio.Future[TransactionEvent]] = {}

    def _new_core(self, first_tns: int) -> Df1Transactions:
        link = Df1DataLink(
            checksum=self.checksum,
            # the ACK comes after our whole frame has gone out: allow for the longest frame's time
            ack_timeout=self.ack_timeout + _LONGEST_FRAME * self.char_time,
            enq_limit=self.retries,
            nak_limit=self.retries,
            char_time=self.char_time,
        )
        return Df1Transactions(
            link,
            station=self.station,
            source=self.source,
            reply_timeout=self.timeout + _LONGEST_FRAME * self.char_time,
            retries=self.retries,
            first_tns=first_tns,
        )

    @property
    def transaction_counters(self) -> TransactionCounters:
        """The transaction core's counters (read-backs, verified writes ...) since the last connect."""
        return self._core.counters

    # --- protocol hooks ---------------------------------------------------------------------

    def on_connect(self) -> None:
        old = self._core.link.counters
        enq, nak, bad = self._link_base
        self._link_base = (enq + old.enqs_sent, nak + old.naks_received, bad + old.bad_frames)
        self._retransmissions_before += old.retransmissions
        # a reconnect goes on from the last TNS (a new core: the line state is gone); a core that sent
        # nothing hands on the TNS it was given, so reconnects in a row never go back to an old one
        self._core = self._new_core(self._core.allocate_tns())
        for waiter in self._waiting.values():
            waiter.cancel()
        self._waiting.clear()

    def abort(self, exc: GatewayError) -> None:
        for waiter in self._waiting.values():
            if not waiter.done():
                waiter.set_exception(exc)

    def data_received(self, data: bytes) -> None:
        self._core.receive_data(data, asyncio.get_running_loop().time())
        self._pump()

    def _pump(self) -> None:
        core = self._core
        out = core.data_to_send()
        if out and self.connected:
            self.send(out)
        while (event := core.next_event()) is not NEED_DATA:
            waiter = self._waiting.pop(event.handle, None)
            if waiter is not None and not waiter.done():
                waiter.set_result(event)
        counters = core.link.counters
        enq, nak, bad = self._link_base
        self.counters.retries_by_kind["enq"] = enq + counters.enqs_sent
        self.counters.retries_by_kind["nak"] = nak + counters.naks_received
        self.counters.crc_errors = bad + counters.bad_frames
        self.follow_deadline(core.next_deadline())

    def on_deadline(self, now: float) -> None:
        self._core.handle_timeout(now)
        self._pump()

    def line_quality(self) -> LineQuality:
        """Bad frames received (BCC / CRC), timeouts, DLE NAKs received and the frames sent again after them."""
        counters = self.counters
        return LineQuality(check_errors=counters.crc_errors, timeouts=counters.timeouts,
                           naks=counters.retries_by_kind.get("nak", 0),
                           retransmits=self._retransmissions_before + self._core.link.counters.retransmissions)

    # --- transactions -----------------------------------------------------------------------

    async def _run(self, request: Request, name: str, is_write: bool) -> PcccReply:
        loop = asyncio.get_running_loop()
        core = self._core
        waiter: asyncio.Future[TransactionEvent] = loop.create_future()
        handle = core.start(request, loop.time(), write=is_write)
        self._waiting[handle] = waiter
        try:
            self._pump()
            event = await waiter
        except BaseException:
            if self._core is core:
                core.abandon("the request was cancelled", loop.time())  # the line is free again for the next one
                self._pump()
            raise
        finally:
            self._waiting.pop(handle, None)
        return transaction_result(self, event, name, getattr(request, "FNC", None))

    async def execute(self, request: Request, name: str = "", line: LineLease | None = None) -> PcccReply:
        """Send ``request`` and return the (successful) reply.  Writes (:func:`pccc_is_write`, the one
        authority) jump ahead of polls; with ``line`` (a write session's lease) it runs on the line
        the session holds."""
        label = name or type(request).__name__
        is_write = pccc_is_write(request)
        priority = Priority.WRITE if is_write else Priority.POLL
        return await self.submit(lambda: self._run(request, label, is_write), priority, line)

    async def probe(self) -> DiagnosticStatusInfo:
        reply = await self.execute(DiagnosticStatus(), "diagnostic status")
        return DiagnosticStatusInfo(reply.data)


class PcccLink(Protocol):
    """What :func:`transaction_result` updates: a full-duplex driver, or a station on a half-duplex line."""

    name: str
    counters: LineCounters
    last_sts: int

    def note_result(self, ok: bool, error: str = "") -> None: ...


def transaction_result(link: PcccLink, event: TransactionEvent, label: str, fnc: int | None) -> PcccReply:
    """The verdict of a transaction core as a result (the module docstring's table): the reply, or
    the exception.  Counts the transaction on ``link`` and judges the link by it (``note_result``)."""
    match event:
        case TransactionDone(reply=reply):
            link.note_result(True)
            return reply
        case TransactionRefused(reply=reply):
            link.note_result(True)
            link.counters.refusals += 1
            link.last_sts = reply.sts
            reply.raise_for_status(command=label, fnc=fnc)
            raise AssertionError("unreachable: a refusal has STS != 0")
        case OutcomeUnknown(reason=reason, shown=shown):
            link.counters.timeouts += 1
            message = f"link {link.name}: {label}: {reason}"
            link.note_result(False, message)
            raise WriteOutcomeUnknown(message, shown=shown)
        case TransactionFailed(reason=reason):
            link.counters.timeouts += 1
            message = f"link {link.name}: {label}: {reason}"
            link.note_result(False, message)
            raise LinkTimeout(message)
    raise AssertionError(f"unexpected transaction event {event!r}")


def check_reply_size(reply: PcccReply, size: int, what: str) -> bytes:
    if len(reply.data) != size:
        raise ProtocolError(f"{what}: {len(reply.data)} data bytes in the reply, {size} expected")
    return reply.data
