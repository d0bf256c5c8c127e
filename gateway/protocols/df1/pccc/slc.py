"""SLC 500 PCCC commands: protected typed logical read / write / masked write, file info, mode, diagnostics.

Manuals: S4516-DF1 Program Development Manual §2.6.2 (protected typed logical read / write with
three address fields, CMD 0F FNC A2 / AA); SLC 500 PCCC command notes §4.0 (command set), §4.36
(protected typed logical write with mask, FNC AB, and the packet size tables), §6.0 (diagnostic
status processor type codes), §6.5 / §7.5 (read file info, FNC 94), §7.3 (a command to write bits),
§7.6 (set processor mode, FNC 80); 1770-6.5.16 pp. 7-17 / 7-18 (FNC A2 / AA) and 1756-PM020F
pp. 91-92 (the two-address-field forms, FNC A1 / A9).

Typed logical commands::

    FNC  SIZE  FILE#  TYPE  ELEMENT#  [SUB#]  [MASK_lo MASK_hi]  [DATA...]

FILE#, ELEMENT# and SUB# are one byte for 0-254, else ``FF lo hi``.  Each request class lists
its fields once in ``PARAMS`` (:mod:`.params`).  This module does no I/O.
"""

from __future__ import annotations

import enum
import struct
from typing import Any, ClassVar, Final

from gateway.frozen import frozen
from gateway.protocols.df1.address import FileType, SlcAddress
from gateway.protocols.df1.pccc.codec import LogicalBinaryAddress, PcccFormatError, Reader, check_range
from gateway.protocols.df1.pccc.codes import CmdByte, DiagnosticFunction, Function
from gateway.protocols.df1.pccc.limits import PLC5_TYPED_LOGICAL, SLC_MODULAR, SLC_SMALL, SizeLimits
from gateway.protocols.df1.pccc.params import (
    AddressField,
    Byte,
    Bytes,
    Decoded,
    Parameters,
    SizeOf,
    Wire,
    Word,
)

