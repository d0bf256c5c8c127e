"""The streaming DF1 frame decoder, full and half duplex (sans-I/O).

Manual: "S4516-DF1 Program Development Manual" §2.5 *How the Receiver Operates* (full duplex);
A-B 1770-6.5.16 p. 5-2 and 1770-KF2 p. 4-24/4-25 (half duplex).  The frames, symbols and events
are those of :mod:`gateway.protocols.df1.framing`.

One engine runs one of two transition tables:

* :data:`FULL_DUPLEX_TRANSITIONS`: ``DLE STX`` frames and DLE ACK / NAK / ENQ.  The peer's receiver
  may embed DLE ACK / DLE NAK inside a frame its transmitter is sending: they are reported and the
  frame goes on.  ``DLE STX`` inside a frame restarts it; DLE ENQ inside one drops it
  (:class:`EnqReceived` with ``aborted_frame``); ``DLE ETX`` outside a frame is a frame whose start
  was lost.
* :data:`HALF_DUPLEX_TRANSITIONS` (``half_duplex=True``): the full-duplex table plus what a 2-wire
  bus carries besides - polls (DLE ENQ STN BCC), master messages (DLE SOH STN DLE STX ...) and
  DLE EOT.  The decoder hears everything on the line, so one decoder serves the master, the
  slaves and a line monitor.  Here a start or response symbol inside a frame reports the frame so
  far as TRUNCATED and is then read as outside one; ``DLE ETX`` outside a frame is ignored.

The decoder never raises on input and never wedges: bytes outside a frame are discarded (with
``report_noise``, a full-duplex station's, reported as :class:`Noise`, once per run discarded at
once), and a frame longer than ``max_message`` bytes stops being stored and is reported as
:class:`BadFrame` when its ``DLE ETX`` arrives.

This module does no I/O.
"""

from __future__ import annotations

import enum
from collections import deque
from typing import Final

from gateway.protocols.df1.checks import bcc, crc16
from gateway.protocols.df1.framing import (
    DEFAULT_MAX_MESSAGE,
    ETX_BYTE,
    NEED_DATA,
    AckReceived,
    BadFrame,
    BadFrameReason,
    Checksum,
    DecoderEvent,
    EnqReceived,
    EotReceived,
    Frame,
    MasterMessage,
    NakReceived,
    NeedData,
    Noise,
    Poll,
    Symbol,
    master_check,
)
from gateway.protocols.transitions import Table, Transition, require_complete

__all__ = [
    "FULL_DUPLEX_TRANSITIONS",
    "HALF_DUPLEX_TRANSITIONS",
    "ByteClass",
    "DecoderAction",
    "DecoderState",
    "FrameDecoder",
    "FullDuplexState",
]


class DecoderState(enum.IntEnum):
    """Decoder states; the decoder keeps them as plain ints.  The first five are both tables'."""

    IDLE = 0  #: hunting for DLE
    IDLE_DLE = 1  #: DLE seen outside a frame
    DATA = 2  #: inside the message
    DATA_DLE = 3  #: DLE seen inside the message
    CHECK = 4  #: collecting the check bytes
    POLL_STN = 5  #: DLE ENQ seen: STN next
    POLL_STN_DLE = 6  #: DLE ENQ DLE: the second DLE of STN 10 next
    POLL_BCC = 7  #: STN read: the poll's BCC next
    HEAD_STN = 8  #: DLE SOH seen: STN next
    HEAD_STN_DLE = 9  #: DLE SOH DLE: the second DLE of STN 10 next
    HEAD_DLE = 10  #: DLE SOH STN: DLE next
    HEAD_STX = 11  #: DLE SOH STN DLE: STX next


class FullDuplexState(enum.IntEnum):
    """The states of the full-duplex table: the first five of :class:`DecoderState`.  IntEnum
    members compare and hash as their values, so each is the :class:`DecoderState` member of its
    name for the table's keys (checked at import)."""

    IDLE = 0
    IDLE_DLE = 1
    DATA = 2
    DATA_DLE = 3
    CHECK = 4


if any(DecoderState(state).name != state.name for state in FullDuplexState):
    raise RuntimeError("FullDuplexState must be the first states of DecoderState")


