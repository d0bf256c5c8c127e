"""DF1 framing, full and half duplex: symbols, error checks, frame encoders and the decoder's events.

Manuals: "S4516-DF1 Program Development Manual" §2.1, §2.3, §2.5 (full duplex, after A-B
1770-6.5.16 chapter 2); A-B 1770-6.5.16 p. 2-6/2-7 (Tables 2.A, 2.C: symbols), p. 5-2 (half-duplex
frames), p. 5-5 (BCC), p. 5-6/5-7 (CRC); 1770-KF2 user manual p. 4-24/4-25.  The half-duplex
reading and its test vectors: ``docs/develop/df1-half-duplex-notes.md``.

Frames on the wire::

    frame           DLE STX <message> DLE ETX <BCC | CRC lo CRC hi>      full duplex; a half-duplex slave
    master message  DLE SOH STN DLE STX <message> DLE ETX <check>        half duplex, master to slave
    poll            DLE ENQ STN BCC                                      half duplex (BCC even on a CRC link)
    symbols         DLE ACK, DLE NAK, DLE ENQ (full duplex: "send your last response again"),
                    DLE EOT (half duplex: the polled slave has nothing to send)

* Message bytes (and a half-duplex STN) of value 10 hex are sent as ``DLE DLE`` (Table 2.C); check
  bytes never are (p. 5-5: "a BCC is not treated like data").
* BCC: two's complement of the 8-bit sum of the message bytes; a master message's BCC also sums
  STN, a poll's BCC is that of STN alone.
* CRC-16 (low byte first): over the message bytes and ETX; a master message's CRC over STN, STX,
  the message bytes and ETX (p. 5-6 table, p. 5-7 pseudo code).  Both checks are
  :mod:`gateway.protocols.df1.checks`.

The full-duplex and the half-duplex framing share these symbols, checks and events; the one
streaming decoder is :class:`gateway.protocols.df1.framing.decoder.FrameDecoder`, whose
``half_duplex`` option adds the master frames, polls and DLE EOT.

This module does no I/O.
"""

from __future__ import annotations

import enum
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.checks import bcc, crc16
from gateway.protocols.need_data import NEED_DATA, NeedData

__all__ = [
    "ACK_SYMBOL",
    "DEFAULT_ACK_TIMEOUT",
    "DEFAULT_CHECKSUM",
    "DEFAULT_MAX_MESSAGE",
    "ENQ_SYMBOL",
    "EOT_SYMBOL",
    "ETX_BYTE",
    "NAK_SYMBOL",
    "NEED_DATA",
    "AckReceived",
    "BadFrame",
    "BadFrameReason",
    "Checksum",
    "DecoderEvent",
    "EnqReceived",
    "EotReceived",
    "Frame",
    "MasterMessage",
    "NakReceived",
    "NeedData",
    "Noise",
    "Poll",
    "Symbol",
    "encode_frame",
    "encode_master_message",
    "encode_poll",
    "frame_check",
    "master_check",
]


class Symbol(enum.IntEnum):
    """DF1 transmission characters (1770-6.5.16 p. 2-6 Table 2.A; NAK per ANSI X3.4 and AG-UM008
    B-5; S4516-DF1 manual §2.1).  SOH and EOT occur on half duplex only."""

    SOH = 0x01
    STX = 0x02
    ETX = 0x03
    EOT = 0x04
    ENQ = 0x05
    ACK = 0x06
    DLE = 0x10
    NAK = 0x15


class Checksum(enum.Enum):
    """Error check chosen per link (channel configuration "Error Detection": BCC or CRC)."""

    BCC = "bcc"
    CRC = "crc"

    @property
    def size(self) -> int:
        """Number of check bytes after DLE ETX."""
        return 1 if self is Checksum.BCC else 2





ACK_SYMBOL: Final = bytes((Symbol.DLE, Symbol.ACK))
NAK_SYMBOL: Final = bytes((Symbol.DLE, Symbol.NAK))
ENQ_SYMBOL: Final = bytes((Symbol.DLE, Symbol.ENQ))
EOT_SYMBOL: Final = bytes((Symbol.DLE, Symbol.EOT))

#: Longest message (DST .. last data byte) the decoder stores.  PCCC packets over DF1 stay
#: under 250 bytes (manual §2: "can not be greater than 250"); a margin costs nothing.
DEFAULT_MAX_MESSAGE: Final = 512

#: The error check of a link that does not name one: CRC, the default "Error Detection" of an SLC 500
#: channel 0 in DF1 (1747-RM001G p. 13-52, Table 13.15).
DEFAULT_CHECKSUM: Final = Checksum.CRC

#: The wait for the peer's DLE ACK of a full-duplex frame before a DLE ENQ: "ACK Timeout" 50 x 20 ms,
#: the default of an SLC 500 channel 0 (1747-RM001G p. 13-52, Table 13.15), the wait a PLC's MSG expects
#: of a target.  A half-duplex master's is its line's (half_duplex_events.HALF_DUPLEX_ACK_TIMEOUT).
DEFAULT_ACK_TIMEOUT: Final = 1.0

#: ETX as the one byte a CRC covers after the message (module docstring: over the message and ETX).
ETX_BYTE: Final = bytes((Symbol.ETX,))


