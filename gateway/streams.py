"""The byte stream interface and serial line settings: what drivers read and write, whoever opens it.

:mod:`gateway.transport` opens streams from URLs (serial ports, device servers, ``sim://``) and
:mod:`gateway.sim` provides simulated ones; both build on this module, so neither needs the other
to define a stream, and the two never import each other.  No I/O here.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

from gateway.frozen import frozen

__all__ = ["MISSING_PORT_HINT", "ByteStream", "SerialSettings"]


#: What to do about a serial port path with nothing behind it (``check-config``'s warning, the link's error).
MISSING_PORT_HINT = "check the name (ls /dev/serial/by-id/ lists USB adapters)"


@frozen
class SerialSettings:
    """Line settings.  Used for local and RFC 2217 ports, and by simulators to pace bytes."""

    baudrate: int = 9600
    bytesize: int = 7
    parity: str = "E"
    stopbits: int = 1

    @property
    def bits_per_char(self) -> int:
        """Start bit + data bits + parity bit + stop bits (10 for both 7E1 and 8N1)."""
        return 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits

    @property
    def char_time(self) -> float:
        """Seconds one character takes on the line."""
        return self.bits_per_char / self.baudrate


class ByteStream(ABC):
    """A bidirectional byte stream.  ``read`` raises ``LinkDown`` when the stream ends."""

    @abstractmethod
    async def read(self) -> bytes:
        """Some bytes (at least one).  Raises ``LinkDown`` at end of stream or on an I/O error."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Queue ``data`` for sending.  Raises ``LinkDown`` if the stream is closed."""

    @abstractmethod
    async def close(self) -> None:
        """Close the stream; idempotent."""

    def char_time(self, settings: SerialSettings) -> float:
        """Seconds one character takes on this stream's line (0: no serial line to wait for)."""
        return settings.char_time

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        """From now on hand every chunk to ``receive`` and a loss to ``lost`` (no more ``read``).

        Returns False when this stream can only be ``read``.
        """
        return False
