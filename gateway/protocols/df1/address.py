"""SLC 500 logical addresses (``N7:3/9``, ``T4:3.ACC``, ``O:5.3/6``, ``B3/37`` ...).

Manual: "SLC 500 Family of Programmable Controllers Addressing Reference" (5000-6.4.23):
Table A (data table memory map), Tables C, E, G, I, K, M, O, Q (address forms), Figures 16, 18,
20 (structure bit maps).  File type codes: SLC 500 PCCC command notes §5.0 / §4.36.

Model::

    SlcAddress(file_type, file_number, element, sub_element, bit)

* data files: ``element`` is the element number (0-255); ``sub_element`` is the word inside a
  structure (timer/counter: 0 control, 1 PRE, 2 ACC; control: 0 control, 1 LEN, 2 POS) and 0
  for one-word and float elements; ``bit`` is 0-15 or None.
* I/O image (``O:slot.word/bit``): ``element`` is the slot (0-30), ``sub_element`` the word in
  the slot, as the protected typed logical commands address file types 0x8B / 0x8C.
* ``T4:3`` (a whole timer / counter / control structure) is ``sub_element=0, bit=None``;
  :attr:`SlcAddress.word_count` is then 3.
* Absolute bits (``B3/37`` = ``B3:2/5``) are normalised: bit ``n`` is word ``n // 16``.

``str(address)`` prints the canonical form, and ``parse_address(str(a)) == a``.
"""

from __future__ import annotations

import enum
import re
from dataclasses import replace
from typing import Final

from gateway.errors import InvalidRequest
from gateway.frozen import frozen

__all__ = [
    "SIGNED_FILE_TYPES",
    "STRUCTURE_FILE_TYPES",
    "AddressError",
    "FileType",
    "SlcAddress",
    "element_words",
    "parse_address",
]


class AddressError(InvalidRequest):
    """An SLC 500 or PLC-5 address that cannot be parsed, encoded or is out of range; the message
    says what is wrong.  A rule the request broke: Modbus 0x03 (``gateway.errors.MODBUS_CODES``)."""


class FileType(enum.IntEnum):
    """SLC file type codes of the protected typed logical commands (notes §5.0, §4.36)."""

    STATUS = 0x84
    BIT = 0x85
    TIMER = 0x86
    COUNTER = 0x87
    CONTROL = 0x88
    INTEGER = 0x89
    FLOAT = 0x8A
    OUTPUT = 0x8B  # output logical by slot (5/03, 5/04)
    INPUT = 0x8C  # input logical by slot (5/03, 5/04)
    STRING = 0x8D
    ASCII = 0x8E

    @property
    def letter(self) -> str:
        return _LETTER[self]


_LETTER: Final = {
    FileType.STATUS: "S",
    FileType.BIT: "B",
    FileType.TIMER: "T",
    FileType.COUNTER: "C",
    FileType.CONTROL: "R",
    FileType.INTEGER: "N",
    FileType.FLOAT: "F",
    FileType.OUTPUT: "O",
    FileType.INPUT: "I",
    FileType.STRING: "ST",
    FileType.ASCII: "A",
}
_BY_LETTER: Final = {letter: file_type for file_type, letter in _LETTER.items()}

#: Table A: files 0-8 have fixed types; 9 (network) and 10-255 take B, T, C, R, N, F.
_FIXED_FILE: Final = {
    FileType.OUTPUT: 0,
    FileType.INPUT: 1,
    FileType.STATUS: 2,
}
_DEFAULT_FILE_TYPE: Final = {
    0: FileType.OUTPUT,
    1: FileType.INPUT,
    2: FileType.STATUS,
    3: FileType.BIT,
    4: FileType.TIMER,
    5: FileType.COUNTER,
    6: FileType.CONTROL,
    7: FileType.INTEGER,
    8: FileType.FLOAT,
}
_USER_TYPES: Final = frozenset(
    {FileType.BIT, FileType.TIMER, FileType.COUNTER, FileType.CONTROL, FileType.INTEGER, FileType.FLOAT}
)
#: The structure files: timers, counters, controls (three words per element).
STRUCTURE_FILE_TYPES: Final = frozenset({FileType.TIMER, FileType.COUNTER, FileType.CONTROL})
#: Files whose words are signed 16-bit numbers: integers, and the words of timers, counters and
#: controls (PRE, ACC, LEN, POS).
SIGNED_FILE_TYPES: Final = frozenset({FileType.INTEGER, *STRUCTURE_FILE_TYPES})


def element_words(file_type: FileType) -> int:
    """Words per element of a file of ``file_type``: timer / counter / control 3, float 2, others 1."""
    if file_type in STRUCTURE_FILE_TYPES:
        return 3
    return 2 if file_type is FileType.FLOAT else 1

#: Files whose bits may be addressed by absolute bit number 0-4095 (page 4 of the reference).
_ABSOLUTE_BIT_TYPES: Final = frozenset(
    {FileType.BIT, FileType.CONTROL, FileType.INPUT, FileType.INTEGER, FileType.OUTPUT, FileType.STATUS}
)

