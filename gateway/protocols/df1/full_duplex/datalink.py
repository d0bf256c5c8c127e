"""DF1 full-duplex data-link layer: one transmitter and one receiver working at the same time.

Manual: "S4516-DF1 Program Development Manual" §2.4 *How the Transmitter Operates*,
§2.5 *How the Receiver Operates* (after A-B 1770-6.5.16, chapter 2, full-duplex protocol).

The receiver and the transmitter are the full-duplex station's
(:class:`~gateway.protocols.df1.full_duplex.FullDuplexStation`, its tables in
:mod:`~gateway.protocols.df1.full_duplex.table`), shared with the target's responder: a good frame
is ACKed and delivered unless it duplicates the last one delivered, a damaged one (or one of fewer
than 6 bytes) NAKed, a DLE ENQ answered with the last response symbol, and noise or a DLE ETX
without DLE STX outside a frame makes the last response DLE NAK (1770-6.5.16 p. 4-8).  The data
link's sink is never full, and it delivers whatever the DST.

The manuals leave two receiver rules open (docs/develop/controller-variants.md); a controller-side link
(the simulator) picks a reading with ``bad_frame`` and ``enq_answer``, the host side keeps the
defaults (p. 4-8: NAK a damaged frame, answer ENQ with the last response).

Transmitter (one frame outstanding at a time)::

    IDLE --send--> AWAIT_ACK --DLE ACK--> IDLE (SendComplete)
                   AWAIT_ACK --DLE NAK--> AWAIT_ACK, the SAME frame again       (at most nak_limit times)
                   AWAIT_ACK --timeout--> AWAIT_ACK, DLE ENQ                    (at most enq_limit times)
                   then                              IDLE (SendFailed)
                   AWAIT_ACK --confirm()--> IDLE (SendComplete): the application saw the reply, so
                                            the peer has the frame (its ACK may come later or never);
                                            the next DLE ACK / NAK is taken as the answer owed to that
                                            frame or to our last DLE ENQ, never as the next frame's

A frame sent with ``idempotent=False`` (a write) is never retransmitted: a DLE NAK is not proof
that the peer discarded it.  Under one reading of the manual (:attr:`EnqAnswer.NAK`) the NAK
answering our DLE ENQ says nothing about the frame, and on a noisy line a DLE ACK can arrive as
a DLE NAK (response symbols carry no check).  With duplicate detection off (S4516-DF1 manual
§5.2) a second copy of a write that did arrive would run again.  The link reports
:attr:`SendFailure.AMBIGUOUS_NAK` and the application layer reads the target back.  Frames
sent with ``idempotent=True`` (reads) are retransmitted on DLE NAK as §2.4 describes.

Once a frame has been ACKed the link reports :class:`SendComplete` and never sends it again.
A DLE ACK / DLE NAK that arrives while the current frame has not yet been taken by
:meth:`Df1DataLink.data_to_send` answers an older frame (for instance the second ACK of a duplicated
frame) and is ignored, so it cannot complete a frame the peer never saw.
Known limit of the protocol: if a whole frame is lost and the peer answers our ENQ with the ACK
of the previous frame, the frame is reported complete although it never arrived; the
application layer (PCCC reply timeout) covers that.  The receiver narrows the window: evidence of
a truncated frame (DLE ETX without DLE STX, DLE ENQ inside a frame) makes its last response DLE NAK.

Usage (the caller owns the port and the clock)::

    link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.2)
    handle = link.send(packet, now)
    port.write(link.data_to_send())
    link.receive_data(port.read(), now)
    while (event := link.next_event()) is not NEED_DATA: ...
    if (deadline := link.next_deadline()) is not None and now >= deadline:
        link.handle_timeout(now)

This module does no I/O.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Final, Unpack

from gateway.errors import InvalidRequest
from gateway.frozen import frozen
from gateway.protocols.df1.full_duplex.station import (
    FullDuplexCounters,
    FullDuplexStation,
    QueuedFrame,
    SendFailure,
    StationOptions,
)
from gateway.protocols.df1.full_duplex.table import (
    TRANSITIONS,
    BadFrameAnswer,
    EnqAnswer,
    TxAction,
    TxInput,
    TxState,
)

__all__ = [
    "TRANSITIONS",
    "BadFrameAnswer",
    "DataLinkCounters",
    "DataLinkEvent",
    "Df1DataLink",
    "EnqAnswer",
    "MessageReceived",
    "SendComplete",
    "SendFailed",
    "SendFailure",
    "TxAction",
    "TxInput",
    "TxState",
]


# --------------------------------------------------------------------------------------- events


@frozen
class MessageReceived:
    """A new application message (PCCC packet, DST .. data) arrived and was ACKed."""

    payload: bytes


@frozen
class SendComplete:
    """The frame queued as ``handle`` was acknowledged with DLE ACK."""

    handle: int


@frozen
class SendFailed:
    """The frame queued as ``handle`` was not acknowledged; ``reason`` says why."""

    handle: int
    reason: SendFailure


DataLinkEvent = MessageReceived | SendComplete | SendFailed


@dataclass(slots=True)
class DataLinkCounters(FullDuplexCounters):
    """Link statistics, as in the DF1 full-duplex diagnostic counters (notes §7.7)."""

    messages_delivered: int = 0
    send_failures: int = 0


# ----------------------------------------------------------------------------------------- link


class Df1DataLink(FullDuplexStation[DataLinkEvent, DataLinkCounters]):
    """Sans-I/O DF1 full-duplex data-link layer: frames and ACK/NAK/ENQ in, events and bytes out."""

    def __init__(
        self,
        *,
        bad_frame: BadFrameAnswer = BadFrameAnswer.NAK,
        enq_answer: EnqAnswer = EnqAnswer.LAST_RESPONSE,
        char_time: float = 0.0,
        min_ack_timeout: float = 0.05,
        **station: Unpack[StationOptions],
    ) -> None:
        super().__init__(DataLinkCounters(), bad_frame=bad_frame, enq_answer=enq_answer, **station)
        #: seconds per character on the line: a frame's ACK comes after its last character
        self.char_time: Final = char_time
        #: the ACK wait adapts to the peer's measured ACK times (see _ack_wait), never below this
        self.min_ack_timeout: Final = min(min_ack_timeout, self.ack_timeout)
        self._ack_times: deque[float] = deque(maxlen=32)

    # ------------------------------------------------------------------------------ public API

    @property
    def pending(self) -> int:
        """Frames queued or awaiting their ACK."""
        return len(self._queue) + (self._current is not None)

    def send(self, payload: bytes, now: float, *, idempotent: bool = True) -> int:
        """Queue ``payload`` (a PCCC packet) for transmission; returns its handle.

        ``idempotent=False`` for a command that must not run twice (a write): see the module doc.
        """
        if not payload:
            raise InvalidRequest("DF1: cannot send an empty message")
        if len(payload) > self.max_message:
            raise InvalidRequest(f"DF1: message of {len(payload)} bytes exceeds {self.max_message}")
        handle = self._enqueue(bytes(payload), idempotent=idempotent)
        self._tx(TxInput.SEND, now)
        return handle

    def receive_data(self, data: bytes, now: float) -> None:
        """Feed bytes read from the port."""
        self._receive(data, now)

    def confirm(self, handle: int, now: float) -> None:
        """The application layer has the reply to frame ``handle``: the peer received it.

        A reply can come before the frame's DLE ACK (or instead of it, when the ACK is lost);
        completing the frame then stops DLE ENQ and, above all, any retransmission of it.
        Does nothing unless ``handle`` is the frame awaiting its ACK.
        """
        if self._current is not None and self._current.handle == handle and not self._frame_unsent:
            self._answer_owed = True
            self._tx(TxInput.CONFIRM, now)

    def reset(self) -> None:
        """Forget the line state (port reopened): fail every queued frame, clear buffers."""
        self._tx(TxInput.RESET, 0.0)

    # ------------------------------------------------------------------------------ the role

    def _deliver(self, message: bytes, now: float) -> None:
        self.counters.messages_delivered += 1
        self._events.append(MessageReceived(message))

    def _sent(self, frame: QueuedFrame, now: float) -> None:
        self._events.append(SendComplete(frame.handle))

    def _failed(self, frame: QueuedFrame, reason: SendFailure) -> None:
        self.counters.send_failures += 1
        self._events.append(SendFailed(frame.handle, reason))

    def _on_answer(self, nak: bool, now: float) -> None:
        current = self._current
        if (not nak and not self._frame_unsent and not self._answer_owed and current is not None
                and self._tx_state is TxState.AWAIT_ACK and self._enq_count == 0 and self._nak_count == 0):
            self._ack_times.append(now - self._sent_at - len(current.frame) * self.char_time)
        super()._on_answer(nak, now)

    def _ack_wait(self, length: int) -> float:
        """How long to wait for the answer to ``length`` bytes just sent: their time on the line
        plus 2 x the slowest of the last 32 ACKs (at least ``min_ack_timeout``), at most
        ``ack_timeout``.  An early DLE ENQ is harmless: it asks for the last response symbol, and
        the peer sends it after it has handled our whole frame (bytes keep their order)."""
        if len(self._ack_times) < 8:
            return self.ack_timeout
        wait = length * self.char_time + max(self.min_ack_timeout, 2 * max(self._ack_times))
        return min(self.ack_timeout, wait)
