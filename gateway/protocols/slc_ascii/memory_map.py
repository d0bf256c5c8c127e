"""The SLC 100/150 memory map, the user address table and the item syntax of the CLI.

Everything here is data from the manual (``shared/docs/slc100-150-ascii-protocol.md``) plus pure lookups:

* "The Memory Map": every described cell with its access class (``*`` read only, ``**`` no access).
* "Reading Data": the start addresses command 02 accepts (:data:`READ_RANGES`).
* "Writing Data Words" / "Writing Data Bytes": the ranges commands 03 accept
  (:data:`WORD_WRITE_RANGES`, :data:`BYTE_WRITE_RANGE`).
* "User Address to Controller Address Table": user bit address <-> (byte address, bit).
* The timer/counter/sequencer words and step counters of numbers 901-932.

All multi-byte values of the SLC 100/150 memory map are MSB first ("The Memory Map").

The map ends at 0112H (access code byte). The user program follows, but the manual gives no
addresses for it, so :func:`region_of` answers ``None`` beyond 0112H.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from enum import Enum
from types import MappingProxyType
from typing import Final

from gateway.errors import InvalidRequest, ProtocolError
from gateway.frozen import frozen

__all__ = [
    "ACCUMULATORS",
    "BYTE_WRITE_RANGE",
    "ERROR_BITS_REGION",
    "FINE_TIMER_BITS",
    "FORCE_SELECT",
    "FORCE_STATE",
    "INPUT_STATE",
    "INTERNAL_RELAYS",
    "MAP_SIZE",
    "MEMORY_MAP",
    "MODE_ADDRESS",
    "MODE_BYTE",
    "OUTPUT_STATE",
    "PRESETS",
    "PROTECT_BIT",
    "READ_RANGES",
    "STEP_COUNTERS",
    "TCS_OUTPUT_BITS",
    "TCS_OVERFLOW_BITS",
    "TIMER_NUMBERS",
    "WORD_VALUE_MASK",
    "WORD_WRITE_RANGES",
    "Access",
    "AddressRange",
    "Item",
    "ItemKind",
    "Region",
    "accumulator_address",
    "all_user_bits",
    "byte_to_user_bit",
    "check_byte_writable",
    "check_readable",
    "check_word_writable",
    "is_byte_writable",
    "is_readable",
    "is_word_writable",
    "is_writable_user_bit",
    "parse_item",
    "preset_address",
    "region_of",
    "step_counter_address",
    "user_bit_to_byte",
]

ADDRESS_MAX = 0xFFFF
"""Addresses are four ASCII hex characters on the wire ("Reading Data")."""

PROTECT_BIT = 0x8000
"""Bit 7 of the MSB of a preset word: 1 = protected ("The Memory Map", 40H-7FH)."""

WORD_VALUE_MASK = 0x7FFF
"""Mask that removes the protect bit from a word ("Reading Data", note)."""


class Access(Enum):
    """Access class of a memory cell ("The Memory Map", WARNING under the table)."""

    READ_WRITE = "read/write"
    """No mark in the map."""
    READ_ONLY = "read only (*)"
    """Marked ``*``: "should not be changed by the controlling device and should be read only"."""
    NO_ACCESS = "no access (**)"
    """Marked ``**``: "should not be accessed in any way"."""


@frozen
class AddressRange:
    """An inclusive range of byte addresses with the manual's name for it."""

    start: int
    end: int
    name: str

    def __post_init__(self) -> None:
        if not 0 <= self.start <= self.end <= ADDRESS_MAX:
            raise ValueError(f"bad address range 0x{self.start:04X}-0x{self.end:04X}")

    def __contains__(self, address: object) -> bool:
        return isinstance(address, int) and self.start <= address <= self.end

    def __str__(self) -> str:
        if self.start == self.end:
            return f"0x{self.start:04X} ({self.name})"
        return f"0x{self.start:04X}-0x{self.end:04X} ({self.name})"


