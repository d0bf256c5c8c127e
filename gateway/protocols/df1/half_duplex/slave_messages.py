"""Messages a slave initiates on a half-duplex line (MSG instructions, report by exception): the answer.

On a DF1 half-duplex line a slave sends its own commands only in answer to a poll (1770-6.5.16
chapter 3; KA p. 11-9); the master core acknowledges them with ``DLE ACK`` like any good slave
message and hands them over as :class:`~gateway.protocols.df1.half_duplex.master.SlaveInitiated`.  The
slave's MSG instruction then waits for the PCCC *reply* (1770-6.5.16 chapter 6: CMD + 40 hex, same
TNS, DST / SRC swapped), which the master sends as a master message (``DLE SOH STN ...``).  This
module decides that reply (sans-I/O):

* a write addressed to the gateway's own station (``DST`` = the line's source address) - PLC-5 word
  range write ``0F 00`` (KF2 p. 5-57), SLC protected typed logical write ``0F AA`` of an integer file,
  or typed write ``0F 67`` of integers - is stored into the sending station's
  :class:`RegisterTable` (each word with the time it arrived) and answered STS 00;
* everything else is refused with the STS the PCCC target core decides for that command's family
  (:func:`~gateway.protocols.df1.pccc.target.refusal`, the one table of both target paths):

  - a write to words the table does not have: the file is not the table's, the first element is
    outside it, or the data runs past its end - an SLC typed logical write STS 50 "address
    problem" (notes §4.36 (d)), a PLC-5 word range / typed write STS F0 with EXT STS 06 "address
    doesn't point to something usable" or 09 "data or file is too large" for data past the end
    (1770-6.5.16 p. 8-4, p. 8-9);
  - anything else (a read, another command, a message for another station - the gateway does not
    route between slaves -, a station without a table): STS 10 "illegal command or format"
    (1770-6.5.16 p. 8-3), the manual's answer to a command a node does not have;

* a packet too short to have a PCCC header, or a reply: no answer (there is nothing to reply to).

No I/O.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator, Sequence

from gateway.frozen import frozen
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import (
    PcccFormatError,
    PcccHeader,
    ProtectedTypedLogicalWrite,
    TypedWrite,
    WordRangeWrite,
    decode_command,
    encode_reply,
)
from gateway.protocols.df1.pccc.commands import Request
from gateway.protocols.df1.pccc.plc5 import DataType
from gateway.protocols.df1.pccc.target import Problem, refusal

__all__ = ["RegisterTable", "SlaveMessageVerdict", "SlaveWrite", "answer_slave_message"]

class SlaveMessageVerdict(enum.Enum):
    STORED = "stored"
    BAD_ADDRESS = "address outside the register table"
    UNSUPPORTED = "unsupported command (STS 10)"
    NO_ANSWER = "not a command: no reply"


@frozen
class SlaveWrite:
    """A decoded write of a slave: ``words`` from element ``element`` of integer file ``file_number``."""

    file_number: int
    element: int
    words: tuple[int, ...]


class RegisterTable:
    """Words a station wrote to the gateway, with their receive times (one per sending station).

    ``RegisterTable(file_number=7, size=100)`` accepts writes to N7:0 .. N7:99 (``first_element``
    shifts the window).  ``value(i)`` / ``received_at(i)`` / ``age(i, now)`` per word, ``values()`` all;
    an unwritten word is 0 with ``received_at`` None.  The integrator serves it as Modbus registers.
    """

    def __init__(self, *, file_number: int = 7, size: int = 100, first_element: int = 0) -> None:
        if not 0 <= file_number <= 999 or not 0 < size <= 10_000 or first_element < 0:
            raise ValueError(f"register table N{file_number}:{first_element} size {size}: out of range")
        self.file_number = file_number
        self.size = size
        self.first_element = first_element
        self._values = [0] * size
        self._received: list[float | None] = [None] * size
        self.writes = 0  #: writes stored
        self.refused = 0  #: writes refused (outside the table)

    def covers(self, write: SlaveWrite) -> bool:
        return self.problem(write) is None

    def problem(self, write: SlaveWrite) -> Problem | None:
        """Why the table cannot take ``write`` (the target core's problems), None if it covers it all."""
        start = write.element - self.first_element
        if write.file_number != self.file_number:
            return Problem.NO_FILE
        if not 0 <= start < self.size:
            return Problem.NOT_USABLE
        if start + len(write.words) > self.size:
            return Problem.PAST_END
        return None

    def store(self, write: SlaveWrite, now: float) -> bool:
        """Store ``write`` if the table covers it all (else nothing, and False)."""
        if not self.covers(write):
            self.refused += 1
            return False
        start = write.element - self.first_element
        for i, word in enumerate(write.words):
            self._values[start + i] = word
            self._received[start + i] = now
        self.writes += 1
        return True

    def value(self, index: int) -> int:
        return self._values[index]

    def values(self) -> list[int]:
        return list(self._values)

    def received_at(self, index: int) -> float | None:
        return self._received[index]

    def age(self, index: int, now: float) -> float | None:
        """Seconds since word ``index`` was last written, None if it never was."""
        at = self._received[index]
        return None if at is None else now - at

    def __iter__(self) -> Iterator[int]:
        return iter(self._values)


def _words(data: bytes) -> tuple[int, ...]:
    return tuple(int.from_bytes(data[i : i + 2], "little") for i in range(0, len(data) - 1, 2))


def decode_slave_write(packet: bytes) -> SlaveWrite | None:
    """The write a slave's command packet carries, None when it is not one we store."""
    try:
        return _slave_write(decode_command(packet).request)
    except PcccFormatError:
        return None


def _slave_write(request: Request) -> SlaveWrite | None:
    if isinstance(request, WordRangeWrite) and request.packet_offset == 0:
        return _file_element_write(request.address.levels, request.data)
    if isinstance(request, ProtectedTypedLogicalWrite):
        if request.file_type == FileType.INTEGER and request.sub_element == 0 and len(request.data) % 2 == 0:
            return SlaveWrite(request.file_number, request.element, _words(request.data))
        return None
    if isinstance(request, TypedWrite) and request.data_type == DataType.INTEGER and request.element_size == 2:
        if request.packet_offset == 0:
            return _file_element_write(request.address.levels, request.data)
    return None


def _file_element_write(levels: Sequence[int], data: bytes) -> SlaveWrite | None:
    """The write of a PLC-5 logical address ``0, file, element`` (a sub-element level, if any, 0);
    None for any other address (a word inside an element is not a register of the table)."""
    if len(levels) in (3, 4) and levels[0] == 0 and (len(levels) == 3 or levels[3] == 0):
        return SlaveWrite(levels[1], levels[2], _words(data))
    return None


def answer_slave_message(
    packet: bytes, *, own_station: int, table: RegisterTable | None, now: float
) -> tuple[SlaveMessageVerdict, bytes | None]:
    """Store what ``packet`` (a slave-initiated message) writes to us; the reply packet to send back."""
    try:
        header = PcccHeader.decode(packet)
    except PcccFormatError:
        return SlaveMessageVerdict.NO_ANSWER, None
    if header.is_reply:
        return SlaveMessageVerdict.NO_ANSWER, None
    try:
        request: Request | None = decode_command(packet).request
    except PcccFormatError:
        request = None
    write = _slave_write(request) if request is not None and header.dst == own_station else None
    if write is None or table is None:
        sts, ext_sts = refusal(request, Problem.FORMAT)
        return SlaveMessageVerdict.UNSUPPORTED, encode_reply(header, sts=sts, ext_sts=ext_sts)
    if not table.store(write, now):
        problem = table.problem(write)
        assert problem is not None  # store() refuses only what the table does not cover
        sts, ext_sts = refusal(request, problem)
        return SlaveMessageVerdict.BAD_ADDRESS, encode_reply(header, sts=sts, ext_sts=ext_sts)
    return SlaveMessageVerdict.STORED, encode_reply(header)
