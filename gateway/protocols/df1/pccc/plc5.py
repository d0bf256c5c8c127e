"""PLC-5 PCCC commands: word range read / write, typed read / write, read-modify-write.

Manuals: S4516-DF1 Program Development Manual §2.6.1 (PLC5 word range read / write, CMD 0F FNC
01 / 00); SLC 500 PCCC command notes §5.0 (data types), §7.4 (typed read FNC 68 / typed write FNC
67) and "Important type/data parameter note"; A-B 1770-6.5.16 chapter 7 p. 7-20 (read-modify-write,
FNC 26) and the 1770-KF2 manual p. 5-57 (word range layouts and limits), as read in
``docs/develop/df1-half-duplex-notes.md`` section 6.

Word range and typed commands (CMD 0F)::

    FNC  OFFSET_lo OFFSET_hi  TOTAL_lo TOTAL_hi  ADDRESS  (SIZE | [type/data] DATA)

with a logical binary ADDRESS (:class:`~gateway.protocols.df1.pccc.codec.LogicalBinaryAddress`) or,
for the byte-level builders at the end, any encoded address (logical binary or logical ASCII, see
:mod:`gateway.protocols.df1.plc5_address`).  This module is the one home of PLC-5 word range and
read-modify-write packet building; ``plc5_address`` keeps the addresses only.  Each request class
lists its fields once in ``PARAMS`` (:mod:`.params`).  It does no I/O.
"""

from __future__ import annotations

import enum
import struct
from typing import Any, ClassVar, Final

from gateway.errors import InvalidRequest
from gateway.frozen import frozen
from gateway.protocols.df1.pccc.codec import LogicalBinaryAddress, PcccFormatError, Reader, check_range
from gateway.protocols.df1.pccc.codes import CmdByte, Function
from gateway.protocols.df1.pccc.limits import PLC5_WORD_RANGE
from gateway.protocols.df1.pccc.params import Byte, Bytes, Decoded, LogicalAddress, Parameters, Wire, Word
from gateway.protocols.df1.plc5_address import AddressError, decode_logical_ascii, decode_logical_binary

__all__ = [
    "PLC5_HEAD",
    "DataType",
    "ReadModifyWrite",
    "ReadModifyWriteRequest",
    "TypeData",
    "TypedData",
    "TypedRead",
    "TypedWrite",
    "WordRangeRead",
    "WordRangeReadParams",
    "WordRangeWrite",
    "WordRangeWriteParams",
    "decode_type_data",
    "decode_typed_data",
    "encode_type_data",
    "encode_typed_data",
    "word_range_params",
]


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


# -------------------------------------------------------------------- type/data parameter


@frozen
class TypeData:
    """Typed read/write type/data parameter (notes "Important type/data parameter note").

    Flag byte: high nibble = type ID, low nibble = size; a nibble with bit 3 set instead gives
    the number (1-7) of following bytes, least significant first, that hold the value.  Type
    ID bytes come before size bytes.
    """

    type_id: int
    size: int

    def __post_init__(self) -> None:
        check_range("type ID", self.type_id, 0, (1 << 56) - 1)
        check_range("type size", self.size, 0, (1 << 56) - 1)


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
    reader = Reader(data, offset)
    flag = reader.u8("type/data parameter")
    values = []
    for nibble in (flag >> 4, flag & 0x0F):
        if nibble & 0x8:
            values.append(int.from_bytes(reader.take(nibble & 0x7, "type/data parameter"), "little"))
        else:
            values.append(nibble)
    return TypeData(values[0], values[1]), reader.pos


@frozen
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

#: ``PACKET OFFSET(2) TOTAL TRANS(2) ADDRESS``: the head of the word range and typed commands
#: (S4516 §2.6.1; 1770-6.5.16 p. 7-30; KF2 p. 5-57), offset and total low byte first.
PLC5_HEAD: Final[tuple[Wire, ...]] = (
    Word("packet_offset", "packet offset"),
    Word("total", "total transaction"),
    LogicalAddress("address"),
)


