"""Differential test: the one DF1 decoder in half-duplex mode against the former half-duplex decoder.

``ReferenceHalfDuplexDecoder`` below is the byte-at-a-time half-duplex decoder as it stood in
``gateway/protocols/df1/half_duplex_framing.py`` before full and half duplex shared one framing
(enum-keyed transition table, one Python call per byte); its events are the shared ones (a slave
message is a :class:`Frame`).  Both decoders are fed the same byte streams, split at the same
chunk boundaries, and must report the same events and the same ``in_frame`` after every chunk.
"""

from __future__ import annotations

import enum
import itertools
import os
from collections import deque
from typing import Final

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    DEFAULT_MAX_MESSAGE,
    EOT_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    BadFrameReason,
    Checksum,
    DecoderEvent,
    EotReceived,
    Frame,
    MasterMessage,
    NakReceived,
    NeedData,
    Poll,
    Symbol,
    encode_frame,
    encode_master_message,
    encode_poll,
    frame_check,
    master_check,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder

# ----------------------------------------------------------- reference (former) implementation


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


class ReferenceHalfDuplexDecoder:
    """The half-duplex decoder as it stood before the framings were one (class name, events and
    check functions aside)."""

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
        self._events: deque[DecoderEvent] = deque()

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

    def next_event(self) -> DecoderEvent | NeedData:
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
                else frame_check(message, self.checksum)
            )
            if check != expected:
                bad = BadFrameReason.CHECKSUM
        if bad is not None:
            self._events.append(BadFrame(bad, self._master))
        elif self._master:
            self._events.append(MasterMessage(self._station, message))
        else:
            self._events.append(Frame(message))


#: Actions that begin a new symbol; inside an open frame they truncate it.
_STARTS: Final = frozenset({_Act.START_POLL, _Act.START_MASTER, _Act.START_SLAVE, _Act.ACK, _Act.NAK, _Act.EOT})


# ------------------------------------------------------------------------------------ harness

Decoder = FrameDecoder | ReferenceHalfDuplexDecoder


def _drain(decoder: Decoder) -> list[DecoderEvent]:
    events: list[DecoderEvent] = []
    while True:
        event = decoder.next_event()
        if isinstance(event, NeedData):
            assert event is NEED_DATA
            return events
        events.append(event)


def _run(decoder: Decoder, chunks: list[bytes], drain_after: list[bool]) -> list[object]:
    """Everything observable: events (drained when asked) and ``in_frame`` after each chunk."""
    trace: list[object] = []
    for chunk, drain in zip(chunks, drain_after, strict=True):
        decoder.feed(chunk)
        trace.append(decoder.in_frame)
        if drain:
            trace.append(_drain(decoder))
    trace.append(_drain(decoder))
    return trace


def _assert_same(checksum: Checksum, max_message: int, chunks: list[bytes], drains: list[bool]) -> None:
    new = FrameDecoder(checksum, half_duplex=True, max_message=max_message)
    ref = ReferenceHalfDuplexDecoder(checksum, max_message=max_message)
    assert _run(new, chunks, drains) == _run(ref, chunks, drains)


# --------------------------------------------------------------------------------- strategies

_SPECIAL = [0x10, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x15]

dle_rich = st.lists(st.one_of(st.sampled_from(_SPECIAL), st.integers(0, 255)), max_size=40).map(bytes)
messages = st.one_of(st.binary(min_size=1, max_size=40), dle_rich.filter(bool))
stations = st.one_of(st.sampled_from([0x10, 0x00, 0xF0, 0xFF, 0x01, 0x02, 0x03]), st.integers(0, 255))
symbols = st.sampled_from([ACK_SYMBOL, NAK_SYMBOL, EOT_SYMBOL, b"\x10\x05", b"\x10\x01", b"\x10\x02",
                           b"\x10\x03", b"\x10", b"\x10\x10", b"\x10\x41"])


@st.composite
def segments(draw: st.DrawFn, checksum: Checksum) -> bytes:
    kind = draw(st.sampled_from(["poll", "master", "slave", "other", "truncated", "corrupt", "inserted",
                                 "garbage", "dle", "symbol"]))
    if kind == "garbage":
        return draw(st.binary(max_size=60))
    if kind == "dle":
        return draw(dle_rich)
    if kind == "symbol":
        return draw(symbols)
    if kind == "poll":
        return encode_poll(draw(stations))
    other = Checksum.CRC if checksum is Checksum.BCC else Checksum.BCC
    use = other if kind == "other" else checksum
    if draw(st.booleans()):
        frame = encode_master_message(draw(stations), draw(messages), use)
    else:
        frame = encode_frame(draw(messages), use)
    if kind == "truncated":
        return frame[: draw(st.integers(0, len(frame) - 1))]
    if kind == "corrupt":
        position = draw(st.integers(0, len(frame) - 1))
        return frame[:position] + bytes((draw(st.integers(0, 255)),)) + frame[position + 1 :]
    if kind == "inserted":
        position = draw(st.integers(0, len(frame)))
        return frame[:position] + draw(st.one_of(symbols, dle_rich)) + frame[position:]
    return frame


