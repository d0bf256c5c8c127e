"""PLC-5 addresses: parsing what a programmer types, logical binary and logical ASCII encodings.

Manual: A-B 1770-6.5.16 chapter 13 "PLC Addressing" (p. 13-11 logical binary addressing, p. 13-12
examples N7:30, B3:300, T4:2.ACC, PD12:10.SP, p. 13-13 the level map, p. 13-15 logical ASCII
addressing) and chapter 7 (p. 7-20 read-modify-write, FNC 26); 1770-KF2 user manual p. 5-57 (word
range read FNC 01 / write FNC 00 layouts); PLC-5 quick reference 1785 p. 2-6 (the address forms
users type).  Reading and vectors: ``docs/develop/df1-half-duplex-notes.md`` section 6.  The word range
read / write and read-modify-write packets that carry these addresses are built in
:mod:`gateway.protocols.df1.pccc.plc5`, the one home of PLC-5 packet building.

Address forms accepted (what a PLC-5 programmer types)::

    N7:0  F8:2  B3:300  S:3  S2:3  O:0  I:017       word (element) addresses; O and I octal
    N7:0/3  B3:2/15  I:017/17                       bit of a word (I/O bits octal 00-07, 10-17)
    B3/5  B3/16                                     direct bit of a binary file (B3/16 = B3:1/0)
    T4:1.ACC  T4:2.PRE  C5:0.ACC  R6:0.LEN  R6:0.POS  sub-element (level 4)
    T4:1/DN  T4:1.DN  C5:0/CU  R6:0/EN              status bit of a timer / counter / control

A logical binary address is a mask byte followed by the levels it marks (bit n = level n + 1):
level 1 data table (0), level 2 file number, level 3 element, level 4 sub-element.  A level value of
255 or more is sent as ``FF lo hi`` (p. 13-11 "Important").

This module does no I/O.
"""

from __future__ import annotations

import re
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.address import AddressError

__all__ = [
    "PLC5_SIGNED",
    "PLC5_STRUCTURES",
    "AddressError",
    "Plc5Address",
    "decode_logical_ascii",
    "decode_logical_binary",
    "encode_logical_ascii",
    "encode_logical_binary",
    "parse_plc5_address",
    "plc5_element_words",
]

#: Most level values the logical binary address can carry (two bytes after FF).
_MAX_LEVEL: Final = 0xFFFF
_FF: Final = 0xFF


#: File type letters -> (default file number or None, words per element, octal element/bit numbers)
_FILE_TYPES: Final[dict[str, tuple[int | None, int, bool]]] = {
    "O": (0, 1, True),
    "I": (1, 1, True),
    "S": (2, 1, False),
    "B": (None, 1, False),
    "N": (None, 1, False),
    "F": (None, 2, False),  # floats are two words long (S4516 §2.6.1; p. 13-13)
    "A": (None, 1, False),
    "D": (None, 1, False),
    "T": (None, 3, False),
    "C": (None, 3, False),
    "R": (None, 3, False),
}

#: Level 4 sub-elements (p. 13-12/13-13: 0 control, 1 preset / length, 2 accumulated / position).
#: Their files, timers, counters and controls, are the structure files.
_SUB_ELEMENTS: Final[dict[str, dict[str, int]]] = {
    "T": {"CTL": 0, "PRE": 1, "ACC": 2},
    "C": {"CTL": 0, "PRE": 1, "ACC": 2},
    "R": {"CTL": 0, "LEN": 1, "POS": 2},
}

#: File type letters of the structure files (timer, counter, control: three words per element).
PLC5_STRUCTURES: Final = frozenset(_SUB_ELEMENTS)
#: File type letters whose words are signed 16-bit numbers: integers, and the words of timers,
#: counters and controls (PRE, ACC, LEN, POS; two's complement, 1770-6.5.16 p. 13-13).
PLC5_SIGNED: Final = frozenset({"N", *PLC5_STRUCTURES})


def plc5_element_words(file_type: str) -> int:
    """Words per element of a file of ``file_type`` (a float 2, a timer / counter / control 3, else 1)."""
    return _FILE_TYPES[file_type][1]

