"""The data table of the simulated SLC 5/04 (``gateway.kinds.df1.sim.slc500``): files as flat byte images."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Final

from gateway.protocols.df1.address import AddressError, FileType, SlcAddress, element_words
from gateway.protocols.df1.pccc import DataType

__all__ = ["FILE_NAME_RE", "SLOTS", "TYPED_ID", "WORDS_PER_SLOT", "DataFile", "data_files"]

#: I/O images: 4 slots of 8 words.
SLOTS: Final = 4
WORDS_PER_SLOT: Final = 8


@dataclass
class DataFile:
    """One data file: ``elements`` elements of ``element_words`` words, as a flat byte image."""

    file_type: FileType
    number: int
    elements: int
    element_words: int
    data: bytearray = field(init=False)

    def __post_init__(self) -> None:
        self.data = bytearray(self.elements * self.element_words * 2)

    @property
    def name(self) -> str:
        return f"{self.file_type.letter}{self.number}"

    @property
    def element_bytes(self) -> int:
        return self.element_words * 2

    @property
    def is_io(self) -> bool:
        return self.file_type in (FileType.INPUT, FileType.OUTPUT)

    @property
    def typed_element_bytes(self) -> int:
        """Element size for typed read / write: I/O images are plain words there."""
        return 2 if self.is_io else self.element_bytes

    def word(self, offset: int) -> int:
        return int.from_bytes(self.data[offset : offset + 2], "little")

    def set_word(self, offset: int, value: int) -> None:
        self.data[offset : offset + 2] = (value & 0xFFFF).to_bytes(2, "little")

    def address_text(self, element: int, sub_element: int) -> str:
        try:
            return str(SlcAddress(self.file_type, self.number, element, sub_element))
        except AddressError:
            return f"{self.name}:{element}.{sub_element}"


#: Type ID of typed read / write per file type (notes §5.0 "Data Type ID for SLC").
TYPED_ID: Final = {
    FileType.OUTPUT: DataType.INTEGER,
    FileType.INPUT: DataType.INTEGER,
    FileType.STATUS: DataType.INTEGER,
    FileType.BIT: DataType.BIT,
    FileType.TIMER: DataType.TIMER,
    FileType.COUNTER: DataType.COUNTER,
    FileType.CONTROL: DataType.CONTROL,
    FileType.INTEGER: DataType.INTEGER,
    FileType.FLOAT: DataType.FLOAT,
}

FILE_NAME_RE: Final = re.compile(r"(?P<letter>[OISBTCRNF])(?P<number>\d*)")


def data_files() -> dict[int, DataFile]:
    sizes = ((FileType.STATUS, 2, 164), (FileType.BIT, 3, 64), (FileType.TIMER, 4, 20), (FileType.COUNTER, 5, 20),
             (FileType.CONTROL, 6, 10), (FileType.INTEGER, 7, 256), (FileType.FLOAT, 8, 64),
             (FileType.INTEGER, 10, 100), (FileType.BIT, 12, 16), (FileType.FLOAT, 13, 10))
    files = [
        DataFile(FileType.OUTPUT, 0, SLOTS, WORDS_PER_SLOT),
        DataFile(FileType.INPUT, 1, SLOTS, WORDS_PER_SLOT),
        *(DataFile(file_type, number, elements, element_words(file_type)) for file_type, number, elements in sizes),
    ]
    return {f.number: f for f in files}