#: Word mnemonics (word index in the structure), Tables L, N, P.
_WORDS: Final[dict[FileType, dict[str, int]]] = {
    FileType.TIMER: {"ACC": 2, "PRE": 1},
    FileType.COUNTER: {"ACC": 2, "PRE": 1},
    FileType.CONTROL: {"LEN": 1, "POS": 2},
}
#: Bit mnemonics (bit of word 0), Figures 16, 18, 20.
_BITS: Final[dict[FileType, dict[str, int]]] = {
    FileType.TIMER: {"EN": 15, "TT": 14, "DN": 13},
    FileType.COUNTER: {"CU": 15, "CD": 14, "DN": 13, "OV": 12, "UN": 11, "UA": 10},
    FileType.CONTROL: {"EN": 15, "EU": 14, "DN": 13, "EM": 12, "ER": 11, "UL": 10, "IN": 9, "FD": 8},
}
_NOUN: Final = {FileType.TIMER: "timers", FileType.COUNTER: "counters", FileType.CONTROL: "control files"}

MAX_ELEMENT: Final = 255
MAX_SLOT: Final = 30
MAX_ABSOLUTE_BIT: Final = 4095

_ADDRESS_RE: Final = re.compile(
    r"""
    \$?
    (?P<letter>ST|[OISBTCRNFA])
    (?P<file>\d+)?
    (?:
        :(?P<element>\d+)
        (?:\.(?P<member>[A-Z]+|\d+))?
        (?:/(?P<bit>[A-Z]+|\d+))?
      |
        /(?P<absolute>\d+)
    )
    """,
    re.VERBOSE,
)


@frozen
class SlcAddress:
    """A parsed SLC 500 logical address; see the module docstring for the field meanings."""

    file_type: FileType
    file_number: int
    element: int
    sub_element: int = 0
    bit: int | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.file_number <= 255:
            raise AddressError(f"file number {self.file_number} out of range 0-255")
        io = self.file_type in (FileType.INPUT, FileType.OUTPUT)
        limit = MAX_SLOT if io else MAX_ELEMENT
        if not 0 <= self.element <= limit:
            raise AddressError(f"{'slot' if io else 'element'} {self.element} out of range 0-{limit}")
        words = 256 if io else self.element_size_words
        if not 0 <= self.sub_element < words or (self.file_type is FileType.FLOAT and self.sub_element):
            raise AddressError(f"sub-element {self.sub_element} out of range for {self.file_type.name}")
        if self.bit is not None and not 0 <= self.bit <= 15:
            raise AddressError(f"bit {self.bit} out of range 0-15")
        if self.bit is not None and self.file_type is FileType.FLOAT:
            raise AddressError("floating-point elements are addressed in their entirety")

    @property
    def element_size_words(self) -> int:
        """Words per element: timer/counter/control 3, float 2, others 1 (:func:`element_words`)."""
        return element_words(self.file_type)

    @property
    def is_structure(self) -> bool:
        """True for a whole timer, counter or control structure (``T4:3``)."""
        return self.file_type in STRUCTURE_FILE_TYPES and self.sub_element == 0 and self.bit is None

    @property
    def word_count(self) -> int:
        """Words designated: the whole element for ``T4:3`` / ``F8:0``, else one word."""
        if self.is_structure or self.file_type is FileType.FLOAT:
            return self.element_size_words
        return 1

    @property
    def byte_count(self) -> int:
        return 2 * self.word_count

    def with_element(self, element: int) -> SlcAddress:
        """The same member of another element (slot, for I/O)."""
        return replace(self, element=element)

    def offset(self, count: int) -> SlcAddress:
        """``count`` elements further on (for I/O: ``count`` words further in the slot)."""
        if self.file_type in (FileType.INPUT, FileType.OUTPUT):
            return replace(self, sub_element=self.sub_element + count)
        return replace(self, element=self.element + count)

    def __str__(self) -> str:
        letter = self.file_type.letter
        bit = "" if self.bit is None else f"/{self.bit}"
        if self.file_type in (FileType.INPUT, FileType.OUTPUT):
            return f"{letter}:{self.element}.{self.sub_element}{bit}"
        if self.file_type is FileType.STATUS:
            return f"S:{self.element}{bit}"
        text = f"{letter}{self.file_number}:{self.element}"
        if self.file_type in STRUCTURE_FILE_TYPES:
            if self.sub_element == 0:
                names = {number: name for name, number in _BITS[self.file_type].items()}
                if self.bit is not None and self.bit in names:
                    return f"{text}/{names[self.bit]}"
                return text + bit
            word = {number: name for name, number in _WORDS[self.file_type].items()}[self.sub_element]
            return f"{text}.{word}{bit}"
        return text + bit


def parse_address(text: str) -> SlcAddress:
    """Parse an SLC 500 logical address; raises :class:`AddressError` saying what is wrong."""
    source = text.strip()
    match = _ADDRESS_RE.fullmatch(source.upper())
    if match is None:
        raise AddressError(
            f"{text!r}: not an SLC 500 address; expected forms like N7:0, B3:2/9, B3/37, T4:3.ACC, O:5.3/6"
        )
    try:
        return _build(match)
    except AddressError as exc:
        raise AddressError(f"{source}: {exc}") from None


