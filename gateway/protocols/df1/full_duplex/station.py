"""The DF1 full-duplex station, in one role or the other: the host's data link and the target's responder.

Both run a receiver and a transmitter at the same time on one line (A-B 1770-6.5.16 chapter 4,
p. 4-2; S4516-DF1 manual §2.4 / §2.5): :class:`~gateway.protocols.df1.full_duplex.datalink.Df1DataLink` sends
commands and receives replies, :class:`~gateway.protocols.df1.full_duplex.responder.Df1Responder` receives
commands and sends replies.  :class:`FullDuplexStation` is the station; it does not know which
role it plays.  It runs the one receiver table and the one transmitter table of
:mod:`~gateway.protocols.df1.full_duplex.table`, and owns:

* one output, in order: every response symbol, frame and DLE ENQ enters it whole;
* the receiver's last response symbol (DLE NAK until a frame has been answered), which a DLE ENQ
  asks for again, and the header (SRC CMD TNS, :func:`~gateway.protocols.df1.pccc.codec.duplicate_key`)
  of the last message delivered, against which duplicates are told (p. 4-8 "LAST-HEADER");
* the transmitter's queue and its one frame on the line, with the frame's DLE NAK and DLE ENQ
  counts (``nak_limit``, ``enq_limit``) and its ACK timer (``next_deadline`` / ``handle_timeout``).
  While that frame still waits in :meth:`~FullDuplexStation.data_to_send` the peer cannot have
  answered it: a DLE ACK / DLE NAK arriving then belongs to an older frame (``STALE``).

The role is given by parameters and a few hooks: the receiver's reading of the open points
(``bad_frame``, ``enq_answer``), the DST it accepts (``accept_dst``), whether its sink is full
(:meth:`~FullDuplexStation._sink_full`), and what a delivered message, a duplicate, a frame
delivered or given up become (``_deliver``, ``_duplicate``, ``_sent``, ``_failed``: the role's events).

This module does no I/O.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from typing import Final, Generic, TypedDict, TypeVar

from gateway.frozen import frozen
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    DEFAULT_ACK_TIMEOUT,
    DEFAULT_CHECKSUM,
    DEFAULT_MAX_MESSAGE,
    ENQ_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    BadFrameReason,
    Checksum,
    EnqReceived,
    Frame,
    NakReceived,
    NeedData,
    Noise,
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.full_duplex.table import (
    TRANSITIONS,
    BadFrameAnswer,
    EnqAnswer,
    RxAction,
    RxInput,
    StationStep,
    TxAction,
    TxInput,
    TxState,
    receiver_table,
)
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, duplicate_key

__all__ = ["FullDuplexCounters", "FullDuplexStation", "QueuedFrame", "SendFailure", "StationOptions", "TxState"]

#: How many steps a station keeps in ``history``.
_HISTORY: Final = 64


class SendFailure(enum.Enum):
    """Why the transmitter gave up on a frame (S4516-DF1 sfunc11 return codes 3 and 4/5)."""

    NAK_LIMIT = "DLE NAK received after every retransmission"
    NO_RESPONSE = "no DLE ACK after every DLE ENQ"
    LINK_RESET = "the link was reset before the frame was acknowledged"
    #: the data link's frames that must not run twice (``datalink.py``); the responder sends none
    AMBIGUOUS_NAK = "DLE NAK for a frame that must not run twice: the peer may or may not have it"


_FAILURE: Final = {
    TxAction.FAIL_NAK: SendFailure.NAK_LIMIT,
    TxAction.FAIL_NO_RESPONSE: SendFailure.NO_RESPONSE,
    TxAction.FAIL_AMBIGUOUS: SendFailure.AMBIGUOUS_NAK,
}


@dataclass(slots=True)
class FullDuplexCounters:
    """The link statistics of both full-duplex stations (each adds its own)."""

    frames_sent: int = 0  #: frames written, retransmissions included
    frames_received: int = 0  #: frames with a valid check, duplicates included
    acks_sent: int = 0
    acks_received: int = 0
    naks_sent: int = 0
    naks_received: int = 0
    enqs_sent: int = 0
    enqs_received: int = 0
    retransmissions: int = 0  #: frames sent again after a DLE NAK
    bad_frames: int = 0  #: damaged, too short, too long, or cut by DLE ENQ
    duplicates: int = 0  #: frames ACKed but not delivered: they repeat the last one delivered
    not_for_us: int = 0  #: frames ACKed but not delivered because of their DST (``accept_dst``)
    sink_full: int = 0  #: new messages NAKed because the sink was full
    noise: int = 0  #: runs of bytes and symbols outside a frame that start nothing


@frozen
class QueuedFrame:
    """A message for the transmitter: the handle its event reports, the message and its frame."""

    handle: int
    message: bytes
    frame: bytes
    idempotent: bool = True  #: False: a DLE NAK is no proof the peer dropped it (``datalink.py``)


EventT = TypeVar("EventT")
CountersT = TypeVar("CountersT", bound=FullDuplexCounters)


class StationOptions(TypedDict, total=False):
    """The keywords of a station (:class:`FullDuplexStation`) its two roles share: the master's data link
    (``datalink.DataLink``) and the target's responder (``responder.Responder``)."""

    checksum: Checksum
    ack_timeout: float
    max_message: int
    nak_limit: int
    enq_limit: int
    duplicate_detect: bool


