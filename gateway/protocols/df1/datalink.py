"""DF1 full-duplex data-link layer: one transmitter and one receiver working at the same time.

Manual: "S4516-DF1 Program Development Manual" §2.4 *How the Transmitter Operates*,
§2.5 *How the Receiver Operates* (after A-B 1770-6.5.16, chapter 2, full-duplex protocol).

Receiver::

    valid frame       -> DLE ACK, deliver (unless it duplicates the last delivered message)
    damaged frame     -> DLE NAK, drop                  (``bad_frame``: see :class:`BadFrameAnswer`)
    DLE ENQ           -> repeat the last response symbol (DLE NAK until a frame has been answered;
                         ``enq_answer``: see :class:`EnqAnswer`)

The manuals leave two receiver rules open (docs/develop/controller-variants.md); a controller-side link
(the simulator) picks a reading with ``bad_frame`` and ``enq_answer``, the host side keeps the
defaults (1770-6.5.16 ch. 2: NAK a damaged frame, answer ENQ with the last response).

Transmitter (one frame outstanding at a time)::

    IDLE --send--> AWAIT_ACK --DLE ACK--> IDLE (SendComplete)
                   AWAIT_ACK --DLE NAK--> AWAIT_ACK, the SAME frame again       (at most max_nak times)
                   AWAIT_ACK --timeout--> AWAIT_ACK, DLE ENQ                    (at most max_enq times)
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
application layer (PCCC reply timeout) covers that.  To narrow the window, the receiver treats
evidence of a truncated frame (DLE ETX without DLE STX, DLE ENQ inside a frame) as a damaged
frame, so its last response becomes DLE NAK.

Usage (the caller owns the port and the clock)::

    link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.2)
    handle = link.send(packet, now)
    port.write(link.data_to_send())
    link.receive_data(port.read(), now)
    while (event := link.next_event()) is not NEED_DATA: ...
    if (deadline := link.next_deadline()) is not None and now >= deadline:
        link.handle_timeout(now)

The output, the last response symbol, the transmit queue and the ACK timer are
:class:`~gateway.protocols.df1.full_duplex.FullDuplexStation`'s, shared with the target-mode
responder.  This module does no I/O.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass
from typing import Final

from gateway.errors import InvalidRequest
from gateway.frozen import frozen
from gateway.protocols.df1.framing import ACK_SYMBOL, DEFAULT_MAX_MESSAGE, NAK_SYMBOL, BadFrameReason, Checksum
from gateway.protocols.df1.full_duplex import FullDuplexCounters, FullDuplexStation, SendFailure, TxState
from gateway.protocols.df1.transitions import Table, TableEnum, Transition, require_complete, stay

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


class BadFrameAnswer(enum.Enum):
    """What a receiver does with a damaged frame (manual §2.5 says NAK; some stay silent)."""

    NAK = "nak"  #: DLE NAK at once (S4516-DF1 manual §2.5)
    SILENCE = "silence"  #: no answer now; the last response becomes DLE NAK (answered on DLE ENQ)
    IGNORE = "ignore"  #: as if nothing arrived: no answer, the last response is unchanged


class EnqAnswer(enum.Enum):
    """How a receiver answers DLE ENQ."""

    LAST_RESPONSE = "last"  #: repeat the last response symbol (1770-6.5.16 ch. 2)
    NAK = "nak"  #: always DLE NAK, "a request for retransmission" (S4516-DF1 manual §2.1)


@dataclass(slots=True)
class DataLinkCounters(FullDuplexCounters):
    """Link statistics, as in the DF1 full-duplex diagnostic counters (notes §7.7)."""

    messages_delivered: int = 0
    send_failures: int = 0


# ---------------------------------------------------------------------------------- transmitter


class TxInput(TableEnum):
    SEND = "a frame is queued"
    ACK = "DLE ACK received"
    NAK = "DLE NAK received, retransmissions left"
    NAK_LIMIT = "DLE NAK received, no retransmission left"
    TIMEOUT = "ACK timer expired, ENQs left"
    TIMEOUT_LIMIT = "ACK timer expired, no ENQ left"
    NAK_NOT_PROOF = "DLE NAK for a frame that must not run twice (not resent: the NAK is no proof)"
    CONFIRM = "the application layer saw the reply to the frame"
    STALE = "DLE ACK / DLE NAK before our frame left data_to_send(): an answer to an older frame"
    RESET = "the line was reset (port reopened)"


class TxAction(TableEnum):
    TRANSMIT = "send the next queued frame, start the ACK timer"
    COMPLETE = "report SendComplete"
    RETRANSMIT = "send the same frame again, restart the ACK timer"
    ENQUIRE = "send DLE ENQ, restart the ACK timer"
    FAIL_NAK = "report SendFailed(NAK_LIMIT)"
    FAIL_NO_RESPONSE = "report SendFailed(NO_RESPONSE)"
    FAIL_AMBIGUOUS = "report SendFailed(AMBIGUOUS_NAK)"
    RESET = "forget the line; report SendFailed(LINK_RESET) for the frame in flight and every queued one"
    IGNORE = "nothing (stray symbol or nothing to do)"


def _tx_table() -> Table[TxState, TxInput, TxAction]:
    T, In, A, IDLE, AWAIT = Transition, TxInput, TxAction, TxState.IDLE, TxState.AWAIT_ACK
    return {
        (IDLE, In.SEND): T(A.TRANSMIT, AWAIT),
        # nothing awaits an answer: a stray or late symbol, a confirm of a frame already done
        **stay(A.IGNORE, IDLE, In.ACK, In.NAK, In.NAK_LIMIT, In.NAK_NOT_PROOF, In.STALE, In.CONFIRM, In.TIMEOUT,
               In.TIMEOUT_LIMIT),
        (IDLE, In.RESET): T(A.RESET, IDLE),
        (AWAIT, In.SEND): T(A.IGNORE, AWAIT),  # queued: it goes when the frame in flight is done
        (AWAIT, In.STALE): T(A.IGNORE, AWAIT),
        (AWAIT, In.ACK): T(A.COMPLETE, IDLE),
        (AWAIT, In.NAK): T(A.RETRANSMIT, AWAIT),
        (AWAIT, In.NAK_LIMIT): T(A.FAIL_NAK, IDLE),
        (AWAIT, In.TIMEOUT): T(A.ENQUIRE, AWAIT),
        (AWAIT, In.TIMEOUT_LIMIT): T(A.FAIL_NO_RESPONSE, IDLE),
        (AWAIT, In.NAK_NOT_PROOF): T(A.FAIL_AMBIGUOUS, IDLE),
        (AWAIT, In.CONFIRM): T(A.COMPLETE, IDLE),
        (AWAIT, In.RESET): T(A.RESET, IDLE),
    }


#: The transmitter's state machine: (state, input) -> (action, next state).
TRANSITIONS: Final = _tx_table()
require_complete(TRANSITIONS, TxState, TxInput, "full-duplex transmitter")


# ----------------------------------------------------------------------------------------- link


class Df1DataLink(FullDuplexStation[DataLinkEvent, DataLinkCounters]):
    """Sans-I/O DF1 full-duplex data-link layer: frames and ACK/NAK/ENQ in, events and bytes out."""

    def __init__(
        self,
        *,
        checksum: Checksum = Checksum.BCC,
        ack_timeout: float = 1.0,
        max_enq: int = 3,
        max_nak: int = 3,
        duplicate_detect: bool = True,
        max_message: int = DEFAULT_MAX_MESSAGE,
        bad_frame: BadFrameAnswer = BadFrameAnswer.NAK,
        enq_answer: EnqAnswer = EnqAnswer.LAST_RESPONSE,
        char_time: float = 0.0,
        min_ack_timeout: float = 0.05,
    ) -> None:
        if ack_timeout <= 0:
            raise ValueError("ack_timeout must be positive")
        if max_enq < 0 or max_nak < 0:
            raise ValueError("max_enq and max_nak must not be negative")
        super().__init__(DataLinkCounters(), checksum=checksum, ack_timeout=ack_timeout, max_message=max_message)
        self.max_enq: Final = max_enq
        self.max_nak: Final = max_nak
        self.duplicate_detect: Final = duplicate_detect
        self.bad_frame: Final = bad_frame
        self.enq_answer: Final = enq_answer
        #: seconds per character on the line: a frame's ACK comes after its last character
        self.char_time: Final = char_time
        #: the ACK wait adapts to the peer's measured ACK times (see _ack_wait), never below this
        self.min_ack_timeout: Final = min(min_ack_timeout, ack_timeout)
        self._ack_times: deque[float] = deque(maxlen=32)
        # receiver
        self._last_delivered: bytes | None = None
        # transmitter
        self._tx_state = TxState.IDLE
        # After confirm(): the next DLE ACK / DLE NAK most likely answers the confirmed frame (its
        # ACK after its reply) or our last DLE ENQ, not the next frame: it is taken as stale.
        self._answer_owed = False

    # ------------------------------------------------------------------------------ public API

    @property
    def tx_state(self) -> TxState:
        return self._tx_state

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
        self._tx_input(TxInput.SEND, now)
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
            self._tx_input(TxInput.CONFIRM, now)

    def reset(self) -> None:
        """Forget the line state (port reopened): fail every queued frame, clear buffers."""
        self._tx_input(TxInput.RESET, 0.0)

    # ------------------------------------------------------------------------------- receiver

    def _is_duplicate(self, message: bytes) -> bool:
        """Same SRC, CMD and TNS as the last delivered message (1770-6.5.16 duplicate detection).

        Messages too short to hold a PCCC header are compared whole.
        """
        last = self._last_delivered
        if last is None:
            return False
        if len(message) < 6 or len(last) < 6:
            return message == last
        return message[1:3] == last[1:3] and message[4:6] == last[4:6]

    def _on_frame(self, message: bytes, now: float) -> None:
        if self.duplicate_detect and self._is_duplicate(message):
            self.counters.duplicates += 1
        else:
            self._last_delivered = message
            self.counters.messages_delivered += 1
            self._events.append(MessageReceived(message))
        self._respond(ACK_SYMBOL)

    def _on_bad_frame(self, reason: BadFrameReason, now: float) -> None:
        self.counters.bad_frames += 1
        if self.bad_frame is BadFrameAnswer.NAK:
            self._respond(NAK_SYMBOL)
        elif self.bad_frame is BadFrameAnswer.SILENCE:
            self._last_response = NAK_SYMBOL

    def _on_enq(self, aborted_frame: bool, now: float) -> None:
        if aborted_frame:
            self.counters.bad_frames += 1
            self._last_response = NAK_SYMBOL
        if self.enq_answer is EnqAnswer.NAK:
            self._respond(NAK_SYMBOL)
        else:
            self._respond(self._last_response)

    # ---------------------------------------------------------------------------- transmitter

    def _on_answer(self, nak: bool, now: float) -> None:
        # stale: it cannot answer the frame on the line (module docstring)
        stale = self._frame_unsent or self._answer_owed
        self._answer_owed = False
        if stale:
            self._tx_input(TxInput.STALE, now)
        elif not nak:
            if (self._tx_state is TxState.AWAIT_ACK and self._current is not None
                    and self._enq_count == 0 and self._nak_count == 0):
                self._ack_times.append(now - self._sent_at - len(self._current.frame) * self.char_time)
            self._tx_input(TxInput.ACK, now)
        elif self._current is not None and not self._current.idempotent:
            self._tx_input(TxInput.NAK_NOT_PROOF, now)
        elif self._nak_count >= self.max_nak:
            self._tx_input(TxInput.NAK_LIMIT, now)
        else:
            self._tx_input(TxInput.NAK, now)

    def _frame_queued(self, now: float) -> None:
        self._tx_input(TxInput.SEND, now)

    def _ack_timer_expired(self, now: float) -> None:
        limit = self._enq_count >= self.max_enq
        self._tx_input(TxInput.TIMEOUT_LIMIT if limit else TxInput.TIMEOUT, now)

    def _tx_input(self, tx_input: TxInput, now: float) -> None:
        action, self._tx_state, _ = TRANSITIONS[self._tx_state, tx_input]
        match action:  # TxAction.IGNORE: no case, nothing to do
            case TxAction.TRANSMIT:
                self._transmit(now)
            case TxAction.RETRANSMIT:
                self._retransmit(now)
            case TxAction.ENQUIRE:
                self._enquire(now)
            case TxAction.COMPLETE:
                self._finish(SendComplete(self._take_current().handle), now)
            case TxAction.FAIL_NAK:
                self._fail(SendFailure.NAK_LIMIT, now)
            case TxAction.FAIL_NO_RESPONSE:
                self._fail(SendFailure.NO_RESPONSE, now)
            case TxAction.FAIL_AMBIGUOUS:
                self._fail(SendFailure.AMBIGUOUS_NAK, now)
            case TxAction.RESET:
                self._reset_line()

    def _fail(self, reason: SendFailure, now: float) -> None:
        self.counters.send_failures += 1
        self._finish(SendFailed(self._take_current().handle, reason), now)

    def _reset_line(self) -> None:
        lost = self._forget_line()
        self._answer_owed = False
        self._last_delivered = None
        for frame in lost:
            self.counters.send_failures += 1
            self._events.append(SendFailed(frame.handle, SendFailure.LINK_RESET))

    def _ack_wait(self, length: int) -> float:
        """How long to wait for the answer to ``length`` bytes just sent: their time on the line
        plus 2 x the slowest of the last 32 ACKs (at least ``min_ack_timeout``), at most
        ``ack_timeout``.  An early DLE ENQ is harmless: it asks for the last response symbol, and
        the peer sends it after it has handled our whole frame (bytes keep their order)."""
        if len(self._ack_times) < 8:
            return self.ack_timeout
        wait = length * self.char_time + max(self.min_ack_timeout, 2 * max(self._ack_times))
        return min(self.ack_timeout, wait)
