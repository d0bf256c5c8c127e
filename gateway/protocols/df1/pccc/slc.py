"""SLC 500 PCCC commands: protected typed logical read / write / masked write, file info, mode, diagnostics.

Manuals: S4516-DF1 Program Development Manual §2.6.2 (protected typed logical read / write with
three address fields, CMD 0F FNC A2 / AA); SLC 500 PCCC command notes §4.0 (command set), §4.36
(protected typed logical write with mask, FNC AB, and the packet size tables), §6.0 (diagnostic
status processor type codes), §6.5 / §7.5 (read file info, FNC 94), §7.3 (a command to write bits),
§7.6 (set processor mode, FNC 80).

Three-address-field commands::

    FNC  SIZE  FILE#  TYPE  ELEMENT#  SUB#  [MASK_lo MASK_hi]  [DATA...]

FILE#, ELEMENT# and SUB# are one byte for 0-254, else ``FF lo hi``.  This module does no I/O.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import ClassVar, Final

from gateway.protocols.df1.address import FileType, SlcAddress
from gateway.protocols.df1.pccc.codec import LogicalBinaryAddress, PcccFormatError, Reader, check_range, encode_field
from gateway.protocols.df1.pccc.codes import Command, DiagnosticFunction, Function
from gateway.protocols.df1.pccc.limits import PLC5_TYPED_LOGICAL, SLC_MODULAR, SLC_SMALL, SizeLimits

__all__ = [
    "DiagnosticStatus",
    "DiagnosticStatusInfo",
    "FileInfo",
    "ProcessorFamily",
    "ProcessorMode",
    "ProtectedTypedLogicalMaskedWrite",
    "ProtectedTypedLogicalRead",
    "ProtectedTypedLogicalWrite",
    "ReadFileInfo",
    "SetProcessorMode",
    "SizeLimits",
    "slc_read_request",
    "slc_write_request",
]


class ProcessorMode(enum.IntEnum):
    """Mode byte of SLC set processor mode, CMD 0F FNC 80 (notes §7.6)."""

    PROGRAM = 0x01
    RUN = 0x06
    TEST_CONTINUOUS = 0x07
    TEST_SINGLE_SCAN = 0x08
    TEST_SINGLE_STEP = 0x09  # not on SLC 500 fixed and 5/01


# ------------------------------------------------------------------------------ size limits


class ProcessorFamily(enum.Enum):
    """Processor families and their packet size limits (notes §4.36 and the size tables)."""

    SLC500_FIXED = "SLC 500 fixed"
    SLC5_01 = "SLC 5/01"
    SLC5_02 = "SLC 5/02"
    SLC5_03 = "SLC 5/03"
    SLC5_04 = "SLC 5/04"
    SLC5_05 = "SLC 5/05"
    PLC5 = "PLC-5"

    @property
    def limits(self) -> SizeLimits:
        return _FAMILY_LIMITS[self]

    @property
    def max_read_bytes(self) -> int:
        return _FAMILY_LIMITS[self].max_read_bytes

    @property
    def max_write_bytes(self) -> int:
        return _FAMILY_LIMITS[self].max_write_bytes

    @classmethod
    def from_processor_type(cls, code: int) -> ProcessorFamily | None:
        """Family of a diagnostic status processor type byte (notes §6.0), or None if unknown."""
        return _PROCESSOR_TYPES.get(code)


_FAMILY_LIMITS: Final = {
    ProcessorFamily.SLC500_FIXED: SLC_SMALL,
    ProcessorFamily.SLC5_01: SLC_SMALL,
    ProcessorFamily.SLC5_02: SLC_SMALL,
    ProcessorFamily.SLC5_03: SLC_MODULAR,
    ProcessorFamily.SLC5_04: SLC_MODULAR,
    ProcessorFamily.SLC5_05: SLC_MODULAR,
    ProcessorFamily.PLC5: PLC5_TYPED_LOGICAL,  # typed logical commands; word range: PLC5_WORD_RANGE
}
_PROCESSOR_TYPES: Final = {
    0x1A: ProcessorFamily.SLC500_FIXED,
    0x18: ProcessorFamily.SLC5_01,
    0x25: ProcessorFamily.SLC5_02,
    0x49: ProcessorFamily.SLC5_03,
    0x5B: ProcessorFamily.SLC5_04,
}


# ------------------------------------------------------------------------------- requests


@dataclass(frozen=True, slots=True)
class ProtectedTypedLogicalRead:
    """SLC 500 protected typed logical read with three address fields (CMD 0F, FNC A2)."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_READ

    file_type: int
    file_number: int
    element: int
    sub_element: int
    size: int  # data bytes to read

    def __post_init__(self) -> None:
        check_range("file type", self.file_type, 0, 0xFF)
        check_range("byte size", self.size, 1, 0xFF)
        for name in ("file_number", "element", "sub_element"):
            check_range(name.replace("_", " "), getattr(self, name), 0, 0xFFFF)

    @property
    def expanded_fields(self) -> int:
        return sum(v >= 0xFF for v in (self.file_number, self.element, self.sub_element))

    def encode_params(self) -> bytes:
        return bytes((self.size,)) + _encode_three(self)

    @classmethod
    def decode_params(cls, reader: Reader) -> ProtectedTypedLogicalRead:
        size = reader.u8("byte size")
        file_number, file_type, element, sub_element = _read_three(reader)
        reader.end("the address")
        return cls(file_type, file_number, element, sub_element, size)


