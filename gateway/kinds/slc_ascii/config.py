"""``[[link]]`` with ``protocol = "slc-ascii"``: an SLC 100/150 over its ASCII protocol.

The link has only the common keys; its memory map is the fixed SLC 100/150 default map, so a
``[[link.map]]`` here is an error. This module is the one place that holds the protocol's serial
defaults.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar, Literal

from gateway.config.link import LinkBase, SerialDefaults

__all__ = ["SLC_ASCII_DEFAULTS", "SlcAsciiLinkConfig"]

#: Manual ("Format of Transmission"): "even parity, and operates at 9600 baud ... 7 - data bits,
#: 1 - parity bit, and 1 - stop bit"; "Normally the SLC will respond within 0.3 seconds".
SLC_ASCII_DEFAULTS = SerialDefaults(baudrate=9600, bytesize=7, parity="E", stopbits=1, timeout=0.3)


class SlcAsciiLinkConfig(LinkBase):
    """``[[link]]`` of an SLC 100/150 (ASCII protocol)."""

    serial_defaults: ClassVar[SerialDefaults] = SLC_ASCII_DEFAULTS
    sim_models: ClassVar[tuple[str, ...]] = ("slc150", "slc100")
    foreign_key_notes: ClassVar[Mapping[str, str]] = {"map": "slc-ascii links use the fixed default map"}

    protocol: Literal["slc-ascii"]

    def describe_lines(self) -> list[str]:
        lines = super().describe_lines()
        lines[-1:-1] = ["# map: the fixed SLC 100/150 default map"]
        return lines
