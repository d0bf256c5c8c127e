"""PLC-5 requests for the PCCC codec: word range read / write of a PLC-5 address, and the coil write.

What a PLC-5 unit sends (1770-6.5.16 chapter 7, 1770-KF2 p. 5-48 and 5-57):

* registers: word range read ``0F 01`` / word range write ``0F 00`` with a logical binary address of
  every level (``07 00 07 1E`` for N7:30, ``0F 00 04 02 02`` for T4:2.ACC - p. 13-12);
* coils: read-modify-write ``0F 26`` of the word holding the bit, ``AND FFFF OR 1<<b`` to set it,
  ``AND ~(1<<b) OR 0000`` to reset it (p. 7-20): only that bit changes, in the controller, in one
  command - no read-then-write race with the ladder.

The request classes are the codec's (``gateway.protocols.df1.pccc``: ``WordRangeRead``,
``WordRangeWrite``, ``ReadModifyWriteRequest``); this module builds them from typed PLC-5 addresses.
This module does no I/O.
"""

from __future__ import annotations

from gateway.protocols.df1.pccc import LogicalBinaryAddress, ReadModifyWriteRequest, WordRangeRead, WordRangeWrite
from gateway.protocols.df1.plc5_address import AddressError, Plc5Address, parse_plc5_address

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


#: The read-modify-write request (the codec's class; kept under this name for the PLC-5 unit).
Plc5ReadModifyWrite = ReadModifyWriteRequest


def plc5_bit_write(address: Plc5Address | str, value: bool) -> Plc5ReadModifyWrite:
    """The coil write of a bit address (``B3/5``, ``N7:0/3``, ``T4:1/DN``)."""
    parsed = _address(address)
    if parsed.bit is None:
        raise AddressError(f"{parsed}: a coil write needs a bit address (B3/5, N7:0/3)")
    word = _logical(Plc5Address(parsed.file_type, parsed.file_number, parsed.element, parsed.sub_element))
    mask = 1 << parsed.bit
    return ReadModifyWriteRequest(((word, 0xFFFF, mask) if value else (word, 0xFFFF & ~mask, 0x0000),))
