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

from gateway.protocols.df1.checks import bcc, crc16

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


_ETX_BYTE: Final = bytes((Symbol.ETX,))


def _check_bytes(message: bytes, checksum: Checksum) -> bytes:
    if checksum is Checksum.BCC:
        return bytes((bcc(message),))
    return crc16(_ETX_BYTE, crc16(message)).to_bytes(2, "little")


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


class _State(enum.IntEnum):
    """Decoder states; the decoder keeps them as plain ints (``int(_State.X)``)."""

    IDLE = 0  #: hunting for DLE STX
    IDLE_DLE = 1  #: DLE seen outside a frame
    IN_FRAME = 2  #: inside a frame
    IN_FRAME_DLE = 3  #: DLE seen inside a frame
    CHECK = 4  #: collecting the check bytes


class _Class(enum.IntEnum):
    """What a byte means after a DLE (outside a DLE only DLE vs OTHER matters)."""

    DLE = 0
    STX = 1
    ETX = 2
    ACK = 3
    NAK = 4
    ENQ = 5
    OTHER = 6


_SYMBOL_CLASS: Final = {
    int(Symbol.DLE): _Class.DLE,
    int(Symbol.STX): _Class.STX,
    int(Symbol.ETX): _Class.ETX,
    int(Symbol.ACK): _Class.ACK,
    int(Symbol.NAK): _Class.NAK,
    int(Symbol.ENQ): _Class.ENQ,
}

#: Byte value -> its class (a 256-entry table).
_CLASS_OF: Final = tuple(_SYMBOL_CLASS.get(byte, _Class.OTHER) for byte in range(256))


class _Act(enum.IntEnum):
    DISCARD = 0  #: discard
    START = 1  #: start a frame
    APPEND = 2  #: append the byte to the message
    APPEND_DLE = 3  #: append one 0x10 (DLE DLE)
    END = 4  #: DLE ETX: collect the check bytes
    ACK = 5  #: report DLE ACK
    NAK = 6  #: report DLE NAK
    ENQ = 7  #: report DLE ENQ
    ENQ_ABORT = 8  #: report DLE ENQ, dropping the truncated frame
    INVALID = 9  #: mark the frame bad (invalid DLE sequence)
    MISSING_START = 10  #: report a frame whose start was lost
    NONE = 11  #: no action


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


def _compile_table() -> tuple[tuple[int, int], ...]:
    """:data:`_TRANSITIONS` keyed by plain ints: entry ``state << 8 | byte`` is (action, next state).

    Enum members hash in Python code; the decoder only ever indexes this tuple with ints.
    CHECK, the last state, has no row (a missing pair for any other state fails here, at import).
    """
    steps: list[tuple[int, int]] = []
    for state in _State:
        if state is _State.CHECK:
            continue
        for byte in range(256):
            action, next_state = _TRANSITIONS[state, _CLASS_OF[byte]]
            steps.append((int(action), int(next_state)))
    return tuple(steps)


_STEP: Final = _compile_table()


def _verify_fast_paths() -> None:
    """The decoder applies some rows of the table to whole runs of bytes at once.

    * IDLE: every non-DLE byte is discarded, so noise up to the next DLE is skipped with
      ``bytes.find``;
    * IN_FRAME: every non-DLE byte is appended, and IN_FRAME_DLE + DLE appends one DLE and
      returns to IN_FRAME, so message data up to the next DLE *not* followed by a DLE is one
      slice, unstuffed with ``bytes.replace``.  APPEND and APPEND_DLE share the length bound,
      which the decoder applies to the unstuffed run.

    Checked at import, so an edit of the table cannot silently disagree with the fast paths.
    """
    expected: dict[tuple[_State, _Class], tuple[_Act, _State]] = {
        (_State.IN_FRAME_DLE, _Class.DLE): (_Act.APPEND_DLE, _State.IN_FRAME),
        (_State.IDLE, _Class.DLE): (_Act.NONE, _State.IDLE_DLE),
        (_State.IN_FRAME, _Class.DLE): (_Act.NONE, _State.IN_FRAME_DLE),
    }
    for cls in _Class:
        if cls is not _Class.DLE:
            expected[_State.IDLE, cls] = (_Act.DISCARD, _State.IDLE)
            expected[_State.IN_FRAME, cls] = (_Act.APPEND, _State.IN_FRAME)
    for key, step in expected.items():
        if _TRANSITIONS[key] != step:
            raise RuntimeError(f"DF1 decoder fast path disagrees with the transition table at {key!r}")


_verify_fast_paths()

# Plain-int copies of the states and actions the decoder's loop tests.
_IDLE: Final = int(_State.IDLE)
_IDLE_DLE: Final = int(_State.IDLE_DLE)
_IN_FRAME: Final = int(_State.IN_FRAME)
_IN_FRAME_DLE: Final = int(_State.IN_FRAME_DLE)
_CHECK: Final = int(_State.CHECK)
_START: Final = int(_Act.START)
_APPEND_DLE: Final = int(_Act.APPEND_DLE)
_END: Final = int(_Act.END)
_ACK: Final = int(_Act.ACK)
_NAK: Final = int(_Act.NAK)
_ENQ: Final = int(_Act.ENQ)
_ENQ_ABORT: Final = int(_Act.ENQ_ABORT)
_INVALID: Final = int(_Act.INVALID)
_MISSING_START: Final = int(_Act.MISSING_START)