# ------------------------------------------------------------------------------------- encoders


def frame_check(message: bytes, checksum: Checksum) -> bytes:
    """Check bytes of a ``DLE STX`` frame: BCC over the message; CRC over the message and ETX."""
    if checksum is Checksum.BCC:
        return bytes((bcc(message),))
    return crc16(ETX_BYTE, crc16(message)).to_bytes(2, "little")


def master_check(station: int, message: bytes, checksum: Checksum) -> bytes:
    """Check bytes of a master message: BCC over STN + message; CRC over STN STX message ETX."""
    if checksum is Checksum.BCC:
        return bytes((bcc(bytes((station,)) + message),))
    return crc16(bytes((station, Symbol.STX)) + message + ETX_BYTE).to_bytes(2, "little")


def _check_station(station: int) -> None:
    if not 0 <= station <= 0xFF:
        raise ValueError(f"DF1 station number must be 0..255, got {station}")


def _stuff(data: bytes) -> bytes:
    return data.replace(b"\x10", b"\x10\x10")


def encode_frame(message: bytes, checksum: Checksum) -> bytes:
    """``DLE STX <message, DLE doubled> DLE ETX <check>``: a full-duplex frame, and a half-duplex
    slave's message (p. 5-2)."""
    if not message:
        raise ValueError("a DF1 frame carries at least one message byte")
    return b"\x10\x02" + _stuff(message) + b"\x10\x03" + frame_check(message, checksum)


def encode_poll(station: int) -> bytes:
    """``DLE ENQ STN BCC``: one BCC byte whatever the link's checksum (p. 5-2, "Important")."""
    _check_station(station)
    return b"\x10\x05" + _stuff(bytes((station,))) + bytes((-station & 0xFF,))


def encode_master_message(station: int, message: bytes, checksum: Checksum) -> bytes:
    """``DLE SOH STN DLE STX <message> DLE ETX <check>`` (p. 5-2; KF2 p. 4-25 Example 1)."""
    _check_station(station)
    if not message:
        raise ValueError("a DF1 master message carries at least one message byte")
    return (
        b"\x10\x01"
        + _stuff(bytes((station,)))
        + b"\x10\x02"
        + _stuff(message)
        + b"\x10\x03"
        + master_check(station, message, checksum)
    )


# --------------------------------------------------------------------------------------- events


@frozen
class Frame:
    """A ``DLE STX`` frame with a valid check (on half duplex: a slave's message); ``message`` is
    unstuffed (DST .. last data byte)."""

    message: bytes

    def __post_init__(self) -> None:
        if not self.message:
            raise ValueError("Frame.message must not be empty")


@frozen
class MasterMessage:
    """Half duplex: a master message with a good check; ``message`` is unstuffed."""

    station: int
    message: bytes

    def __post_init__(self) -> None:
        _check_station(self.station)
        if not self.message:
            raise ValueError("MasterMessage.message must not be empty")


@frozen
class Poll:
    """Half duplex: ``DLE ENQ STN BCC`` with a good BCC."""

    station: int

    def __post_init__(self) -> None:
        _check_station(self.station)


@frozen
class AckReceived:
    """DLE ACK: the peer received our frame."""


@frozen
class NakReceived:
    """DLE NAK: full duplex, the peer received our frame damaged (or could not take it); half
    duplex, from the master, the global link reset (Table 2.C)."""


@frozen
class EnqReceived:
    """Full duplex: DLE ENQ, the peer asks for our last response symbol again.

    ``aborted_frame`` is true when the ENQ arrived in the middle of a frame: the peer's
    transmitter never does that, so the frame in progress was truncated and is dropped.
    """

    aborted_frame: bool = False


@frozen
class EotReceived:
    """Half duplex: DLE EOT, the polled slave has nothing to send."""


@frozen
class Noise:
    """Full duplex, reported only by a decoder made with ``report_noise``: bytes outside a frame
    that start nothing (a byte other than DLE, a DLE followed by no symbol), which the decoder
    discards.  1770-6.5.16 p. 4-8: "else LAST-RESPONSE = NAK"."""


class BadFrameReason(enum.Enum):
    """Why a frame was rejected.  A full-duplex receiver answers each with DLE NAK; a half-duplex
    receiver never NAKs: it stays silent."""

    CHECKSUM = "check bytes do not match"
    INVALID_DLE_SEQUENCE = "DLE followed by an invalid character inside a frame"
    TOO_LONG = "frame longer than the maximum message length"
    EMPTY = "frame without message bytes"
    MISSING_START = "DLE ETX without DLE STX (start of frame lost)"
    TRUNCATED = "a new symbol started before the frame ended"
    BAD_STATION = "station number not sent as DLE DLE, or header without DLE STX"


@frozen
class BadFrame:
    """A damaged frame; ``master`` tells a half-duplex master frame (DLE SOH / DLE ENQ) from a
    ``DLE STX`` one."""

    reason: BadFrameReason
    master: bool = False


DecoderEvent = Frame | MasterMessage | Poll | AckReceived | NakReceived | EnqReceived | EotReceived | BadFrame | Noise