class ByteClass(enum.IntEnum):
    """What a byte means to the decoder (the input of its tables)."""

    DLE = 0
    SOH = 1
    STX = 2
    ETX = 3
    EOT = 4
    ENQ = 5
    ACK = 6
    NAK = 7
    OTHER = 8


_SYMBOL_CLASS: Final = {int(Symbol[cls.name]): cls for cls in ByteClass if cls is not ByteClass.OTHER}

#: Byte value -> its class (a 256-entry table).
_CLASS_OF: Final = tuple(_SYMBOL_CLASS.get(byte, ByteClass.OTHER) for byte in range(256))


class DecoderAction(enum.IntEnum):
    NONE = 0  #: nothing (noise outside a frame, or a DLE waiting for the next byte)
    START = 1  #: DLE STX: a frame starts
    APPEND = 2  #: append the byte to the message
    APPEND_DLE = 3  #: append one 0x10 (DLE DLE)
    END = 4  #: DLE ETX: collect the check bytes
    CHECK_BYTE = 5  #: one check byte; the last one ends the frame (CHECK, or IDLE)
    ACK = 6  #: report DLE ACK
    NAK = 7  #: report DLE NAK
    ENQ = 8  #: report DLE ENQ
    ENQ_ABORT = 9  #: report DLE ENQ, dropping the truncated frame
    INVALID = 10  #: mark the frame bad (invalid DLE sequence)
    MISSING_START = 11  #: report a frame whose start was lost
    EOT = 12  #: report DLE EOT
    START_POLL = 13  #: DLE ENQ: a poll starts
    START_MASTER = 14  #: DLE SOH: a master message starts
    STATION = 15  #: store the byte as STN
    STATION_DLE = 16  #: store 10 hex as STN
    POLL_END = 17  #: the byte is the poll's BCC: report the poll
    BODY = 18  #: DLE STX after a master header: the message starts
    BAD_STATION = 19  #: the frame is broken in its header: report it
    TRUNCATE = 20  #: report the frame so far as TRUNCATED; the byte is read again in the next state


S, C, A = DecoderState, ByteClass, DecoderAction
_Table = Table[DecoderState, ByteClass, DecoderAction]

def _full_duplex_table() -> _Table:
    T = Transition
    table: _Table = {}
    for cls in ByteClass:
        # Outside a frame: only DLE is interesting.
        table[S.IDLE, cls] = T(A.NONE, S.IDLE)
        table[S.IDLE_DLE, cls] = T(A.NONE, S.IDLE)
        # Inside a frame every non-DLE byte is message data; DLE <other> is invalid.
        table[S.DATA, cls] = T(A.APPEND, S.DATA)
        table[S.DATA_DLE, cls] = T(A.INVALID, S.DATA)
        # The check bytes are counted, whatever their value.
        table[S.CHECK, cls] = T(A.CHECK_BYTE, S.CHECK, frozenset({S.IDLE}))
    table.update(
        {
            (S.IDLE, C.DLE): T(A.NONE, S.IDLE_DLE),
            (S.DATA, C.DLE): T(A.NONE, S.DATA_DLE),
            # DLE <x> outside a frame
            (S.IDLE_DLE, C.STX): T(A.START, S.DATA),
            (S.IDLE_DLE, C.ACK): T(A.ACK, S.IDLE),
            (S.IDLE_DLE, C.NAK): T(A.NAK, S.IDLE),
            (S.IDLE_DLE, C.ENQ): T(A.ENQ, S.IDLE),
            (S.IDLE_DLE, C.ETX): T(A.MISSING_START, S.IDLE),
            # DLE DLE outside a frame: the first DLE is noise (or the tail of a lost frame); keep
            # the second as a possible start of DLE STX rather than pairing them, so a stray DLE
            # (e.g. of a damaged DLE ENQ) cannot swallow the next frame's start.
            (S.IDLE_DLE, C.DLE): T(A.NONE, S.IDLE_DLE),
            # DLE <x> inside a frame
            (S.DATA_DLE, C.DLE): T(A.APPEND_DLE, S.DATA),
            (S.DATA_DLE, C.ETX): T(A.END, S.CHECK),
            (S.DATA_DLE, C.STX): T(A.START, S.DATA),
            (S.DATA_DLE, C.ACK): T(A.ACK, S.DATA),
            (S.DATA_DLE, C.NAK): T(A.NAK, S.DATA),
            (S.DATA_DLE, C.ENQ): T(A.ENQ_ABORT, S.IDLE),
        }
    )
    return table


