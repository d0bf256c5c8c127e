"""PCCC command parameters stated once: each request class lists its fields in wire order.

A request class (:mod:`.slc`, :mod:`.plc5`) derives from :class:`Parameters` and sets ``PARAMS`` to
the tuple of its fields, in the order they stand after the FNC byte.  ``encode_params``,
``decode_params`` and the range checks of ``__post_init__`` all walk that one tuple, so the layout of
a command is written in one place.  The shared groups (the three address fields of the SLC typed
logical commands, the packet offset / total transaction / address head of the PLC-5 commands) are
tuples of these fields, spliced into the classes' ``PARAMS``.

Encodings (S4516-DF1 manual §2.6; SLC 500 PCCC command notes §7.3):

* :class:`Byte` / :class:`Word` - one byte / two bytes low byte first;
* :class:`AddressField` - a file, element or sub-element number: one byte for 0-254, else
  ``FF lo hi`` (notes §7.3; 1770-6.5.16 p. 7-17);
* :class:`LogicalAddress` - a PLC-5 logical binary address (notes §6.0);
* :class:`SizeOf` + :class:`Bytes` - a one-byte byte count of a data field that follows later
  (the "byte size" of the typed logical writes), and the data itself (counted, or the rest of the
  packet).

This module does no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, Self

from gateway.frozen import frozen
from gateway.protocols.df1.pccc.codec import LogicalBinaryAddress, Reader, check_range, encode_field

__all__ = [
    "AddressField",
    "Byte",
    "Bytes",
    "Decoded",
    "LogicalAddress",
    "Parameters",
    "SizeOf",
    "Wire",
    "Word",
]


@dataclass(slots=True)
class Decoded:
    """What the fields read so far: constructor arguments, and byte counts read ahead of their data."""

    values: dict[str, Any] = field(default_factory=dict)
    sizes: dict[str, int] = field(default_factory=dict)


class Wire(Protocol):
    """One field of a command's parameters."""

    def encode(self, request: Any) -> bytes: ...

    def decode(self, reader: Reader, decoded: Decoded) -> None: ...

    def check(self, request: Any) -> None: ...


@frozen
class Byte:
    """An attribute sent as one byte; ``what`` names it in errors."""

    attr: str
    what: str
    low: int = 0
    high: int = 0xFF
    WIDTH: ClassVar[int] = 1

    def encode(self, request: Any) -> bytes:
        value: int = getattr(request, self.attr)
        return value.to_bytes(self.WIDTH, "little")

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        decoded.values[self.attr] = int.from_bytes(reader.take(self.WIDTH, self.what), "little")

    def check(self, request: Any) -> None:
        """Range check; None is a default the class fills in from fields checked already."""
        value: int | None = getattr(request, self.attr)
        if value is not None:
            check_range(self.what, value, self.low, self.high)


@frozen
class Word(Byte):
    """An attribute sent as two bytes, low byte first."""

    high: int = 0xFFFF
    WIDTH: ClassVar[int] = 2


@frozen
class AddressField:
    """A file / element / sub-element number: one byte for 0-254, else ``FF lo hi`` (notes §7.3)."""

    attr: str
    what: str

    def encode(self, request: Any) -> bytes:
        return encode_field(self.what, getattr(request, self.attr))

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        decoded.values[self.attr] = reader.field(self.what)

    def check(self, request: Any) -> None:
        check_range(self.what, getattr(request, self.attr), 0, 0xFFFF)

    def expanded(self, request: Any) -> bool:
        """Whether the field goes out in its three-byte form."""
        value: int = getattr(request, self.attr)
        return value >= 0xFF


@frozen
class LogicalAddress:
    """A PLC-5 logical binary address (mask byte, then one field per level; notes §6.0)."""

    attr: str

    def encode(self, request: Any) -> bytes:
        address: LogicalBinaryAddress = getattr(request, self.attr)
        return address.encode()

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        decoded.values[self.attr] = LogicalBinaryAddress.read(reader)

    def check(self, request: Any) -> None:
        """The address checks itself when it is built."""


@frozen
class SizeOf:
    """The one-byte byte count of the data attribute ``of``, sent ahead of it."""

    of: str
    what: str
    low: int = 0

    def encode(self, request: Any) -> bytes:
        return bytes((len(getattr(request, self.of)),))

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        decoded.sizes[self.of] = reader.u8(self.what)

    def check(self, request: Any) -> None:
        check_range(self.what, len(getattr(request, self.of)), self.low, 0xFF)


@frozen
class Bytes:
    """Data bytes: as many as a :class:`SizeOf` before it said, else the rest of the packet."""

    attr: str
    what: str
    high: int | None = None  #: most bytes allowed, when no :class:`SizeOf` bounds them

    def encode(self, request: Any) -> bytes:
        data: bytes = getattr(request, self.attr)
        return data

    def decode(self, reader: Reader, decoded: Decoded) -> None:
        size = decoded.sizes.get(self.attr)
        decoded.values[self.attr] = reader.rest() if size is None else reader.take(size, self.what)

    def check(self, request: Any) -> None:
        if self.high is not None:
            check_range(f"{self.what} bytes", len(getattr(request, self.attr)), 0, self.high)


class Parameters:
    """Mixin of the request classes: encode, decode and check the fields listed in ``PARAMS``."""

    __slots__ = ()

    PARAMS: ClassVar[tuple[Wire, ...]]

    def __post_init__(self) -> None:
        self.check_params()

    def check_params(self) -> None:
        """Range-check every field (a class with its own ``__post_init__`` calls it from there)."""
        for wire in self.PARAMS:
            wire.check(self)

    def fill_default(self, attr: str, value: object) -> None:
        """Set a field left None to the default computed from the others, and check it too."""
        object.__setattr__(self, attr, value)
        self.check_params()

    def encode_params(self) -> bytes:
        """The bytes after the FNC byte."""
        return b"".join(wire.encode(self) for wire in self.PARAMS)

    @classmethod
    def decode_params(cls, reader: Reader) -> Self:
        """Read the fields after the FNC byte; nothing may follow them."""
        decoded = Decoded()
        for wire in cls.PARAMS:
            wire.decode(reader, decoded)
        reader.end("the parameters")
        return cls(**decoded.values)

    @property
    def expanded_fields(self) -> int:
        """How many file / element / sub-element numbers go out in their 3-byte form (notes §4.36)."""
        return sum(wire.expanded(self) for wire in self.PARAMS if isinstance(wire, AddressField))
