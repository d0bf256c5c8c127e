"""Asyncio driver for DF1 full duplex + PCCC (SLC 500, PLC-5): thin around the sans-I/O core.

One transaction: allocate a TNS, queue the command packet on the ``Df1Link`` (which frames it,
waits for DLE ACK, sends DLE ENQ on timeout and retransmits on DLE NAK), wait for the link's
verdict, then for the reply with the same TNS and CMD | 0x40.

Exactly-once writes: a write the link could not deliver because every copy was NAKed was
never accepted, and is sent again as a new transaction.  A write whose frame the controller
acknowledged is never sent again: if its reply does not come, the caller gets
``WriteOutcomeUnknown`` (a ``LinkTimeout``) and may read back to find out.  Reads are simply
retried.
"""

from __future__ import annotations

import asyncio
import random
from pathlib import Path
from typing import Final

from gateway.drivers.base import LinkDriver, OpenStream, Priority
from gateway.errors import ControllerRefused, GatewayError, LinkTimeout, ProtocolError, format_seconds
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.link import Df1Link, MessageReceived, SendComplete, SendFailed, SendFailure
from gateway.protocols.df1.pccc import (
    DiagnosticStatus,
    DiagnosticStatusInfo,
    PcccFormatError,
    PcccReply,
    ProcessorFamily,
    Request,
    TnsAllocator,
    decode_reply,
    encode_command,
)
from gateway.transport import SerialSettings, open_stream

__all__ = ["DF1_SETTINGS", "Df1Driver", "WriteOutcomeUnknown"]

#: DF1 full duplex default line settings: 19200 baud 8N1.
DF1_SETTINGS: Final = SerialSettings(baudrate=19200, bytesize=8, parity="N", stopbits=1)

_WRITE_TYPES: Final = ("ProtectedTypedLogicalWrite", "ProtectedTypedLogicalMaskedWrite", "TypedWrite",
                       "WordRangeWrite", "SetProcessorMode")


#: Characters of the longest DF1 frame: 6 header + 4 + 236 data bytes, framing, CRC, some DLE doubling.
_LONGEST_FRAME: Final = 280


class WriteOutcomeUnknown(LinkTimeout):
    """The controller acknowledged the write's frame but its reply never came."""


