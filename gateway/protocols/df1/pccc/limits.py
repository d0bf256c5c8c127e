"""PCCC packet size limits: the one table that commands, simulators, planners and units read.

Two PLC-5 limits exist because they belong to different commands:

* the SLC 500 typed logical commands (0F A2 / AA / AB) sent to a PLC-5: 230 data bytes read,
  222 written (SLC 500 PCCC command notes, tables "PLC5 Read" and "PLC5 Write - LOCAL");
* the PLC-5 word range commands (0F 01 / 00): a reply carries up to 244 data bytes
  (1770-6.5.16, word range read, "data up to 244 bytes"; S4516 §2.6.1), a command at most
  239 bytes of address and data (1770-KF2 p. 5-57).

The gateway polls a PLC-5 with word range commands (``links/df1/plc5_unit.py``), so
:data:`PLC5_WORD_RANGE` sizes its blocks; :data:`FAMILY_LIMITS` sizes typed logical packets.
This module does no I/O.
"""

from __future__ import annotations

from typing import Final

from gateway.frozen import frozen

__all__ = [
    "MAX_DATA_BYTES",
    "PLC5_TYPED",
    "PLC5_TYPED_LOGICAL",
    "PLC5_WORD_RANGE",
    "SLC_MODULAR",
    "SLC_SMALL",
    "SizeLimits",
]


@frozen
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

    def lowered(self, max_read_bytes: int = 0, max_write_bytes: int = 0) -> SizeLimits:
        """These limits with a link's overrides (0: not given), each at most the limit it overrides:
        a controller refuses a packet over its limit whatever a config says."""
        return SizeLimits(min(max_read_bytes or self.max_read_bytes, self.max_read_bytes),
                          min(max_write_bytes or self.max_write_bytes, self.max_write_bytes))


#: SLC 500 fixed, 5/01, 5/02: 0-82 bytes (notes §4.36).
SLC_SMALL: Final = SizeLimits(82, 82)
#: SLC 5/03 - 5/05: "500 CPU Read - LOCAL" 236; "500 CPU Write - LOCAL" without the Internet field 228.
SLC_MODULAR: Final = SizeLimits(236, 228)
#: Typed logical commands to a PLC-5: "PLC5 Read" 230, "PLC5 Write - LOCAL" 222 (notes).
PLC5_TYPED_LOGICAL: Final = SizeLimits(230, 222)
#: PLC-5 word range read (reply data bytes) and write (address + data bytes).
PLC5_WORD_RANGE: Final = SizeLimits(244, 239)
#: PLC-5 typed read (reply: type/data parameter + data, 244 as a word range read's, KF2 p. 5-57) and
#: typed write (command: address + type/data parameter + data, 1770-6.5.16 p. 7-30, KF2 p. 5-51: 240).
PLC5_TYPED: Final = SizeLimits(PLC5_WORD_RANGE.max_read_bytes, 240)
#: The most data bytes a packet of any family carries: the highest a link's override may ask for,
#: and what the longest frame a driver waits for holds.
MAX_DATA_BYTES: Final = max(
    max(limits.max_read_bytes, limits.max_write_bytes)
    for limits in (SLC_SMALL, SLC_MODULAR, PLC5_TYPED_LOGICAL, PLC5_WORD_RANGE, PLC5_TYPED)
)
