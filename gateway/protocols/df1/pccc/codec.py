"""PCCC packet codec: field encodings, the common header, replies, logical binary addresses, TNS.

Manuals: S4516-DF1 Program Development Manual §2.2 (command / reply packet bytes), §2.6 (packet
formats), Appendix A (STS, EXT STS); SLC 500 PCCC command notes §6.0 (logical binary addressing)
and §7.3 (a field of 0-254 is one byte, else ``FF lo hi``).

Every packet starts with the same header; numbers are little-endian::

    command:  DST SRC CMD STS TNS_lo TNS_hi [FNC parameters...]
    reply:    DST SRC CMD|0x40 STS TNS_lo TNS_hi [EXT_STS [owner]] [data...]

``check_range``, ``encode_field`` and ``Reader`` are the building blocks of the command modules
(:mod:`.slc`, :mod:`.plc5`); they are not re-exported by the package.  This module does no I/O.
"""

from __future__ import annotations

import struct
from dataclasses import field
from typing import Final

from gateway.errors import InvalidRequest, ProtocolError
from gateway.frozen import frozen
from gateway.protocols.df1.address import SlcAddress
from gateway.protocols.df1.pccc.codes import REPLY_BIT
from gateway.protocols.df1.pccc.status import OWNER_EXT_STS, PcccError, Sts, describe_status

__all__ = [
    "HEADER_SIZE",
    "LogicalBinaryAddress",
    "PcccFormatError",
    "PcccHeader",
    "PcccReply",
    "Reader",
    "TnsAllocator",
    "check_range",
    "decode_reply",
    "duplicate_key",
    "encode_field",
    "encode_reply",
    "reply_matches",
]

#: DST SRC CMD STS TNS: "the minimum number of bytes contained in any one message packet is 6"
#: (S4516 §2); a shorter frame is "too small" for a DF1 receiver (1770-6.5.16 p. 4-8).
HEADER_SIZE: Final = 6


def duplicate_key(packet: bytes) -> tuple[int, int, int]:
    """SRC, CMD, TNS: "the combination of SRC, CMD, and TNS bytes uniquely identifies every message
    packet" (1770-6.5.16 p. 6-3); a receiver with duplicate detection drops a packet whose key is
    the last one's (p. 4-8, p. 4-13; KA p. 11-12 on half duplex).  DST and STS are not part of it."""
    if len(packet) < HEADER_SIZE:
        raise PcccFormatError(f"PCCC: packet of {len(packet)} bytes is shorter than the 6-byte header")
    return packet[1], packet[2], packet[4] | packet[5] << 8


class PcccFormatError(ProtocolError):
    """A packet that does not follow the PCCC formats.

    ``header`` is set when the packet had a readable header, so that a controller can answer
    with ``STS 0x10`` (illegal command or format).
    """

    def __init__(self, message: str, *, header: PcccHeader | None = None) -> None:
        super().__init__(message)
        self.header = header


# ------------------------------------------------------------------------ field encodings


def check_range(name: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise InvalidRequest(f"PCCC: {name} {value} out of range {low}-{high}")


def encode_field(name: str, value: int) -> bytes:
    """One byte for 0-254, else ``FF lo hi`` (notes §7.3; 257 -> FF 01 01)."""
    check_range(name, value, 0, 0xFFFF)
    if value < 0xFF:
        return bytes((value,))
    return b"\xff" + value.to_bytes(2, "little")


class Reader:
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


@frozen
class LogicalBinaryAddress:
    """PLC-5 logical binary address (notes §6.0): mask byte + one field per level present.

    ``mask`` bit ``n`` set means level ``n`` is present; ``levels`` holds their values in order.
    ``LogicalBinaryAddress.of(0, 4, 2, 2)`` is T4:2.ACC: ``0F 00 04 02 02``.
    """

    mask: int
    levels: tuple[int, ...]

    def __post_init__(self) -> None:
        check_range("address mask", self.mask, 1, 0xFF)
        if bin(self.mask).count("1") != len(self.levels):
            raise InvalidRequest(f"PCCC: mask 0x{self.mask:02X} does not match {len(self.levels)} levels")
        for value in self.levels:
            check_range("address level", value, 0, 0xFFFF)

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
        return bytes((self.mask,)) + b"".join(encode_field("address level", v) for v in self.levels)

    @classmethod
    def read(cls, reader: Reader) -> LogicalBinaryAddress:
        mask = reader.u8("address mask")
        if mask == 0:
            raise reader.fail("PCCC: address mask 0 (logical ASCII addresses are not supported)")
        levels = tuple(reader.field("address level") for _ in range(bin(mask).count("1")))
        return cls(mask, levels)


# -------------------------------------------------------------------------------- packets


@frozen
class PcccHeader:
    """``DST SRC CMD STS TNS`` common to commands and replies."""

    dst: int
    src: int
    cmd: int
    sts: int
    tns: int

    def __post_init__(self) -> None:
        for name in ("dst", "src", "cmd", "sts"):
            check_range(name.upper(), getattr(self, name), 0, 0xFF)
        check_range("TNS", self.tns, 0, 0xFFFF)

    @property
    def is_reply(self) -> bool:
        return bool(self.cmd & REPLY_BIT)

    def encode(self) -> bytes:
        return struct.pack("<BBBBH", self.dst, self.src, self.cmd, self.sts, self.tns)

    @classmethod
    def decode(cls, packet: bytes) -> PcccHeader:
        if len(packet) < HEADER_SIZE:
            raise PcccFormatError(f"PCCC: packet of {len(packet)} bytes is shorter than the 6-byte header")
        return cls(*struct.unpack_from("<BBBBH", packet))


@frozen
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
    reader = Reader(packet, HEADER_SIZE, header=header)
    ext_sts = owner = None
    if header.sts == Sts.EXTENDED:
        ext_sts = reader.u8("EXT STS")
        if ext_sts in OWNER_EXT_STS and reader.pos < len(packet):
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
        check_range("EXT STS", ext_sts, 0, 0xFF)
        tail = bytes((ext_sts,))
        if owner_node is not None:
            check_range("owner node", owner_node, 0, 0xFF)
            tail += bytes((owner_node,))
    return header.encode() + tail + data


def reply_matches(command: PcccHeader | bytes, reply: PcccReply | PcccHeader) -> bool:
    """True when ``reply`` answers ``command``: the same TNS and CMD | 0x40.  The one matcher of
    both the full-duplex and the half-duplex cores.

    DST and SRC are not compared.  1770-6.5.16 p. 6-4 forms a reply's DST / SRC by interchanging
    the command's, but the same page has a module overwrite a SRC of 0 with its own node number
    (so the reply's DST is that number, not ours), an SLC on full duplex ignores the command's DST
    (its reply's SRC is its own address), and some devices do not interchange them at all.  The
    TNS (ch. 3: "matches a reply with its command") identifies the transaction; on a half-duplex
    line the poll's station number says who answered.  Every reading is in
    docs/develop/controller-variants.md ("reply_addresses").
    """
    header = PcccHeader.decode(command) if isinstance(command, bytes | bytearray) else command
    return reply.tns == header.tns and reply.cmd == header.cmd | REPLY_BIT


# ------------------------------------------------------------------------------------ TNS


class TnsAllocator:
    """Transaction numbers: unique among outstanding commands, incrementing, wrapping at 0xFFFF."""

    def __init__(self, start: int) -> None:
        check_range("TNS", start, 0, 0xFFFF)
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