def _build(match: re.Match[str]) -> SlcAddress:
    letter = match["letter"]
    file_type = _BY_LETTER[letter]
    if file_type in (FileType.STRING, FileType.ASCII):
        raise AddressError(f"{letter} files are not supported")
    file_number = _file_number(file_type, match["file"])

    if match["absolute"] is not None:
        return _absolute(file_type, file_number, int(match["absolute"]))

    element = int(match["element"])
    member, bit_text = match["member"], match["bit"]
    if file_type in (FileType.INPUT, FileType.OUTPUT):
        if member is not None and not member.isdigit():
            raise AddressError(f"I/O words are numbers ({letter}:slot.word/bit)")
        word = int(member) if member is not None else 0
        return SlcAddress(file_type, file_number, element, word, _numeric_bit(bit_text))
    if file_type in STRUCTURE_FILE_TYPES:
        return _structure(file_type, file_number, element, member, bit_text)
    if member is not None:
        what = (
            "floating-point elements are addressed in their entirety"
            if file_type is FileType.FLOAT
            else (f"{_name(file_type)} elements have no sub-elements")
        )
        raise AddressError(what)
    return SlcAddress(file_type, file_number, element, 0, _numeric_bit(bit_text))


def _name(file_type: FileType) -> str:
    return file_type.name.lower()


def _file_number(file_type: FileType, text: str | None) -> int:
    if file_type in _FIXED_FILE:
        fixed = _FIXED_FILE[file_type]
        if text is not None and int(text) != fixed:
            raise AddressError(f"the {_name(file_type)} file is always file {fixed}")
        return fixed
    if text is None:
        raise AddressError(f"a file number is required after {file_type.letter}")
    number = int(text)
    if number > 255:
        raise AddressError(f"file number {number} out of range (SLC 500 files are 0-255)")
    default = _DEFAULT_FILE_TYPE.get(number)
    if default is not None and default is not file_type:
        shown = f"{default.letter}{number}" if number > 2 else f"{default.letter}:"
        raise AddressError(f"file {number} is the {_name(default)} file ({shown})")
    if file_type not in _USER_TYPES:
        raise AddressError(f"{file_type.letter} files cannot be user files")
    return number


def _numeric_bit(text: str | None) -> int | None:
    if text is None:
        return None
    if not text.isdigit():
        raise AddressError("bit must be a number 0-15")
    bit = int(text)
    if bit > 15:
        raise AddressError("bit must be 0-15")
    return bit


def _absolute(file_type: FileType, file_number: int, bit_number: int) -> SlcAddress:
    if file_type not in _ABSOLUTE_BIT_TYPES:
        raise AddressError(f"{_name(file_type)} files cannot be addressed by absolute bit number")
    if bit_number > MAX_ABSOLUTE_BIT:
        raise AddressError(f"absolute bit {bit_number} out of range 0-{MAX_ABSOLUTE_BIT}")
    word, bit = divmod(bit_number, 16)
    if file_type in (FileType.INPUT, FileType.OUTPUT):
        raise AddressError(f"I/O bits need a slot: {file_type.letter}:slot/bit")
    if file_type is FileType.CONTROL:
        element, sub_element = divmod(word, 3)
        return SlcAddress(file_type, file_number, element, sub_element, bit)
    return SlcAddress(file_type, file_number, word, 0, bit)


def _structure(
    file_type: FileType, file_number: int, element: int, member: str | None, bit_text: str | None
) -> SlcAddress:
    words, bits = _WORDS[file_type], _BITS[file_type]
    noun = _NOUN[file_type]
    members = ", ".join([*words, *bits])
    if member is not None and member in bits:
        if bit_text is not None:
            raise AddressError(f".{member} is a bit; it takes no /{bit_text}")
        return SlcAddress(file_type, file_number, element, 0, bits[member])
    if member is not None and member not in words:
        raise AddressError(f"unknown sub-element; {noun} have {members}")
    sub_element = words[member] if member is not None else 0
    if bit_text is None:
        return SlcAddress(file_type, file_number, element, sub_element, None)
    if not bit_text.isdigit():
        if bit_text in bits:
            if member is None:
                return SlcAddress(file_type, file_number, element, 0, bits[bit_text])
            raise AddressError(f"{bit_text} is a bit of word 0; write /{bit_text} without .{member}")
        if bit_text in words:
            raise AddressError(f"/{bit_text} is a word; write .{bit_text}")
        raise AddressError(f"unknown bit; {noun} have {', '.join(bits)}")
    bit = _numeric_bit(bit_text)
    if member is None and file_type is not FileType.CONTROL:
        raise AddressError(f"{noun} have bits {', '.join(bits)} in word 0 (numbered bits: .PRE/n, .ACC/n)")
    return SlcAddress(file_type, file_number, element, sub_element, bit)