#: Status bits in the control word (sub-element 0) of timers, counters and controls.
_STATUS_BITS: Final[dict[str, dict[str, int]]] = {
    "T": {"EN": 15, "TT": 14, "DN": 13},
    "C": {"CU": 15, "CD": 14, "DN": 13, "OV": 12, "UN": 11},
    "R": {"EN": 15, "EU": 14, "DN": 13, "EM": 12, "ER": 11, "UL": 10, "IN": 9, "FD": 8},
}

_PATTERN: Final = re.compile(
    r"""^\s*\$?(?P<type>[A-Z])(?P<file>\d{1,3})?
        (?:
            :(?P<element>\d{1,5})
            (?:\.(?P<member>[A-Z]{2,3}))?
            (?:/(?P<bit>\d{1,2}|[A-Z]{2}))?
          | /(?P<direct>\d{1,5})
        )\s*$""",
    re.VERBOSE | re.IGNORECASE,
)


@frozen
class Plc5Address:
    """A parsed PLC-5 data table address (file type letter, file, element, sub-element, bit)."""

    file_type: str
    file_number: int
    element: int
    sub_element: int | None = None
    bit: int | None = None

    def __post_init__(self) -> None:
        if self.file_type not in _FILE_TYPES:
            raise AddressError(f"unknown PLC-5 file type {self.file_type!r}")
        if not 0 <= self.file_number <= 999:
            raise AddressError(f"file number {self.file_number} out of range 0..999")
        if not 0 <= self.element <= _MAX_LEVEL:
            raise AddressError(f"element {self.element} out of range")
        if self.sub_element is not None and not 0 <= self.sub_element <= _MAX_LEVEL:
            raise AddressError(f"sub-element {self.sub_element} out of range")
        if self.bit is not None and not 0 <= self.bit <= 15:
            raise AddressError(f"bit {self.bit} out of range 0..15")

    @property
    def levels(self) -> tuple[int, ...]:
        """Logical binary levels: data table 0, file, element[, sub-element]."""
        base = (0, self.file_number, self.element)
        return base if self.sub_element is None else (*base, self.sub_element)

    @property
    def words(self) -> int:
        """Words one element at this address occupies (a float 2, a whole timer 3, else 1)."""
        if self.sub_element is not None or self.bit is not None:
            return 1
        return plc5_element_words(self.file_type)

    def __str__(self) -> str:
        octal = _FILE_TYPES[self.file_type][2]
        element = f"{self.element:o}" if octal else str(self.element)
        default = _FILE_TYPES[self.file_type][0]
        file_part = "" if default == self.file_number and self.file_type in "OIS" else str(self.file_number)
        text = f"{self.file_type}{file_part}:{element}"
        if self.sub_element is not None:
            names = {v: k for k, v in _SUB_ELEMENTS.get(self.file_type, {}).items()}
            text += f".{names.get(self.sub_element, str(self.sub_element))}"
        if self.bit is not None:
            text += f"/{self.bit:o}" if octal else f"/{self.bit}"
        return text


def _number(text: str, *, octal: bool, what: str, original: str) -> int:
    if octal and any(c in "89" for c in text):
        raise AddressError(f"{original!r}: {what} {text} is octal on a PLC-5 I/O file (digits 0-7)")
    return int(text, 8 if octal else 10)


