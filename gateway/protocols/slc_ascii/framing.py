"""SLC 100/150 ASCII protocol framing: CRC, frame encoding, streaming decoding, message IDs.

Manual: "SLC Programmable Controller Communications Protocol", *Format of Transmission*.

Frames, all ASCII, hexadecimal upper case when we send them::

    host -> controller    #  <count:2> <code:2> <params:2n> <ID:2> <CRC:2> CR     (count = 1 + n bytes)
                          ;Z <ID:2> <CRC:2> CR                                     (retransmit request)
    controller -> host    :  <body> <ID:2> <CRC:2> CR                              (data reply)
                          ;R <ID:2> <CRC:2> CR   acknowledge
                          ;E <ID:2> <CRC:2> CR   command illegal (refused, not executed)
                          ;T <ID:2> <CRC:2> CR   fault (unsolicited; the ID is meaningless)
                          ;I <id:2> <CRC:2> CR   unexpected message ID; id = the last valid ID

The leading character (``#``, ``:``, ``;``) is not part of the CRC; the CRC covers every
character after it up to and including the ID.  The CRC is the manual's BASIC program with
its 16-entry nibble table, which is normative (the printed polynomial, implemented MSB-first,
gives other values).

This module does no I/O.  Decoders are fed bytes and hand out events, or ``NEED_DATA``.
"""

from __future__ import annotations

import re
from collections import deque
from typing import Final, Generic, TypeVar

from gateway.frozen import frozen
from gateway.protocols.need_data import NEED_DATA, NeedData
from gateway.protocols.slc_ascii.commands import Command

__all__ = [
    "CR",
    "MAX_FRAME",
    "NEED_DATA",
    "Ack",
    "CommandDecoder",
    "CommandFrame",
    "DataReply",
    "Fault",
    "Garbled",
    "HostEvent",
    "IdMismatch",
    "NeedData",
    "Refused",
    "ReplyDecoder",
    "ReplyEvent",
    "RetransmitRequest",
    "crc",
    "encode_ack",
    "encode_data_reply",
    "encode_fault",
    "encode_id_mismatch",
    "encode_refused",
    "encode_retransmit",
    "frame_command",
]

CR: Final = 0x0D
LF: Final = 0x0A
#: Longest line we accept (a download block is 1 + 2 + 4 + 30 + 4 = 41 characters plus CR).
MAX_FRAME: Final = 96
#: The highest message ID; after it the sequence rolls over to 01 (never back to 00).
MAX_ID: Final = 0x7F

# The manual's BASIC program: DATA 0, 23, 46, 57, 92, 75, 114, 101, 184, 175, 150, 129, 228, 243, 202, 221
_CRC_NIBBLE_TABLE: Final = (0, 23, 46, 57, 92, 75, 114, 101, 184, 175, 150, 129, 228, 243, 202, 221)
_HEX_DIGITS: Final = frozenset(b"0123456789ABCDEFabcdef")
#: Bit 7 cleared: a port set to 8 data bits hands over the parity bit as bit 7.
_MASK_BIT_7: Final = bytes(b & 0x7F for b in range(256))


def _slc_crc_table() -> tuple[int, ...]:
    """The BASIC loop processes two nibbles per character; precompute it per (checksum ^ char) byte."""
    table = []
    for value in range(256):
        checksum, char = 0, value
        for _ in range(2):
            index = (checksum ^ char) & 0x0F
            checksum = (checksum >> 4) ^ _CRC_NIBBLE_TABLE[index]
            char >>= 4
        table.append(checksum)
    return tuple(table)


_CRC_BYTE_TABLE: Final = _slc_crc_table()


def crc(data: bytes) -> int:
    """The SLC CRC byte of ``data`` (characters after the leading character, through the ID).

    >>> f"{crc(b'010800'):02X}", f"{crc(b'R03'):02X}"
    ('A3', '8D')
    """
    checksum = 0
    table = _CRC_BYTE_TABLE
    for char in data:
        # Both nibble steps depend only on (checksum ^ char) in the low byte, and the checksum
        # is always 8 bits, so one table look-up per character does the BASIC program's inner loop.
        checksum = table[checksum ^ char]
    return checksum


def _hex2(value: int) -> bytes:
    return b"%02X" % value


def _check_id(msg_id: int) -> None:
    if not 0 <= msg_id <= MAX_ID:
        raise ValueError(f"message ID {msg_id} out of range 0..{MAX_ID}")


def _frame(lead: bytes, text: bytes) -> bytes:
    return b"%s%s%02X\r" % (lead, text, crc(text))


def frame_command(command: Command, msg_id: int) -> bytes:
    """``#<count><code><params><ID><CRC>CR`` for ``command`` with message ``msg_id``."""
    _check_id(msg_id)
    text = b"%02X%02X%s%02X" % (1 + len(command.params), command.code, command.params.hex().upper().encode(), msg_id)
    return _frame(b"#", text)


