"""PCCC application packets for SLC 500 and PLC-5: builders, parsers, status codes, size limits.

Manuals: "S4516-DF1 Program Development Manual" §2.2, §2.6 and Appendix A (after A-B 1770-6.5.16),
"SLC 500 PCCC command notes" (PLC-5 and SLC-5/04 communication driver comparison) §4-§7, §4.36.

Every packet starts with the same header; numbers are little-endian::

    command:  DST SRC CMD STS TNS_lo TNS_hi [FNC parameters...]
    reply:    DST SRC CMD|0x40 STS TNS_lo TNS_hi [EXT_STS [owner]] [data...]

``EXT STS`` follows only when ``STS == 0xF0``; for EXT STS 0x1A / 0x1B one more byte names
the node that owns the file / program.

SLC 500 three-address-field commands (CMD 0F, FNC A2 / AA / AB)::

    FNC  SIZE  FILE#  TYPE  ELEMENT#  SUB#  [MASK_lo MASK_hi]  [DATA...]

FILE#, ELEMENT# and SUB# are one byte for 0-254, else ``FF lo hi``.

PLC-5 word range and typed commands (CMD 0F, FNC 01 / 00 / 68 / 67)::

    FNC  OFFSET_lo OFFSET_hi  TOTAL_lo TOTAL_hi  ADDRESS  (SIZE | [type/data] DATA)

with a logical binary ADDRESS: a mask byte (bit n set = level n present) and one
1- or 3-byte field per level (section, file, element, sub-element).

This module does no I/O.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field
from typing import ClassVar, Final

from gateway.errors import ControllerRefused, InvalidRequest, ProtocolError
from gateway.protocols.df1.address import FileType, SlcAddress

__all__ = [
    "REPLY_BIT",
    "Command",
    "DataType",
    "DiagnosticFunction",
    "DiagnosticStatus",
    "DiagnosticStatusInfo",
    "FileInfo",
    "Function",
    "LogicalBinaryAddress",
    "PcccCommand",
    "PcccError",
    "PcccFormatError",
    "PcccHeader",
    "PcccReply",
    "ProcessorFamily",
    "ProcessorMode",
    "ProtectedTypedLogicalMaskedWrite",
    "ProtectedTypedLogicalRead",
    "ProtectedTypedLogicalWrite",
    "ReadFileInfo",
    "Request",
    "SetProcessorMode",
    "SizeLimits",
    "Sts",
    "TnsAllocator",
    "TypeData",
    "TypedData",
    "TypedRead",
    "TypedWrite",
    "WordRangeRead",
    "WordRangeWrite",
    "decode_command",
    "decode_reply",
    "decode_type_data",
    "decode_typed_data",
    "describe_status",
    "encode_command",
    "encode_reply",
    "encode_type_data",
    "encode_typed_data",
    "reply_matches",
    "slc_read_request",
    "slc_write_request",
]

#: CMD bit 6: 0 in a command, 1 in a reply (S4516-DF1 manual, Appendix B block 1).
REPLY_BIT: Final = 0x40
_HEADER_SIZE: Final = 6


class Command(enum.IntEnum):
    """CMD byte (notes §4.0 command table)."""

    DIAGNOSTIC = 0x06
    EXTENDED = 0x0F  # PLC-5 / SLC 500 command set, FNC selects the function


class Function(enum.IntEnum):
    """FNC byte of CMD 0x0F (notes §4.0 command table; S4516-DF1 manual §2.6)."""

    WORD_RANGE_WRITE = 0x00
    WORD_RANGE_READ = 0x01
    TYPED_WRITE = 0x67
    TYPED_READ = 0x68
    SET_PROCESSOR_MODE = 0x80
    READ_FILE_INFO = 0x94
    PROTECTED_TYPED_LOGICAL_READ = 0xA2
    PROTECTED_TYPED_LOGICAL_WRITE = 0xAA
    PROTECTED_TYPED_LOGICAL_MASKED_WRITE = 0xAB


class DiagnosticFunction(enum.IntEnum):
    """FNC byte of CMD 0x06 (notes §4.0 command table)."""

    DIAGNOSTIC_STATUS = 0x03


class ProcessorMode(enum.IntEnum):
    """Mode byte of SLC set processor mode, CMD 0F FNC 80 (notes §7.6)."""

    PROGRAM = 0x01
    RUN = 0x06
    TEST_CONTINUOUS = 0x07
    TEST_SINGLE_SCAN = 0x08
    TEST_SINGLE_STEP = 0x09  # not on SLC 500 fixed and 5/01


class DataType(enum.IntEnum):
    """Type IDs of the typed read / write type/data parameter (notes §5.0, 1770-6.5.16 App. E)."""

    BIT = 0x01
    BIT_STRING = 0x02
    BYTE_STRING = 0x03  # ASCII
    INTEGER = 0x04
    TIMER = 0x05
    COUNTER = 0x06
    CONTROL = 0x07
    FLOAT = 0x08
    ARRAY = 0x09
    BCD = 0x10
    PID = 0x15
    MESSAGE = 0x16
    SFC_STATUS = 0x1D
    STRING = 0x1E
    BLOCK_TRANSFER = 0x20


class Sts(enum.IntEnum):
    """STS byte (S4516-DF1 manual Appendix A): low nibble local, high nibble remote errors."""

    SUCCESS = 0x00
    CANNOT_GUARANTEE_DELIVERY = 0x02
    DUPLICATE_TOKEN_HOLDER = 0x03
    LOCAL_PORT_DISCONNECTED = 0x04
    APPLICATION_TIMEOUT = 0x05
    DUPLICATE_NODE = 0x06
    STATION_OFFLINE = 0x07
    HARDWARE_FAULT = 0x08
    ILLEGAL_COMMAND_OR_FORMAT = 0x10
    HOST_PROBLEM = 0x20
    REMOTE_HOST_MISSING = 0x30
    HOST_HARDWARE_FAULT = 0x40
    ADDRESSING_PROBLEM = 0x50
    COMMAND_PROTECTION = 0x60
    PROGRAM_MODE = 0x70
    COMPATIBILITY_FILE_MISSING = 0x80
    CANNOT_BUFFER_COMMAND = 0x90
    DOWNLOAD_PROBLEM = 0xB0
    ACTIVE_IPBS = 0xC0
    EXTENDED = 0xF0  # the error code is in the EXT STS byte


_LOCAL_STS: Final = {
    0x01: "Not used",
    0x02: "Cannot guarantee delivery: link layer",
    0x03: "Duplicate token holder detected",
    0x04: "Local port is disconnected",
    0x05: "Application layer timed out waiting for a response",
    0x06: "Duplicate node detected",
    0x07: "Station is off-line",
    0x08: "Hardware fault",
}
_REMOTE_STS: Final = {
    0x10: "Illegal command or format",
    0x20: "Host has a problem and will not communicate",
    0x30: "Remote node host is missing, disconnected or shut down",
    0x40: "Host could not complete function due to hardware fault",
    0x50: "Addressing problem or memory protect rungs",
    0x60: "Function disallowed due to command protection selection",
    0x70: "Processor is in program mode",
    0x80: "Compatibility mode file missing or communication zone problem",
    0x90: "Remote node cannot buffer command",
    0xA0: "Not used",
    0xB0: "Remote node problem due to download",
    0xC0: "Cannot execute command due to active IPBs",
    0xD0: "Not used",
    0xE0: "Not used",
    0xF0: "There is an error code in the EXT STS byte",
}
#: EXT STS for CMD 0x0F (Appendix A).
_EXT_STS_0F: Final = {
    0x01: "A field has an illegal value",
    0x02: "Less levels specified in address than minimum for any address",
    0x03: "More levels specified in address than system supports",
    0x04: "Symbol not found",
    0x05: "Symbol is of improper format",
    0x06: "Address doesn't point to something usable",
    0x07: "File is wrong size",
    0x08: "Cannot complete request, situation has changed since the start of the command",
    0x09: "Data or file is too large",
    0x0A: "Transaction size plus word address is too large",
    0x0B: "Access denied, improper privilege",
    0x0C: "Condition cannot be generated - resource is not available",
    0x0D: "Condition already exists - resource is already available",
    0x0E: "Command cannot be executed",
    0x0F: "Histogram overflow",
    0x10: "No access",
    0x11: "Illegal data type",
    0x12: "Invalid parameter or invalid data",
    0x13: "Address reference exists to deleted area",
    0x14: "Command execution failure for unknown reason; possible PLC-3 histogram overflow",
    0x15: "Data conversion error",
    0x16: "Scanner not able to communicate with 1771 rack adapter",
    0x17: "Adapter cannot communicate with module",
    0x18: "1771 module response was not valid",
    0x19: "Duplicated label",
    0x1A: "File is open; another node owns it",
    0x1B: "Another node is the program owner",
}
#: EXT STS for CMD 0x0E (Appendix A).
_EXT_STS_0E: Final = {
    0x00: "Multi-defined processors on ring",
    0x01: "Processor is already allocated",
    0x02: "Processor must be allocated for this command",
    0x03: "Extended function in progress",
    0x04: "Function not available in this processor command set",
    0x05: "Function not available in this processor mode",
    0x06: "Processor number in program and hardware do not match",
    0x07: "Invalid address",
    0x08: "Memory protection access violation",
    0x09: "Invalid parameter",
    0x0A: "Search unsuccessful",
    0x0B: "Program needs to be stored - RAM and PROM do not match",
    0x0C: "External EEPROM is defective, cannot transfer contents correctly",
    0x0D: "Invalid user program",
    0x0F: "Device resource unavailable",
    0x20: "Processor already allocated by requesting node",
    0x21: "Processor already allocated by another remote node",
    0x22: "Processor not allocated",
    0x23: "Data length invalid",
    0x24: "Data size too large",
    0x25: "Data size too large",
    0x26: "Data size too small",
    0x27: "At least one of the addresses points to a read-only area",
    0x28: "Address past end of memory",
    0x29: "Memory protected, addresses to program area illegal",
    0x2A: "Memory protected, address to processor status area illegal",
    0x2B: "Memory protected, address to protected timer or counter",
    0x2C: "Processor not in program mode, address to program area",
    0x2D: "Address past 'end of used memory'",
    0x2E: "'Program valid' bit not set in PLC-4 program ID byte",
    0x2F: "Invalid PLC-4 select value",
    0x7C: "PLC-4 ring disconnected",
    0x7D: "No PLC-4 response",
    0x7F: "Invalid PLC-4 selected byte",
}
#: Command-specific wording from the SLC notes (§7.5 read file info, §7.6 set processor mode).
_SPECIFIC: Final[dict[tuple[int, int, int | None], str]] = {
    (Function.READ_FILE_INFO, 0x50, None): "Bad address; file doesn't exist",
    (Function.READ_FILE_INFO, 0xF0, 0x1B): "File protection error",
    (Function.SET_PROCESSOR_MODE, 0xF0, 0x0B): "Access denied: channel read protect",
    (Function.SET_PROCESSOR_MODE, 0xF0, 0x0C): "Condition cannot be generated (keyswitch not in REM)",
}
#: EXT STS values followed by the owner's node address.
_OWNER_EXT_STS: Final = frozenset({0x1A, 0x1B})


def describe_status(
    sts: int, ext_sts: int | None = None, *, cmd: int = Command.EXTENDED, fnc: int | None = None
) -> str:
    """The manual's description of ``STS`` (and ``EXT STS``), e.g. for error messages."""
    if fnc is not None and (fnc, sts, ext_sts) in _SPECIFIC:
        return _SPECIFIC[fnc, sts, ext_sts]
    if sts == 0:
        return "Success - no error"
    parts = []
    if sts & 0x0F:
        parts.append(_LOCAL_STS.get(sts & 0x0F, f"Unknown local error 0x{sts & 0x0F:02X}"))
    remote = sts & 0xF0
    if remote == 0xF0:
        table = _EXT_STS_0E if (cmd & ~REPLY_BIT) == 0x0E else _EXT_STS_0F
        if ext_sts is None:
            parts.append("Error code in EXT STS, but the EXT STS byte is missing")
        else:
            parts.append(table.get(ext_sts, f"Unknown extended status 0x{ext_sts:02X}"))
    elif remote:
        parts.append(_REMOTE_STS[remote])
    return "; ".join(parts)


