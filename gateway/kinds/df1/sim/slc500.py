"""A simulated SLC 5/04 on DF1 full duplex (controller side), with fault injection.

The processor (data table, ladder, PCCC commands: :mod:`gateway.kinds.df1.sim.slc500_processor`) behind a
controller-side :class:`~gateway.protocols.df1.full_duplex.datalink.Df1DataLink` (duplicate detection on), so ACK /
NAK / ENQ, retransmission after DLE NAK and DLE ENQ after the ACK timeout behave as the link
module specifies (S4516-DF1 Program Development Manual; DF1 manual 1770-6.5.16 ch. 4).

Fault injection (``1 in N`` drawn from a seeded generator; 0 = off):

* ``corrupt=N`` (alias ``garble``): flip a message byte of an outgoing frame, so the check fails,
  the host answers DLE NAK and the link sends the frame again.  Retransmissions and link symbols
  are never corrupted, so a corrupted reply still arrives (after one NAK) and is never lost;
* ``drop=N``: the command is executed but its reply is never queued;
* ``withhold_ack=N``: the DLE ACK of a received good frame is not sent; the link still counts
  the frame as ACKed, so the host's DLE ENQ is answered DLE ACK;
* ``duplicate=N``: an outgoing frame goes on the wire twice;
* ``noise=N``: an output is preceded by 1-8 random bytes without DLE, which a receiver
  hunting for DLE STX discards;
* ``delay=S``: replies are queued on the link S seconds after the command arrived;
* ``scan=S`` or ``scan=MIN-MAX`` (:mod:`gateway.sim.scan`): the program scans in S seconds (MIN to
  MAX, varying); a command is executed at once, but its reply is queued at the end of the scan in
  progress (plus ``delay``).  The link's DLE ACK is not held: the channel answers it at once;
* ``lose_in=N``: a frame from the host is lost whole on the way in (the controller never sees
  it; a DLE ENQ then gets the last response, the ACK of the previous frame);
* ``corrupt_in=N``: a frame from the host arrives damaged (its check fails): the controller
  answers as its ``bad_frame`` variant says;
* ``faults_on=writes``: ``drop``, ``lose_in`` and ``corrupt_in`` strike only commands that
  write (with N = 1: every write's reply lost after execution, or every write frame lost).

Variants (``variants={"name": "value"}``, ``--variant name=value``; the first value is the
default; docs/develop/controller-variants.md gives the manuals' words for each):

* ``duplicate_detect`` ``on`` | ``off``: a frame with the SRC, CMD and TNS of the last one is
  ACKed and dropped, or (off, as the S4516-DF1 manual tells users to set it) executed again;
* ``duplicate_reply`` ``ack_only`` | ``resend``: with detection on, a duplicate is only ACKed,
  or its last reply is sent again;
* ``ack_order`` ``ack_first`` | ``reply_first`` | ``embedded``: the DLE ACK of a command goes
  before its reply, just after it, or inside the reply frame (an embedded response);
* ``bad_frame`` ``nak`` | ``silence`` | ``ignore``: a damaged frame is answered DLE NAK, not
  answered (a DLE ENQ then gets DLE NAK), or not answered at all (ENQ gets the last response);
* ``enq_answer`` ``last`` | ``nak``: DLE ENQ is answered with the last response symbol, or
  always with DLE NAK ("a request for retransmission");
* ``reply_addresses`` ``swapped`` | ``unswapped`` | ``own_station``: DST / SRC of a reply are the
  command's interchanged (1770-6.5.16 p. 6-4), left as the command had them, or DST = the command's
  SRC and SRC = the ``station`` option (an SLC on full duplex ignores the command's DST).

Known limit: a duplicated frame is ACKed twice by the host; if the second ACK arrives after
the next reply frame left, the link takes it for that frame's ACK (see ``gateway.protocols.df1.full_duplex.datalink``).

Beside this module: ``slc500_processor`` (data table, ladder, commands), ``slc500_options``
(options, counters), ``slc500_data`` (the data files), ``slc500_line`` (cutting the wire into
frames, the damage faults do).

This class does no I/O: ``receive(data, now)`` / ``poll(now)`` return the bytes to send.
``gateway.sim.serve`` runs it in-process, over TCP or on a pty.
"""

from __future__ import annotations

import random
from collections import deque
from collections.abc import Mapping
from typing import ClassVar, Self