@frozen
class Region:
    """One row of "The Memory Map".

    ``access`` is the row's mark in the map. ``readable`` says whether the row is in the "Reading
    Data" list of command 02: then every byte of it can be read, though a read in a word table
    (00H-3FH, 40H-7FH) must start at or before the MSB of its last word (:data:`READ_RANGES`).
    """

    name: str
    start: int
    end: int
    access: Access
    readable: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.start <= self.end <= ADDRESS_MAX:
            raise ValueError(f"bad region 0x{self.start:04X}-0x{self.end:04X}")

    def __contains__(self, address: object) -> bool:
        return isinstance(address, int) and self.start <= address <= self.end

    @property
    def size(self) -> int:
        """Number of bytes in the region."""
        return self.end - self.start + 1


_RW, _RO, _NO = Access.READ_WRITE, Access.READ_ONLY, Access.NO_ACCESS

# The rows other modules name (the plan's blocks, the error bits the driver reads after ;T, mode selection)
ACCUMULATORS: Final = Region("timer/counter/sequencer accumulators", 0x0000, 0x003F, _RW, readable=True)
PRESETS: Final = Region("timer/counter presets", 0x0040, 0x007F, _RW, readable=True)
ERROR_BITS_REGION: Final = Region("controller error mode bits", 0x0084, 0x0085, _RW, readable=True)
FORCE_SELECT: Final = Region("force select table", 0x0086, 0x0095, _RW, readable=True)
OUTPUT_STATE: Final = Region("output state table", 0x0096, 0x009C, _RO, readable=True)
INPUT_STATE: Final = Region("input state table", 0x009D, 0x00A5, _RO, readable=True)
INTERNAL_RELAYS: Final = Region("internal relays", 0x00A6, 0x00BA, _RO, readable=True)
FINE_TIMER_BITS: Final = Region("fine timer bits, AUTO/MAN switch", 0x00BB, 0x00BB, _RO, readable=True)
STEP_COUNTERS: Final = Region("sequencer step counters", 0x00BC, 0x00DB, _RO, readable=True)
TCS_OUTPUT_BITS: Final = Region("timer/counter/sequencer output bits", 0x00DC, 0x00DF, _RO, readable=True)
TCS_OVERFLOW_BITS: Final = Region("timer/counter/sequencer overflow bits", 0x00E0, 0x00E3, _RO, readable=True)
MODE_BYTE: Final = Region("controller mode byte", 0x0101, 0x0101, _RW)
FORCE_STATE: Final = Region("force state table", 0x0102, 0x0111, _RW, readable=True)

MEMORY_MAP: tuple[Region, ...] = (
    ACCUMULATORS,
    PRESETS,
    Region("checksum of last ladder diagram", 0x0080, 0x0081, _NO),
    Region("current rung number", 0x0082, 0x0083, _RO),
    ERROR_BITS_REGION,
    FORCE_SELECT,
    OUTPUT_STATE,
    INPUT_STATE,
    INTERNAL_RELAYS,
    FINE_TIMER_BITS,
    STEP_COUNTERS,
    TCS_OUTPUT_BITS,
    TCS_OVERFLOW_BITS,
    Region("timer/counter/sequencer immediate rung bits", 0x00E4, 0x00E7, _RO),
    Region("reset instruction immediate rung state bits", 0x00E8, 0x00EB, _RO),
    Region("up counter/timer/sequencer last state bits", 0x00EC, 0x00EF, _NO),
    Region("down counter last state bits", 0x00F0, 0x00F3, _NO),
    Region("RTF instruction start up (trigger) bits", 0x00F4, 0x00F7, _NO),
    Region("flags to identify sequencer instructions", 0x00F8, 0x00FB, _NO),
    Region("RTF instruction identifier bits", 0x00FC, 0x00FF, _NO),
    Region("RAM size, new check sum flag, watchdog fault", 0x0100, 0x0100, _RO),
    MODE_BYTE,
    FORCE_STATE,
    Region("access code byte", 0x0112, 0x0112, _RW, readable=True),
)
"""Every cell of "The Memory Map" with an address, in address order, without gaps."""

