"""What the two DF1 full-duplex stations share: the host's data link and the target's responder.

Both run a receiver and a transmitter at the same time on one line (A-B 1770-6.5.16 chapter 2 and
p. 4-2; S4516-DF1 manual §2.4 / §2.5): :class:`~gateway.protocols.df1.datalink.Df1DataLink` sends
commands and receives replies, :class:`~gateway.protocols.df1.responder.Df1Responder` receives
commands and sends replies.  :class:`FullDuplexStation` is the part they have in common:

* one output, in order: every response symbol, frame and DLE ENQ enters it whole;
* the receiver's last response symbol (DLE NAK until a frame has been answered), which a DLE ENQ
  asks for again;
* the transmitter's queue and its one frame on the line (:class:`TxState`), with the frame's DLE
  NAK and DLE ENQ counts and its ACK timer (``next_deadline`` / ``handle_timeout``), and why it
  gives a frame up (:class:`SendFailure`).  While that frame still waits in
  :meth:`~FullDuplexStation.data_to_send` the peer cannot have answered it: a DLE ACK / DLE NAK
  arriving then belongs to an older frame.

The base counts what the decoder reports and hands it on (``_on_frame``, ``_on_bad_frame``,
``_on_answer`` for DLE ACK / DLE NAK, ``_on_enq``); each station keeps its own receiver rules and
transmitter table, and tells the base how a queued frame and an expired ACK timer enter that
table (``_frame_queued``, ``_ack_timer_expired``).

This module does no I/O.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from typing import Final, Generic, TypeVar

from gateway.frozen import frozen
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
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
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.transitions import TableEnum

__all__ = ["FullDuplexCounters", "FullDuplexStation", "QueuedFrame", "SendFailure", "TxState"]


class TxState(TableEnum):
    """The transmitter's state, one frame on the line at a time (S4516-DF1 manual §2.4;
    1770-6.5.16 p. 4-6).  Both stations' transition tables are keyed by it."""

    IDLE = "no frame of ours on the line"
    AWAIT_ACK = "our frame sent, waiting for its DLE ACK"


class SendFailure(enum.Enum):
    """Why the transmitter gave up on a frame (S4516-DF1 sfunc11 return codes 3 and 4/5)."""

    NAK_LIMIT = "DLE NAK received after every retransmission"
    NO_RESPONSE = "no DLE ACK after every DLE ENQ"
    LINK_RESET = "the link was reset before the frame was acknowledged"
    #: the data link's frames that must not run twice (``datalink.py``); the responder sends none
    AMBIGUOUS_NAK = "DLE NAK for a frame that must not run twice: the peer may or may not have it"


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
    bad_frames: int = 0
    duplicates: int = 0  #: frames ACKed but not delivered: they repeat the last one delivered


@frozen
class QueuedFrame:
    """A message for the transmitter: the handle its event reports, the message and its frame."""

    handle: int
    message: bytes
    frame: bytes
    idempotent: bool = True  #: False: a DLE NAK is no proof the peer dropped it (``datalink.py``)


EventT = TypeVar("EventT")
CountersT = TypeVar("CountersT", bound=FullDuplexCounters)


class FullDuplexStation(ABC, Generic[EventT, CountersT]):
    """The output, the last response symbol, the transmitter's frames and its ACK timer of one
    full-duplex station (module docstring)."""

    def __init__(self, counters: CountersT, *, checksum: Checksum, ack_timeout: float, max_message: int) -> None:
        self.checksum: Final = checksum
        self.ack_timeout: Final = ack_timeout
        self.max_message: Final = max_message
        self.counters = counters
        self._decoder = FrameDecoder(checksum, max_message=max_message)
        self._events: deque[EventT] = deque()
        self._out = bytearray()
        # receiver
        self._last_response = NAK_SYMBOL
        # transmitter
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

    # ------------------------------------------------------------------------------ public API

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
        self._ack_timer_expired(now)

    # ------------------------------------------------------------------------------ the station's rules

    @abstractmethod
    def _on_frame(self, message: bytes, now: float) -> None:
        """A frame with a valid check (counted in ``frames_received``)."""

    @abstractmethod
    def _on_bad_frame(self, reason: BadFrameReason, now: float) -> None:
        """A damaged frame, or DLE ETX without DLE STX (``MISSING_START``)."""

    @abstractmethod
    def _on_answer(self, nak: bool, now: float) -> None:
        """The peer's DLE ACK, or DLE NAK with ``nak`` (counted): the answer to our frame, unless
        it belongs to an older one."""

    @abstractmethod
    def _on_enq(self, aborted_frame: bool, now: float) -> None:
        """DLE ENQ from the peer (counted); ``aborted_frame``: it cut a frame short."""

    @abstractmethod
    def _frame_queued(self, now: float) -> None:
        """A frame waits in the queue: feed the transmitter table its "send" input."""

    @abstractmethod
    def _ack_timer_expired(self, now: float) -> None:
        """The ACK timer of the frame on the line ran out: feed the transmitter table its timeout."""

    # ------------------------------------------------------------------------------ receiver

    def _receive(self, data: bytes, now: float) -> bool:
        """Feed ``data`` to the decoder and handle what it reports; whether it reported anything."""
        self._decoder.feed(data)
        heard = False
        while (event := self._decoder.next_event()) is not NEED_DATA:
            heard = True
            match event:  # counted here, handed to the station's rules
                case Frame(message=message):
                    self.counters.frames_received += 1
                    self._on_frame(message, now)
                case BadFrame(reason=reason):
                    self._on_bad_frame(reason, now)
                case AckReceived():
                    self.counters.acks_received += 1
                    self._on_answer(False, now)
                case NakReceived():
                    self.counters.naks_received += 1
                    self._on_answer(True, now)
                case EnqReceived(aborted_frame=aborted):
                    self.counters.enqs_received += 1
                    self._on_enq(aborted, now)
        return heard

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
        """Queue ``message`` for the transmitter; its handle."""
        handle = self._next_handle
        self._next_handle += 1
        self._queue.append(QueuedFrame(handle, message, encode_frame(message, self.checksum), idempotent))
        return handle

    def _transmit(self, now: float) -> None:
        """The next queued frame goes on the line; the ACK timer starts."""
        self._current = self._queue.popleft()
        self._nak_count = self._enq_count = 0
        self._write_current(now)

    def _retransmit(self, now: float) -> None:
        """The same frame again after a DLE NAK; the ACK timer restarts."""
        self._nak_count += 1
        self.counters.retransmissions += 1
        self._write_current(now)

    def _enquire(self, now: float) -> None:
        """DLE ENQ for the frame on the line; the ACK timer restarts."""
        self._enq_count += 1
        self.counters.enqs_sent += 1
        self._out += ENQ_SYMBOL
        self._deadline = now + self._ack_wait(len(ENQ_SYMBOL))

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

    def _finish(self, event: EventT, now: float) -> None:
        """Report what became of a frame; the next queued one goes."""
        self._events.append(event)
        if self._queue:
            self._frame_queued(now)

    def _forget_line(self) -> list[QueuedFrame]:
        """Forget the line (port reopened): output, decoder, timer, last response; the frames
        queued or on the line, which are lost, the one on the line first."""
        lost = [self._current] if self._current is not None else []
        lost += self._queue
        self._queue.clear()
        self._current = None
        self._deadline = None
        self._frame_unsent = False
        self._decoder.reset()
        self._out.clear()
        self._last_response = NAK_SYMBOL
        return lost
