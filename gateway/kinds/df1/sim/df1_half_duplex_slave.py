"""A DF1 half-duplex slave station, sans-I/O, with a switch for every reading of the manual.

Several of these on one byte stream make a multi-drop line: every station hears every byte and
answers only polls and messages carrying its own STN.  The PCCC side is a callable
``handler(command) -> reply | None`` so the model serves any controller model (the SLC 500
simulator's, a PLC-5's, or a test's).

Manual: 1775-KA p. 11-11/11-12 and 1770-KF2 p. 4-31/4-32 (slave transceiver actions);
1770-6.5.16 p. 2-7 Table 2.C (DLE NAK = global link reset, DLE EOT).  Readings: section 4 and 5 of
``docs/develop/df1-half-duplex-notes.md``.  The slave has no clock of its own: the caller passes ``now``
with the bytes, and ``answer_at(now)`` (the end of the controller's scan in progress, given by the
line simulator) holds a reply back until then; latency and lost bytes are the line's business (the test harness
or the line simulator).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Final

from gateway.frozen import frozen
from gateway.kinds.df1.sim.slc500_line import REPLY_ADDRESSES, address_reply
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    EOT_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    Checksum,
    MasterMessage,
    NakReceived,
    Poll,
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, duplicate_key
from gateway.sim.variants import VariantTable, resolve_variants

__all__ = ["VARIANTS", "HalfDuplexSlave", "SlaveVariant"]

#: name -> readings (the first is the manual's / the default).  See docs/develop/df1-half-duplex-notes.md §5.
VARIANTS: Final[VariantTable] = {
    # §5 row 1: a master frame with a bad check: silence (KF2 Fig. 4.18) or DLE NAK.
    "bad_frame_reply": ("silent", "nak"),
    # §5 row 2: an unacknowledged message is resent at every poll until ACKed, or given up after 3.
    "reply_retries": ("unlimited", "3", "0"),
    # §5 row 3: duplicate detection of master messages (RM "Duplicate Packet Detect").
    "duplicate_detect": ("on", "off"),
    # §5 row 5: a poll while the reply is not ready: DLE EOT, or no answer at all.
    "when_busy": ("eot", "silent"),
    # DST / SRC of a reply: swapped (1770-6.5.16 p. 6-4), as the command had them, or SRC = own station.
    "reply_addresses": REPLY_ADDRESSES,
}


@frozen
class SlaveVariant:
    bad_frame_reply: str = "silent"
    reply_retries: int | None = None  #: None: resend until ACKed
    duplicate_detect: bool = True
    silent_when_busy: bool = False
    reply_addresses: str = "swapped"

    @classmethod
    def from_choices(cls, chosen: Mapping[str, str]) -> SlaveVariant:
        values = resolve_variants("df1-half-duplex-slave", VARIANTS, chosen)
        retries = values["reply_retries"]
        return cls(
            bad_frame_reply=values["bad_frame_reply"],
            reply_retries=None if retries == "unlimited" else int(retries),
            duplicate_detect=values["duplicate_detect"] == "on",
            silent_when_busy=values["when_busy"] == "silent",
            reply_addresses=values["reply_addresses"],
        )


@dataclass(slots=True)
class SlaveCounters:
    polls: int = 0
    eots: int = 0
    messages: int = 0
    executed: int = 0
    duplicates: int = 0
    bad_frames: int = 0
    resends: int = 0
    given_up: int = 0
    link_resets: int = 0


@dataclass(slots=True)
class _Outgoing:
    message: bytes
    sends: int = 0
    ready_at: float = float("-inf")  #: polls before this time are answered as a busy slave's


@dataclass(slots=True)
class HalfDuplexSlave:
    """One slave station on a half-duplex line."""

    station: int
    checksum: Checksum
    handler: Callable[[bytes], bytes | None]
    variant: SlaveVariant = field(default_factory=SlaveVariant)
    #: replies (or MSGs) ready to go, and the one sent but not yet acknowledged
    outgoing: deque[_Outgoing] = field(default_factory=deque)
    #: messages held back: ``busy`` replies become ready one poll later (a slow CPU)
    busy: int = 0
    #: when the reply to a message heard at ``now`` is ready (None: at once)
    answer_at: Callable[[float], float] | None = None
    counters: SlaveCounters = field(default_factory=SlaveCounters)
    _decoder: FrameDecoder = field(init=False)
    _out: bytearray = field(default_factory=bytearray)
    _last_head: tuple[int, int, int] | None = None
    _sent: bool = False  #: outgoing[0] was sent in answer to the last poll

    def __post_init__(self) -> None:
        self._decoder = FrameDecoder(self.checksum, half_duplex=True)

    def initiate(self, message: bytes) -> None:
        """Queue a slave-initiated message (an MSG instruction in the controller)."""
        self.outgoing.append(_Outgoing(message))

    def data_to_send(self) -> bytes:
        data = bytes(self._out)
        self._out.clear()
        return data

    def receive_data(self, data: bytes, now: float = 0.0) -> None:
        """Master bytes heard at ``now`` (seconds; only compared with ``ready_at``)."""
        self._decoder.feed(data)
        while (event := self._decoder.next_event()) is not NEED_DATA:
            if isinstance(event, Poll):
                if event.station == self.station:
                    self._on_poll(now)
            elif isinstance(event, MasterMessage):
                if event.station == self.station:
                    self._on_message(event.message, now)
            elif isinstance(event, AckReceived):
                if self._sent and self.outgoing:
                    self.outgoing.popleft()
                self._sent = False
            elif isinstance(event, NakReceived):
                self.counters.link_resets += 1  # Table 2.C: cancel everything queued for the master
                self.outgoing.clear()
                self._sent = False
            elif isinstance(event, BadFrame) and event.master:
                self.counters.bad_frames += 1
                if self.variant.bad_frame_reply == "nak":
                    self._out += NAK_SYMBOL
            # Slave frames, EOTs, bad slave frames: another station talking.  Ignored.

    def _on_poll(self, now: float) -> None:
        self.counters.polls += 1
        if self._sent and self.outgoing:
            head = self.outgoing[0]
            limit = self.variant.reply_retries
            if limit is not None and head.sends > limit:
                self.counters.given_up += 1  # KA p. 11-12: error to the originator, next message
                self.outgoing.popleft()
            else:
                self.counters.resends += 1
        self._sent = False
        not_ready = bool(self.outgoing) and now < self.outgoing[0].ready_at
        if self.busy > 0 or not_ready:
            self.busy = max(0, self.busy - 1)
            if self.variant.silent_when_busy:
                return
            self.counters.eots += 1
            self._out += EOT_SYMBOL
            return
        if not self.outgoing:
            self.counters.eots += 1
            self._out += EOT_SYMBOL
            return
        head = self.outgoing[0]
        head.sends += 1
        self._sent = True
        self._out += encode_frame(head.message, self.checksum)

    def _on_message(self, message: bytes, now: float) -> None:
        self.counters.messages += 1
        # KA p. 11-12 compares SRC, CMD and both TNS bytes; a runt is never a repeat
        key = duplicate_key(message) if len(message) >= HEADER_SIZE else None
        if self.variant.duplicate_detect and key is not None and key == self._last_head:
            self.counters.duplicates += 1
            self._out += ACK_SYMBOL
            return
        self._last_head = key
        self._out += ACK_SYMBOL
        self.counters.executed += 1
        reply = self.handler(message)
        if reply is not None:
            ready_at = self.answer_at(now) if self.answer_at is not None else float("-inf")
            reply = address_reply(message, reply, self.variant.reply_addresses, self.station)
            self.outgoing.append(_Outgoing(reply, ready_at=ready_at))