__all__ = [
    "THREE_ADDRESS_FIELDS", "TWO_ADDRESS_FIELDS", "DiagnosticStatus", "DiagnosticStatusInfo", "Echo", "FileInfo",
    "ProcessorFamily", "ProcessorMode", "ProtectedTypedLogicalMaskedWrite", "ProtectedTypedLogicalRead",
    "ProtectedTypedLogicalTwoFieldRead", "ProtectedTypedLogicalTwoFieldWrite", "ProtectedTypedLogicalWrite",
    "ReadFileInfo", "SetProcessorMode", "SizeLimits", "slc_read_request", "slc_write_request",
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

#: FILE# TYPE ELEMENT# of the typed logical commands with two address fields (0F A1 / A9).
TWO_ADDRESS_FIELDS: Final[tuple[Wire, ...]] = (
    AddressField("file_number", "file number"),
    Byte("file_type", "file type"),
    AddressField("element", "element"),
)
#: FILE# TYPE ELEMENT# SUB# of the typed logical commands with three address fields (0F A2 / AA / AB).
THREE_ADDRESS_FIELDS: Final[tuple[Wire, ...]] = (*TWO_ADDRESS_FIELDS, AddressField("sub_element", "sub element"))
#: SIZE of a read: the data bytes asked for.
_READ_SIZE: Final = Byte("size", "byte size", 1)
#: SIZE of a write (the length of its data, sent ahead of the address) and the data at the end.
_WRITE_SIZE: Final = SizeOf("data", "byte size", 1)
_WRITE_DATA: Final = Bytes("data", "write data")


@frozen
class _TwoFieldAddress(Parameters):
    """The address of the typed logical commands: file type, file number, element."""

    file_type: int
    file_number: int
    element: int


@frozen
class _ThreeFieldAddress(_TwoFieldAddress):
    """The address with a sub-element (the word inside a timer, counter or control structure)."""

    sub_element: int


@frozen
class ProtectedTypedLogicalRead(_ThreeFieldAddress):
    """SLC 500 protected typed logical read with three address fields (CMD 0F, FNC A2; 1770-6.5.16 p. 7-17)."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_READ
    PARAMS: ClassVar[tuple[Wire, ...]] = (_READ_SIZE, *THREE_ADDRESS_FIELDS)

    size: int  # data bytes to read


@frozen
class ProtectedTypedLogicalWrite(_ThreeFieldAddress):
    """SLC 500 protected typed logical write with three address fields (CMD 0F, FNC AA; 1770-6.5.16 p. 7-18)."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_WRITE
    PARAMS: ClassVar[tuple[Wire, ...]] = (_WRITE_SIZE, *THREE_ADDRESS_FIELDS, _WRITE_DATA)

    data: bytes


@frozen
class ProtectedTypedLogicalMaskedWrite(_ThreeFieldAddress):
    """SLC 500 protected typed logical write with mask (CMD 0F, FNC AB; notes §4.36, §7.3).

    Bits set in ``mask`` are written; the one 16-bit mask applies to every word.  The byte size
    may be 0 (notes §4.36).
    """

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_MASKED_WRITE
    PARAMS: ClassVar[tuple[Wire, ...]] = (
        SizeOf("data", "byte size"), *THREE_ADDRESS_FIELDS, Word("mask", "bit mask"), _WRITE_DATA
    )

    mask: int
    data: bytes


@frozen
class ProtectedTypedLogicalTwoFieldRead(_TwoFieldAddress):
    """Protected typed logical read with two address fields (CMD 0F, FNC A1): no sub-element.

    ``SIZE FILE# TYPE ELEMENT#`` (1756-PM020F p. 91, "SLC Protected Typed Logical Read with 2
    Address Fields"; 1770-6.5.16 ch. 7 beside the three-field form of p. 7-17).
    """

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_READ_TWO_FIELDS
    PARAMS: ClassVar[tuple[Wire, ...]] = (_READ_SIZE, *TWO_ADDRESS_FIELDS)

    size: int  # data bytes to read


@frozen
class ProtectedTypedLogicalTwoFieldWrite(_TwoFieldAddress):
    """Protected typed logical write with two address fields (CMD 0F, FNC A9; 1756-PM020F p. 92)."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.PROTECTED_TYPED_LOGICAL_WRITE_TWO_FIELDS
    PARAMS: ClassVar[tuple[Wire, ...]] = (_WRITE_SIZE, *TWO_ADDRESS_FIELDS, _WRITE_DATA)

    data: bytes


@frozen
class _DataTableFile:
    """Read file info's address (notes §7.5): mask 06, major type 80 (data table), the file number."""

    attr: str
    DATA_TABLE: ClassVar[int] = 0x80

    def encode(self, request: Any) -> bytes:
        return LogicalBinaryAddress(0x06, (self.DATA_TABLE, getattr(request, self.attr))).encode()

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        address = LogicalBinaryAddress.read(reader)
        if address.mask != 0x06 or address.levels[0] != self.DATA_TABLE:
            raise reader.fail("PCCC: read file info needs mask 06, major type 80 (data table)")
        decoded.values[self.attr] = address.levels[1]

    def check(self, request: Any) -> None:
        check_range("file number", getattr(request, self.attr), 0, 0xFFFF)


@frozen
class ReadFileInfo(Parameters):
    """SLC 5/03, 5/04 read file info (CMD 0F, FNC 94; notes §7.5): ``94 06 80 <file>``."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.READ_FILE_INFO
    PARAMS: ClassVar[tuple[Wire, ...]] = (_DataTableFile("file_number"),)

    file_number: int


@frozen
class SetProcessorMode(Parameters):
    """SLC set processor mode (CMD 0F, FNC 80; notes §7.6); keyswitch must be in REM."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.SET_PROCESSOR_MODE
    PARAMS: ClassVar[tuple[Wire, ...]] = (Byte("mode", "mode"),)

    mode: int


@frozen
class DiagnosticStatus(Parameters):
    """Diagnostic status (CMD 06, FNC 03): identify the host processor."""

    CMD: ClassVar[int] = CmdByte.DIAGNOSTIC
    FNC: ClassVar[int] = DiagnosticFunction.DIAGNOSTIC_STATUS
    PARAMS: ClassVar[tuple[Wire, ...]] = ()


@frozen
class Echo(Parameters):
    """Echo, also "diagnostic loop" (CMD 06, FNC 00): the node sends ``data`` back unchanged.

    Up to 243 data bytes (1770-KF2 manual p. 5-10, "Diagnostic Loop"; notes §4.0 command table:
    "echo data sent, debug", PLC-5 and SLC).
    """

    CMD: ClassVar[int] = CmdByte.DIAGNOSTIC
    FNC: ClassVar[int] = DiagnosticFunction.ECHO
    MAX_BYTES: ClassVar[int] = 243
    PARAMS: ClassVar[tuple[Wire, ...]] = (Bytes("data", "echo data", MAX_BYTES),)

    data: bytes


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


@frozen
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


@frozen
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
        name = catalog.encode("ascii")[:11].ljust(11)  # bytes.ljust pads with spaces
        return cls(bytes((mode_status, 0xEE, 0x00, processor_type, series_revision & 0xFF)) + name)
