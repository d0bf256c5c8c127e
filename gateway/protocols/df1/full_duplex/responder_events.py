"""Events and counters of the DF1 full-duplex responder (``gateway.protocols.df1.full_duplex.responder``).

What the responder reports to its driver (``next_event()``) and its link statistics.  Sans-I/O:
plain data.
"""

from __future__ import annotations

from dataclasses import dataclass

from gateway.frozen import frozen
from gateway.protocols.df1.full_duplex.station import FullDuplexCounters, SendFailure

__all__ = [
    "CommandReceived",
    "DuplicateReceived",
    "ReplyDelivered",
    "ReplyLost",
    "ResponderCounters",
    "ResponderEvent",
]


@frozen
class CommandReceived:
    """A new command (PCCC packet, DST .. data), ACKed; answer it with :meth:`Df1Responder.send_reply`."""

    packet: bytes
    src: int
    dst: int
    cmd: int
    tns: int


@frozen
class DuplicateReceived:
    """The peer sent the last command again (its DLE ACK was lost); ACKed, not delivered.

    ``reply_handle`` is the handle of the stored reply queued again (only with the responder's
    ``resend_reply``), or None (the default, 1770-6.5.16 p. 4-13: one reply per command; or no reply
    given yet, or it is still on its way).
    """

    packet: bytes
    src: int
    cmd: int
    tns: int
    reply_handle: int | None


@frozen
class ReplyDelivered:
    """The peer ACKed the reply queued as ``handle``."""

    handle: int
    packet: bytes


@frozen
class ReplyLost:
    """The responder gave up on the reply queued as ``handle``; the peer may or may not have it."""

    handle: int
    packet: bytes
    reason: SendFailure


ResponderEvent = CommandReceived | DuplicateReceived | ReplyDelivered | ReplyLost


@dataclass(slots=True)
class ResponderCounters(FullDuplexCounters):
    """Link statistics of the responder: ``frames_received`` are commands, duplicates, refused and
    not for us; ``bad_frames`` (damaged, too short, too long, or cut by DLE ENQ) are NAKed;
    ``sink_full`` counts new commands NAKed because ``max_pending`` commands await their reply."""

    commands_delivered: int = 0
    replies_resent: int = 0  #: stored replies queued again for a duplicate command (``resend_reply``)
    replies_delivered: int = 0
    replies_lost: int = 0
