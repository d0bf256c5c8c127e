"""SLC 100/150 ``;T`` faults: the error bits at 84H and 85H ("Format of Transmission").

After ``;T`` "the user should read the bytes at addresses 84H and 85H"; these functions turn
the two bytes into the error numbers the programmer displays.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from types import MappingProxyType

from gateway.errors import ControllerFault
from gateway.frozen import frozen
from gateway.protocols.slc_ascii.command_types import check_int

__all__ = ["ERROR_BITS", "ERROR_DESCRIPTIONS", "ErrorBit", "controller_fault", "decode_error_bits", "error_description"]


@frozen
class ErrorBit:
    """One bit of the error word ("Format of Transmission", format of the error word)."""

    address: int
    bit: int
    number: int
    """The error number displayed by the programmer."""


ERROR_BITS: tuple[ErrorBit, ...] = tuple(
    ErrorBit(address, bit, number)
    for address, numbers in (
        (0x84, (62, 4, 6, 3, 8, 5, 2, 1)),  # bits 7..0
        (0x85, (None, 26, 25, 24, 9, 51, 7, 51)),  # bits 7..0; bit 7 unused
    )
    for bit, number in zip(range(7, -1, -1), numbers, strict=True)
    if number is not None
)
"""The manual's error word table; error 51 has two bits (85H bits 2 and 0)."""

ERROR_DESCRIPTIONS: Mapping[int, str] = MappingProxyType({
    number: f"error {number} (" + ", ".join(
        f"{e.address:02X}H bit {e.bit}" for e in ERROR_BITS if e.number == number) + ")"
    for number in sorted({e.number for e in ERROR_BITS})
})
"""Short description of each error number. The manual names only the number the programmer
displays and its bit, so that is what the description says."""


def error_description(number: int) -> str:
    """Description of an error number, ``"error N"`` for a number not in the table."""
    return ERROR_DESCRIPTIONS.get(number, f"error {number}")


def decode_error_bits(b84: int, b85: int) -> tuple[int, ...]:
    """Error numbers, ascending and without repeats, of the bytes read at 84H and 85H.

    After ``;T`` "the user should read the bytes at addresses 84H and 85H". 85H bit 7 is unused
    and ignored.
    """
    values = {
        0x84: check_int("byte 84H", b84, 0, 0xFF, "a byte is 0-255"),
        0x85: check_int("byte 85H", b85, 0, 0xFF, "a byte is 0-255"),
    }
    return tuple(sorted({e.number for e in ERROR_BITS if values[e.address] >> e.bit & 1}))


def controller_fault(b84: int, b85: int) -> ControllerFault:
    """The :class:`ControllerFault` for a ``;T`` whose error bytes 84H and 85H were read."""
    numbers = decode_error_bits(b84, b85)
    reasons: Iterable[str] = (error_description(n) for n in numbers)
    detail = "; ".join(reasons) or "no error bit set"
    return ControllerFault(f"controller fault (84H=0x{b84:02X}, 85H=0x{b85:02X}): {detail}", errors=numbers)