@frozen
class WordRangeRead(Parameters):
    """PLC-5 word range read (CMD 0F, FNC 01; S4516-DF1 manual §2.6.1).

    ``packet_offset`` and ``total`` are in words (elements), ``size`` in bytes.
    """

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.WORD_RANGE_READ
    PARAMS: ClassVar[tuple[Wire, ...]] = (*PLC5_HEAD, Byte("size", "byte size", 1, PLC5_WORD_RANGE.max_read_bytes))

    address: LogicalBinaryAddress
    size: int
    packet_offset: int = 0
    total: int | None = None  # default: size // 2

    def __post_init__(self) -> None:
        self.check_params()
        if self.total is None:
            self.fill_default("total", (self.size + 1) // 2)

    @property
    def total_words(self) -> int:
        return self.total if self.total is not None else (self.size + 1) // 2


@frozen
class WordRangeWrite(Parameters):
    """PLC-5 word range write (CMD 0F, FNC 00; S4516-DF1 manual §2.6.1); even data bytes."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.WORD_RANGE_WRITE
    PARAMS: ClassVar[tuple[Wire, ...]] = (*PLC5_HEAD, Bytes("data", "write data"))

    address: LogicalBinaryAddress
    data: bytes
    packet_offset: int = 0
    total: int | None = None  # default: len(data) // 2

    def __post_init__(self) -> None:
        if not self.data or len(self.data) % 2:
            raise InvalidRequest("PCCC: word range write data must be a non-zero even number of bytes")
        size, most = len(self.address.encode()) + len(self.data), PLC5_WORD_RANGE.max_write_bytes
        if size > most:
            raise InvalidRequest(f"PCCC: address + data bytes {size} out of range 1-{most}")
        self.check_params()
        if self.total is None:
            self.fill_default("total", len(self.data) // 2)

    @property
    def total_words(self) -> int:
        return self.total if self.total is not None else len(self.data) // 2


@frozen
class TypedRead(Parameters):
    """Typed read (CMD 0F, FNC 68; notes §7.4): ``count`` elements, logical binary address."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.TYPED_READ
    PARAMS: ClassVar[tuple[Wire, ...]] = (*PLC5_HEAD, Word("count", "element count", 1))

    address: LogicalBinaryAddress
    count: int
    packet_offset: int = 0
    total: int | None = None  # default: count

    def __post_init__(self) -> None:
        self.check_params()
        if self.total is None:
            self.fill_default("total", self.count)

    @property
    def total_elements(self) -> int:
        return self.total if self.total is not None else self.count


@frozen
class _TypedBody:
    """The type/data parameter(s) and the data of a typed write (notes §7.4, type/data note)."""

    def encode(self, request: Any) -> bytes:
        return encode_typed_data(request.data_type, request.element_size, request.data)

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        try:
            typed = decode_typed_data(reader.rest())
        except (PcccFormatError, InvalidRequest) as exc:
            raise reader.fail(str(exc)) from exc
        decoded.values.update(data_type=typed.data_type, element_size=typed.element_size, data=typed.data)

    def check(self, request: Any) -> None:
        """``TypedWrite.__post_init__`` checks the data against the element size."""


@frozen
class TypedWrite(Parameters):
    """Typed write (CMD 0F, FNC 67; notes §7.4): type/data parameter then the data."""

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.TYPED_WRITE
    PARAMS: ClassVar[tuple[Wire, ...]] = (*PLC5_HEAD, _TypedBody())

    address: LogicalBinaryAddress
    data_type: int
    element_size: int
    data: bytes
    packet_offset: int = 0
    total: int | None = None  # default: number of elements

    def __post_init__(self) -> None:
        if self.element_size <= 0 or not self.data or len(self.data) % self.element_size:
            raise InvalidRequest(f"PCCC: typed write data must be whole {self.element_size}-byte elements")
        self.check_params()
        if self.total is None:
            self.fill_default("total", self.count)

    @property
    def count(self) -> int:
        return len(self.data) // self.element_size

    @property
    def total_elements(self) -> int:
        return self.total if self.total is not None else self.count


@frozen
class _MaskSets:
    """Repeated ``ADDRESS AND(2) OR(2)`` sets up to the end of the packet (1770-6.5.16 p. 7-20)."""

    attr: str

    def encode(self, request: Any) -> bytes:
        sets: tuple[tuple[LogicalBinaryAddress, int, int], ...] = getattr(request, self.attr)
        return b"".join(a.encode() + struct.pack("<HH", m_and, m_or) for a, m_and, m_or in sets)

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        sets: list[tuple[LogicalBinaryAddress, int, int]] = []
        while reader.pos < len(reader.data):  # no set at all: check() refuses it
            address = LogicalBinaryAddress.read(reader)
            sets.append((address, reader.u16("AND mask"), reader.u16("OR mask")))
        decoded.values[self.attr] = tuple(sets)

    def check(self, request: Any) -> None:
        sets: tuple[tuple[LogicalBinaryAddress, int, int], ...] = getattr(request, self.attr)
        if not sets:
            raise InvalidRequest("PCCC: read-modify-write needs at least one address")
        for _address, and_mask, or_mask in sets:
            check_range("AND mask", and_mask, 0, 0xFFFF)
            check_range("OR mask", or_mask, 0, 0xFFFF)


@frozen
class ReadModifyWriteRequest(Parameters):
    """Read-modify-write (CMD 0F, FNC 26; 1770-6.5.16 p. 7-20, KF2 p. 5-48): ``ADDRESS AND(2) OR(2)`` sets.

    Each addressed word becomes ``(word & AND) | OR`` in the controller, in one command: the coil
    write of a PLC-5 (no read-then-write race with the ladder).  Addresses must point to a word.
    """

    CMD: ClassVar[int] = CmdByte.EXTENDED
    FNC: ClassVar[int] = Function.READ_MODIFY_WRITE
    PARAMS: ClassVar[tuple[Wire, ...]] = (_MaskSets("sets"),)

    sets: tuple[tuple[LogicalBinaryAddress, int, int], ...]


# ------------------------------------------------------ byte-level builders (any encoded address)


def word_range_params(packet_offset: int, total: int, address: bytes, tail: bytes) -> bytes:
    """``PACKET OFFSET(2) TOTAL TRANS(2) ADDRESS tail`` (S4516 §2.6.1; KF2 p. 5-57), low byte first.

    :data:`PLC5_HEAD` and a tail, for an address already encoded (logical binary or logical
    ASCII): the word range read (tail = SIZE byte) and write (tail = data) parameters of the
    byte-level builders below.  For a logical binary address it gives the bytes
    :class:`WordRangeRead` / :class:`WordRangeWrite` encode.
    """
    return struct.pack("<HH", packet_offset, total) + address + tail


def _u16(name: str, value: int) -> int:
    if not 0 <= value <= 0xFFFF:
        raise AddressError(f"{name} {value} out of range 0..65535")
    return value


def _checked_word_range(packet_offset: int, total: int, address: bytes, tail: bytes) -> bytes:
    """:func:`word_range_params`, PACKET OFFSET and TOTAL TRANS checked to fit 16 bits."""
    return word_range_params(_u16("packet offset", packet_offset), _u16("total transaction", total), address, tail)


def _word_range_head(params: bytes) -> tuple[int, int, int]:
    """PACKET OFFSET, TOTAL TRANS and where the address after them ends (AddressError when the
    parameters stop inside them: the address decoders say so for the address)."""
    try:
        offset, total = struct.unpack_from("<HH", params)
    except struct.error:
        raise AddressError("word range parameters are truncated") from None
    return offset, total, _address_end(params, 4)


@frozen
class WordRangeReadParams:
    """FNC 01 parameters for an already encoded address (logical binary or ASCII; KF2 p. 5-57).

    ``SIZE`` in bytes: even, 2 up to ``PLC5_WORD_RANGE.max_read_bytes`` (``limits.py``).  The header
    (DST SRC 0F STS TNS FNC) is the codec's.
    """

    address: bytes  #: an encoded logical binary or ASCII address
    size: int  #: data bytes to read (even, at most PLC5_WORD_RANGE.max_read_bytes)
    packet_offset: int = 0  #: in words
    total_transaction: int | None = None  #: in words; default size / 2

    def encode(self) -> bytes:
        most = PLC5_WORD_RANGE.max_read_bytes
        if self.size < 2 or self.size % 2 or self.size > most:
            raise AddressError(f"word range read size {self.size}: an even number of bytes 2..{most}")
        total = self.size // 2 if self.total_transaction is None else self.total_transaction
        return _checked_word_range(self.packet_offset, total, self.address, bytes((self.size,)))

    @classmethod
    def decode(cls, params: bytes) -> WordRangeReadParams:
        offset, total, end = _word_range_head(params)
        if end + 1 != len(params):
            raise AddressError("word range read: one SIZE byte must follow the address")
        return cls(params[4:end], params[end], offset, total)


@frozen
class WordRangeWriteParams:
    """FNC 00 parameters for an already encoded address (KF2 p. 5-57), data low byte first."""

    address: bytes
    data: bytes
    packet_offset: int = 0
    total_transaction: int | None = None

    def encode(self) -> bytes:
        if not self.data or len(self.data) % 2:
            raise AddressError("word range write data must be a whole number of words")
        most = PLC5_WORD_RANGE.max_write_bytes
        if len(self.address) + len(self.data) > most:
            raise AddressError(f"word range write: address + data may be at most {most} bytes (KF2 p. 5-57)")
        total = len(self.data) // 2 if self.total_transaction is None else self.total_transaction
        return _checked_word_range(self.packet_offset, total, self.address, self.data)

    @classmethod
    def decode(cls, params: bytes) -> WordRangeWriteParams:
        offset, total, end = _word_range_head(params)
        return cls(params[4:end], params[end:], offset, total)


@frozen
class ReadModifyWrite:
    """FNC 26: repeated ``ADDRESS AND(2) OR(2)`` sets, masks low byte first (1770-6.5.16 p. 7-20).

    AND mask: 0 resets a bit, 1 keeps it; OR mask: 1 sets a bit.  A coil write of bit ``b``:
    :meth:`set_bit` / :meth:`reset_bit`.
    """

    sets: tuple[tuple[bytes, int, int], ...]

    @classmethod
    def set_bit(cls, address: bytes, bit: int) -> ReadModifyWrite:
        return cls(((address, 0xFFFF, 1 << _bit(bit)),))

    @classmethod
    def reset_bit(cls, address: bytes, bit: int) -> ReadModifyWrite:
        return cls(((address, 0xFFFF & ~(1 << _bit(bit)), 0x0000),))

    def encode(self) -> bytes:
        if not self.sets:
            raise AddressError("read-modify-write needs at least one address")
        body = b"".join(
            a + _u16("AND mask", m_and).to_bytes(2, "little") + _u16("OR mask", m_or).to_bytes(2, "little")
            for a, m_and, m_or in self.sets
        )
        if len(body) > 243:
            raise AddressError("read-modify-write sets may be at most 243 bytes (p. 7-20)")
        return body

    @classmethod
    def decode(cls, params: bytes) -> ReadModifyWrite:
        sets: list[tuple[bytes, int, int]] = []
        position = 0
        while position < len(params):
            end = _address_end(params, position)
            if end + 4 > len(params):
                raise AddressError("read-modify-write set is truncated")
            and_mask = int.from_bytes(params[end : end + 2], "little")
            or_mask = int.from_bytes(params[end + 2 : end + 4], "little")
            sets.append((params[position:end], and_mask, or_mask))
            position = end + 4
        return cls(tuple(sets))

    def apply(self, word: int) -> int:
        """The word after the first set's masks: ``(word & AND) | OR``."""
        _address, and_mask, or_mask = self.sets[0]
        return (word & and_mask) | or_mask


def _bit(bit: int) -> int:
    if not 0 <= bit <= 15:
        raise AddressError(f"bit {bit} out of range 0..15")
    return bit


def _address_end(data: bytes, offset: int) -> int:
    """Offset after a logical binary or logical ASCII address starting at ``offset``."""
    if data[offset : offset + 2] == b"\x00$":
        return decode_logical_ascii(data, offset)[1]
    return decode_logical_binary(data, offset)[1]
