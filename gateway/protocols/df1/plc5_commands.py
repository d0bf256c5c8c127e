"""PLC-5 requests for the PCCC codec: word range read / write of a PLC-5 address, and the coil write.

What a PLC-5 unit sends (issue #12; 1770-6.5.16 chapter 7, 1770-KF2 p. 5-48 and 5-57):

* registers: word range read ``0F 01`` / word range write ``0F 00`` with a logical binary address of
  every level (``07 00 07 1E`` for N7:30, ``0F 00 04 02 02`` for T4:2.ACC - p. 13-12);
* coils: read-modify-write ``0F 26`` of the word holding the bit, ``AND FFFF OR 1<<b`` to set it,
  ``AND ~(1<<b) OR 0000`` to reset it (p. 7-20): only that bit changes, in the controller, in one
  command - no read-then-write race with the ladder.

The word range classes are the codec's (``gateway.protocols.df1.pccc``); the read-modify-write
request class (CMD / FNC / ``encode_params`` for the codec's ``encode_command``) is here; its sets are
encoded by ``pccc.plc5.ReadModifyWrite``.  This module does no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from gateway.protocols.df1.pccc import Function, LogicalBinaryAddress, WordRangeRead, WordRangeWrite
from gateway.protocols.df1.pccc.plc5 import ReadModifyWrite
from gateway.protocols.df1.plc5_address import (
    AddressError,
    Plc5Address,
    encode_logical_binary,
    parse_plc5_address,
)

__all__ = ["Plc5ReadModifyWrite", "plc5_bit_write", "plc5_read", "plc5_write"]


def _address(address: Plc5Address | str) -> Plc5Address:
    return parse_plc5_address(address) if isinstance(address, str) else address


def _logical(address: Plc5Address) -> LogicalBinaryAddress:
    return LogicalBinaryAddress.of(*address.levels)


def plc5_read(address: Plc5Address | str, words: int | None = None) -> WordRangeRead:
    """Word range read of ``words`` words (default: the address's own size) from ``address``."""
    parsed = _address(address)
    if parsed.bit is not None:
        raise AddressError(f"{parsed}: read the word, not the bit (word range read)")
    count = parsed.words if words is None else words
    return WordRangeRead(_logical(parsed), 2 * count)


def plc5_write(address: Plc5Address | str, data: bytes) -> WordRangeWrite:
    """Word range write of ``data`` (whole words, low byte first) at ``address``."""
    parsed = _address(address)
    if parsed.bit is not None:
        raise AddressError(f"{parsed}: a bit is written with plc5_bit_write (read-modify-write)")
    return WordRangeWrite(_logical(parsed), data)


@dataclass(frozen=True, slots=True)
class Plc5ReadModifyWrite:
    """``CMD 0F FNC 26``: ``(address, AND mask, OR mask)`` sets, addresses logical binary (p. 7-20)."""

    CMD: ClassVar[int] = 0x0F
    FNC: ClassVar[int] = Function.READ_MODIFY_WRITE

    sets: tuple[tuple[Plc5Address, int, int], ...]

    def encode_params(self) -> bytes:
        return ReadModifyWrite(tuple((encode_logical_binary(a), m_and, m_or) for a, m_and, m_or in self.sets)).encode()


def plc5_bit_write(address: Plc5Address | str, value: bool) -> Plc5ReadModifyWrite:
    """The coil write of a bit address (``B3/5``, ``N7:0/3``, ``T4:1/DN``)."""
    parsed = _address(address)
    if parsed.bit is None:
        raise AddressError(f"{parsed}: a coil write needs a bit address (B3/5, N7:0/3)")
    word = Plc5Address(parsed.file_type, parsed.file_number, parsed.element, parsed.sub_element)
    mask = 1 << parsed.bit
    return Plc5ReadModifyWrite(((word, 0xFFFF, mask) if value else (word, 0xFFFF & ~mask, 0x0000),))