def parse_plc5_address(text: str) -> Plc5Address:
    """Parse what a PLC-5 programmer types (module docstring); AddressError says what is wrong."""
    match = _PATTERN.match(text)
    if match is None:
        raise AddressError(f"{text!r} is not a PLC-5 address; expected forms like N7:0, B3/5, N7:0/3, T4:1.ACC, F8:2")
    file_type = match["type"].upper()
    if file_type not in _FILE_TYPES:
        raise AddressError(f"{text!r}: unknown file type {file_type!r} (known: {', '.join(_FILE_TYPES)})")
    default, _words, octal = _FILE_TYPES[file_type]
    if match["file"] is not None:
        file_number = int(match["file"])
    elif default is not None:
        file_number = default
    else:
        raise AddressError(f"{text!r}: a {file_type} file needs its file number (e.g. {file_type}7:0)")
    if match["direct"] is not None:
        if file_type != "B":
            raise AddressError(f"{text!r}: direct bit addresses (x/bit) exist only for binary (B) files")
        bit_number = int(match["direct"])
        if bit_number > 15999:
            raise AddressError(f"{text!r}: binary file bit {bit_number} is beyond 15999")
        return Plc5Address(file_type, file_number, bit_number // 16, bit=bit_number % 16)
    element = _number(match["element"], octal=octal, what="element", original=text)
    sub_element: int | None = None
    bit: int | None = None
    member = match["member"].upper() if match["member"] else None
    bit_text = match["bit"].upper() if match["bit"] else None
    status = _STATUS_BITS.get(file_type, {})
    if member is not None:
        if member in _SUB_ELEMENTS.get(file_type, {}):
            sub_element = _SUB_ELEMENTS[file_type][member]
        elif member in status and bit_text is None:
            sub_element, bit = 0, status[member]
        else:
            raise AddressError(f"{text!r}: {file_type} files have no member .{member}")
    if bit_text is not None:
        if bit_text.isdigit():
            bit = _number(bit_text, octal=octal, what="bit", original=text)
            if sub_element is None and file_type in _SUB_ELEMENTS:
                raise AddressError(f"{text!r}: name the word of a {file_type} element (.PRE, .ACC) before /bit")
        elif bit_text in status and member is None:
            sub_element, bit = 0, status[bit_text]
        else:
            raise AddressError(f"{text!r}: {file_type} files have no status bit {bit_text}")
    # A bare T4:1 is the whole element: three words from its control word (``words``).
    return Plc5Address(file_type, file_number, element, sub_element, bit)


# ----------------------------------------------------------------------- logical binary / ASCII


def _encode_level(value: int) -> bytes:
    if not 0 <= value <= _MAX_LEVEL:
        raise AddressError(f"address level {value} out of range 0..65535")
    if value < _FF:
        return bytes((value,))
    return bytes((_FF,)) + value.to_bytes(2, "little")  # p. 13-11: >= 255 is FF lo hi


def encode_logical_binary(address: Plc5Address, *, compact: bool = False) -> bytes:
    """Mask byte + levels (p. 13-11).  ``compact`` leaves level 1 (data table 0) to its default,
    as the B3:300 example on p. 13-12 does; the default encodes every level, as N7:30 does."""
    levels = address.levels
    mask = (1 << len(levels)) - 1
    if compact:
        mask &= ~1
    return bytes((mask,)) + b"".join(_encode_level(v) for i, v in enumerate(levels) if mask >> i & 1)


def decode_logical_binary(data: bytes, offset: int = 0) -> tuple[tuple[int, ...], int]:
    """Levels (defaults filled in) and the offset after the address; AddressError when short."""
    try:
        mask = data[offset]
        offset += 1
        if mask == 0 or mask > 0x0F:
            raise AddressError(f"PLC-5 logical binary mask {mask:#04x} names no level 1..4")
        levels: list[int] = []
        for level in range(mask.bit_length()):
            if not mask >> level & 1:
                levels.append(0)  # p. 13-11: an omitted level takes its default (0)
                continue
            value = data[offset]
            offset += 1
            if value == _FF:
                if offset + 2 > len(data):
                    raise IndexError
                value = int.from_bytes(data[offset : offset + 2], "little")
                offset += 2
            levels.append(value)
    except IndexError:
        raise AddressError("PLC-5 logical binary address is truncated") from None
    return tuple(levels), offset


def encode_logical_ascii(address: Plc5Address | str) -> bytes:
    """``NUL $ <address> NUL`` (1770-6.5.16 p. 13-15; KF2 p. 6-13 Figure 6.9)."""
    text = str(address) if isinstance(address, Plc5Address) else address.strip()
    if not text or not text.isascii() or "\x00" in text:
        raise AddressError(f"{text!r} cannot be sent as a logical ASCII address")
    return b"\x00$" + text.encode("ascii") + b"\x00"


def decode_logical_ascii(data: bytes, offset: int = 0) -> tuple[str, int]:
    if data[offset : offset + 2] != b"\x00$":
        raise AddressError("a PLC-5 logical ASCII address starts with NUL $")
    end = data.find(b"\x00", offset + 2)
    if end < 0:
        raise AddressError("PLC-5 logical ASCII address without its closing NUL")
    return data[offset + 2 : end].decode("ascii", "replace"), end + 1
