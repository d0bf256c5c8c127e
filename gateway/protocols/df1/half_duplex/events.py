"""Configuration and events of the DF1 half-duplex master (``gateway.protocols.df1.half_duplex.master``).

The tunables of a line and of each station, checked when made, and what the master core reports
to its driver (``next_event()``).  Sans-I/O: plain data.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.framing import Checksum

__all__ = [
    "DEFAULT_MESSAGE_RESENDS",
    "DEMOTE_AFTER",
    "HALF_DUPLEX_ACK_TIMEOUT",
    "REPLY_WAIT",
    "FailReason",
    "LineConfig",
    "MasterEvent",
    "MessageDelivered",
    "ReplyReceived",
    "RequestFailed",
    "SlaveInitiated",
    "StationConfig",
    "StationCounters",
    "StationDemoted",
    "StationRestored",
    "StrayReply",
]


# ---------------------------------------------------------------------------------- configuration


def _positive(name: str, value: float, *, allow_zero: bool = True) -> None:
    if value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {value}")


#: Answerless polls / unacknowledged messages in a row before a station is demoted.  Five, not the
#: three of Kepware's "demote after 3 timeouts" (each of those a request with its own retries): one
#: failure here is one lost frame, and with 1 in 10 frames lost on a noisy radio line three in a row
#: hit a live station every minute or two of continuous polling, which then serves 0x0B until its next
#: slow poll; five in a row is some hours (tests/e2e/test_half_duplex_acceptance.py measures it).
DEMOTE_AFTER = 5
#: A half-duplex master's wait for the DLE ACK of its message, counted from its last byte.  1747-RM001G
#: p. 13-61 sizes it to the line (modem turnaround, RTS send delay, the slave's scan); on a wire a slave's
#: two-byte ACK comes within that, so 0.5 s, not the SLC channel's 1.0 s default, which allows for
#: modems: a radio line sets the ``ack_timeout`` key.
HALF_DUPLEX_ACK_TIMEOUT: Final = 0.5
#: Identical resends of a master message without its DLE ACK (the ``message_retries`` key's default).
DEFAULT_MESSAGE_RESENDS: Final = 3
#: A half-duplex master's wait after a slave's DLE ACK, and after each DLE EOT it answers while its reply
#: is not ready, before it polls the slave for the reply: one 20 ms step of the SLC's "Reply Message Wait
#: Time" (1747-RM001G p. 13-67).  A controller answers at the end of its program scan (tens of ms): polled
#: at once, it answers DLE EOT again and again, and each poll is one more chance of a lost frame and its
#: poll timeout (0.5 s), which a write cannot afford within its write_timeout.
REPLY_WAIT: Final = 0.02


@frozen
class StationConfig:
    """Tunables of one slave station (seconds)."""

    station: int
    poll_timeout: float = 0.5  #: wait for the answer to a poll (RM p. 13-61: the ACK timeout)
    reply_timeout: float = 5.0  #: from the ACK of a command to its reply
    reply_wait: float = REPLY_WAIT  #: after the ACK or a DLE EOT, before the next poll for the reply
    max_polls: int = 20  #: DLE EOT answers tolerated while waiting for one reply
    demote_after: int = DEMOTE_AFTER  #: answerless polls / unacknowledged messages in a row before demotion
    poll_interval: float = 1.0  #: background poll period for slave-initiated messages
    slow_poll_interval: float = 10.0  #: poll period of a demoted station
    max_outstanding: int = 1  #: commands delivered and awaiting their reply at once

    def __post_init__(self) -> None:
        if not 0 <= self.station <= 0xFE:
            raise ValueError(f"station must be 0..254 (255 is broadcast), got {self.station}")
        _positive("poll_timeout", self.poll_timeout, allow_zero=False)
        _positive("reply_timeout", self.reply_timeout, allow_zero=False)
        _positive("reply_wait", self.reply_wait)
        _positive("poll_interval", self.poll_interval, allow_zero=False)
        _positive("slow_poll_interval", self.slow_poll_interval, allow_zero=False)
        if self.max_polls < 1 or self.demote_after < 1 or self.max_outstanding < 1:
            raise ValueError("max_polls, demote_after and max_outstanding must be at least 1")


@frozen
class LineConfig:
    """Tunables of the line (seconds)."""

    checksum: Checksum
    ack_timeout: float = HALF_DUPLEX_ACK_TIMEOUT  #: wait for DLE ACK after a master message
    #: identical copies sent again of a master message without its DLE ACK
    message_resends: int = DEFAULT_MESSAGE_RESENDS
    char_time: float = 0.0  #: time of one character on the wire (11 bits / baud); 0 = instantaneous
    pre_transmit_delay: float = 0.0  #: quiet time after the last byte heard before transmitting
    rts_send_delay: float = 0.0  #: RTS on to first byte (modem key-up, RM p. 13-59)
    rts_off_delay: float = 0.0  #: last byte to RTS off (RM p. 13-59)
    echo: bool = False  #: 2-wire RS-485: the master hears its own bytes
    max_messages_per_turn: int = 8  #: polls of one station in a row while it has messages
    #: how long writes (urgent requests) may go ahead of other waiting work
    write_precedence: float = 1.0

    def __post_init__(self) -> None:
        _positive("ack_timeout", self.ack_timeout, allow_zero=False)
        for name in ("char_time", "pre_transmit_delay", "rts_send_delay", "rts_off_delay", "write_precedence"):
            _positive(name, getattr(self, name))
        if self.message_resends < 0 or self.max_messages_per_turn < 1:
            raise ValueError("message_resends must be >= 0 and max_messages_per_turn >= 1")


# ------------------------------------------------------------------------------------------ events


class FailReason(enum.Enum):
    NO_ACK = "the station never acknowledged the command"
    NO_REPLY = "the station acknowledged the command but its reply never came"
    STATION_DEMOTED = "the station does not answer polls (demoted to slow poll)"
    LINK_RESET = "the link was reset"


@frozen
class ReplyReceived:
    request_id: int
    station: int
    message: bytes


@frozen
class RequestFailed:
    """``may_have_executed``: the slave may have received (and executed) the command."""

    request_id: int
    station: int
    reason: FailReason
    may_have_executed: bool


@frozen
class SlaveInitiated:
    """A command the slave sent on its own (an MSG instruction), already acknowledged."""

    station: int
    message: bytes


@frozen
class MessageDelivered:
    """A master message sent with :meth:`HalfDuplexMaster.send_reply` was acknowledged (DLE ACK)."""

    request_id: int
    station: int


@frozen
class StrayReply:
    """A reply matching no request of the polled station (late after a failure): discarded."""

    station: int
    message: bytes


@frozen
class StationDemoted:
    station: int


@frozen
class StationRestored:
    station: int


MasterEvent = (
    ReplyReceived | RequestFailed | SlaveInitiated | MessageDelivered | StrayReply | StationDemoted | StationRestored
)


@dataclass(slots=True)
class StationCounters:
    polls: int = 0
    eots: int = 0
    messages_sent: int = 0
    messages_received: int = 0
    resends: int = 0  #: master messages sent again (identical) for a missing DLE ACK
    timeouts: int = 0
    bad_frames: int = 0
    duplicates: int = 0
    demotions: int = 0