@st.composite
def streams(draw: st.DrawFn) -> tuple[Checksum, int, list[bytes], list[bool]]:
    checksum = draw(st.sampled_from(list(Checksum)))
    max_message = draw(st.sampled_from([1, 2, 5, 16, DEFAULT_MAX_MESSAGE]))
    data = b"".join(draw(st.lists(segments(checksum), max_size=10)))
    mode = draw(st.sampled_from(["whole", "bytes", "fixed"]))
    if mode == "whole":
        chunks = [data]
    elif mode == "bytes":
        chunks = [data[i : i + 1] for i in range(len(data))]
    else:
        size = draw(st.integers(1, 16))
        chunks = [data[i : i + size] for i in range(0, len(data), size)]
    drains = draw(st.lists(st.booleans(), min_size=len(chunks), max_size=len(chunks)))
    return checksum, max_message, chunks, drains


# ---------------------------------------------------------------------------------------- tests

#: examples of the reference comparison; fewer under ``make mutation`` (tools/mutation.py sets
#: SLC_GATEWAY_MUTATION), where every surviving decoder mutant runs them all: a wrong decoder fails
#: within the first examples, and the full count is the suite's
REFERENCE_EXAMPLES = 300 if os.environ.get("SLC_GATEWAY_MUTATION") else 1000


@settings(max_examples=REFERENCE_EXAMPLES, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(streams())
def test_same_events_as_reference(case: tuple[Checksum, int, list[bytes], list[bool]]) -> None:
    _assert_same(*case)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400), st.sampled_from(list(Checksum)), st.integers(1, 9))
def test_same_events_on_raw_noise(data: bytes, checksum: Checksum, size: int) -> None:
    chunks = [data[i : i + size] for i in range(0, len(data), size)]
    _assert_same(checksum, DEFAULT_MAX_MESSAGE, chunks, [True] * len(chunks))
    _assert_same(checksum, 4, [data], [False])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(dle_rich, st.booleans()), max_size=8), st.sampled_from(list(Checksum)))
def test_same_after_reset(parts: list[tuple[bytes, bool]], checksum: Checksum) -> None:
    new = FrameDecoder(checksum, half_duplex=True, max_message=16)
    ref = ReferenceHalfDuplexDecoder(checksum, max_message=16)
    frame = encode_master_message(0x10, b"\x01\x10\x02", checksum)
    for data, reset in parts:
        for decoder in (new, ref):
            decoder.feed(data)
            if reset:
                decoder.reset()
            decoder.feed(frame[:4])
        assert new.in_frame == ref.in_frame
        assert _drain(new) == _drain(ref)


_ALPHABET = bytes([0x10, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x15, 0x41])


@pytest.mark.parametrize("checksum", list(Checksum))
@pytest.mark.parametrize("prefix", [b"", b"\x10\x02\x41", b"\x10\x01", b"\x10\x01\x07\x10", b"\x10\x05"])
def test_every_short_sequence(checksum: Checksum, prefix: bytes) -> None:
    """All strings of up to 4 significant bytes after each prefix, then an end, whole and byte by byte."""
    for length in range(5):
        for combo in itertools.product(_ALPHABET, repeat=length):
            data = prefix + bytes(combo) + b"\x10\x03\x00\x00"
            _assert_same(checksum, 2, [data], [True])
            _assert_same(checksum, 2, [bytes((b,)) for b in data], [True] * len(data))


def test_reference_is_exercised() -> None:
    """Sanity: the reference really decodes (the differential tests compare something)."""
    ref = ReferenceHalfDuplexDecoder(Checksum.CRC)
    ref.feed(encode_poll(0x10) + encode_master_message(3, b"\x01", Checksum.CRC) + encode_frame(b"\x02", Checksum.CRC)
             + b"\x10\x02\x01" + EOT_SYMBOL)
    assert _drain(ref) == [Poll(0x10), MasterMessage(3, b"\x01"), Frame(b"\x02"),
                           BadFrame(BadFrameReason.TRUNCATED, False), EotReceived()]
