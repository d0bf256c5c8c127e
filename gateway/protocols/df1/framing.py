"""DF1 full-duplex framing: DLE symbols, BCC / CRC-16, frame encoding and a streaming decoder.

Manual: "S4516-DF1 Program Development Manual", §2.1 *Full Duplex Transmission Characters*,
§2.3 *Packet Format for Full Duplex Protocol*, §2.5 *How the Receiver Operates*
(after A-B 1770-6.5.16, chapter 2).

A frame on the wire::

    +-----+-----+--------------------------------+-----+-----+-----------------+
    | DLE | STX | message (each 0x10 sent twice)  | DLE | ETX | check (1 or 2)  |
    +-----+-----+--------------------------------+-----+-----+-----------------+

* BCC (1 byte): two's complement of the 8-bit sum of the message bytes (a doubled DLE counts once).
* CRC-16 (2 bytes, low byte first): reflected polynomial 0xA001, initial value 0, computed over
  the message bytes followed by ETX (0x03).

The check bytes are not DLE-doubled.  Link symbols are two bytes: DLE ACK, DLE NAK, DLE ENQ.
Because the link is full duplex, the peer's receiver may embed DLE ACK / DLE NAK inside a frame
its transmitter is sending; the decoder reports them and keeps assembling the frame.

The decoder never raises on input and never wedges: bytes outside ``DLE STX .. DLE ETX`` are
discarded, ``DLE STX`` inside a frame restarts it, and a frame longer than ``max_message``
bytes stops being stored and is reported as :class:`BadFrame` when its ``DLE ETX`` arrives.

This module does no I/O.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass
from typing import Final

__all__ = [
    "ACK_SYMBOL",
    "DEFAULT_MAX_MESSAGE",
    "ENQ_SYMBOL",
    "NAK_SYMBOL",
    "NEED_DATA",
    "AckReceived",
    "BadFrame",
    "BadFrameReason",
    "Checksum",
    "DecoderEvent",
    "EnqReceived",
    "Frame",
    "FrameDecoder",
    "NakReceived",
    "NeedData",
    "Symbol",
    "bcc",
    "crc16",
    "encode_frame",
]


class Symbol(enum.IntEnum):
    """Full-duplex transmission characters (S4516-DF1 manual §2.1)."""

    STX = 0x02
    ETX = 0x03
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


class NeedData(enum.Enum):
    """Sentinel type: the decoder needs more bytes before it can report anything."""

    NEED_DATA = "NEED_DATA"

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA

ACK_SYMBOL: Final = bytes((Symbol.DLE, Symbol.ACK))
NAK_SYMBOL: Final = bytes((Symbol.DLE, Symbol.NAK))
ENQ_SYMBOL: Final = bytes((Symbol.DLE, Symbol.ENQ))

#: Longest message (DST .. last data byte) the decoder stores.  PCCC packets over DF1 stay
#: under 250 bytes (manual §2: "can not be greater than 250"); a margin costs nothing.
DEFAULT_MAX_MESSAGE: Final = 512

_DLE: Final = int(Symbol.DLE)


def bcc(message: bytes) -> int:
    """Block check character: two's complement of the 8-bit sum of ``message`` (unstuffed)."""
    return -sum(message) & 0xFF


def _crc_table() -> tuple[int, ...]:
    table = []
    for value in range(256):
        crc = value
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _crc_table()


def crc16(message: bytes) -> int:
    """DF1 CRC-16 of ``message`` (unstuffed) followed by ETX; reflected 0xA001, initial 0."""
    crc = 0
    for byte in message:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return (crc >> 8) ^ _CRC_TABLE[(crc ^ Symbol.ETX) & 0xFF]


def _check_bytes(message: bytes, checksum: Checksum) -> bytes:
    if checksum is Checksum.BCC:
        return bytes((bcc(message),))
    return crc16(message).to_bytes(2, "little")


def encode_frame(message: bytes, checksum: Checksum) -> bytes:
    """``DLE STX <message, DLE doubled> DLE ETX <check>``."""
    if not message:
        raise ValueError("a DF1 frame carries at least one message byte")
    stuffed = message.replace(b"\x10", b"\x10\x10")
    return b"\x10\x02" + stuffed + b"\x10\x03" + _check_bytes(message, checksum)


# --------------------------------------------------------------------------------------- events