def _half_duplex_table(full: _Table) -> _Table:
    """The full-duplex table with the half-duplex frames: polls, master headers, DLE EOT."""
    T = Transition
    table = dict(full)
    for cls in ByteClass:
        table[S.POLL_STN, cls] = T(A.STATION, S.POLL_BCC)
        table[S.POLL_STN_DLE, cls] = T(A.BAD_STATION, S.IDLE)
        table[S.POLL_BCC, cls] = T(A.POLL_END, S.IDLE)
        table[S.HEAD_STN, cls] = T(A.STATION, S.HEAD_DLE)
        table[S.HEAD_STN_DLE, cls] = T(A.BAD_STATION, S.IDLE)
        table[S.HEAD_DLE, cls] = T(A.BAD_STATION, S.IDLE)
        table[S.HEAD_STX, cls] = T(A.BAD_STATION, S.IDLE)
    # The symbols that start something; DLE ETX outside a frame is ignored.
    starts = {
        C.ENQ: T(A.START_POLL, S.POLL_STN),
        C.SOH: T(A.START_MASTER, S.HEAD_STN),
        C.STX: T(A.START, S.DATA),
        C.ACK: T(A.ACK, S.IDLE),
        C.NAK: T(A.NAK, S.IDLE),
        C.EOT: T(A.EOT, S.IDLE),
    }
    table.update({(S.IDLE_DLE, cls): step for cls, step in starts.items()})
    table[S.IDLE_DLE, C.ETX] = T(A.NONE, S.IDLE)
    # Wherever a DLE may be followed by one of them inside a frame, the frame is truncated.
    for state in (S.POLL_STN_DLE, S.HEAD_STN_DLE, S.HEAD_STX, S.DATA_DLE):
        for cls in starts:
            table[state, cls] = T(A.TRUNCATE, S.IDLE_DLE)
    table.update(
        {
            (S.POLL_STN, C.DLE): T(A.NONE, S.POLL_STN_DLE),
            (S.POLL_STN_DLE, C.DLE): T(A.STATION_DLE, S.POLL_BCC),
            (S.HEAD_STN, C.DLE): T(A.NONE, S.HEAD_STN_DLE),
            (S.HEAD_STN_DLE, C.DLE): T(A.STATION_DLE, S.HEAD_DLE),
            (S.HEAD_DLE, C.DLE): T(A.NONE, S.HEAD_STX),
            (S.HEAD_STX, C.STX): T(A.BODY, S.DATA),
        }
    )
    return table


#: (state, byte class) -> transition, full duplex.
FULL_DUPLEX_TRANSITIONS: Final = _full_duplex_table()
#: (state, byte class) -> transition, half duplex.
HALF_DUPLEX_TRANSITIONS: Final = _half_duplex_table(FULL_DUPLEX_TRANSITIONS)

require_complete(FULL_DUPLEX_TRANSITIONS, map(DecoderState, FullDuplexState), ByteClass, "full-duplex decoder")
require_complete(HALF_DUPLEX_TRANSITIONS, DecoderState, ByteClass, "half-duplex decoder")


def _compile(table: _Table) -> tuple[tuple[int, int], ...]:
    """``table`` keyed by plain ints: entry ``state << 8 | byte`` is (action, next state).

    Enum members hash in Python code; the decoder only ever indexes this tuple with ints.  CHECK
    is counted by the decoder itself and has no row here; neither has a state outside ``table``.
    """
    steps: list[tuple[int, int]] = []
    for state in DecoderState:
        for byte in range(256):
            entry = table.get((state, _CLASS_OF[byte])) if state is not S.CHECK else None
            steps.append((-1, -1) if entry is None else (int(entry.action), int(entry.next_state)))
    return tuple(steps)