@dataclass(frozen=True, slots=True)
class ProtectedTypedLogicalWrite:
    """SLC 500 protected typed logical write with three address fields (CMD 0F, FNC AA)."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_WRITE

    file_type: int
    file_number: int
    element: int
    sub_element: int
    data: bytes

    def __post_init__(self) -> None:
        check_range("file type", self.file_type, 0, 0xFF)
        check_range("byte size", len(self.data), 1, 0xFF)
        for name in ("file_number", "element", "sub_element"):
            check_range(name.replace("_", " "), getattr(self, name), 0, 0xFFFF)

    @property
    def expanded_fields(self) -> int:
        return sum(v >= 0xFF for v in (self.file_number, self.element, self.sub_element))

    def encode_params(self) -> bytes:
        return bytes((len(self.data),)) + _encode_three(self) + self.data

    @classmethod
    def decode_params(cls, reader: Reader) -> ProtectedTypedLogicalWrite:
        size = reader.u8("byte size")
        file_number, file_type, element, sub_element = _read_three(reader)
        data = reader.take(size, "write data")
        reader.end("the write data")
        return cls(file_type, file_number, element, sub_element, data)


@dataclass(frozen=True, slots=True)
class ProtectedTypedLogicalMaskedWrite:
    """SLC 500 protected typed logical write with mask (CMD 0F, FNC AB; notes §4.36, §7.3).

    Bits set in ``mask`` are written; the one 16-bit mask applies to every word.
    """

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_MASKED_WRITE

    file_type: int
    file_number: int
    element: int
    sub_element: int
    mask: int
    data: bytes

    def __post_init__(self) -> None:
        check_range("file type", self.file_type, 0, 0xFF)
        check_range("byte size", len(self.data), 0, 0xFF)
        check_range("bit mask", self.mask, 0, 0xFFFF)
        for name in ("file_number", "element", "sub_element"):
            check_range(name.replace("_", " "), getattr(self, name), 0, 0xFFFF)

    @property
    def expanded_fields(self) -> int:
        return sum(v >= 0xFF for v in (self.file_number, self.element, self.sub_element))

    def encode_params(self) -> bytes:
        return bytes((len(self.data),)) + _encode_three(self) + self.mask.to_bytes(2, "little") + self.data

    @classmethod
    def decode_params(cls, reader: Reader) -> ProtectedTypedLogicalMaskedWrite:
        size = reader.u8("byte size")
        file_number, file_type, element, sub_element = _read_three(reader)
        mask = reader.u16("bit mask")
        data = reader.take(size, "write data")
        reader.end("the write data")
        return cls(file_type, file_number, element, sub_element, mask, data)


def _encode_three(
    request: ProtectedTypedLogicalRead | ProtectedTypedLogicalWrite | ProtectedTypedLogicalMaskedWrite,
) -> bytes:
    return (
        encode_field("file number", request.file_number)
        + bytes((request.file_type,))
        + encode_field("element", request.element)
        + encode_field("sub-element", request.sub_element)
    )


def _read_three(reader: Reader) -> tuple[int, int, int, int]:
    file_number = reader.field("file number")
    file_type = reader.u8("file type")
    element = reader.field("element")
    sub_element = reader.field("sub-element")
    return file_number, file_type, element, sub_element


@dataclass(frozen=True, slots=True)
class ReadFileInfo:
    """SLC 5/03, 5/04 read file info (CMD 0F, FNC 94; notes §7.5): ``94 06 80 <file>``."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.READ_FILE_INFO
    DATA_TABLE: ClassVar[int] = 0x80  # major file type: data table file

    file_number: int

    def __post_init__(self) -> None:
        check_range("file number", self.file_number, 0, 0xFFFF)

    def encode_params(self) -> bytes:
        return LogicalBinaryAddress(0x06, (self.DATA_TABLE, self.file_number)).encode()

    @classmethod
    def decode_params(cls, reader: Reader) -> ReadFileInfo:
        address = LogicalBinaryAddress.read(reader)
        reader.end("the address")
        if address.mask != 0x06 or address.levels[0] != cls.DATA_TABLE:
            raise reader.fail("PCCC: read file info needs mask 06, major type 80 (data table)")
        return cls(address.levels[1])