MAP_SIZE: Final = MEMORY_MAP[-1].end + 1
"""Bytes from 0000H to the end of the map (0112H, the access code byte), 113H."""
MODE_ADDRESS: Final = MODE_BYTE.start
"""Mode selection writes the controller mode byte: ``#0403 0101 <mode>`` ("Mode Selection")."""

READ_RANGES: tuple[AddressRange, ...] = (
    AddressRange(0x0000, 0x003E, "timer/counter/sequencer accumulator"),
    AddressRange(0x0040, 0x007E, "timer/counter presets"),
    AddressRange(0x0084, 0x0085, "error bits"),
    AddressRange(0x0086, 0x0095, "force select table"),
    AddressRange(0x0096, 0x009C, "output state table"),
    AddressRange(0x009D, 0x00A5, "input state table"),
    AddressRange(0x00A6, 0x00BA, "internal relay table"),
    AddressRange(0x00BB, 0x00BB, "fine timer bits, auto/man switch"),
    AddressRange(0x00BC, 0x00DB, "sequencer step counters"),
    AddressRange(0x00DC, 0x00DF, "timer/counter/sequencer output table"),
    AddressRange(0x00E0, 0x00E3, "timer/counter/sequencer overflow table"),
    AddressRange(0x0102, 0x0111, "force state table"),
    AddressRange(0x0112, 0x0112, "access code byte"),
)
"""Start addresses accepted by command 02, verbatim from "Reading Data".

The word tables are listed by the start of their last word (003EH, 007EH); their last bytes
(003FH, 007FH) are read as the second byte of a 2-byte read.
"""

WORD_WRITE_RANGES: tuple[AddressRange, ...] = (
    AddressRange(0x0000, 0x003E, "timer/counter/sequencer accumulator"),
    AddressRange(0x0040, 0x007E, "timer/counter presets"),
)
"""Addresses accepted by the word write (``#0503``); they must also be even ("Writing Data Words")."""

BYTE_WRITE_RANGE = AddressRange(0x00A6, 0x00B4, "internal relay table - 701 thru 820 only")
"""Addresses accepted by the byte write (``#0403``) ("Writing Data Bytes").

The memory map marks the internal relays ``*`` (read only); the command section explicitly allows
writing 00A6H-00B4H, and the controller itself checks the range, so the command section wins.
"""

READ_COUNTS = (1, 2)
"""Command 02 reads "either 0001 or 0002" bytes ("Reading Data")."""

TIMER_NUMBERS = range(901, 933)
"""Timer/counter/sequencer numbers 901-932 (32 words at 00H-3FH and 40H-7FH)."""


# --------------------------------------------------------------------------------------------------
# Regions and access checks


def _check_address(address: object) -> int:
    if isinstance(address, bool) or not isinstance(address, int):
        raise InvalidRequest(f"address {address!r} is not an integer")
    if not 0 <= address <= ADDRESS_MAX:
        raise InvalidRequest(f"address {address} is out of range 0x0000-0xFFFF")
    return address


def region_of(address: int) -> Region | None:
    """The memory map row holding ``address``, or ``None`` beyond 0112H ("The Memory Map").

    Raises :class:`InvalidRequest` when ``address`` is not an integer in 0x0000-0xFFFF.
    """
    address = _check_address(address)
    for region in MEMORY_MAP:
        if address in region:
            return region
    return None


def _readable_list() -> str:
    return ", ".join(str(r) for r in READ_RANGES)


