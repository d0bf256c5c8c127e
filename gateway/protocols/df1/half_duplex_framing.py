"""DF1 half-duplex framing: poll, master message and slave message frames, and a streaming decoder.

Manual: A-B 1770-6.5.16 "DF1 Protocol and Command Set", p. 2-6/2-7 (Tables 2.A, 2.C: symbols),
p. 5-2 (half-duplex frames), p. 5-5 (BCC), p. 5-6/5-7 (CRC); 1770-KF2 user manual p. 4-24/4-25.
Reading and test vectors: ``docs/df1-half-duplex-notes.md``.

Frames on the wire::

    poll            DLE ENQ STN BCC                                      (BCC even on a CRC link)
    master message  DLE SOH STN DLE STX <message> DLE ETX <BCC | CRC lo CRC hi>
    slave message   DLE STX <message> DLE ETX <BCC | CRC lo CRC hi>    (as full duplex)
    responses       DLE ACK, DLE NAK (master only: global link reset), DLE EOT (slave: nothing to send)

* STN and message bytes of value 10 hex are sent as ``DLE DLE`` (Table 2.C); check bytes never
  are (p. 5-5: "a BCC is not treated like data").
* Poll BCC: two's complement of STN.  Master BCC: two's complement of the sum of STN and the
  message bytes.  Slave BCC: of the message bytes (p. 5-2).
* Master CRC: over STN, STX, the message bytes and ETX.  Slave CRC: over the message bytes and
  ETX (p. 5-6 table, p. 5-7 pseudo code).  Register cleared, reflected 0xA001, low byte first.

The decoder hears everything on the line (a 2-wire bus carries both directions), so one decoder
serves the master, the slaves and a line monitor.  It never raises on input and never wedges:
bytes outside a frame are discarded, a new start symbol inside a frame reports the truncated frame
as :class:`BadFrame` and starts the new one, and a frame longer than ``max_message`` is reported
as :class:`BadFrame` when its end arrives.

This module does no I/O.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass
from typing import Final

from gateway.protocols.df1.checks import bcc, crc16
from gateway.protocols.df1.framing import Checksum

__all__ = [
    "ACK",
    "DEFAULT_MAX_MESSAGE",
    "EOT",
    "NAK",
    "NEED_DATA",
    "AckReceived",
    "BadFrame",
    "BadFrameReason",
    "Checksum",
    "EotReceived",
    "HalfDuplexDecoder",
    "HalfDuplexEvent",
    "MasterMessage",
    "NakReceived",
    "NeedData",
    "Poll",
    "SlaveMessage",
    "Symbol",
    "bcc",
    "crc16",
    "encode_master_message",
    "encode_poll",
    "encode_slave_message",
    "master_check",
    "slave_check",
]


class Symbol(enum.IntEnum):
    """Half-duplex characters (1770-6.5.16 p. 2-6 Table 2.A; NAK per ANSI X3.4 and AG-UM008 B-5)."""

    SOH = 0x01
    STX = 0x02
    ETX = 0x03
    EOT = 0x04
    ENQ = 0x05
    ACK = 0x06
    DLE = 0x10
    NAK = 0x15


class NeedData(enum.Enum):
    """Sentinel type: the decoder needs more bytes before it can report anything."""

    NEED_DATA = "NEED_DATA"

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA

ACK: Final = bytes((Symbol.DLE, Symbol.ACK))
NAK: Final = bytes((Symbol.DLE, Symbol.NAK))
EOT: Final = bytes((Symbol.DLE, Symbol.EOT))

#: Longest message stored (DST .. last data byte); PCCC over DF1 stays under 250 bytes.
DEFAULT_MAX_MESSAGE: Final = 512


def _check(covered: bytes, summed: bytes, checksum: Checksum) -> bytes:
    if checksum is Checksum.BCC:
        return bytes((bcc(summed),))
    return crc16(covered).to_bytes(2, "little")


def master_check(station: int, message: bytes, checksum: Checksum) -> bytes:
    """Check bytes of a master message: BCC over STN + message; CRC over STN STX message ETX."""
    return _check(bytes((station, Symbol.STX)) + message + bytes((Symbol.ETX,)), bytes((station,)) + message, checksum)


def slave_check(message: bytes, checksum: Checksum) -> bytes:
    """Check bytes of a slave message: BCC over the message; CRC over message ETX."""
    return _check(message + bytes((Symbol.ETX,)), message, checksum)


def _check_station(station: int) -> None:
    if not 0 <= station <= 0xFF:
        raise ValueError(f"DF1 station number must be 0..255, got {station}")


def _stuff(data: bytes) -> bytes:
    return data.replace(b"\x10", b"\x10\x10")


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


def encode_slave_message(message: bytes, checksum: Checksum) -> bytes:
    """``DLE STX <message> DLE ETX <check>``, the full-duplex frame (p. 5-2)."""
    if not message:
        raise ValueError("a DF1 slave message carries at least one message byte")
    return b"\x10\x02" + _stuff(message) + b"\x10\x03" + slave_check(message, checksum)


# --------------------------------------------------------------------------------------- events


@dataclass(frozen=True, slots=True)
class Poll:
    """``DLE ENQ STN BCC`` with a good BCC."""

    station: int

    def __post_init__(self) -> None:
        _check_station(self.station)


@dataclass(frozen=True, slots=True)
class MasterMessage:
    """A master message with a good check; ``message`` is unstuffed (DST .. last data byte)."""

    station: int
    message: bytes

    def __post_init__(self) -> None:
        _check_station(self.station)
        if not self.message:
            raise ValueError("MasterMessage.message must not be empty")


@dataclass(frozen=True, slots=True)
class SlaveMessage:
    """A slave message with a good check; ``message`` is unstuffed."""

    message: bytes

    def __post_init__(self) -> None:
        if not self.message:
            raise ValueError("SlaveMessage.message must not be empty")


@dataclass(frozen=True, slots=True)
class AckReceived:
    """DLE ACK."""


@dataclass(frozen=True, slots=True)
class NakReceived:
    """DLE NAK (from the master: global link reset, Table 2.C)."""


@dataclass(frozen=True, slots=True)
class EotReceived:
    """DLE EOT: the polled slave has nothing to send."""


class BadFrameReason(enum.Enum):
    """Why a frame was rejected.  A half-duplex receiver never NAKs: it stays silent."""

    CHECKSUM = "check bytes do not match"
    INVALID_DLE_SEQUENCE = "DLE followed by an invalid character"
    TOO_LONG = "frame longer than the maximum message length"
    EMPTY = "frame without message bytes"
    TRUNCATED = "a new symbol started before the frame ended"
    BAD_STATION = "station number not sent as DLE DLE, or header without DLE STX"


@dataclass(frozen=True, slots=True)
class BadFrame:
    """A damaged poll or message; ``master`` tells a master frame (DLE SOH / DLE ENQ) from a slave one."""

    reason: BadFrameReason
    master: bool


HalfDuplexEvent = Poll | MasterMessage | SlaveMessage | AckReceived | NakReceived | EotReceived | BadFrame


# -------------------------------------------------------------------------------------- decoder


class _State(enum.Enum):
    IDLE = "idle"  #: hunting for DLE
    IDLE_DLE = "idle-dle"  #: DLE seen outside a frame
    POLL_STN = "poll-stn"  #: DLE ENQ seen: STN next
    POLL_STN_DLE = "poll-stn-dle"  #: DLE ENQ DLE: the second DLE of STN 10 next
    POLL_BCC = "poll-bcc"  #: STN read: BCC next
    HEAD_STN = "head-stn"  #: DLE SOH seen: STN next
    HEAD_STN_DLE = "head-stn-dle"  #: DLE SOH DLE: second DLE of STN 10 next
    HEAD_DLE = "head-dle"  #: DLE SOH STN: DLE next
    HEAD_STX = "head-stx"  #: DLE SOH STN DLE: STX next
    DATA = "data"  #: inside the message
    DATA_DLE = "data-dle"  #: DLE inside the message
    CHECK = "check"  #: collecting the check bytes (counted)


class _Class(enum.Enum):
    DLE = "dle"
    SOH = "soh"
    STX = "stx"
    ETX = "etx"
    EOT = "eot"
    ENQ = "enq"
    ACK = "ack"
    NAK = "nak"
    OTHER = "other"


_SYMBOL_CLASS: Final[dict[int, _Class]] = {
    int(Symbol.DLE): _Class.DLE,
    int(Symbol.SOH): _Class.SOH,
    int(Symbol.STX): _Class.STX,
    int(Symbol.ETX): _Class.ETX,
    int(Symbol.EOT): _Class.EOT,
    int(Symbol.ENQ): _Class.ENQ,
    int(Symbol.ACK): _Class.ACK,
    int(Symbol.NAK): _Class.NAK,
}
_CLASS_OF: Final = tuple(_SYMBOL_CLASS.get(byte, _Class.OTHER) for byte in range(256))


class _Act(enum.Enum):
    NONE = "none"
    START_POLL = "start-poll"  #: DLE ENQ
    START_MASTER = "start-master"  #: DLE SOH
    START_SLAVE = "start-slave"  #: DLE STX outside a header
    STATION = "station"  #: store the byte as STN
    STATION_DLE = "station-dle"  #: store 10 hex as STN
    POLL_END = "poll-end"  #: the byte is the poll BCC
    BODY = "body"  #: DLE STX after a master header: the message starts
    APPEND = "append"
    APPEND_DLE = "append-dle"
    END = "end"  #: DLE ETX: collect the check
    ACK = "ack"
    NAK = "nak"
    EOT = "eot"
    BAD_STATION = "bad-station"  #: the frame is broken in its header: report, back to IDLE
    INVALID = "invalid"  #: mark the message bad and keep reading to DLE ETX


_SYMBOL_ACTS: Final = {
    _Class.ENQ: (_Act.START_POLL, _State.POLL_STN),
    _Class.SOH: (_Act.START_MASTER, _State.HEAD_STN),
    _Class.STX: (_Act.START_SLAVE, _State.DATA),
    _Class.ACK: (_Act.ACK, _State.IDLE),
    _Class.NAK: (_Act.NAK, _State.IDLE),
    _Class.EOT: (_Act.EOT, _State.IDLE),
}


def _build_table() -> dict[tuple[_State, _Class], tuple[_Act, _State]]:
    """(state, byte class) -> (action, next state); CHECK is a counted state outside the table.

    A start or response symbol (DLE ENQ/SOH/STX/ACK/NAK/EOT) is honoured in every state where a
    DLE may be followed by it: inside a frame it reports the frame so far as TRUNCATED (the
    ``_Act`` handlers do that when a frame is open) and then acts as outside one.
    """
    table: dict[tuple[_State, _Class], tuple[_Act, _State]] = {}
    for cls in _Class:
        table[_State.IDLE, cls] = (_Act.NONE, _State.IDLE)
        table[_State.IDLE_DLE, cls] = (_Act.NONE, _State.IDLE)
        table[_State.POLL_STN, cls] = (_Act.STATION, _State.POLL_BCC)
        table[_State.POLL_STN_DLE, cls] = (_Act.BAD_STATION, _State.IDLE)
        table[_State.POLL_BCC, cls] = (_Act.POLL_END, _State.IDLE)
        table[_State.HEAD_STN, cls] = (_Act.STATION, _State.HEAD_DLE)
        table[_State.HEAD_STN_DLE, cls] = (_Act.BAD_STATION, _State.IDLE)
        table[_State.HEAD_DLE, cls] = (_Act.BAD_STATION, _State.IDLE)
        table[_State.HEAD_STX, cls] = (_Act.BAD_STATION, _State.IDLE)
        table[_State.DATA, cls] = (_Act.APPEND, _State.DATA)
        table[_State.DATA_DLE, cls] = (_Act.INVALID, _State.DATA)
    for cls, step in _SYMBOL_ACTS.items():
        table[_State.IDLE_DLE, cls] = step
        table[_State.POLL_STN_DLE, cls] = step
        table[_State.HEAD_STN_DLE, cls] = step
        table[_State.HEAD_STX, cls] = step
        table[_State.DATA_DLE, cls] = step
    table.update(
        {
            (_State.IDLE, _Class.DLE): (_Act.NONE, _State.IDLE_DLE),
            # DLE DLE outside a frame: keep the second DLE as a possible start of a symbol.
            (_State.IDLE_DLE, _Class.DLE): (_Act.NONE, _State.IDLE_DLE),
            (_State.POLL_STN, _Class.DLE): (_Act.NONE, _State.POLL_STN_DLE),
            (_State.POLL_STN_DLE, _Class.DLE): (_Act.STATION_DLE, _State.POLL_BCC),
            (_State.HEAD_STN, _Class.DLE): (_Act.NONE, _State.HEAD_STN_DLE),
            (_State.HEAD_STN_DLE, _Class.DLE): (_Act.STATION_DLE, _State.HEAD_DLE),
            (_State.HEAD_DLE, _Class.DLE): (_Act.NONE, _State.HEAD_STX),
            (_State.HEAD_STX, _Class.STX): (_Act.BODY, _State.DATA),
            (_State.DATA, _Class.DLE): (_Act.NONE, _State.DATA_DLE),
            (_State.DATA_DLE, _Class.DLE): (_Act.APPEND_DLE, _State.DATA),
            (_State.DATA_DLE, _Class.ETX): (_Act.END, _State.CHECK),
        }
    )
    return table


#: The decoder's state machine.
TRANSITIONS: Final = _build_table()


class HalfDuplexDecoder:
    """Streaming half-duplex decoder: ``feed(bytes)`` then ``next_event()`` until ``NEED_DATA``."""

    def __init__(self, checksum: Checksum, *, max_message: int = DEFAULT_MAX_MESSAGE) -> None:
        if max_message < 1:
            raise ValueError("max_message must be at least 1")
        self.checksum: Final = checksum
        self.max_message: Final = max_message
        self._state = _State.IDLE
        self._master = False  #: the open frame is a master message
        self._station = 0
        self._message = bytearray()
        self._check = bytearray()
        self._bad: BadFrameReason | None = None
        self._events: deque[HalfDuplexEvent] = deque()

    @property
    def in_frame(self) -> bool:
        """True while part of a poll or message has been received."""
        return self._state not in (_State.IDLE, _State.IDLE_DLE)

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
                    self._finish_message()
                    self._state = _State.IDLE
                continue
            was_in_frame = self.in_frame and self._state is not _State.POLL_BCC
            action, next_state = TRANSITIONS[self._state, _CLASS_OF[byte]]
            if action in _STARTS and was_in_frame:
                self._events.append(BadFrame(BadFrameReason.TRUNCATED, self._master))
            self._apply(action, byte)
            self._state = next_state

    def next_event(self) -> HalfDuplexEvent | NeedData:
        """The next frame, symbol or bad frame, or ``NEED_DATA``."""
        if self._events:
            return self._events.popleft()
        return NEED_DATA

    def _apply(self, action: _Act, byte: int) -> None:
        if action is _Act.NONE:
            return
        if action is _Act.APPEND:
            self._append(byte)
        elif action is _Act.APPEND_DLE:
            self._append(Symbol.DLE)
        elif action is _Act.START_POLL:
            self._open(master=True)
        elif action is _Act.START_MASTER:
            self._open(master=True)
        elif action is _Act.START_SLAVE:
            self._open(master=False)
        elif action is _Act.STATION:
            self._station = byte
        elif action is _Act.STATION_DLE:
            self._station = Symbol.DLE
        elif action is _Act.POLL_END:
            if byte == -self._station & 0xFF:
                self._events.append(Poll(self._station))
            else:
                self._events.append(BadFrame(BadFrameReason.CHECKSUM, True))
        elif action is _Act.BODY:
            self._message.clear()
        elif action is _Act.END:
            self._check.clear()
        elif action is _Act.ACK:
            self._events.append(AckReceived())
        elif action is _Act.NAK:
            self._events.append(NakReceived())
        elif action is _Act.EOT:
            self._events.append(EotReceived())
        elif action is _Act.BAD_STATION:
            self._events.append(BadFrame(BadFrameReason.BAD_STATION, self._master))
        elif action is _Act.INVALID and self._bad is None:
            self._bad = BadFrameReason.INVALID_DLE_SEQUENCE

    def _open(self, *, master: bool) -> None:
        self._master = master
        self._message.clear()
        self._bad = None

    def _append(self, byte: int) -> None:
        if len(self._message) >= self.max_message:
            self._bad = BadFrameReason.TOO_LONG
        else:
            self._message.append(byte)

    def _finish_message(self) -> None:
        message = bytes(self._message)
        check = bytes(self._check)
        bad = self._bad
        self._message.clear()
        self._check.clear()
        self._bad = None
        if bad is None and not message:
            bad = BadFrameReason.EMPTY
        if bad is None:
            expected = (
                master_check(self._station, message, self.checksum)
                if self._master
                else slave_check(message, self.checksum)
            )
            if check != expected:
                bad = BadFrameReason.CHECKSUM
        if bad is not None:
            self._events.append(BadFrame(bad, self._master))
        elif self._master:
            self._events.append(MasterMessage(self._station, message))
        else:
            self._events.append(SlaveMessage(message))


#: Actions that begin a new symbol; inside an open frame they truncate it.
_STARTS: Final = frozenset({_Act.START_POLL, _Act.START_MASTER, _Act.START_SLAVE, _Act.ACK, _Act.NAK, _Act.EOT})
