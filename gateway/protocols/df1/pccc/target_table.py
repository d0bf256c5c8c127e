"""The data table of the DF1 target: typed data files N, B, F and L that PLC MSG instructions read and write.

When the gateway answers the MSG instructions a PLC sends it ("DF1 target mode",
:mod:`.target`), these files are what the PLC's messages address.  Each file has a number, a
type and an element count; each element holds a value or "never written" (None) and the time of
its last write (the ``now`` the caller passes; no clock here).

File types, their element size and their codes on the wire:

====  ====================  =====  =============================  ========================
kind  element               words  SLC file type (0F A1/A2/A9/    typed read / write type
                                   AA/AB)                         ID (0F 67 / 68)
====  ====================  =====  =============================  ========================
N     16-bit signed int     1      89 (1770-6.5.16 p. 7-17)       4 integer (notes §5.0)
B     16 bits               1      85 (p. 7-17)                   1 bit (notes §5.0)
F     IEEE 754 single       2      8A (p. 7-17)                   8 float (notes §5.0)
L     32-bit signed int     2      91 (1756-PM020F p. 90, "Long   none: the notes' type table
                                   - MicroLogix only")            has no 32-bit integer
====  ====================  =====  =============================  ========================

Byte image: every element is little-endian, and a two-word element sends its low-order word
first (the layout of PCCC replies from the SLC 5/03-5/05, as ``gateway.kinds.df1.sim.slc500_processor``
documents).  The commands address a file as that flat byte image; :meth:`TableFile.read_bytes` and
:meth:`TableFile.write_bytes` are the only ways in, and a write changes every element it touches
or, when it does not fit, none.  An element stores its raw bits (16 or 32), so an F element gives
back exactly the bits written, NaN payloads included.

A never-written element reads as zeros in the byte image; :meth:`TableFile.read_bytes` says which
elements those were, and :mod:`.target` decides what a read of one answers.  A write of part of an
element (one word of an F or L, one byte of an N, bits under a mask) completes it with zeros where
it was never written.

No I/O.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Iterable, Iterator
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc.plc5 import DataType

__all__ = ["LONG_FILE_TYPE", "DataTable", "ElementRef", "TableFile", "TableFileKind"]

#: SLC file type code of a long integer (L) file: 1756-PM020F p. 90 ("91hex (Long - MicroLogix only)").
LONG_FILE_TYPE: Final = 0x91
#: Elements per file: the largest element number a logical address can carry is 0xFFFF.
_MAX_ELEMENTS: Final = 0x10000


class TableFileKind(enum.Enum):
    """N, B, F, L: letter, words per element, SLC file type code, typed ID (module docstring table)."""

    INTEGER = ("N", 1, FileType.INTEGER, DataType.INTEGER, "<h")
    BIT = ("B", 1, FileType.BIT, DataType.BIT, "<H")
    FLOAT = ("F", 2, FileType.FLOAT, DataType.FLOAT, "<f")
    LONG = ("L", 2, LONG_FILE_TYPE, None, "<i")

    def __init__(self, letter: str, words: int, file_type: int, type_id: int | None, layout: str) -> None:
        self.letter = letter
        self.words = words
        self.file_type = file_type
        #: Type ID of the typed read / write type/data parameter; None: typed commands refuse the file.
        self.type_id = type_id
        self.layout = layout

    @property
    def element_bytes(self) -> int:
        return 2 * self.words

    @classmethod
    def from_letter(cls, letter: str) -> TableFileKind:
        for kind in cls:
            if kind.letter == letter.upper():
                return kind
        raise ValueError(f"data table file type {letter!r}: expected N, B, F or L")

    def to_raw(self, value: int | float) -> int:
        """The element's bits for ``value`` (ValueError when it does not fit)."""
        try:
            packed = struct.pack(self.layout, value)
        except struct.error as exc:
            raise ValueError(f"{value!r} does not fit an {self.letter} element: {exc}") from None
        return int.from_bytes(packed, "little")

    def from_raw(self, raw: int) -> int | float:
        value: int | float = struct.unpack(self.layout, raw.to_bytes(self.element_bytes, "little"))[0]
        return value


@frozen
class ElementRef:
    """One element of one file, e.g. ``ElementRef(7, 3)`` is N7:3 when file 7 is an N file."""

    file: int
    element: int