def check_readable(address: int, count: int = 1) -> None:
    """Raise :class:`InvalidRequest` unless command 02 may read ``count`` bytes at ``address``.

    Rules ("Reading Data", "The Memory Map"): ``count`` is 1 or 2; the start address is in the
    "Reading Data" list (:data:`READ_RANGES`); every byte read lies in a row of that list, so no
    byte is a ``**`` cell.
    """
    if type(address) is int and type(count) is int and (address, count) in _READABLE:
        return  # every poll passes here: the answer is precomputed (bools are not numbers here)
    address = _check_address(address)
    if isinstance(count, bool) or not isinstance(count, int) or count not in READ_COUNTS:
        raise InvalidRequest(f"byte count {count!r} is not allowed: command 02 reads 1 or 2 bytes")
    _check_readable_byte(address, f"address 0x{address:04X}")
    if not any(address in r for r in READ_RANGES):
        region = region_of(address)
        assert region is not None  # _check_readable_byte passed
        raise InvalidRequest(
            f"address 0x{address:04X} is the LSB of the last word of {region.name}: a read must start "
            f"at 0x{region.start:04X}-0x{region.end - 1:04X}; read 2 bytes at 0x{address - 1:04X}")
    for byte in range(address + 1, address + count):
        _check_readable_byte(
            byte, f"reading {count} bytes at 0x{address:04X} would also read 0x{byte:04X}, which")


def _check_readable_byte(byte: int, what: str) -> None:
    if byte > ADDRESS_MAX:
        raise InvalidRequest(f"{what} is beyond 0xFFFF")
    region = region_of(byte)
    if region is None:
        raise InvalidRequest(
            f"{what} is outside the described memory map (0x0000-0x0112); readable: {_readable_list()}")
    if region.access is Access.NO_ACCESS:
        raise InvalidRequest(f"{what} is in a no-access (**) cell: {region.name}")
    if not region.readable:
        raise InvalidRequest(
            f"{what} ({region.name}) is not in the manual's list of readable addresses; "
            f"readable: {_readable_list()}")


def is_readable(address: int, count: int = 1) -> bool:
    """Whether command 02 may read ``count`` bytes at ``address`` (see :func:`check_readable`)."""
    return type(address) is int and type(count) is int and (address, count) in _READABLE


def _all_readable() -> frozenset[tuple[int, int]]:
    readable = set()
    for address in range(MAP_SIZE):
        for count in READ_COUNTS:
            try:
                check_readable(address, count)
            except InvalidRequest:
                continue
            readable.add((address, count))
    return frozenset(readable)


#: Every (address, count) command 02 may read, computed once from the rules above.
_READABLE: frozenset[tuple[int, int]] = frozenset()
_READABLE = _all_readable()


def check_word_writable(address: int) -> None:
    """Raise :class:`InvalidRequest` unless the word write (``#0503``) accepts ``address``.

    "Writing Data Words": the address must be even and in 0000H-003EH or 0040H-007EH.
    """
    address = _check_address(address)
    if not any(address in r for r in WORD_WRITE_RANGES):
        allowed = " or ".join(str(r) for r in WORD_WRITE_RANGES)
        raise InvalidRequest(f"address 0x{address:04X} is not word-writable: the word write takes {allowed}")
    if address % 2:
        raise InvalidRequest(f"address 0x{address:04X} is odd: the word write needs an even address")


def is_word_writable(address: int) -> bool:
    """Whether the word write (``#0503``) accepts ``address``."""
    try:
        check_word_writable(address)
    except InvalidRequest:
        return False
    return True


def check_byte_writable(address: int) -> None:
    """Raise :class:`InvalidRequest` unless the byte write (``#0403``) accepts ``address``.

    "Writing Data Bytes": 00A6H-00B4H only (internal relays 701-820). The controller mode byte
    (0101H) is written only through the mode selection command.
    """
    address = _check_address(address)
    if address not in BYTE_WRITE_RANGE:
        raise InvalidRequest(
            f"address 0x{address:04X} is not byte-writable: the byte write takes only {BYTE_WRITE_RANGE}")