from gateway.kinds.df1.sim.slc500_line import (
    REPLY_ADDRESSES,
    address_reply,
    corrupt_frame,
    frame_message,
    garbage,
    is_write_packet,
    split_incoming,
    split_output,
)
from gateway.kinds.df1.sim.slc500_options import Slc500Counters, Slc500Options
from gateway.kinds.df1.sim.slc500_processor import ExtSts, Slc500Processor
from gateway.protocols.df1.framing import ACK_SYMBOL, NEED_DATA, Symbol
from gateway.protocols.df1.full_duplex.datalink import (
    BadFrameAnswer,
    Df1DataLink,
    EnqAnswer,
    MessageReceived,
    SendComplete,
    SendFailed,
)
from gateway.sim.scan import scan_clock
from gateway.sim.serve import Output
from gateway.sim.variants import resolve_variants

__all__ = ["ExtSts", "Output", "Slc500Counters", "Slc500Options", "Slc500Processor", "Slc500Simulator"]


class Slc500Simulator(Slc500Processor):
    """One SLC 5/04 on a DF1 full-duplex link.  Not thread-safe; drive it from one event loop."""

    #: One switch per reading of the manuals (module docstring); the first value is the default.
    VARIANTS: ClassVar[dict[str, tuple[str, ...]]] = {
        "duplicate_detect": ("on", "off"),
        "duplicate_reply": ("ack_only", "resend"),
        "ack_order": ("ack_first", "reply_first", "embedded"),
        "bad_frame": tuple(answer.value for answer in BadFrameAnswer),
        "enq_answer": tuple(answer.value for answer in EnqAnswer),
        "reply_addresses": REPLY_ADDRESSES,
    }

    def __init__(
        self,
        options: Slc500Options | None = None,
        *,
        ladder: bool = True,
        variants: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(options, ladder=ladder)
        self.variants = resolve_variants("slc504", self.VARIANTS, variants or {})
        self.link = Df1DataLink(
            checksum=self.options.checksum,
            ack_timeout=self.options.link_ack_timeout,
            duplicate_detect=self.variants["duplicate_detect"] == "on",
            bad_frame=BadFrameAnswer(self.variants["bad_frame"]),
            enq_answer=EnqAnswer(self.variants["enq_answer"]),
        )
        self._reply_first = self.variants["ack_order"] != "ack_first"
        self._embed_acks = self.variants["ack_order"] == "embedded"
        self._resend_reply = self.variants["duplicate_reply"] == "resend"
        self._rx = bytearray()  # bytes from the host not yet a whole frame or symbol
        self._last_reply: bytes | None = None  # the reply to the last message delivered
        self._held_acks = 0  # DLE ACKs owed, to go right after the next reply (reply_first)
        self._rng = random.Random(self.options.seed)
        self._scan_clock = scan_clock(self.options.scan, self.options.seed)
        self._pending: deque[tuple[float, bytes]] = deque()  # (due, reply packet)
        self._last_frame: bytes | None = None  # the last frame the link wrote, before faults

    @classmethod
    def from_options(
        cls, fault_options: Mapping[str, str], *, ladder: bool = True, variants: Mapping[str, str] | None = None
    ) -> Self:
        """From ``sim://slc504?...`` (``sim://plc5?...``) options; ValueError for an unknown option,
        variant or bad value."""
        return cls(Slc500Options.from_options(fault_options), ladder=ladder, variants=variants)

    # --- the line ---------------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[Output]:
        """Bytes from the host -> bytes to send (response symbols, replies, retransmissions)."""
        self.advance(now)
        out: list[Output] = []
        link = self.link
        self._rx += data
        for token in self._incoming_tokens():
            for index in range(len(token)):
                frames_before = link.counters.frames_received
                duplicates_before = link.counters.duplicates
                link.receive_data(token[index : index + 1], now)
                new_frame = link.counters.frames_received > frames_before
                duplicate = link.counters.duplicates > duplicates_before
                if new_frame:
                    self.counters.frames_received += 1
                    self.counters.duplicates_received += duplicate
                response = link.data_to_send()
                hold = new_frame and self._reply_first and response == ACK_SYMBOL
                withhold = new_frame and self._one_in(self.options.withhold_ack)
                replies_before = self.counters.replies_sent
                if hold:
                    self._held_acks += 1
                    if withhold:  # the held ACK is the one lost
                        self._held_acks -= 1
                        self.counters.withheld_acks += 1
                else:
                    self._emit(out, response, withhold=withhold)
                self._drain_events(now)
                if duplicate and self._resend_reply and self._last_reply is not None:
                    self.counters.replies_resent += 1
                    self._pending.append((self._reply_due(now), self._last_reply))
                self._send_due(now)
                self._emit(out, link.data_to_send())
                if hold and self.counters.replies_sent == replies_before and not self._pending:
                    self._release_acks(out, embed=False)  # nothing to answer (dropped, ignored ...): ACK now
            # held ACKs follow the reply that went out in this step
            if self._held_acks and not self._pending:
                self._release_acks(out)
        return out

    def _release_acks(self, out: list[Output], *, embed: bool = True) -> None:
        acks = ACK_SYMBOL * self._held_acks
        self._held_acks = 0
        if embed and self._embed_acks and out:
            # inside the reply frame that just went out, right after its DLE STX
            # (1770-6.5.16 ch. 4: a receiver may embed its response symbols in a frame it sends)
            data = out[-1].data
            start = data.find(bytes((Symbol.DLE, Symbol.STX)))
            if start >= 0:
                out[-1] = Output(out[-1].delay, data[: start + 2] + acks + data[start + 2 :])
                return
        out.append(Output(0.0, acks))

    def _incoming_tokens(self) -> list[bytes]:
        """Whole frames and symbols from ``_rx`` (a partial one stays), after the inbound faults."""
        tokens: list[bytes] = []
        for token, whole_frame in split_incoming(self._rx, self.options.checksum):
            if not whole_frame or not self._strikes(token):
                tokens.append(token)
            elif self._one_in(self.options.lose_in):
                self.counters.lost_in += 1
            elif self._one_in(self.options.corrupt_in):
                self.counters.corrupted_in += 1
                tokens.append(corrupt_frame(token, self.options.checksum, self._rng))
            else:
                tokens.append(token)
        return tokens

    def poll(self, now: float) -> list[Output]:
        """Run the timers: the link's ACK timer and replies waiting for their turnaround."""
        self.advance(now)
        out: list[Output] = []
        deadline = self.link.next_deadline()
        if deadline is not None and now >= deadline:
            self.link.handle_timeout(now)
        self._drain_events(now)
        self._send_due(now)
        self._emit(out, self.link.data_to_send())
        if self._held_acks and not self._pending:
            self._release_acks(out)
        return out

    def next_deadline(self) -> float | None:
        deadlines = [
            d for d in (self.link.next_deadline(), self._pending[0][0] if self._pending else None) if d is not None
        ]
        return min(deadlines) if deadlines else None

    def _drain_events(self, now: float) -> None:
        while (event := self.link.next_event()) is not NEED_DATA:
            match event:
                case MessageReceived(payload=payload):
                    reply = self._handle(payload)
                    if reply is not None:
                        reply = address_reply(payload, reply, self.variants["reply_addresses"], self.options.station)
                    self._last_reply = reply
                    if reply is None:
                        continue
                    if self._is_write(payload) and self._one_in(self.options.drop):
                        self.counters.dropped += 1
                        continue
                    self._pending.append((self._reply_due(now), reply))
                case SendComplete():
                    self.counters.replies_acked += 1
                case SendFailed():
                    self.counters.replies_failed += 1

    def _reply_due(self, now: float) -> float:
        """When a reply to a command that arrived at ``now`` goes on the link: the end of the scan in
        progress (``scan``), plus ``delay``."""
        at = self._scan_clock.answer_at(now) if self._scan_clock is not None else now
        return at + self.options.delay

    def _send_due(self, now: float) -> None:
        while self._pending and self._pending[0][0] <= now:
            _, reply = self._pending.popleft()
            self.link.send(reply, now)
            self.counters.replies_sent += 1

    # --- fault injection --------------------------------------------------------------------

    def _is_write(self, packet: bytes) -> bool:
        """Do the faults restricted by ``faults_on`` strike this command packet?"""
        return self.options.faults_on == "all" or is_write_packet(packet)

    def _strikes(self, frame: bytes) -> bool:
        """May an inbound fault strike this whole frame (``faults_on``)?"""
        if self.options.faults_on == "all":
            return True
        message = frame_message(frame, self.options.checksum)
        return message is not None and is_write_packet(message)

    def _one_in(self, n: int) -> bool:
        return n > 0 and self._rng.randrange(n) == 0

    def _emit(self, out: list[Output], data: bytes, *, withhold: bool = False) -> None:
        """Turn link output into outputs, one per frame or symbol, applying the faults."""
        for token in split_output(data, self.options.checksum):
            if withhold and token == ACK_SYMBOL:
                withhold = False
                self.counters.withheld_acks += 1
                continue
            copies = [token]
            if len(token) > 2 and token[1] == Symbol.STX:
                retransmission, self._last_frame = token == self._last_frame, token
                if not retransmission and self._one_in(self.options.corrupt):
                    self.counters.corrupted += 1
                    copies = [corrupt_frame(token, self.options.checksum, self._rng)]
                elif self._one_in(self.options.duplicate):
                    self.counters.duplicates += 1
                    copies = [token, token]
            for copy in copies:
                if self._one_in(self.options.noise):
                    self.counters.noise += 1
                    copy = garbage(self._rng) + copy
                out.append(Output(0.0, copy))
