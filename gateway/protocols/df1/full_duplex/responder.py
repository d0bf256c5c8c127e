"""DF1 full-duplex responder: the link layer of the station that a PLC's MSG instruction addresses.

In DF1 target mode the gateway stands where the S4516-DF1 board stands in its manual (§4-§6: a
PLC-5, SLC 500 or ControlLogix channel 0 in System (point-to-point) mode, its MSG instruction
aimed at us).  Commands come in, replies go out.  Manual: A-B 1770-6.5.16, chapter 4 ("p. 4-x");
defaults from the SLC 500 channel 0 configuration, 1747-RM001G p. 13-52 Table 13.15 ("RM").

Receiver (p. 4-8, the RECEIVER program; its last response starts as DLE NAK)::

    good frame, new command     -> DLE ACK, CommandReceived, remember SRC CMD TNS ("save last header")
    good frame, same SRC CMD TNS -> DLE ACK, not delivered, no second reply (DuplicateReceived; p. 4-13)
    good frame, sink full       -> DLE NAK ("else if message sink is full send DLE NAK")
    damaged / < 6 bytes / long  -> DLE NAK ("too small", "too large", BCC/CRC not valid)
    DLE ENQ inside a frame      -> DLE NAK for the truncated frame (a control symbol other than DLE ETX)
    DLE ENQ                     -> the last response symbol again (p. 4-8 / 4-9)
    anything else outside a frame (noise, DLE ETX without DLE STX) -> last response := DLE NAK
                                   ("else LAST-RESPONSE = NAK"; p. 4-7 "a false control or data symbol")

The receiver's rules do not depend on the transmitter: the two work at the same time (p. 4-2,
Figure 4.1).  The peer's DLE ACK / DLE NAK for our replies share the circuit with its frames, so one
may arrive inside a frame: the decoder hands it to the transmitter and keeps the frame (p. 4-8,
GET-SYMBOL: "if char is an ACK or NAK send it to the transmitter").  Our own response symbols are
never embedded: every frame and symbol enters the output whole, which a peer with "Embedded
Responses" enabled or auto-detect (RM) accepts.

Duplicates (``duplicate_detect``, RM default: enabled): "The combination of SRC, CMD, and TNS bytes
uniquely identifies every message packet ... If all fields are the same, the message is ignored and
is considered to be a duplicate" (p. 6-3); the receiver compares them with the last message passed
to the sink (p. 4-8: LAST-HEADER, 4 bytes; p. 4-13: a lost DLE ACK makes the peer send the message
again, "the receiver discards the duplicate message (if duplicate message detection is enabled)").
DST and STS are not part of it.  A duplicate is never delivered, so never executed twice, and it
gets no second reply: p. 4-13 shows the copy discarded and one reply returned, so the peer has one
reply per TNS.  ``resend_reply`` (off by default) is a reading for a peer that sends the command
again because it lost our reply: the stored reply, when it was given
(:meth:`Df1Responder.send_reply`) and is not on its way, is queued again (docs/develop/controller-variants.md).

DST (``check_dst``, default False): the full-duplex receiver never looks at DST (the p. 4-8 program
tests only the check, the length, the header and the sink); RM p. 13-76 names ignoring "packets
received that have a destination address other than its own" as half-duplex behaviour, and S4516
§4.4 / §6.4 need the station address only through a Data Highway bridge.  With ``check_dst`` a
frame whose DST is not ``station`` is ACKed (it arrived intact) but not delivered, and counted.

Transmitter (p. 4-6 flowchart; RM: ACK timeout 50 x 20 ms, NAK retries 3, ENQ retries 3), one
reply on the line at a time, the others queued in order::

    IDLE --reply--> AWAIT_ACK --DLE ACK--> IDLE (ReplyDelivered), next reply
                    AWAIT_ACK --DLE NAK--> the same frame again              (at most nak_limit times)
                    AWAIT_ACK --ack_timeout--> DLE ENQ                        (at most enq_limit times)
                    then IDLE (ReplyLost), next reply

A DLE ACK / DLE NAK that arrives while our frame still waits in :meth:`data_to_send` answers an
older frame and is ignored.  Known limit of the protocol: a frame lost whole leaves no trace, and
the DLE ENQ that follows is answered with the previous frame's ACK (p. 4-8: the last response), so
the peer takes it as delivered; the application layer's reply timeout covers that.

The receiver and the transmitter are the full-duplex station's
(:class:`~gateway.protocols.df1.full_duplex.FullDuplexStation`, its tables in
:mod:`~gateway.protocols.df1.full_duplex.table`), shared with the host's data link; the responder
adds its role: the message sink of ``max_pending`` commands awaiting their reply, the DST check,
the stored reply, and its events and counters (:mod:`~gateway.protocols.df1.full_duplex.responder_events`).
This module does no I/O: the caller passes ``now`` and moves the bytes.
"""

from __future__ import annotations

from typing import Final, Unpack

from gateway.protocols.df1.full_duplex.responder_events import (
    CommandReceived,
    DuplicateReceived,
    ReplyDelivered,
    ReplyLost,
    ResponderCounters,
    ResponderEvent,
)
from gateway.protocols.df1.full_duplex.station import (
    FullDuplexStation,
    QueuedFrame,
    SendFailure,
    StationOptions,
    TxState,
)
from gateway.protocols.df1.full_duplex.table import TxInput
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, PcccHeader, duplicate_key
from gateway.protocols.df1.pccc.codes import REPLY_BIT

__all__ = ["Df1Responder"]