def is_byte_writable(address: int) -> bool:
    """Whether the byte write (``#0403``) accepts ``address``."""
    return isinstance(address, int) and not isinstance(address, bool) and address in BYTE_WRITE_RANGE


# --------------------------------------------------------------------------------------------------
# User address table


def _build_user_bits() -> dict[int, tuple[int, int]]:
    """"User Address to Controller Address Table", "User Program Addresses"."""
    table: dict[int, tuple[int, int]] = {}
    for group in range(7):
        base = group * 100
        for bit in range(8):
            table[base + 11 + bit] = (0x96 + group, bit)  # outputs g11-g18: 96H-9CH
            table[base + 1 + bit] = (0x9D + group, bit)  # inputs g01-g08: 9DH-A3H
        for k, offset in enumerate((9, 10)):
            # inputs g09, g10: A4H bits 2-7 then A5H bits 0-7, two bits per group (A4H bits 0, 1 unused)
            position = 2 + 2 * group + k
            table[base + offset] = (0xA4 + position // 8, position % 8)
    for i in range(176):  # internal relays 701-868 (A6H-BAH), fine timer / auto-man 869-876 (BBH)
        table[701 + i] = (0xA6 + i // 8, i % 8)
    for i in range(32):
        table[901 + i] = (0xDC + i // 8, i % 8)  # timer/counter/sequencer outputs 901-932
        table[951 + i] = (0xE0 + i // 8, i % 8)  # timer/counter/sequencer overflow 951-982
    return dict(sorted(table.items()))


_USER_BITS: Mapping[int, tuple[int, int]] = MappingProxyType(_build_user_bits())
_BYTE_BITS: Mapping[tuple[int, int], int] = MappingProxyType({v: k for k, v in _USER_BITS.items()})

_USER_BIT_RULE = (
    "valid bit addresses are inputs 1-10, 101-110, ..., 601-610, outputs 11-18, 111-118, ..., "
    "611-618, internal relays 701-868, fine timer bits / auto-man switch 869-876, "
    "timer/counter/sequencer outputs 901-932 and overflow bits 951-982"
)


def user_bit_to_byte(user_address: int) -> tuple[int, int]:
    """``(byte address, bit)`` of a user bit address ("User Program Addresses").

    >>> user_bit_to_byte(701), user_bit_to_byte(9), user_bit_to_byte(610)
    ((166, 0), (164, 2), (165, 7))

    Raises :class:`InvalidRequest` for an address that is not in the table.
    """
    if isinstance(user_address, bool) or not isinstance(user_address, int):
        raise InvalidRequest(f"user address {user_address!r} is not an integer; {_USER_BIT_RULE}")
    try:
        return _USER_BITS[user_address]
    except KeyError:
        raise InvalidRequest(f"user address {user_address} is not a bit address; {_USER_BIT_RULE}") from None


def byte_to_user_bit(byte_address: int, bit: int) -> int | None:
    """The user bit address stored at ``bit`` of ``byte_address``, or ``None`` if there is none.

    ``None`` for unused bits (A4H bits 0 and 1) and for bytes outside the table. The bytes
    E4H-EBH reuse the numbers 901-932 in the manual's table, but those numbers name the output bits
    at DCH-DFH, so E4H-EBH answer ``None``. Raises :class:`InvalidRequest` for a bit outside 0-7.
    """
    byte_address = _check_address(byte_address)
    if isinstance(bit, bool) or not isinstance(bit, int) or not 0 <= bit <= 7:
        raise InvalidRequest(f"bit {bit!r} is not a bit number 0-7")
    return _BYTE_BITS.get((byte_address, bit))


def all_user_bits() -> Iterator[int]:
    """Every valid user bit address, ascending."""
    return iter(_USER_BITS)


def is_writable_user_bit(user_address: int) -> bool:
    """Whether a user bit can be written: internal relays 701-820 ("Writing Data Bytes").

    The protocol writes whole bytes only, so writing one bit is a read-modify-write of its byte.
    """
    if user_address not in _USER_BITS:
        return False
    return _USER_BITS[user_address][0] in BYTE_WRITE_RANGE


# --------------------------------------------------------------------------------------------------
# Timer / counter / sequencer numbers 901-932


def _check_timer_number(number: int) -> int:
    if isinstance(number, bool) or not isinstance(number, int) or number not in TIMER_NUMBERS:
        raise InvalidRequest(f"timer/counter/sequencer number {number!r} is not in 901-932")
    return number


def accumulator_address(number: int) -> int:
    """Address of the accumulator word (MSB) of timer/counter/sequencer ``number`` (00H-3FH)."""
    return ACCUMULATORS.start + 2 * (_check_timer_number(number) - TIMER_NUMBERS.start)


def preset_address(number: int) -> int:
    """Address of the preset word (MSB) of timer/counter ``number`` (40H-7FH)."""
    return PRESETS.start + 2 * (_check_timer_number(number) - TIMER_NUMBERS.start)


def step_counter_address(number: int) -> int:
    """Address of the step counter byte of sequencer ``number`` (BCH-DBH, one byte each)."""
    return STEP_COUNTERS.start + (_check_timer_number(number) - TIMER_NUMBERS.start)


# --------------------------------------------------------------------------------------------------
# Items (CLI)


class ItemKind(Enum):
    """What an :class:`Item` names."""

    ACCUMULATOR = "ACC"
    """``901.ACC``: accumulator word, protect bit masked."""
    PRESET = "PRE"
    """``901.PRE``: preset word, protect bit masked."""
    PROTECTED = "PROTECTED"
    """``901.PROTECTED``: the preset's protect bit (bit 7 of its MSB)."""
    STEP = "STEP"
    """``901.STEP``: sequencer step counter byte."""
    BIT = "BIT"
    """``701``: a user bit address."""
    BYTE = "BYTE"
    """``@0x84``: a raw byte."""


#: A timer item's cell and the bytes read from it (PROTECTED: the preset's MSB, bit 7).
_TIMER_ITEMS: Final = {ItemKind.ACCUMULATOR: (accumulator_address, 2), ItemKind.PRESET: (preset_address, 2),
                       ItemKind.PROTECTED: (preset_address, 1), ItemKind.STEP: (step_counter_address, 1)}
_SUFFIXES = {kind.value: kind for kind in _TIMER_ITEMS}

_ITEM_RULE = (
    "use NNN.ACC, NNN.PRE, NNN.PROTECTED or NNN.STEP with NNN = 901-932, a user bit address "
    "(e.g. 1, 11, 701, 909, 951), or @ADDR for a raw byte at a hex address (e.g. @0x84 or @84)"
)
_TIMER_ITEM = re.compile(r"(\d+)\.([A-Za-z]+)")
_BIT_ITEM = re.compile(r"\d+")
_BYTE_ITEM = re.compile(r"@(?:0[xX])?([0-9A-Fa-f]{1,4})")


@frozen
class Item:
    """A readable (and maybe writable) thing named on the command line; see :func:`parse_item`.

    ``text`` is the canonical spelling (``901.ACC``, ``701``, ``@0x0084``). Read ``read_count``
    bytes at ``read_address`` with command 02 and pass them to :meth:`decode`.

    Writing (:mod:`~gateway.protocols.slc_ascii.commands` builds the commands, this module only knows
    the map): ``commands.write_item`` for ACC, PRE and raw bytes in 00A6H-00B4H. A user bit (``bit``
    is set) can only be written as a whole byte: read the byte, then call ``commands.write_item_bit``
    with its current value. The other bits of that byte are written back with the values read, so
    a change the ladder program makes to them between the read and the write is lost.
    """

    text: str
    kind: ItemKind
    read_address: int
    read_count: int
    bit: int | None = None
    number: int | None = None
    """The timer/counter/sequencer number (901-932) or the user bit address; ``None`` for @ bytes."""

    def __post_init__(self) -> None:
        check_readable(self.read_address, self.read_count)
        if (self.bit is not None) != (self.kind is ItemKind.BIT):
            raise ValueError("bit is set exactly for ItemKind.BIT")
        if self.bit is not None and not 0 <= self.bit <= 7:
            raise ValueError(f"bad bit {self.bit}")

    @property
    def writable(self) -> bool:
        """Whether the protocol can write this item (directly or by read-modify-write)."""
        if self.kind in (ItemKind.ACCUMULATOR, ItemKind.PRESET):
            return True
        if self.kind in (ItemKind.BIT, ItemKind.BYTE):
            return self.read_address in BYTE_WRITE_RANGE
        return False

    @property
    def read_modify_write(self) -> bool:
        """True for bits: writing needs the current byte (``commands.write_item_bit``)."""
        return self.kind is ItemKind.BIT

    def decode(self, data: bytes) -> int | bool:
        """The item's value from the ``read_count`` bytes read at ``read_address`` (MSB first)."""
        if len(data) != self.read_count:
            raise ProtocolError(f"{self.text}: expected {self.read_count} byte(s), got {len(data)}")
        if self.kind in (ItemKind.ACCUMULATOR, ItemKind.PRESET):
            return int.from_bytes(data, "big") & WORD_VALUE_MASK
        if self.kind is ItemKind.PROTECTED:
            return bool(data[0] & 0x80)
        if self.kind is ItemKind.BIT:
            assert self.bit is not None
            return bool(data[0] >> self.bit & 1)
        return data[0]  # STEP, BYTE

    def write_rule(self) -> str:
        return (
            "the protocol writes only NNN.ACC, NNN.PRE (values 0-9999), internal relays 701-820 "
            f"and raw bytes {BYTE_WRITE_RANGE}"
        )


def parse_item(text: str) -> Item:
    """Parse a CLI item: ``901.ACC``, ``901.PRE``, ``901.PROTECTED``, ``901.STEP``, ``701``, ``@0x84``.

    Suffixes are case-insensitive. ``@`` addresses are always hexadecimal (``@84`` = ``@0x84``)
    and must be readable with command 02 ("Reading Data"). Raises :class:`InvalidRequest` naming
    what is allowed.
    """
    if not isinstance(text, str):
        raise InvalidRequest(f"item {text!r} is not text; {_ITEM_RULE}")
    stripped = text.strip()
    if match := _TIMER_ITEM.fullmatch(stripped):
        number, suffix = int(match.group(1)), match.group(2).upper()
        if number not in TIMER_NUMBERS:
            raise InvalidRequest(f"item {text!r}: {number} is not a timer/counter/sequencer number 901-932")
        kind = _SUFFIXES.get(suffix)
        if kind is None:
            raise InvalidRequest(f"item {text!r}: unknown suffix {match.group(2)!r}; {_ITEM_RULE}")
        where, count = _TIMER_ITEMS[kind]
        return Item(f"{number}.{kind.value}", kind, where(number), count, number=number)
    if _BIT_ITEM.fullmatch(stripped):
        user_address = int(stripped)
        if user_address not in _USER_BITS:
            raise InvalidRequest(f"item {text!r} is not a user bit address; {_USER_BIT_RULE}")
        byte_address, bit = _USER_BITS[user_address]
        return Item(str(user_address), ItemKind.BIT, byte_address, 1, bit=bit, number=user_address)
    if match := _BYTE_ITEM.fullmatch(stripped):
        address = int(match.group(1), 16)
        try:
            check_readable(address, 1)
        except InvalidRequest as exc:
            raise InvalidRequest(f"item {text!r}: {exc}") from exc
        return Item(f"@0x{address:04X}", ItemKind.BYTE, address, 1)
    raise InvalidRequest(f"item {text!r} is not valid; {_ITEM_RULE}")