def encode_retransmit(msg_id: int) -> bytes:
    """``;Z<ID><CRC>CR``: ask the controller to repeat its last reply.  Does not use up an ID."""
    _check_id(msg_id)
    return _frame(b";", b"Z" + _hex2(msg_id))


def encode_data_reply(body_hex: str, msg_id: int) -> bytes:
    """Controller side: ``:<body><ID><CRC>CR``."""
    _check_id(msg_id)
    return _frame(b":", body_hex.upper().encode("ascii") + _hex2(msg_id))


def encode_ack(msg_id: int) -> bytes:
    """Controller side: ``;R<ID><CRC>CR``."""
    _check_id(msg_id)
    return _frame(b";", b"R" + _hex2(msg_id))


def encode_refused(msg_id: int) -> bytes:
    """Controller side: ``;E<ID><CRC>CR``."""
    _check_id(msg_id)
    return _frame(b";", b"E" + _hex2(msg_id))


def encode_fault(msg_id: int = 0) -> bytes:
    """Controller side: ``;T<ID><CRC>CR`` (the ID is meaningless)."""
    _check_id(msg_id)
    return _frame(b";", b"T" + _hex2(msg_id))


def encode_id_mismatch(last_valid_id: int) -> bytes:
    """Controller side: ``;I<id><CRC>CR`` where ``id`` is the last valid ID."""
    _check_id(last_valid_id)
    return _frame(b";", b"I" + _hex2(last_valid_id))


# --- events ---------------------------------------------------------------------------------


@frozen
class DataReply:
    """``:`` data reply.  ``body_hex`` is the upper-case hex text between ``:`` and the ID."""

    body_hex: str
    msg_id: int


@frozen
class _IdOnly:
    """A frame that carries nothing but its message ID; each subclass is one kind of frame."""

    msg_id: int


class Ack(_IdOnly):
    """``;R``: the command was valid and executed."""

    __slots__ = ()


class Refused(_IdOnly):
    """``;E``: the command or its parameters were illegal (mode or range); not executed."""

    __slots__ = ()


class Fault(_IdOnly):
    """``;T``: the controller detected a fault; read bytes 84H-85H for the reason."""

    __slots__ = ()


@frozen
class IdMismatch:
    """``;I``: the message had an unexpected ID and was not executed; ``last_valid_id`` as reported."""

    last_valid_id: int


@frozen
class Garbled:
    """A line that is not a valid frame (CRC, format, length).  The caller treats it as a missing reply."""

    raw: bytes
    reason: str


@frozen
class CommandFrame:
    """Controller side: a ``#`` command as received."""

    code: int
    params: bytes
    msg_id: int


class RetransmitRequest(_IdOnly):
    """Controller side: ``;Z``."""

    __slots__ = ()


ReplyEvent = DataReply | Ack | Refused | Fault | IdMismatch | Garbled
HostEvent = CommandFrame | RetransmitRequest | Garbled
#: the events of one decoder's side: ``ReplyEvent`` or ``HostEvent``
_EventT = TypeVar("_EventT")

_SEMICOLON_REPLIES: Final[dict[int, type[Ack] | type[Refused] | type[Fault]]] = {
    ord("R"): Ack,
    ord("E"): Refused,
    ord("T"): Fault,
}


# --- decoders -------------------------------------------------------------------------------


class _LineSplitter:
    """Cuts a byte stream into candidate frames: from a leading character up to CR.

    Liberal in what it accepts: bit 7 is masked (parity seen as data on a port set to 8 bits),
    LF is ignored, bytes before a leading character are discarded, a leading character in the
    middle of a line starts a new frame (the partial one before it is reported garbled), and a
    line longer than MAX_FRAME is dropped.
    """

    __slots__ = ("_buffer", "_pending", "_special")

    def __init__(self, leads: bytes) -> None:
        # the bytes that end a run of frame characters: a leading character or CR
        self._special = re.compile(b"[" + re.escape(leads) + b"\r]")
        self._buffer = bytearray()
        self._pending: deque[bytes | Garbled] = deque()  # a whole line, or the bytes of a garbled one

    def feed(self, data: bytes) -> None:
        # Whole runs of ordinary characters are copied at once; only the leading characters and
        # CR are looked at one by one.
        data = data.translate(_MASK_BIT_7).replace(b"\n", b"")
        buffer = self._buffer
        position = 0
        for match in self._special.finditer(data):
            at = match.start()
            if buffer and at > position:
                self._append(data[position:at])
            if data[at] == CR:
                if buffer:
                    self._pending.append(bytes(buffer))
                    buffer.clear()
                # A CR outside a frame is line noise: ignore it.
            else:
                if buffer:
                    self._pending.append(Garbled(bytes(buffer), "frame interrupted by a new leading character"))
                    buffer.clear()
                buffer.append(data[at])
            position = at + 1
        if buffer and position < len(data):
            self._append(data[position:])
        # Bytes outside any frame (noise before a leading character) are discarded.

    def _append(self, run: bytes) -> None:
        buffer = self._buffer
        room = MAX_FRAME - len(buffer)
        if len(run) <= room:
            buffer += run
            return
        buffer += run[:room]
        self._pending.append(Garbled(bytes(buffer), "line too long"))
        buffer.clear()  # the rest of the line is dropped up to the next leading character

    def next_line(self) -> bytes | Garbled | None:
        if self._pending:
            return self._pending.popleft()
        return None

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def flush(self) -> bytes:
        """Give up on the partial line (its end never came): its bytes, now forgotten."""
        line = bytes(self._buffer)
        self._buffer.clear()
        return line