@dataclass(frozen=True, slots=True)
class Frame:
    """A frame with a valid check; ``message`` is unstuffed (DST .. last data byte)."""

    message: bytes

    def __post_init__(self) -> None:
        if not self.message:
            raise ValueError("Frame.message must not be empty")


@dataclass(frozen=True, slots=True)
class AckReceived:
    """DLE ACK: the peer received our frame."""


@dataclass(frozen=True, slots=True)
class NakReceived:
    """DLE NAK: the peer received our frame damaged (or could not take it)."""


@dataclass(frozen=True, slots=True)
class EnqReceived:
    """DLE ENQ: the peer asks for our last response symbol again.

    ``aborted_frame`` is true when the ENQ arrived in the middle of a frame: the peer's
    transmitter never does that, so the frame in progress was truncated and is dropped.
    """

    aborted_frame: bool = False


class BadFrameReason(enum.Enum):
    """Why a frame was rejected; every one of these must be answered with DLE NAK."""

    CHECKSUM = "check bytes do not match"
    INVALID_DLE_SEQUENCE = "DLE followed by an invalid character inside a frame"
    TOO_LONG = "frame longer than the maximum message length"
    EMPTY = "frame without message bytes"
    MISSING_START = "DLE ETX without DLE STX (start of frame lost)"


@dataclass(frozen=True, slots=True)
class BadFrame:
    """A damaged frame; the receiver answers DLE NAK (manual §2.5)."""

    reason: BadFrameReason


DecoderEvent = Frame | AckReceived | NakReceived | EnqReceived | BadFrame


# -------------------------------------------------------------------------------------- decoder


class _State(enum.Enum):
    IDLE = "hunting for DLE STX"
    IDLE_DLE = "DLE seen outside a frame"
    IN_FRAME = "inside a frame"
    IN_FRAME_DLE = "DLE seen inside a frame"
    CHECK = "collecting the check bytes"


class _Class(enum.Enum):
    """What a byte means after a DLE (outside a DLE only DLE vs OTHER matters)."""

    DLE = Symbol.DLE
    STX = Symbol.STX
    ETX = Symbol.ETX
    ACK = Symbol.ACK
    NAK = Symbol.NAK
    ENQ = Symbol.ENQ
    OTHER = None


_CLASS_OF: Final = {int(c.value): c for c in _Class if c.value is not None}


class _Act(enum.Enum):
    DISCARD = "discard"
    START = "start a frame"
    APPEND = "append the byte to the message"
    APPEND_DLE = "append one 0x10 (DLE DLE)"
    END = "DLE ETX: collect the check bytes"
    ACK = "report DLE ACK"
    NAK = "report DLE NAK"
    ENQ = "report DLE ENQ"
    ENQ_ABORT = "report DLE ENQ, dropping the truncated frame"
    INVALID = "mark the frame bad (invalid DLE sequence)"
    MISSING_START = "report a frame whose start was lost"
    NONE = "no action"


def _build_table() -> dict[tuple[_State, _Class], tuple[_Act, _State]]:
    table: dict[tuple[_State, _Class], tuple[_Act, _State]] = {}
    for cls in _Class:
        # Outside a frame: only DLE is interesting.
        table[_State.IDLE, cls] = (_Act.DISCARD, _State.IDLE)
        # Inside a frame every non-DLE byte is message data.
        table[_State.IN_FRAME, cls] = (_Act.APPEND, _State.IN_FRAME)
    table[_State.IDLE, _Class.DLE] = (_Act.NONE, _State.IDLE_DLE)
    table[_State.IN_FRAME, _Class.DLE] = (_Act.NONE, _State.IN_FRAME_DLE)
    table.update(
        {
            # DLE <x> outside a frame
            (_State.IDLE_DLE, _Class.STX): (_Act.START, _State.IN_FRAME),
            (_State.IDLE_DLE, _Class.ACK): (_Act.ACK, _State.IDLE),
            (_State.IDLE_DLE, _Class.NAK): (_Act.NAK, _State.IDLE),
            (_State.IDLE_DLE, _Class.ENQ): (_Act.ENQ, _State.IDLE),
            (_State.IDLE_DLE, _Class.ETX): (_Act.MISSING_START, _State.IDLE),
            # DLE DLE outside a frame: the first DLE is noise (or the tail of a lost frame); keep
            # the second as a possible start of DLE STX rather than pairing them, so a stray DLE
            # (e.g. of a damaged DLE ENQ) cannot swallow the next frame's start.
            (_State.IDLE_DLE, _Class.DLE): (_Act.NONE, _State.IDLE_DLE),
            (_State.IDLE_DLE, _Class.OTHER): (_Act.DISCARD, _State.IDLE),
            # DLE <x> inside a frame
            (_State.IN_FRAME_DLE, _Class.DLE): (_Act.APPEND_DLE, _State.IN_FRAME),
            (_State.IN_FRAME_DLE, _Class.ETX): (_Act.END, _State.CHECK),
            (_State.IN_FRAME_DLE, _Class.STX): (_Act.START, _State.IN_FRAME),
            (_State.IN_FRAME_DLE, _Class.ACK): (_Act.ACK, _State.IN_FRAME),
            (_State.IN_FRAME_DLE, _Class.NAK): (_Act.NAK, _State.IN_FRAME),
            (_State.IN_FRAME_DLE, _Class.ENQ): (_Act.ENQ_ABORT, _State.IDLE),
            (_State.IN_FRAME_DLE, _Class.OTHER): (_Act.INVALID, _State.IN_FRAME),
        }
    )
    return table