class TableFile:
    """One data file: ``count`` elements of one :class:`TableFileKind`, each raw bits or None."""

    def __init__(self, kind: TableFileKind, number: int, count: int) -> None:
        if not 0 <= number <= 0xFFFF:
            raise ValueError(f"file number {number}: 0-65535")
        if not 0 < count <= _MAX_ELEMENTS:
            raise ValueError(f"{kind.letter}{number}: element count {count} outside 1-{_MAX_ELEMENTS}")
        self.kind = kind
        self.number = number
        self.count = count
        self._raw: list[int | None] = [None] * count
        self._written_at: list[float | None] = [None] * count

    @property
    def name(self) -> str:
        return f"{self.kind.letter}{self.number}"

    @property
    def size_bytes(self) -> int:
        return self.count * self.kind.element_bytes

    def value(self, element: int) -> int | float | None:
        """The element's value, None if it was never written (IndexError outside the file)."""
        raw = self._raw[self._index(element)]
        return None if raw is None else self.kind.from_raw(raw)

    def written_at(self, element: int) -> float | None:
        """The ``now`` of the element's last write, None if it was never written."""
        return self._written_at[self._index(element)]

    def set_value(self, element: int, value: int | float, now: float) -> None:
        """Write one element from the gateway's side (ValueError when the value does not fit)."""
        raw = self.kind.to_raw(value)
        index = self._index(element)
        self._raw[index] = raw
        self._written_at[index] = now

    def forget(self, element: int) -> None:
        """Make the element never-written again (a write whose commit failed is taken back)."""
        index = self._index(element)
        self._raw[index] = None
        self._written_at[index] = None

    def read_bytes(self, offset: int, size: int) -> tuple[bytes, tuple[int, ...]]:
        """``size`` bytes of the byte image from ``offset``, and the never-written elements among them."""
        first, last = self._span(offset, size)
        element_bytes = self.kind.element_bytes
        image = bytearray()
        unwritten = []
        for element in range(first, last + 1):
            raw = self._raw[element]
            if raw is None:
                unwritten.append(element)
            image += (raw or 0).to_bytes(element_bytes, "little")
        start = offset - first * element_bytes
        return bytes(image[start : start + size]), tuple(unwritten)

    def write_bytes(self, offset: int, data: bytes, now: float, mask: bytes = b"") -> tuple[int, ...]:
        """Write ``data`` into the byte image at ``offset``; the elements written.

        With ``mask`` (two bytes, the 16-bit mask low byte first) only the bits set in it change,
        ``mask[i % 2]`` over data byte ``i`` (notes §7.3: one mask for every word, its low byte for an
        odd last byte).  Every element is checked to fit before any changes (IndexError otherwise).
        """
        first, last = self._span(offset, len(data))
        element_bytes = self.kind.element_bytes
        image = bytearray()
        for element in range(first, last + 1):
            image += (self._raw[element] or 0).to_bytes(element_bytes, "little")
        start = offset - first * element_bytes
        for i, byte in enumerate(data):
            bits = mask[i % 2] if mask else 0xFF
            image[start + i] = (image[start + i] & ~bits & 0xFF) | (byte & bits)
        elements = tuple(range(first, last + 1))
        for k, element in enumerate(elements):
            self._raw[element] = int.from_bytes(image[k * element_bytes : (k + 1) * element_bytes], "little")
            self._written_at[element] = now
        return elements

    def fits(self, offset: int, size: int) -> bool:
        """Whether ``size`` bytes from ``offset`` lie inside the file."""
        return 0 <= offset and offset + size <= self.size_bytes

    def _span(self, offset: int, size: int) -> tuple[int, int]:
        if size <= 0 or not self.fits(offset, size):
            raise IndexError(f"{self.name}: bytes {offset}-{offset + size - 1} outside 0-{self.size_bytes - 1}")
        element_bytes = self.kind.element_bytes
        return offset // element_bytes, (offset + size - 1) // element_bytes

    def _index(self, element: int) -> int:
        if not 0 <= element < self.count:
            raise IndexError(f"{self.name}: element {element} outside 0-{self.count - 1}")
        return element


class DataTable:
    """The target's data files, by number (one file per number, as in a controller)."""

    def __init__(self, files: Iterable[TableFile] = ()) -> None:
        self._files: dict[int, TableFile] = {}
        for table_file in files:
            self._add(table_file)

    @classmethod
    def of(cls, *specs: str) -> DataTable:
        """Files from specs like ``"N7:100"`` (file N7, 100 elements), ``"F8:10"``, ``"L9:4"``."""
        files = []
        for spec in specs:
            name, _, count = spec.partition(":")
            if len(name) < 2 or not name[1:].isdigit() or not count.isdigit():
                raise ValueError(f"data table file {spec!r}: expected a spec like N7:100")
            files.append(TableFile(TableFileKind.from_letter(name[0]), int(name[1:]), int(count)))
        return cls(files)

    def _add(self, table_file: TableFile) -> None:
        if table_file.number in self._files:
            raise ValueError(f"file number {table_file.number} is defined twice")
        self._files[table_file.number] = table_file

    def add(self, kind: TableFileKind, number: int, count: int) -> TableFile:
        table_file = TableFile(kind, number, count)
        self._add(table_file)
        return table_file

    def get(self, number: int) -> TableFile | None:
        return self._files.get(number)

    def __getitem__(self, number: int) -> TableFile:
        return self._files[number]

    def __iter__(self) -> Iterator[TableFile]:
        return iter(self._files.values())