def _split_checked(line: bytes) -> tuple[bytes, int] | Garbled:
    """``line`` is lead + text + CRC.  Returns (text upper-cased, ID), or the line garbled with the reason."""
    text = line[1:]
    if len(text) < 5:  # at least one letter or count digit, 2 ID, 2 CRC
        return Garbled(line, "frame too short")
    received_crc, text = text[-2:], text[:-2]
    if not all(c in _HEX_DIGITS for c in received_crc):
        return Garbled(line, "CRC is not hex")
    if crc(text.upper()) != int(received_crc, 16) and crc(text) != int(received_crc, 16):
        return Garbled(line, f"CRC mismatch (received {received_crc.decode()}, computed {crc(text):02X})")
    id_text = text[-2:]
    if not all(c in _HEX_DIGITS for c in id_text):
        return Garbled(line, "message ID is not hex")
    msg_id = int(id_text, 16)
    if msg_id > MAX_ID:
        return Garbled(line, f"message ID {msg_id:02X} out of range")
    return text.upper(), msg_id


class _Decoder(Generic[_EventT]):
    """Cuts lines, checks CRC and ID; a subclass turns a checked line into its own event."""

    __slots__ = ("_lines",)

    LEADS = b""

    def __init__(self) -> None:
        self._lines = _LineSplitter(self.LEADS)

    def receive_data(self, data: bytes) -> None:
        self._lines.feed(data)

    @property
    def partial(self) -> bool:
        """Part of a frame has arrived, without its CR."""
        return self._lines.buffered > 0

    def flush_partial(self) -> Garbled | None:
        """The rest of a partial frame is not coming (the caller's inter-character timeout):
        report it garbled now instead of when the next frame starts."""
        line = self._lines.flush()
        if not line:
            return None
        return Garbled(line, "frame cut short (no CR)")

    def next_event(self) -> _EventT | Garbled | NeedData:
        """The next frame's event, a Garbled line, or NEED_DATA."""
        line = self._lines.next_line()
        if line is None:
            return NEED_DATA
        if isinstance(line, Garbled):
            return line
        checked = _split_checked(line)
        if isinstance(checked, Garbled):
            return checked
        text, msg_id = checked
        return self._event(line, text, msg_id)

    def _event(self, line: bytes, text: bytes, msg_id: int) -> _EventT | Garbled:
        """The event of ``line``, whose CRC and ID are good; ``text`` is the line upper-cased from after
        the leading character through the ID."""
        raise NotImplementedError


class ReplyDecoder(_Decoder[ReplyEvent]):
    """Host side: bytes from the controller -> ``ReplyEvent`` or ``NEED_DATA``."""

    __slots__ = ()

    LEADS = b":;"

    def _event(self, line: bytes, text: bytes, msg_id: int) -> ReplyEvent:
        if line[0] == ord(":"):
            body = text[:-2]
            if not body or len(body) % 2 or not all(c in _HEX_DIGITS for c in body):
                return Garbled(line, "data reply body is not whole hex bytes")
            return DataReply(body.decode(), msg_id)
        if len(text) != 3:
            return Garbled(line, "reply has the wrong length")
        letter = text[0]
        if letter == ord("I"):
            return IdMismatch(msg_id)
        kind = _SEMICOLON_REPLIES.get(letter)
        if kind is None:
            return Garbled(line, f"unknown reply ;{chr(letter)}")
        return kind(msg_id)


class CommandDecoder(_Decoder[HostEvent]):
    """Controller side: bytes from the host -> ``HostEvent`` or ``NEED_DATA`` (used by the simulator)."""

    __slots__ = ()

    LEADS = b"#;"

    def _event(self, line: bytes, text: bytes, msg_id: int) -> HostEvent:
        if line[0] == ord(";"):
            if text[0] == ord("Z") and len(text) == 3:
                return RetransmitRequest(msg_id)
            return Garbled(line, "unknown ; command")
        fields = text[:-2]
        if len(fields) < 4 or len(fields) % 2 or not all(c in _HEX_DIGITS for c in fields):
            return Garbled(line, "command is not whole hex bytes")
        raw = bytes.fromhex(fields.decode())
        count, code, params = raw[0], raw[1], raw[2:]
        if count != 1 + len(params):
            return Garbled(line, f"byte count {count:02X} does not match {1 + len(params)} bytes")
        return CommandFrame(code, params, msg_id)
