"""Differential test: the optimised FrameDecoder against a verbatim copy of the original one.

``ReferenceFrameDecoder`` below is the byte-at-a-time decoder exactly as it stood in
``gateway/protocols/df1/framing.py`` before the fast path (enum-keyed transition table, one
Python call per byte); only the class name differs.  Both decoders are fed the same byte
streams, split at the same chunk boundaries, and must report the same events (frames, link
symbols, bad-frame reasons, ``NEED_DATA``) and the same ``in_frame`` after every chunk.
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

from gateway.protocols.df1.checks import bcc, crc16
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    DEFAULT_MAX_MESSAGE,
    ENQ_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    BadFrameReason,
    Checksum,
    DecoderEvent,
    EnqReceived,
    Frame,
    NakReceived,
    NeedData,
    Symbol,
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder

# ----------------------------------------------------------- reference (original) implementation

_DLE: Final = int(Symbol.DLE)


def _reference_bcc(message: bytes) -> int:
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


def _reference_crc16(message: bytes) -> int:
    crc = 0
    for byte in message:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return (crc >> 8) ^ _CRC_TABLE[(crc ^ Symbol.ETX) & 0xFF]


def _check_bytes(message: bytes, checksum: Checksum) -> bytes:
    if checksum is Checksum.BCC:
        return bytes((_reference_bcc(message),))
    return _reference_crc16(message).to_bytes(2, "little")


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


class ReferenceFrameDecoder:
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


# ------------------------------------------------------------------------------------ harness

Decoder = FrameDecoder | ReferenceFrameDecoder


def _drain(decoder: Decoder) -> list[DecoderEvent]:
    events: list[DecoderEvent] = []
    while True:
        event = decoder.next_event()
        if isinstance(event, NeedData):
            assert event is NEED_DATA
            # NEED_DATA is sticky: asking again changes nothing.
            assert decoder.next_event() is NEED_DATA
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


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({cut % (len(data) + 1) for cut in cuts})
    bounds = [0, *points, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(bounds)]


def _assert_same(data: bytes, checksum: Checksum, max_message: int, chunks: list[bytes], drains: list[bool]) -> None:
    assert b"".join(chunks) == data
    new = FrameDecoder(checksum, max_message=max_message)
    ref = ReferenceFrameDecoder(checksum, max_message=max_message)
    assert _run(new, chunks, drains) == _run(ref, chunks, drains)
    assert len(new._message) <= max_message


# --------------------------------------------------------------------------------- strategies

_SPECIAL = [0x10, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x15]

#: Bytes with plenty of DLE and of the characters that mean something after a DLE.
dle_rich = st.lists(st.one_of(st.sampled_from(_SPECIAL), st.integers(0, 255)), max_size=60).map(bytes)
messages = st.one_of(st.binary(min_size=1, max_size=40), dle_rich.filter(bool), st.binary(min_size=1, max_size=300))
symbols = st.sampled_from(
    [ACK_SYMBOL, NAK_SYMBOL, ENQ_SYMBOL, b"\x10\x02", b"\x10\x03", b"\x10", b"\x10\x10", b"\x10\x41"]
)


@st.composite
def segments(draw: st.DrawFn, checksum: Checksum) -> bytes:
    kind = draw(st.sampled_from(["frame", "frame", "other", "truncated", "corrupt", "inserted", "garbage", "dle",
                                 "symbol", "long"]))
    if kind == "garbage":
        return draw(st.binary(max_size=80))
    if kind == "dle":
        return draw(dle_rich)
    if kind == "symbol":
        return draw(symbols)
    if kind == "long":
        size = draw(st.sampled_from([DEFAULT_MAX_MESSAGE - 1, DEFAULT_MAX_MESSAGE, DEFAULT_MAX_MESSAGE + 1, 700]))
        return encode_frame(bytes(draw(st.integers(0, 255)) for _ in range(1)) * size, checksum)
    message = draw(messages)
    frame = encode_frame(message, Checksum.CRC if (kind == "other") == (checksum is Checksum.BCC) else Checksum.BCC)
    if kind == "truncated":
        return frame[: draw(st.integers(0, len(frame) - 1))]
    if kind == "corrupt":
        position = draw(st.integers(0, len(frame) - 1))
        return frame[:position] + bytes((draw(st.integers(0, 255)),)) + frame[position + 1 :]
    if kind == "inserted":
        # Anywhere, or just before DLE ETX (after the last message byte).
        position = draw(st.one_of(st.integers(0, len(frame)), st.just(len(frame) - 2 - checksum.size)))
        return frame[:position] + draw(st.one_of(symbols, dle_rich)) + frame[position:]
    return frame


@st.composite
def streams(draw: st.DrawFn) -> tuple[bytes, Checksum, int, list[bytes], list[bool]]:
    checksum = draw(st.sampled_from(list(Checksum)))
    max_message = draw(st.sampled_from([1, 2, 5, 16, 64, 200, DEFAULT_MAX_MESSAGE]))
    data = b"".join(draw(st.lists(segments(checksum), max_size=12)))
    mode = draw(st.sampled_from(["whole", "bytes", "fixed", "random"]))
    if mode == "whole":
        chunks = [data]
    elif mode == "bytes":
        chunks = [data[i : i + 1] for i in range(len(data))]
    elif mode == "fixed":
        size = draw(st.integers(1, 16))
        chunks = [data[i : i + size] for i in range(0, len(data), size)]
    else:
        chunks = _split(data, draw(st.lists(st.integers(0, 10_000), max_size=40)))
    if draw(st.booleans()):
        chunks = [b"", *chunks]  # empty feeds are allowed anywhere
    drains = draw(st.lists(st.booleans(), min_size=len(chunks), max_size=len(chunks)))
    return data, checksum, max_message, chunks, drains


# ---------------------------------------------------------------------------------------- tests

#: examples of the reference comparison; fewer under ``make mutation`` (tools/mutation.py sets
#: SLC_GATEWAY_MUTATION), where every surviving decoder mutant runs them all: a wrong decoder fails
#: within the first examples, and the full count is the suite's
REFERENCE_EXAMPLES = 300 if os.environ.get("SLC_GATEWAY_MUTATION") else 1500


@settings(max_examples=REFERENCE_EXAMPLES, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(streams())
def test_same_events_as_reference(case: tuple[bytes, Checksum, int, list[bytes], list[bool]]) -> None:
    _assert_same(*case)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600), st.sampled_from(list(Checksum)), st.sampled_from([1, 3, 64, DEFAULT_MAX_MESSAGE]),
       st.integers(1, 9))
def test_same_events_on_raw_noise(data: bytes, checksum: Checksum, max_message: int, size: int) -> None:
    chunks = [data[i : i + size] for i in range(0, len(data), size)]
    _assert_same(data, checksum, max_message, chunks, [True] * len(chunks))
    _assert_same(data, checksum, max_message, [data], [False])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(dle_rich, st.booleans()), max_size=8), st.sampled_from(list(Checksum)))
def test_same_after_reset(parts: list[tuple[bytes, bool]], checksum: Checksum) -> None:
    """``reset()`` between feeds forgets the same things in both decoders."""
    new = FrameDecoder(checksum, max_message=16)
    ref = ReferenceFrameDecoder(checksum, max_message=16)
    frame = encode_frame(b"\x01\x10\x02", checksum)
    for data, reset in parts:
        for decoder in (new, ref):
            decoder.feed(data)
            if reset:
                decoder.reset()
            decoder.feed(frame[:3])
        assert new.in_frame == ref.in_frame
        assert _drain(new) == _drain(ref)


_ALPHABET = bytes([0x10, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x15, 0x41])


@pytest.mark.parametrize("checksum", list(Checksum))
@pytest.mark.parametrize("suffix", [b"", b"\x10\x03\x00\x00"])
@pytest.mark.parametrize("prefix", [b"", b"\x10\x02\x41", b"\x10\x02\x41\x10\x03"])
def test_every_short_sequence(checksum: Checksum, prefix: bytes, suffix: bytes) -> None:
    """All strings of up to 4 significant bytes between each prefix and suffix, whole and byte by byte."""
    for length in range(5):
        for combo in itertools.product(_ALPHABET, repeat=length):
            data = prefix + bytes(combo) + suffix
            for max_message in (1, 2):
                _assert_same(data, checksum, max_message, [data], [True])
                _assert_same(data, checksum, max_message, [bytes((b,)) for b in data], [True] * len(data))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=700))
def test_checks_unchanged(message: bytes) -> None:
    assert bcc(message) == _reference_bcc(message)
    assert crc16(message + b"\x03") == _reference_crc16(message)
    if message:
        for checksum in Checksum:
            stuffed = message.replace(b"\x10", b"\x10\x10")
            assert encode_frame(message, checksum) == b"\x10\x02" + stuffed + b"\x10\x03" + _check_bytes(
                message, checksum
            )


def test_reference_is_exercised() -> None:
    """Sanity: the reference really decodes (the differential tests compare something)."""
    frame = encode_frame(b"\x01\x10\x02", Checksum.CRC)
    ref = ReferenceFrameDecoder(Checksum.CRC)
    ref.feed(ACK_SYMBOL + frame[:3] + NAK_SYMBOL + frame[3:] + b"\x10\x03" + ENQ_SYMBOL)
    assert _drain(ref) == [
        AckReceived(),
        NakReceived(),
        Frame(b"\x01\x10\x02"),
        BadFrame(BadFrameReason.MISSING_START),
        EnqReceived(),
    ]