def _verify_fast_paths(table: _Table) -> None:
    """The decoder applies some rows of a table to whole runs of bytes at once.

    * IDLE: every non-DLE byte is discarded, so noise up to the next DLE is skipped with
      ``bytes.find``;
    * DATA: every non-DLE byte is appended, and DATA_DLE + DLE appends one DLE and returns to
      DATA, so message data up to the next DLE *not* followed by a DLE is one slice, unstuffed
      with ``bytes.replace``.  APPEND and APPEND_DLE share the length bound, which the decoder
      applies to the unstuffed run;
    * CHECK: every byte is a check byte, taken as a slice up to the check's size.

    Checked at import, so an edit of a table cannot silently disagree with the fast paths.
    """
    expected: _Table = {
        (S.DATA_DLE, C.DLE): Transition(A.APPEND_DLE, S.DATA),
        (S.IDLE, C.DLE): Transition(A.NONE, S.IDLE_DLE),
        (S.DATA, C.DLE): Transition(A.NONE, S.DATA_DLE),
    }
    for cls in ByteClass:
        if cls is not C.DLE:
            expected[S.IDLE, cls] = Transition(A.NONE, S.IDLE)
            expected[S.DATA, cls] = Transition(A.APPEND, S.DATA)
        expected[S.CHECK, cls] = Transition(A.CHECK_BYTE, S.CHECK, frozenset({S.IDLE}))
    for key, step in expected.items():
        if table[key] != step:
            raise RuntimeError(f"DF1 decoder fast path disagrees with the transition table at {key!r}")


_verify_fast_paths(FULL_DUPLEX_TRANSITIONS)
_verify_fast_paths(HALF_DUPLEX_TRANSITIONS)

_FULL_DUPLEX_STEP: Final = _compile(FULL_DUPLEX_TRANSITIONS)
_HALF_DUPLEX_STEP: Final = _compile(HALF_DUPLEX_TRANSITIONS)

# Plain-int copies of the states and actions the decoder's loop tests.
_DLE: Final = int(Symbol.DLE)
_IDLE: Final = int(S.IDLE)
_IDLE_DLE: Final = int(S.IDLE_DLE)
_DATA: Final = int(S.DATA)
_DATA_DLE: Final = int(S.DATA_DLE)
_CHECK: Final = int(S.CHECK)
_NONE: Final = int(A.NONE)
_START: Final = int(A.START)
_APPEND_DLE: Final = int(A.APPEND_DLE)
_END: Final = int(A.END)
_ACK: Final = int(A.ACK)
_NAK: Final = int(A.NAK)
_ENQ: Final = int(A.ENQ)
_ENQ_ABORT: Final = int(A.ENQ_ABORT)
_INVALID: Final = int(A.INVALID)
_MISSING_START: Final = int(A.MISSING_START)
_EOT: Final = int(A.EOT)
_START_POLL: Final = int(A.START_POLL)
_START_MASTER: Final = int(A.START_MASTER)
_STATION: Final = int(A.STATION)
_STATION_DLE: Final = int(A.STATION_DLE)
_POLL_END: Final = int(A.POLL_END)
_BODY: Final = int(A.BODY)
_BAD_STATION: Final = int(A.BAD_STATION)
_TRUNCATE: Final = int(A.TRUNCATE)