class FrameDecoder:
    """Streaming DF1 decoder: ``feed(bytes)`` then ``next_event()`` until ``NEED_DATA``.

    The state machine is :data:`_TRANSITIONS`, applied through its int-keyed form
    :data:`_STEP` one byte at a time after a DLE.  Between DLEs (hunting for a frame, or inside
    one) every byte takes the same transition, so such a run is skipped or copied with one
    ``bytes.find`` and one slice (see :func:`_verify_fast_paths`); a read that lies wholly
    inside a frame's data is appended in one step.  The events are exactly those of feeding
    the table one byte at a time (``tests/test_df1_framing_equivalence.py``).
    """

    def __init__(self, checksum: Checksum, *, max_message: int = DEFAULT_MAX_MESSAGE) -> None:
        if max_message < 1:
            raise ValueError("max_message must be at least 1")
        self.checksum: Final = checksum
        self.max_message: Final = max_message
        self._check_size: Final = checksum.size
        self._state = _IDLE
        self._message = bytearray()
        self._bad: BadFrameReason | None = None
        self._check = bytearray()
        self._events: deque[DecoderEvent] = deque()

    @property
    def in_frame(self) -> bool:
        """True while part of a frame has been received."""
        return self._state >= _IN_FRAME  # IN_FRAME, IN_FRAME_DLE or CHECK

    def reset(self) -> None:
        """Forget any partial frame and pending events."""
        self._state = _IDLE
        self._message.clear()
        self._check.clear()
        self._bad = None
        self._events.clear()

    def feed(self, data: bytes) -> None:
        """Consume ``data``; complete frames and symbols are queued for :meth:`next_event`."""
        if type(data) is not bytes:
            data = bytes(data)
        state = self._state
        message = self._message
        if state == _IN_FRAME and _DLE not in data and len(message) + len(data) <= self.max_message:
            message += data  # the common case of a small read: nothing but message data
            return
        end = len(data)
        pos = 0
        find = data.find
        while pos < end:
            if state == _IN_FRAME:
                # Message data up to the next DLE that is not doubled, unstuffed in one slice.
                dle = find(_DLE, pos)
                doubled = False
                while 0 <= dle < end - 1 and data[dle + 1] == _DLE:
                    doubled = True
                    dle = find(_DLE, dle + 2)
                if dle < 0:
                    run = data[pos:]
                    pos = end
                else:
                    run = data[pos:dle]
                    pos = dle + 1
                    state = _IN_FRAME_DLE
                if doubled:
                    run = run.replace(b"\x10\x10", b"\x10")
                room = self.max_message - len(message)
                if len(run) <= room:
                    message += run
                else:
                    message += run[:room]
                    self._bad = BadFrameReason.TOO_LONG
            elif state == _IDLE:
                # Noise up to the next DLE is discarded.
                dle = find(_DLE, pos)
                if dle < 0:
                    break
                pos = dle + 1
                state = _IDLE_DLE
            elif state == _CHECK:
                check = self._check
                take = self._check_size - len(check)
                check += data[pos : pos + take]
                pos += take
                if len(check) == self._check_size:
                    self._finish_frame()
                    state = _IDLE
            else:
                action, state = _STEP[state << 8 | data[pos]]
                pos += 1
                if action == _START:
                    message.clear()
                    self._bad = None
                elif action == _END:
                    self._check.clear()
                elif action == _APPEND_DLE:
                    if len(message) >= self.max_message:
                        self._bad = BadFrameReason.TOO_LONG
                    else:
                        message.append(_DLE)
                elif action == _ACK:
                    self._events.append(AckReceived())
                elif action == _NAK:
                    self._events.append(NakReceived())
                elif action == _ENQ:
                    self._events.append(EnqReceived())
                elif action == _ENQ_ABORT:
                    message.clear()
                    self._bad = None
                    self._events.append(EnqReceived(aborted_frame=True))
                elif action == _INVALID:
                    if self._bad is None:
                        self._bad = BadFrameReason.INVALID_DLE_SEQUENCE
                elif action == _MISSING_START:
                    self._events.append(BadFrame(BadFrameReason.MISSING_START))
                # DISCARD and NONE: nothing to do.
        self._state = state

    def next_event(self) -> DecoderEvent | NeedData:
        """The next frame, link symbol or bad frame, or ``NEED_DATA``."""
        if self._events:
            return self._events.popleft()
        return NEED_DATA

    def _finish_frame(self) -> None:
        message = bytes(self._message)
        check = self._check
        bad = self._bad
        self._message.clear()
        self._bad = None
        if bad is None and not message:
            bad = BadFrameReason.EMPTY
        if bad is None:
            if self.checksum is Checksum.BCC:
                good = check[0] == bcc(message)
            else:
                good = check[0] | check[1] << 8 == crc16(_ETX_BYTE, crc16(message))
            if not good:
                bad = BadFrameReason.CHECKSUM
        check.clear()
        self._events.append(Frame(message) if bad is None else BadFrame(bad))