class PcccError(ControllerRefused):
    """The controller answered with a non-zero STS; ``description`` is the manual's text."""

    def __init__(
        self,
        message: str,
        *,
        command: str = "",
        sts: int,
        ext_sts: int | None = None,
        description: str = "",
        owner_node: int | None = None,
    ) -> None:
        super().__init__(message, command=command, reason=description, code=sts)
        self.sts = sts
        self.ext_sts = ext_sts
        self.description = description
        self.owner_node = owner_node


class PcccFormatError(ProtocolError):
    """A packet that does not follow the PCCC formats.

    ``header`` is set when the packet had a readable header, so that a controller can answer
    with ``STS 0x10`` (illegal command or format).
    """

    def __init__(self, message: str, *, header: PcccHeader | None = None) -> None:
        super().__init__(message)
        self.header = header


# ------------------------------------------------------------------------------ size limits


@dataclass(frozen=True, slots=True)
class SizeLimits:
    """Data bytes per packet; writes lose 2 bytes per address field in 3-byte form (notes §4.36)."""

    max_read_bytes: int
    max_write_bytes: int

    def __post_init__(self) -> None:
        if not (0 < self.max_read_bytes <= 255 and 0 < self.max_write_bytes <= 255):
            raise ValueError("size limits must be 1-255 bytes (one-byte size field)")

    def write_limit(self, expanded_fields: int = 0) -> int:
        return max(0, self.max_write_bytes - 2 * expanded_fields)

    def max_read_elements(self, element_bytes: int) -> int:
        return self.max_read_bytes // element_bytes

    def max_write_elements(self, element_bytes: int, expanded_fields: int = 0) -> int:
        return self.write_limit(expanded_fields) // element_bytes


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