class FrameDecoder:
    """Streaming DF1 decoder: ``feed(bytes)`` then ``next_event()`` until ``NEED_DATA``.

    The state machine is :data:`FULL_DUPLEX_TRANSITIONS` (or :data:`HALF_DUPLEX_TRANSITIONS` with
    ``half_duplex``), applied through its int-keyed form one byte at a time after a DLE.  Between
    DLEs (hunting for a frame, or inside one) every byte takes the same transition, so such a run
    is skipped or copied with one ``bytes.find`` and one slice (see :func:`_verify_fast_paths`);
    a read that lies wholly inside a frame's data is appended in one step.  The events are exactly
    those of feeding the table one byte at a time (``tests/protocols/df1/framing/test_decoder_equivalence.py``).
    """

    def __init__(
        self,
        checksum: Checksum,
        *,
        half_duplex: bool = False,
        max_message: int = DEFAULT_MAX_MESSAGE,
        report_noise: bool = False,
    ) -> None:
        if max_message < 1:
            raise ValueError("max_message must be at least 1")
        self.checksum: Final = checksum
        self.half_duplex: Final = half_duplex
        #: report the bytes discarded outside a frame as Noise events, in order with the others
        self.report_noise: Final = report_noise
        self.max_message: Final = max_message
        self._check_size: Final = checksum.size
        self._step: Final = _HALF_DUPLEX_STEP if half_duplex else _FULL_DUPLEX_STEP
        self._state = _IDLE
        self._master = False  #: the open frame is a master frame (poll or master message)
        self._station = 0
        self._message = bytearray()
        self._bad: BadFrameReason | None = None
        self._check = bytearray()
        self._events: deque[DecoderEvent] = deque()

    @property
    def in_frame(self) -> bool:
        """True while part of a frame (or a poll) has been received."""
        return self._state >= _DATA  # every state but IDLE and IDLE_DLE

    def reset(self) -> None:
        """Forget any partial frame and pending events."""
        self._state = _IDLE
        self._message.clear()
        self._check.clear()
        self._bad = None
        self._events.clear()

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Consume ``data`` (any bytes-like read); complete frames and symbols are queued for
        :meth:`next_event`."""
        if type(data) is not bytes:
            data = bytes(data)
        state = self._state
        message = self._message
        if state == _DATA and _DLE not in data and len(message) + len(data) <= self.max_message:
            message += data  # the common case of a small read: nothing but message data
            return
        end = len(data)
        pos = 0
        find = data.find
        step = self._step
        while pos < end:
            if state == _DATA:
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
                    state = _DATA_DLE
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
                if self.report_noise and dle != pos:
                    self._events.append(Noise())
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
                byte = data[pos]
                after_dle = state == _IDLE_DLE
                action, state = step[state << 8 | byte]
                pos += 1
                if action == _NONE:
                    # DLE <no symbol> outside a frame (DLE DLE: the first DLE) is noise
                    if after_dle and self.report_noise:
                        self._events.append(Noise())
                elif action == _START:
                    message.clear()
                    self._bad = None
                    self._master = False
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
                elif action == _INVALID:
                    if self._bad is None:
                        self._bad = BadFrameReason.INVALID_DLE_SEQUENCE
                elif action >= _EOT:
                    self._half_duplex_action(action, byte)
                    if action == _TRUNCATE:
                        pos -= 1  # the symbol is read again, as outside a frame
                elif action == _ENQ:
                    self._events.append(EnqReceived())
                elif action == _ENQ_ABORT:
                    message.clear()
                    self._bad = None
                    self._events.append(EnqReceived(aborted_frame=True))
                elif action == _MISSING_START:
                    self._events.append(BadFrame(BadFrameReason.MISSING_START))
        self._state = state

    def next_event(self) -> DecoderEvent | NeedData:
        """The next frame, symbol or bad frame, or ``NEED_DATA``."""
        if self._events:
            return self._events.popleft()
        return NEED_DATA

    def _half_duplex_action(self, action: int, byte: int) -> None:
        """The actions only :data:`HALF_DUPLEX_TRANSITIONS` has."""
        if action == _EOT:
            self._events.append(EotReceived())
        elif action == _START_POLL or action == _START_MASTER:
            self._master = True
            self._message.clear()
            self._bad = None
        elif action == _STATION:
            self._station = byte
        elif action == _STATION_DLE:
            self._station = _DLE
        elif action == _POLL_END:
            if byte == -self._station & 0xFF:
                self._events.append(Poll(self._station))
            else:
                self._events.append(BadFrame(BadFrameReason.CHECKSUM, True))
        elif action == _BODY:
            self._message.clear()
        elif action == _BAD_STATION:
            self._events.append(BadFrame(BadFrameReason.BAD_STATION, self._master))
        elif action == _TRUNCATE:
            self._events.append(BadFrame(BadFrameReason.TRUNCATED, self._master))

    def _finish_frame(self) -> None:
        message = bytes(self._message)
        check = self._check
        bad = self._bad
        self._message.clear()
        self._bad = None
        if bad is None and not message:
            bad = BadFrameReason.EMPTY
        if bad is None:
            if self._master:
                good = check == master_check(self._station, message, self.checksum)
            elif self.checksum is Checksum.BCC:
                good = check[0] == bcc(message)
            else:
                good = check[0] | check[1] << 8 == crc16(ETX_BYTE, crc16(message))
            if not good:
                bad = BadFrameReason.CHECKSUM
        check.clear()
        if bad is not None:
            self._events.append(BadFrame(bad, self._master))
        elif self._master:
            self._events.append(MasterMessage(self._station, message))
        else:
            self._events.append(Frame(message))