#: (state, byte class) -> (action, next state).  CHECK is a counted state outside the table.
_TRANSITIONS: Final = _build_table()


class FrameDecoder:
    """Streaming DF1 decoder: ``feed(bytes)`` then ``next_event()`` until ``NEED_DATA``."""

    def __init__(self, checksum: Checksum, *, max_message: int = DEFAULT_MAX_MESSAGE) -> None:
        if max_message < 1:
            raise ValueError("max_message must be at least 1")
        self.checksum: Final = checksum
        self.max_message: Final = max_message
        self._state = _State.IDLE
        self._message = bytearray()
        self._bad: BadFrameReason | None = None
        self._check = bytearray()
        self._events: deque[DecoderEvent] = deque()

    @property
    def in_frame(self) -> bool:
        """True while part of a frame has been received."""
        return self._state is not _State.IDLE and self._state is not _State.IDLE_DLE

    def reset(self) -> None:
        """Forget any partial frame and pending events."""
        self._state = _State.IDLE
        self._message.clear()
        self._check.clear()
        self._bad = None
        self._events.clear()

    def feed(self, data: bytes) -> None:
        """Consume ``data``; complete frames and symbols are queued for :meth:`next_event`."""
        for byte in data:
            if self._state is _State.CHECK:
                self._check.append(byte)
                if len(self._check) == self.checksum.size:
                    self._finish_frame()
                continue
            action, self._state = _TRANSITIONS[self._state, _CLASS_OF.get(byte, _Class.OTHER)]
            self._perform(action, byte)

    def next_event(self) -> DecoderEvent | NeedData:
        """The next frame, link symbol or bad frame, or ``NEED_DATA``."""
        if self._events:
            return self._events.popleft()
        return NEED_DATA

    def _perform(self, action: _Act, byte: int) -> None:
        match action:
            case _Act.DISCARD | _Act.NONE:
                pass
            case _Act.START:
                self._message.clear()
                self._bad = None
            case _Act.APPEND:
                self._append(byte)
            case _Act.APPEND_DLE:
                self._append(_DLE)
            case _Act.END:
                self._check.clear()
            case _Act.ACK:
                self._events.append(AckReceived())
            case _Act.NAK:
                self._events.append(NakReceived())
            case _Act.ENQ:
                self._events.append(EnqReceived())
            case _Act.ENQ_ABORT:
                self._message.clear()
                self._bad = None
                self._events.append(EnqReceived(aborted_frame=True))
            case _Act.INVALID:
                if self._bad is None:
                    self._bad = BadFrameReason.INVALID_DLE_SEQUENCE
            case _Act.MISSING_START:
                self._events.append(BadFrame(BadFrameReason.MISSING_START))

    def _append(self, byte: int) -> None:
        if len(self._message) >= self.max_message:
            self._bad = BadFrameReason.TOO_LONG
            return
        self._message.append(byte)

    def _finish_frame(self) -> None:
        message = bytes(self._message)
        check = bytes(self._check)
        bad = self._bad
        self._message.clear()
        self._check.clear()
        self._bad = None
        self._state = _State.IDLE
        if bad is None and not message:
            bad = BadFrameReason.EMPTY
        if bad is None and check != _check_bytes(message, self.checksum):
            bad = BadFrameReason.CHECKSUM
        self._events.append(Frame(message) if bad is None else BadFrame(bad))