class Df1Driver(LinkDriver):
    """One DF1 full-duplex link to one node."""

    def __init__(
        self,
        url: str,
        *,
        name: str = "",
        settings: SerialSettings = DF1_SETTINGS,
        checksum: Checksum = Checksum.CRC,
        station: int = 1,
        source: int = 0,
        family: ProcessorFamily = ProcessorFamily.SLC5_04,
        timeout: float = 1.0,
        ack_timeout: float | None = None,
        retries: int = 3,
        trace: Path | None = None,
        reconnect_min: float = 0.5,
        reconnect_max: float = 30.0,
        opener: OpenStream = open_stream,
    ) -> None:
        super().__init__(
            url,
            name=name,
            settings=settings,
            trace=trace,
            reconnect_min=reconnect_min,
            reconnect_max=reconnect_max,
            opener=opener,
        )
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
        self._tns = TnsAllocator(random.randrange(1, 0x10000))
        self._link = self._new_link()
        self._link_base = (0, 0, 0)  # enq, nak, bad frames of links before this one
        self._sends: dict[int, asyncio.Future[SendFailure | None]] = {}
        self._replies: dict[int, asyncio.Future[PcccReply]] = {}
        self._timer: asyncio.TimerHandle | None = None

    def _new_link(self) -> Df1Link:
        return Df1Link(
            checksum=self.checksum,
            # the ACK comes after our whole frame has gone out: allow for the longest frame's time
            ack_timeout=self.ack_timeout + _LONGEST_FRAME * self.char_time,
            max_enq=self.retries,
            max_nak=self.retries,
        )

    # --- protocol hooks ---------------------------------------------------------------------

    def on_connect(self) -> None:
        old = self._link.counters
        enq, nak, bad = self._link_base
        self._link_base = (enq + old.enqs_sent, nak + old.naks_received, bad + old.bad_frames)
        self._link = self._new_link()
        for send in self._sends.values():
            send.cancel()
        for reply in self._replies.values():
            reply.cancel()
        self._sends.clear()
        self._replies.clear()

    def abort(self, exc: GatewayError) -> None:
        for send in self._sends.values():
            if not send.done():
                send.set_exception(exc)
        for reply in self._replies.values():
            if not reply.done():
                reply.set_exception(exc)
                reply.exception()  # awaited only after its send: mark it retrieved either way

    def data_received(self, data: bytes) -> None:
        self._link.receive_data(data, asyncio.get_running_loop().time())
        self._pump()

    def _pump(self) -> None:
        link = self._link
        out = link.data_to_send()
        if out:
            self.send(out)
        while True:
            event = link.next_event()
            if isinstance(event, MessageReceived):
                self._on_message(event.payload)
            elif isinstance(event, SendComplete):
                self._settle(event.handle, None)
            elif isinstance(event, SendFailed):
                self._settle(event.handle, event.reason)
            else:
                break
        counters = link.counters
        enq, nak, bad = self._link_base
        self.counters.enq_sent = enq + counters.enqs_sent
        self.counters.nak_received = nak + counters.naks_received
        self.counters.crc_errors = bad + counters.bad_frames
        self._arm_timer()

    def _settle(self, handle: int, outcome: SendFailure | None) -> None:
        future = self._sends.pop(handle, None)
        if future is not None and not future.done():
            future.set_result(outcome)

    def _on_message(self, payload: bytes) -> None:
        try:
            reply = decode_reply(payload)
        except PcccFormatError:
            return  # a command addressed to us, or junk that passed the check: not ours to answer
        future = self._replies.pop(reply.tns, None)
        if future is not None and not future.done():
            future.set_result(reply)

    def _arm_timer(self) -> None:
        deadline = self._link.next_deadline()
        timer = self._timer
        if timer is not None:
            if deadline is not None and timer.when() == deadline:
                return
            timer.cancel()
            self._timer = None
        if deadline is not None:
            self._timer = asyncio.get_running_loop().call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        if self.connected:
            self._link.handle_timeout(asyncio.get_running_loop().time())
            self._pump()

    # --- transactions -----------------------------------------------------------------------

    async def _once(self, request: Request, name: str) -> PcccReply | SendFailure:
        """One attempt: the link's verdict (a SendFailure) or the reply."""
        loop = asyncio.get_running_loop()
        tns = self._tns.allocate()
        packet = encode_command(request, dst=self.station, src=self.source, tns=tns)
        reply: asyncio.Future[PcccReply] = loop.create_future()
        sent: asyncio.Future[SendFailure | None] = loop.create_future()
        self._replies[tns] = reply
        try:
            handle = self._link.send(packet, loop.time())
            self._sends[handle] = sent
            self._pump()
            # The link's own timers bound this wait (ACK timeout x (ENQ retries + 1)).
            failure = await sent
            if failure is not None:
                return failure
            async with asyncio.timeout(self.timeout + _LONGEST_FRAME * self.char_time):
                return await reply
        finally:
            self._replies.pop(tns, None)
            self._tns.release(tns)

    async def _transaction(self, request: Request, name: str) -> PcccReply:
        is_write = type(request).__name__ in _WRITE_TYPES
        attempts = self.retries + 1
        for attempt in range(attempts):
            try:
                result = await self._once(request, name)
            except TimeoutError:
                self.counters.timeouts += 1
                if is_write:
                    raise WriteOutcomeUnknown(
                        f"link {self.name}: {name}: the controller took the frame but its reply did not come "
                        f"within {format_seconds(self.timeout)} s; the write may or may not have been applied"
                    ) from None
                continue
            if isinstance(result, SendFailure):
                self.counters.timeouts += 1
                if is_write and result is not SendFailure.NAK_LIMIT:
                    raise WriteOutcomeUnknown(f"link {self.name}: {name}: {result.value}; outcome unknown")
                if attempt + 1 < attempts:
                    continue
                raise LinkTimeout(f"link {self.name}: {name}: {result.value}")
            if not result.ok:
                self.counters.refusals += 1
                self.last_sts = result.sts
                result.raise_for_status(command=name, fnc=getattr(request, "FNC", None))
            return result
        raise LinkTimeout(f"link {self.name}: no reply to {name} after {attempts} tries of {self.timeout:g} s")

    async def _run(self, request: Request, name: str) -> PcccReply:
        try:
            reply = await self._transaction(request, name)
        except ControllerRefused:
            self.note_result(True)
            raise
        except GatewayError as exc:
            self.note_result(False, str(exc))
            raise
        self.note_result(True)
        return reply

    async def execute(self, request: Request, name: str = "", *, write: bool | None = None) -> PcccReply:
        """Send ``request`` and return the (successful) reply.  Writes jump ahead of polls."""
        label = name or type(request).__name__
        is_write = type(request).__name__ in _WRITE_TYPES if write is None else write
        priority = Priority.WRITE if is_write else Priority.POLL
        return await self.submit(lambda: self._run(request, label), priority)

    async def probe(self) -> DiagnosticStatusInfo:
        reply = await self.execute(DiagnosticStatus(), "diagnostic status")
        return DiagnosticStatusInfo(reply.data)


def check_reply_size(reply: PcccReply, size: int, what: str) -> bytes:
    if len(reply.data) != size:
        raise ProtocolError(f"{what}: {len(reply.data)} data bytes in the reply, {size} expected")
    return reply.data