class FullDuplexStation(ABC, Generic[EventT, CountersT]):
    """One full-duplex station: its receiver and transmitter tables, output, timer (module docstring)."""

    def __init__(
        self,
        counters: CountersT,
        *,
        checksum: Checksum = DEFAULT_CHECKSUM,
        ack_timeout: float = DEFAULT_ACK_TIMEOUT,
        max_message: int = DEFAULT_MAX_MESSAGE,
        nak_limit: int = 3,
        enq_limit: int = 3,
        duplicate_detect: bool = True,
        accept_dst: int | None = None,
        bad_frame: BadFrameAnswer = BadFrameAnswer.NAK,
        enq_answer: EnqAnswer = EnqAnswer.LAST_RESPONSE,
    ) -> None:
        if ack_timeout <= 0:
            raise ValueError("ack_timeout must be positive")
        if nak_limit < 0 or enq_limit < 0:
            raise ValueError("nak_limit and enq_limit must not be negative")
        if max_message < HEADER_SIZE:
            raise ValueError(f"max_message must be at least {HEADER_SIZE}")
        self.checksum: Final = checksum
        self.ack_timeout: Final = ack_timeout
        self.max_message: Final = max_message
        #: DLE NAKs a frame may get and still be sent again; DLE ENQs sent for one frame (p. 4-6: 3)
        self.nak_limit: Final = nak_limit
        self.enq_limit: Final = enq_limit
        self.duplicate_detect: Final = duplicate_detect
        #: deliver only messages with this DST (None: any; p. 4-8 does not look at DST)
        self.accept_dst: Final = accept_dst
        self.bad_frame: Final = bad_frame
        self.enq_answer: Final = enq_answer
        self.receiver: Final = receiver_table(bad_frame, enq_answer)
        self.counters = counters
        #: the last steps taken, newest last
        self.history: deque[StationStep] = deque(maxlen=_HISTORY)
        self._decoder = FrameDecoder(checksum, max_message=max_message, report_noise=True)
        self._events: deque[EventT] = deque()
        self._out = bytearray()
        # receiver
        self._last_response = NAK_SYMBOL
        self._last_header: tuple[int, int, int] | None = None  #: SRC CMD TNS of the last delivered
        # transmitter
        self._tx_state = TxState.IDLE
        self._queue: deque[QueuedFrame] = deque()
        self._current: QueuedFrame | None = None
        # the DLE NAK and DLE ENQ counts of the frame on the line, zeroed as each frame goes on
        # the line (_transmit); with no frame on the line what they decide is ignored
        self._nak_count = 0
        self._enq_count = 0
        self._deadline: float | None = None
        self._sent_at = 0.0  #: when the current frame was last written
        self._next_handle = 1
        # True while the current frame still sits in the output buffer: the peer cannot have
        # answered it yet, so a DLE ACK / DLE NAK arriving then belongs to an older frame.
        self._frame_unsent = False
        # After the data link's confirm(): the next DLE ACK / DLE NAK most likely answers the
        # confirmed frame or our last DLE ENQ, not the next frame: it is taken as stale.
        self._answer_owed = False

    # ------------------------------------------------------------------------------ public API

    @property
    def tx_state(self) -> TxState:
        return self._tx_state

    def next_event(self) -> EventT | NeedData:
        """The next event, or ``NEED_DATA``."""
        if self._events:
            return self._events.popleft()
        return NEED_DATA

    def data_to_send(self) -> bytes:
        """Bytes to write to the line (response symbols, frames, DLE ENQ), in order."""
        out = bytes(self._out)
        self._out.clear()
        self._frame_unsent = False
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`handle_timeout` must be called, or None without a running timer."""
        return self._deadline

    def handle_timeout(self, now: float) -> None:
        """Call at or after :meth:`next_deadline`; early calls do nothing."""
        if self._deadline is None or now < self._deadline:
            return
        self._tx(TxInput.TIMEOUT_LIMIT if self._enq_count >= self.enq_limit else TxInput.TIMEOUT, now)

    # ------------------------------------------------------------------------------ the role

    @abstractmethod
    def _deliver(self, message: bytes, now: float) -> None:
        """A new message, ACKed (its header is remembered): the role's event."""

    def _duplicate(self, message: bytes, now: float) -> None:
        """A duplicate of the last message delivered, ACKed and counted, not delivered."""

    def _sink_full(self) -> bool:
        """Whether the message sink has no room for a new message (p. 4-8: then DLE NAK)."""
        return False

    @abstractmethod
    def _sent(self, frame: QueuedFrame, now: float) -> None:
        """``frame`` was delivered (DLE ACK, or confirmed): the role's event."""

    @abstractmethod
    def _failed(self, frame: QueuedFrame, reason: SendFailure) -> None:
        """``frame`` was given up: the role's event."""

    # ------------------------------------------------------------------------------ receiver

    def _receive(self, data: bytes, now: float) -> None:
        """Feed ``data`` to the decoder and handle what it reports, in order."""
        self._decoder.feed(data)
        while (event := self._decoder.next_event()) is not NEED_DATA:
            match event:
                case Frame(message=message):
                    self.counters.frames_received += 1
                    self._rx(self._classify(message), now, message)
                case BadFrame(reason=reason):
                    # DLE ETX without DLE STX is a false symbol outside a frame, not a frame (p. 4-8)
                    self._rx(RxInput.NOISE if reason is BadFrameReason.MISSING_START else RxInput.BAD_FRAME, now)
                case Noise():
                    self._rx(RxInput.NOISE, now)
                case AckReceived():
                    self.counters.acks_received += 1
                    self._on_answer(False, now)
                case NakReceived():
                    self.counters.naks_received += 1
                    self._on_answer(True, now)
                case EnqReceived(aborted_frame=aborted):
                    self.counters.enqs_received += 1
                    self._rx(RxInput.ENQ_IN_FRAME if aborted else RxInput.ENQ, now)

    def _classify(self, message: bytes) -> RxInput:
        """A good frame's input (p. 4-8: too small, then the header, then the sink)."""
        if len(message) < HEADER_SIZE:
            return RxInput.BAD_FRAME
        if self.accept_dst is not None and message[0] != self.accept_dst:
            return RxInput.NOT_FOR_US
        if self.duplicate_detect and duplicate_key(message) == self._last_header:
            return RxInput.DUPLICATE
        if self._sink_full():
            return RxInput.SINK_FULL
        return RxInput.MESSAGE

    def _rx(self, what: RxInput, now: float, message: bytes = b"") -> None:
        action = self.receiver[what]
        self.history.append(StationStep(self._tx_state, what, action, self._tx_state))
        counters = self.counters
        match action:  # RxAction.IGNORE: no case, nothing to do
            case RxAction.DELIVER:
                self._respond(ACK_SYMBOL)
                self._last_header = duplicate_key(message)
                self._deliver(message, now)
            case RxAction.ACK_DUPLICATE:
                self._respond(ACK_SYMBOL)
                counters.duplicates += 1
                self._duplicate(message, now)
            case RxAction.ACK_ONLY:
                self._respond(ACK_SYMBOL)
                counters.not_for_us += 1
            case RxAction.REFUSE:
                self._respond(NAK_SYMBOL)
                counters.sink_full += 1
            case RxAction.REJECT:
                self._respond(NAK_SYMBOL)
            case RxAction.LAST_NAK:
                self._last_response = NAK_SYMBOL
            case RxAction.ANSWER_ENQ:
                self._respond(self._last_response)
            case RxAction.ANSWER_NAK:
                self._respond(NAK_SYMBOL)
        if what is RxInput.NOISE:
            counters.noise += 1
        elif what is RxInput.BAD_FRAME or what is RxInput.ENQ_IN_FRAME:
            counters.bad_frames += 1

    def _respond(self, symbol: bytes) -> None:
        """Send a response symbol; it becomes the last response."""
        self._last_response = symbol
        self._out += symbol
        if symbol == ACK_SYMBOL:
            self.counters.acks_sent += 1
        else:
            self.counters.naks_sent += 1

    # ------------------------------------------------------------------------------ transmitter

    def _enqueue(self, message: bytes, *, idempotent: bool = True) -> int:
        """Queue ``message`` for the transmitter; its handle.  The caller then feeds ``SEND``."""
        handle = self._next_handle
        self._next_handle += 1
        self._queue.append(QueuedFrame(handle, message, encode_frame(message, self.checksum), idempotent))
        return handle

    def _on_answer(self, nak: bool, now: float) -> None:
        """The peer's DLE ACK, or DLE NAK with ``nak``: the answer to our frame, unless stale."""
        stale = self._frame_unsent or self._answer_owed
        self._answer_owed = False
        if stale:
            self._tx(TxInput.STALE, now)
        elif not nak:
            self._tx(TxInput.ACK, now)
        elif self._current is not None and not self._current.idempotent:
            self._tx(TxInput.NAK_NOT_PROOF, now)
        elif self._tx_state is TxState.AWAIT_ACK and self._nak_count >= self.nak_limit:
            self._tx(TxInput.NAK_LIMIT, now)
        else:
            self._tx(TxInput.NAK, now)

    def _tx(self, what: TxInput, now: float) -> None:
        state = self._tx_state
        action, next_state, _ = TRANSITIONS[state, what]
        self.history.append(StationStep(state, what, action, next_state))
        self._tx_state = next_state
        match action:  # TxAction.IGNORE: no case, nothing to do
            case TxAction.TRANSMIT:
                self._current = self._queue.popleft()
                self._nak_count = self._enq_count = 0
                self._write_current(now)
            case TxAction.RETRANSMIT:
                self._nak_count += 1
                self.counters.retransmissions += 1
                self._write_current(now)
            case TxAction.ENQUIRE:
                self._enq_count += 1
                self.counters.enqs_sent += 1
                self._out += ENQ_SYMBOL
                self._deadline = now + self._ack_wait(len(ENQ_SYMBOL))
            case TxAction.COMPLETE:
                self._sent(self._take_current(), now)
                self._next(now)
            case TxAction.FAIL_NAK | TxAction.FAIL_NO_RESPONSE | TxAction.FAIL_AMBIGUOUS:
                self._failed(self._take_current(), _FAILURE[action])
                self._next(now)
            case TxAction.RESET:
                for frame in self._forget_line():
                    self._failed(frame, SendFailure.LINK_RESET)

    def _next(self, now: float) -> None:
        if self._queue:
            self._tx(TxInput.SEND, now)

    def _write_current(self, now: float) -> None:
        assert self._current is not None
        frame = self._current.frame
        self._out += frame
        self._frame_unsent = True
        self.counters.frames_sent += 1
        self._sent_at = now
        self._deadline = now + self._ack_wait(len(frame))

    def _ack_wait(self, length: int) -> float:
        """How long to wait for the answer to ``length`` bytes just sent."""
        return self.ack_timeout

    def _take_current(self) -> QueuedFrame:
        """The frame on the line is done (answered or given up); its timer stops."""
        current = self._current
        assert current is not None
        self._current = None
        self._deadline = None
        self._frame_unsent = False
        return current

    def _forget_line(self) -> list[QueuedFrame]:
        """Forget the line (port reopened): output, decoder, timer, last response and last header;
        the frames queued or on the line, which are lost, the one on the line first."""
        lost = [self._current] if self._current is not None else []
        lost += self._queue
        self._queue.clear()
        self._current = None
        self._deadline = None
        self._frame_unsent = False
        self._answer_owed = False
        self._decoder.reset()
        self._out.clear()
        self._last_response = NAK_SYMBOL
        self._last_header = None
        return lost