@dataclass(frozen=True, slots=True)
class SetProcessorMode:
    """SLC set processor mode (CMD 0F, FNC 80; notes §7.6); keyswitch must be in REM."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.SET_PROCESSOR_MODE

    mode: int

    def __post_init__(self) -> None:
        check_range("mode", self.mode, 0, 0xFF)

    def encode_params(self) -> bytes:
        return bytes((self.mode,))

    @classmethod
    def decode_params(cls, reader: Reader) -> SetProcessorMode:
        mode = reader.u8("mode")
        reader.end("the mode")
        return cls(mode)


@dataclass(frozen=True, slots=True)
class DiagnosticStatus:
    """Diagnostic status (CMD 06, FNC 03): identify the host processor."""

    CMD: ClassVar[int] = Command.DIAGNOSTIC
    FNC: ClassVar[int] = DiagnosticFunction.DIAGNOSTIC_STATUS

    def encode_params(self) -> bytes:
        return b""

    @classmethod
    def decode_params(cls, reader: Reader) -> DiagnosticStatus:
        reader.end("the function code")
        return cls()


def slc_read_request(address: SlcAddress, size: int | None = None) -> ProtectedTypedLogicalRead:
    """Protected typed logical read of ``address``; ``size`` bytes, default the address's own size."""
    return ProtectedTypedLogicalRead(
        address.file_type,
        address.file_number,
        address.element,
        address.sub_element,
        address.byte_count if size is None else size,
    )


def slc_write_request(address: SlcAddress, data: bytes) -> ProtectedTypedLogicalWrite:
    """Protected typed logical write of ``data`` starting at ``address``."""
    return ProtectedTypedLogicalWrite(
        address.file_type, address.file_number, address.element, address.sub_element, data
    )


# ---------------------------------------------------------------------------- reply data


@dataclass(frozen=True, slots=True)
class FileInfo:
    """Read file info reply data (notes §7.5): 4-byte size, 2-byte element count, reserved, type."""

    size_bytes: int
    element_count: int
    file_type: int

    @property
    def known_type(self) -> FileType | None:
        try:
            return FileType(self.file_type)
        except ValueError:
            return None

    def encode(self) -> bytes:
        return struct.pack("<IHBB", self.size_bytes, self.element_count, 0, self.file_type)

    @classmethod
    def decode(cls, data: bytes) -> FileInfo:
        if len(data) < 8:
            raise PcccFormatError(f"PCCC: read file info reply has {len(data)} bytes, expected 8")
        size, count, _reserved, file_type = struct.unpack_from("<IHBB", data)
        return cls(size, count, file_type)


@dataclass(frozen=True, slots=True)
class DiagnosticStatusInfo:
    """Diagnostic status reply data (layout of 1770-6.5.16 for SLC processors).

    ``mode_status, type_extender, interface_type, processor_type, series_revision, catalog...``;
    processor type codes and the series/revision bits are from the notes §6.0.
    """

    raw: bytes

    def _byte(self, index: int) -> int | None:
        return self.raw[index] if len(self.raw) > index else None

    @property
    def mode_status(self) -> int | None:
        return self._byte(0)

    @property
    def processor_type(self) -> int | None:
        return self._byte(3)

    @property
    def family(self) -> ProcessorFamily | None:
        code = self.processor_type
        return None if code is None else ProcessorFamily.from_processor_type(code)

    @property
    def series(self) -> str | None:
        value = self._byte(4)
        return None if value is None else chr(ord("A") + (value >> 5))

    @property
    def frn(self) -> int | None:
        value = self._byte(4)
        return None if value is None else (value & 0x1F) + 1

    @property
    def catalog(self) -> str | None:
        if len(self.raw) <= 5:
            return None
        return self.raw[5:16].decode("ascii", "replace").strip(" \x00")

    @classmethod
    def build(
        cls, *, processor_type: int, series: str = "A", frn: int = 1, catalog: str = "", mode_status: int = 0
    ) -> DiagnosticStatusInfo:
        """Reply data a simulated controller can send."""
        series_revision = (ord(series.upper()) - ord("A")) << 5 | (frn - 1) & 0x1F
        name = catalog.encode("ascii")[:11].ljust(11, b" ")
        return cls(bytes((mode_status, 0xEE, 0x00, processor_type, series_revision & 0xFF)) + name)