_SMALL: Final = SizeLimits(82, 82)  # 500, 5/01, 5/02: 0-82 bytes (§4.36)
_MODULAR: Final = SizeLimits(236, 228)  # 500 CPU read LOCAL 236; write without Internet field 228
_FAMILY_LIMITS: Final = {
    ProcessorFamily.SLC500_FIXED: _SMALL,
    ProcessorFamily.SLC5_01: _SMALL,
    ProcessorFamily.SLC5_02: _SMALL,
    ProcessorFamily.SLC5_03: _MODULAR,
    ProcessorFamily.SLC5_04: _MODULAR,
    ProcessorFamily.SLC5_05: _MODULAR,
    ProcessorFamily.PLC5: SizeLimits(230, 222),  # "PLC5 Read" / "PLC5 Write - LOCAL" tables
}
_PROCESSOR_TYPES: Final = {
    0x1A: ProcessorFamily.SLC500_FIXED,
    0x18: ProcessorFamily.SLC5_01,
    0x25: ProcessorFamily.SLC5_02,
    0x49: ProcessorFamily.SLC5_03,
    0x5B: ProcessorFamily.SLC5_04,
}


# ------------------------------------------------------------------------ field encodings


def _check_range(name: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise InvalidRequest(f"PCCC: {name} {value} out of range {low}-{high}")


def _encode_field(name: str, value: int) -> bytes:
    """One byte for 0-254, else ``FF lo hi`` (notes §7.3; 257 -> FF 01 01)."""
    _check_range(name, value, 0, 0xFFFF)
    if value < 0xFF:
        return bytes((value,))
    return b"\xff" + value.to_bytes(2, "little")


class _Reader:
    """Cursor over a packet body; every read checks the length."""

    def __init__(self, data: bytes, offset: int = 0, *, header: PcccHeader | None = None) -> None:
        self.data = data
        self.pos = offset
        self.header = header

    def fail(self, message: str) -> PcccFormatError:
        return PcccFormatError(message, header=self.header)

    def take(self, count: int, what: str) -> bytes:
        if self.pos + count > len(self.data):
            raise self.fail(f"PCCC: packet too short for {what}")
        chunk = self.data[self.pos : self.pos + count]
        self.pos += count
        return chunk

    def u8(self, what: str) -> int:
        return self.take(1, what)[0]

    def u16(self, what: str) -> int:
        return int.from_bytes(self.take(2, what), "little")

    def field(self, what: str) -> int:
        first = self.u8(what)
        return self.u16(what) if first == 0xFF else first

    def rest(self) -> bytes:
        chunk = self.data[self.pos :]
        self.pos = len(self.data)
        return chunk

    def end(self, what: str) -> None:
        if self.pos != len(self.data):
            raise self.fail(f"PCCC: {len(self.data) - self.pos} unexpected bytes after {what}")


@dataclass(frozen=True, slots=True)
class LogicalBinaryAddress:
    """PLC-5 logical binary address (notes §6.0): mask byte + one field per level present.

    ``mask`` bit ``n`` set means level ``n`` is present; ``levels`` holds their values in order.
    ``LogicalBinaryAddress.of(0, 4, 2, 2)`` is T4:2.ACC: ``0F 00 04 02 02``.
    """

    mask: int
    levels: tuple[int, ...]

    def __post_init__(self) -> None:
        _check_range("address mask", self.mask, 1, 0xFF)
        if bin(self.mask).count("1") != len(self.levels):
            raise InvalidRequest(f"PCCC: mask 0x{self.mask:02X} does not match {len(self.levels)} levels")
        for value in self.levels:
            _check_range("address level", value, 0, 0xFFFF)

    @classmethod
    def of(cls, *levels: int) -> LogicalBinaryAddress:
        """Consecutive levels from level 1 (section, file, element, sub-element)."""
        return cls((1 << len(levels)) - 1, tuple(levels))

    @classmethod
    def for_element(cls, file_number: int, element: int, sub_element: int = 0) -> LogicalBinaryAddress:
        """Data table (section 0) address, four levels, as in the S4516-DF1 sample code."""
        return cls.of(0, file_number, element, sub_element)

    @classmethod
    def from_slc(cls, address: SlcAddress) -> LogicalBinaryAddress:
        return cls.for_element(address.file_number, address.element, address.sub_element)

    def encode(self) -> bytes:
        return bytes((self.mask,)) + b"".join(_encode_field("address level", v) for v in self.levels)

    @classmethod
    def _read(cls, reader: _Reader) -> LogicalBinaryAddress:
        mask = reader.u8("address mask")
        if mask == 0:
            raise reader.fail("PCCC: address mask 0 (logical ASCII addresses are not supported)")
        levels = tuple(reader.field("address level") for _ in range(bin(mask).count("1")))
        return cls(mask, levels)


# -------------------------------------------------------------------- type/data parameter


@dataclass(frozen=True, slots=True)
class TypeData:
    """Typed read/write type/data parameter (notes "Important type/data parameter note").

    Flag byte: high nibble = type ID, low nibble = size; a nibble with bit 3 set instead gives
    the number (1-7) of following bytes, least significant first, that hold the value.  Type
    ID bytes come before size bytes.
    """

    type_id: int
    size: int

    def __post_init__(self) -> None:
        _check_range("type ID", self.type_id, 0, (1 << 56) - 1)
        _check_range("type size", self.size, 0, (1 << 56) - 1)


def _nibble(value: int) -> tuple[int, bytes]:
    if value <= 7:
        return value, b""
    extra = value.to_bytes((value.bit_length() + 7) // 8, "little")
    return 0x8 | len(extra), extra


def encode_type_data(type_id: int, size: int) -> bytes:
    """The shortest encoding (ID 4 size 3 -> ``43``; ID 9 size 5 -> ``99 09 05``)."""
    TypeData(type_id, size)  # range check
    id_nibble, id_bytes = _nibble(type_id)
    size_nibble, size_bytes = _nibble(size)
    return bytes((id_nibble << 4 | size_nibble,)) + id_bytes + size_bytes


def decode_type_data(data: bytes, offset: int = 0) -> tuple[TypeData, int]:
    """Decode a type/data parameter at ``offset``; returns it and the offset after it.

    Accepts every equivalent encoding, including zero-padded extension bytes (cases 1-3 of the note).
    """
    reader = _Reader(data, offset)
    flag = reader.u8("type/data parameter")
    values = []
    for nibble in (flag >> 4, flag & 0x0F):
        if nibble & 0x8:
            values.append(int.from_bytes(reader.take(nibble & 0x7, "type/data parameter"), "little"))
        else:
            values.append(nibble)
    return TypeData(values[0], values[1]), reader.pos


@dataclass(frozen=True, slots=True)
class TypedData:
    """Elements of one type as carried by typed read replies and typed write commands."""

    data_type: int
    element_size: int
    data: bytes

    @property
    def count(self) -> int:
        return len(self.data) // self.element_size if self.element_size else 0


def encode_typed_data(data_type: int, element_size: int, data: bytes) -> bytes:
    """Type/data parameter(s) and data: a bare element for one element, else an array.

    Array: ``[ARRAY, size = len(element descriptor) + len(data)] [type, element_size] data``.
    """
    if element_size <= 0 or len(data) % element_size:
        raise InvalidRequest(f"PCCC: {len(data)} data bytes are not whole {element_size}-byte elements")
    element = encode_type_data(data_type, element_size)
    if len(data) == element_size:
        return element + data
    return encode_type_data(DataType.ARRAY, len(element) + len(data)) + element + data


def decode_typed_data(data: bytes) -> TypedData:
    """Decode a typed read reply body (or typed write data): bare element or array of elements."""
    outer, pos = decode_type_data(data)
    if outer.type_id != DataType.ARRAY:
        body = data[pos:]
        if outer.size and len(body) % outer.size:
            raise PcccFormatError(f"PCCC: {len(body)} data bytes are not whole {outer.size}-byte elements")
        return TypedData(outer.type_id, outer.size, body)
    end = pos + outer.size
    if end > len(data):
        raise PcccFormatError("PCCC: typed data shorter than its array size")
    inner, pos = decode_type_data(data[:end], pos)
    body = data[pos:end]
    if inner.size and len(body) % inner.size:
        raise PcccFormatError(f"PCCC: {len(body)} array bytes are not whole {inner.size}-byte elements")
    return TypedData(inner.type_id, inner.size, body)


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
        _check_range("file type", self.file_type, 0, 0xFF)
        _check_range("byte size", self.size, 1, 0xFF)
        for name in ("file_number", "element", "sub_element"):
            _check_range(name.replace("_", " "), getattr(self, name), 0, 0xFFFF)

    @property
    def expanded_fields(self) -> int:
        return sum(v >= 0xFF for v in (self.file_number, self.element, self.sub_element))

    def encode_params(self) -> bytes:
        return bytes((self.size,)) + _encode_three(self)

    @classmethod
    def decode_params(cls, reader: _Reader) -> ProtectedTypedLogicalRead:
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
        _check_range("file type", self.file_type, 0, 0xFF)
        _check_range("byte size", len(self.data), 1, 0xFF)
        for name in ("file_number", "element", "sub_element"):
            _check_range(name.replace("_", " "), getattr(self, name), 0, 0xFFFF)

    @property
    def expanded_fields(self) -> int:
        return sum(v >= 0xFF for v in (self.file_number, self.element, self.sub_element))

    def encode_params(self) -> bytes:
        return bytes((len(self.data),)) + _encode_three(self) + self.data

    @classmethod
    def decode_params(cls, reader: _Reader) -> ProtectedTypedLogicalWrite:
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
        _check_range("file type", self.file_type, 0, 0xFF)
        _check_range("byte size", len(self.data), 0, 0xFF)
        _check_range("bit mask", self.mask, 0, 0xFFFF)
        for name in ("file_number", "element", "sub_element"):
            _check_range(name.replace("_", " "), getattr(self, name), 0, 0xFFFF)

    @property
    def expanded_fields(self) -> int:
        return sum(v >= 0xFF for v in (self.file_number, self.element, self.sub_element))

    def encode_params(self) -> bytes:
        return bytes((len(self.data),)) + _encode_three(self) + self.mask.to_bytes(2, "little") + self.data

    @classmethod
    def decode_params(cls, reader: _Reader) -> ProtectedTypedLogicalMaskedWrite:
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
        _encode_field("file number", request.file_number)
        + bytes((request.file_type,))
        + _encode_field("element", request.element)
        + _encode_field("sub-element", request.sub_element)
    )


def _read_three(reader: _Reader) -> tuple[int, int, int, int]:
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
        _check_range("file number", self.file_number, 0, 0xFFFF)

    def encode_params(self) -> bytes:
        return LogicalBinaryAddress(0x06, (self.DATA_TABLE, self.file_number)).encode()

    @classmethod
    def decode_params(cls, reader: _Reader) -> ReadFileInfo:
        address = LogicalBinaryAddress._read(reader)
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
        _check_range("mode", self.mode, 0, 0xFF)

    def encode_params(self) -> bytes:
        return bytes((self.mode,))

    @classmethod
    def decode_params(cls, reader: _Reader) -> SetProcessorMode:
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
    def decode_params(cls, reader: _Reader) -> DiagnosticStatus:
        reader.end("the function code")
        return cls()


@dataclass(frozen=True, slots=True)
class WordRangeRead:
    """PLC-5 word range read (CMD 0F, FNC 01; S4516-DF1 manual §2.6.1).

    ``packet_offset`` and ``total`` are in words (elements), ``size`` in bytes.
    """

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.WORD_RANGE_READ

    address: LogicalBinaryAddress
    size: int
    packet_offset: int = 0
    total: int | None = None  # default: size // 2

    def __post_init__(self) -> None:
        _check_range("byte size", self.size, 1, 0xFF)
        _check_range("packet offset", self.packet_offset, 0, 0xFFFF)
        if self.total is None:
            object.__setattr__(self, "total", (self.size + 1) // 2)
        _check_range("total transaction", self.total_words, 0, 0xFFFF)

    @property
    def total_words(self) -> int:
        return self.total if self.total is not None else (self.size + 1) // 2

    def encode_params(self) -> bytes:
        return struct.pack("<HH", self.packet_offset, self.total_words) + self.address.encode() + bytes((self.size,))

    @classmethod
    def decode_params(cls, reader: _Reader) -> WordRangeRead:
        offset = reader.u16("packet offset")
        total = reader.u16("total transaction")
        address = LogicalBinaryAddress._read(reader)
        size = reader.u8("size")
        reader.end("the size")
        return cls(address, size, offset, total)


@dataclass(frozen=True, slots=True)
class WordRangeWrite:
    """PLC-5 word range write (CMD 0F, FNC 00; S4516-DF1 manual §2.6.1); even data bytes."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.WORD_RANGE_WRITE

    address: LogicalBinaryAddress
    data: bytes
    packet_offset: int = 0
    total: int | None = None  # default: len(data) // 2

    def __post_init__(self) -> None:
        if not self.data or len(self.data) % 2:
            raise InvalidRequest("PCCC: word range write data must be a non-zero even number of bytes")
        _check_range("packet offset", self.packet_offset, 0, 0xFFFF)
        if self.total is None:
            object.__setattr__(self, "total", len(self.data) // 2)
        _check_range("total transaction", self.total_words, 0, 0xFFFF)

    @property
    def total_words(self) -> int:
        return self.total if self.total is not None else len(self.data) // 2

    def encode_params(self) -> bytes:
        return struct.pack("<HH", self.packet_offset, self.total_words) + self.address.encode() + self.data

    @classmethod
    def decode_params(cls, reader: _Reader) -> WordRangeWrite:
        offset = reader.u16("packet offset")
        total = reader.u16("total transaction")
        address = LogicalBinaryAddress._read(reader)
        data = reader.rest()
        if not data or len(data) % 2:
            raise reader.fail("PCCC: word range write data must be a non-zero even number of bytes")
        return cls(address, data, offset, total)


@dataclass(frozen=True, slots=True)
class TypedRead:
    """Typed read (CMD 0F, FNC 68; notes §7.4): ``count`` elements, logical binary address."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.TYPED_READ

    address: LogicalBinaryAddress
    count: int
    packet_offset: int = 0
    total: int | None = None  # default: count

    def __post_init__(self) -> None:
        _check_range("element count", self.count, 1, 0xFFFF)
        _check_range("packet offset", self.packet_offset, 0, 0xFFFF)
        if self.total is None:
            object.__setattr__(self, "total", self.count)
        _check_range("total transaction", self.total_elements, 0, 0xFFFF)

    @property
    def total_elements(self) -> int:
        return self.total if self.total is not None else self.count

    def encode_params(self) -> bytes:
        return (
            struct.pack("<HH", self.packet_offset, self.total_elements)
            + self.address.encode()
            + self.count.to_bytes(2, "little")
        )

    @classmethod
    def decode_params(cls, reader: _Reader) -> TypedRead:
        offset = reader.u16("packet offset")
        total = reader.u16("total transaction")
        address = LogicalBinaryAddress._read(reader)
        count = reader.u16("size")
        reader.end("the size")
        return cls(address, count, offset, total)


@dataclass(frozen=True, slots=True)
class TypedWrite:
    """Typed write (CMD 0F, FNC 67; notes §7.4): type/data parameter then the data."""

    CMD: ClassVar[int] = Command.EXTENDED
    FNC: ClassVar[int] = Function.TYPED_WRITE

    address: LogicalBinaryAddress
    data_type: int
    element_size: int
    data: bytes
    packet_offset: int = 0
    total: int | None = None  # default: number of elements

    def __post_init__(self) -> None:
        if self.element_size <= 0 or not self.data or len(self.data) % self.element_size:
            raise InvalidRequest(f"PCCC: typed write data must be whole {self.element_size}-byte elements")
        _check_range("packet offset", self.packet_offset, 0, 0xFFFF)
        if self.total is None:
            object.__setattr__(self, "total", self.count)
        _check_range("total transaction", self.total_elements, 0, 0xFFFF)

    @property
    def count(self) -> int:
        return len(self.data) // self.element_size

    @property
    def total_elements(self) -> int:
        return self.total if self.total is not None else self.count

    def encode_params(self) -> bytes:
        return (
            struct.pack("<HH", self.packet_offset, self.total_elements)
            + self.address.encode()
            + encode_typed_data(self.data_type, self.element_size, self.data)
        )

    @classmethod
    def decode_params(cls, reader: _Reader) -> TypedWrite:
        offset = reader.u16("packet offset")
        total = reader.u16("total transaction")
        address = LogicalBinaryAddress._read(reader)
        try:
            typed = decode_typed_data(reader.rest())
        except (PcccFormatError, InvalidRequest) as exc:
            raise reader.fail(str(exc)) from exc
        if not typed.data or not typed.element_size:
            raise reader.fail("PCCC: typed write without data")
        return cls(address, typed.data_type, typed.element_size, typed.data, offset, total)


Request = (
    ProtectedTypedLogicalRead
    | ProtectedTypedLogicalWrite
    | ProtectedTypedLogicalMaskedWrite
    | ReadFileInfo
    | SetProcessorMode
    | DiagnosticStatus
    | WordRangeRead
    | WordRangeWrite
    | TypedRead
    | TypedWrite
)

_REQUEST_TYPES: Final[dict[tuple[int, int], type[Request]]] = {
    (cls.CMD, cls.FNC): cls
    for cls in (
        ProtectedTypedLogicalRead,
        ProtectedTypedLogicalWrite,
        ProtectedTypedLogicalMaskedWrite,
        ReadFileInfo,
        SetProcessorMode,
        DiagnosticStatus,
        WordRangeRead,
        WordRangeWrite,
        TypedRead,
        TypedWrite,
    )
}


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


# -------------------------------------------------------------------------------- packets


@dataclass(frozen=True, slots=True)
class PcccHeader:
    """``DST SRC CMD STS TNS`` common to commands and replies."""

    dst: int
    src: int
    cmd: int
    sts: int
    tns: int

    def __post_init__(self) -> None:
        for name in ("dst", "src", "cmd", "sts"):
            _check_range(name.upper(), getattr(self, name), 0, 0xFF)
        _check_range("TNS", self.tns, 0, 0xFFFF)

    @property
    def is_reply(self) -> bool:
        return bool(self.cmd & REPLY_BIT)

    def encode(self) -> bytes:
        return struct.pack("<BBBBH", self.dst, self.src, self.cmd, self.sts, self.tns)

    @classmethod
    def decode(cls, packet: bytes) -> PcccHeader:
        if len(packet) < _HEADER_SIZE:
            raise PcccFormatError(f"PCCC: packet of {len(packet)} bytes is shorter than the 6-byte header")
        return cls(*struct.unpack_from("<BBBBH", packet))


@dataclass(frozen=True, slots=True)
class PcccCommand:
    """A decoded command packet (controller side)."""

    header: PcccHeader
    request: Request


def encode_command(request: Request, *, dst: int, src: int, tns: int) -> bytes:
    """``DST SRC CMD 00 TNS FNC params`` for ``request``."""
    header = PcccHeader(dst, src, request.CMD, 0, tns)
    return header.encode() + bytes((request.FNC,)) + request.encode_params()


def decode_command(packet: bytes) -> PcccCommand:
    """Parse a command packet; :class:`PcccFormatError` (with ``header`` when known) otherwise."""
    header = PcccHeader.decode(packet)
    if header.is_reply:
        raise PcccFormatError(f"PCCC: CMD 0x{header.cmd:02X} is a reply, not a command", header=header)
    reader = _Reader(packet, _HEADER_SIZE, header=header)
    fnc = reader.u8("function code")
    request_type = _REQUEST_TYPES.get((header.cmd, fnc))
    if request_type is None:
        raise reader.fail(f"PCCC: unsupported command CMD 0x{header.cmd:02X} FNC 0x{fnc:02X}")
    try:
        return PcccCommand(header, request_type.decode_params(reader))
    except InvalidRequest as exc:
        raise reader.fail(str(exc)) from exc


@dataclass(frozen=True, slots=True)
class PcccReply:
    """A decoded reply packet; ``data`` excludes EXT STS and the owner node."""

    dst: int
    src: int
    cmd: int
    sts: int
    tns: int
    ext_sts: int | None = None
    owner_node: int | None = None
    data: bytes = field(default=b"")

    @property
    def ok(self) -> bool:
        return self.sts == 0

    @property
    def command(self) -> int:
        """The CMD of the command this reply answers."""
        return self.cmd & ~REPLY_BIT

    def error(self, *, command: str = "", fnc: int | None = None) -> PcccError | None:
        """The refusal as a :class:`PcccError`, or None for STS 0."""
        if self.ok:
            return None
        description = describe_status(self.sts, self.ext_sts, cmd=self.command, fnc=fnc)
        code = f"STS 0x{self.sts:02X}" + ("" if self.ext_sts is None else f" EXT STS 0x{self.ext_sts:02X}")
        owner = "" if self.owner_node is None else f" (owner node {self.owner_node})"
        label = f"{command}: " if command else ""
        return PcccError(
            f"{label}controller refused: {code}: {description}{owner}",
            command=command,
            sts=self.sts,
            ext_sts=self.ext_sts,
            description=description,
            owner_node=self.owner_node,
        )

    def raise_for_status(self, *, command: str = "", fnc: int | None = None) -> None:
        error = self.error(command=command, fnc=fnc)
        if error is not None:
            raise error


def decode_reply(packet: bytes) -> PcccReply:
    """Parse a reply packet (CMD bit 6 set)."""
    header = PcccHeader.decode(packet)
    if not header.is_reply:
        raise PcccFormatError(f"PCCC: CMD 0x{header.cmd:02X} is a command, not a reply", header=header)
    reader = _Reader(packet, _HEADER_SIZE, header=header)
    ext_sts = owner = None
    if header.sts == Sts.EXTENDED:
        ext_sts = reader.u8("EXT STS")
        if ext_sts in _OWNER_EXT_STS and reader.pos < len(packet):
            owner = reader.u8("owner node")
    data = reader.rest()
    return PcccReply(header.dst, header.src, header.cmd, header.sts, header.tns, ext_sts, owner, data)


def encode_reply(
    command: PcccHeader,
    *,
    sts: int = 0,
    ext_sts: int | None = None,
    owner_node: int | None = None,
    data: bytes = b"",
) -> bytes:
    """The reply to ``command``: DST/SRC swapped, CMD | 0x40, same TNS (controller side)."""
    if (sts == Sts.EXTENDED) != (ext_sts is not None):
        raise InvalidRequest("PCCC: EXT STS goes with STS 0xF0 and only with it")
    header = PcccHeader(command.src, command.dst, command.cmd | REPLY_BIT, sts, command.tns)
    tail = b""
    if ext_sts is not None:
        _check_range("EXT STS", ext_sts, 0, 0xFF)
        tail = bytes((ext_sts,))
        if owner_node is not None:
            _check_range("owner node", owner_node, 0, 0xFF)
            tail += bytes((owner_node,))
    return header.encode() + tail + data


def reply_matches(command: PcccHeader | bytes, reply: PcccReply) -> bool:
    """True when ``reply`` answers ``command``: same TNS and CMD | 0x40."""
    header = PcccHeader.decode(command) if isinstance(command, bytes | bytearray) else command
    return reply.tns == header.tns and reply.cmd == header.cmd | REPLY_BIT


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


# ------------------------------------------------------------------------------------ TNS


class TnsAllocator:
    """Transaction numbers: unique among outstanding commands, incrementing, wrapping at 0xFFFF."""

    def __init__(self, start: int = 1) -> None:
        _check_range("TNS", start, 0, 0xFFFF)
        self._next = start
        self._outstanding: set[int] = set()

    @property
    def outstanding(self) -> frozenset[int]:
        return frozenset(self._outstanding)

    def allocate(self) -> int:
        if len(self._outstanding) > 0xFFFF:
            raise InvalidRequest("PCCC: every TNS is in use")
        while self._next in self._outstanding:
            self._next = (self._next + 1) & 0xFFFF
        tns = self._next
        self._outstanding.add(tns)
        self._next = (tns + 1) & 0xFFFF
        return tns

    def release(self, tns: int) -> None:
        self._outstanding.discard(tns)