class Df1Responder(FullDuplexStation[ResponderEvent, ResponderCounters]):
    """Sans-I/O DF1 full-duplex responder: commands in, replies out (module docstring).

    ``feed(data, now)`` the bytes read, ``next_event()`` until ``NEED_DATA``, answer every
    :class:`CommandReceived` with ``send_reply(packet, now)`` (the PCCC target answers every
    command, errors included: "For each command message sent, a reply message is generated",
    S4516 §2; one it does not take as a command is given up with ``no_reply(packet)``), write
    ``data_to_send()``, and call ``handle_timeout(now)`` at ``next_deadline()``.
    """

    def __init__(
        self,
        *,
        station: int = 0,
        check_dst: bool = False,
        max_pending: int = 4,
        resend_reply: bool = False,
        **options: Unpack[StationOptions],
    ) -> None:
        if not 0 <= station <= 254:
            raise ValueError("station must be 0..254")
        if max_pending < 1:
            raise ValueError("max_pending must be at least 1")
        super().__init__(ResponderCounters(), accept_dst=station if check_dst else None, **options)
        self.station: Final = station
        self.check_dst: Final = check_dst
        #: a duplicate command gets the stored reply again (module docstring; off: p. 4-13)
        self.resend_reply: Final = resend_reply
        #: the message sink's size: commands delivered whose reply was not given yet; p. 4-6
        #: suggests peers keep one to three messages outstanding
        self.max_pending: Final = max_pending
        self._last_reply: tuple[int, bytes] | None = None  # handle and packet of the last command's reply
        self._pending: list[tuple[int, int, int]] = []  # SRC, CMD, TNS of commands awaiting a reply

    # ------------------------------------------------------------------------------ public API

    @property
    def state(self) -> TxState:
        return self._tx_state

    @property
    def pending_commands(self) -> int:
        """Commands delivered whose reply was not given yet."""
        return len(self._pending)

    @property
    def queued_replies(self) -> int:
        """Replies queued or on the line."""
        return len(self._queue) + (self._current is not None)

    def feed(self, data: bytes, now: float) -> None:
        """Consume bytes read from the line."""
        self._receive(data, now)

    def send_reply(self, packet: bytes, now: float) -> int:
        """Queue a reply packet (DST .. data); returns its handle, which one event will report:
        :class:`ReplyDelivered` or :class:`ReplyLost`."""
        packet = bytes(packet)
        if not HEADER_SIZE <= len(packet) <= self.max_message:
            raise ValueError(f"DF1 reply of {len(packet)} bytes: must be {HEADER_SIZE}..{self.max_message}")
        handle = self._enqueue(packet)
        header = self._answered(packet)
        if header is not None and header == self._last_header:
            self._last_reply = (handle, packet)
        self._tx(TxInput.SEND, now)
        return handle

    def no_reply(self, packet: bytes) -> None:
        """The delivered ``packet`` gets no reply (the application layer does not take it as a
        command, e.g. a reply sent to us): it no longer holds a place in the sink."""
        header = duplicate_key(packet)
        if header in self._pending:
            self._pending.remove(header)

    def reset(self) -> None:
        """Forget the line (port reopened): every reply queued or on the line is lost."""
        self._tx(TxInput.RESET, 0.0)
        self._last_reply = None
        self._pending.clear()

    # ------------------------------------------------------------------------------ the role

    def _sink_full(self) -> bool:
        return len(self._pending) >= self.max_pending

    def _deliver(self, message: bytes, now: float) -> None:
        header = duplicate_key(message)
        self._last_reply = None
        self._pending.append(header)
        self.counters.commands_delivered += 1
        src, cmd, tns = header
        self._events.append(CommandReceived(message, src, message[0], cmd, tns))

    def _duplicate(self, message: bytes, now: float) -> None:
        handle = None
        if self.resend_reply and self._last_reply is not None and not self._on_its_way(self._last_reply[0]):
            packet = self._last_reply[1]
            handle = self._enqueue(packet)
            self._last_reply = (handle, packet)
            self.counters.replies_resent += 1
        src, cmd, tns = duplicate_key(message)
        self._events.append(DuplicateReceived(message, src, cmd, tns, handle))
        if handle is not None:
            self._tx(TxInput.SEND, now)

    def _sent(self, frame: QueuedFrame, now: float) -> None:
        self.counters.replies_delivered += 1
        self._events.append(ReplyDelivered(frame.handle, frame.message))

    def _failed(self, frame: QueuedFrame, reason: SendFailure) -> None:
        self.counters.replies_lost += 1
        self._events.append(ReplyLost(frame.handle, frame.message, reason))

    # ------------------------------------------------------------------------------ helpers

    def _on_its_way(self, handle: int) -> bool:
        """Reply ``handle`` is queued or on the line."""
        current = self._current is not None and self._current.handle == handle
        return current or any(queued.handle == handle for queued in self._queue)

    def _answered(self, reply: bytes) -> tuple[int, int, int] | None:
        """Take the pending command ``reply`` answers (CMD | 0x40, same TNS; its DST = the command's
        SRC if one such is pending, p. 6-4) off the sink; its header, or None."""
        answer = PcccHeader.decode(reply)
        cmd, tns = answer.cmd & ~REPLY_BIT, answer.tns
        matches = [header for header in self._pending if header[1] == cmd and header[2] == tns]
        if not matches:
            return None
        header = next((header for header in matches if header[0] == answer.dst), matches[0])
        self._pending.remove(header)
        return header
