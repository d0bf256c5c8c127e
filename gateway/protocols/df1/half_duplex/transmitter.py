"""The half-duplex master's side of the wire: quiet time, RTS keying, echo suppression (sans-I/O).

Manual: SLC 500 1747-RM001 p. 13-59 (RTS send delay, RTS off delay); the reading is in
``docs/develop/df1-half-duplex-notes.md``.  The master core (``master.py``) decides what to send; this
module decides when the bytes may go and what of the bytes heard are the line's, not our own:

* the line is quiet ``pre_transmit_delay`` after the last byte heard before the master transmits;
* ``rts`` goes true ``rts_send_delay`` before the first byte and false ``rts_off_delay`` after the
  last one (transmission time = bytes x ``char_time``).  These are deadlines, never sleeps;
* with ``echo`` (2-wire RS-485) the master hears its own bytes first and they are stripped; a byte
  that differs is a collision, counted.

This module does no I/O.
"""

from __future__ import annotations

from typing import Final

from gateway.protocols.df1.half_duplex.events import LineConfig

__all__ = ["HalfDuplexTransmitter"]


class HalfDuplexTransmitter:
    """Bytes out, their timing and RTS; echo suppression of the bytes heard (module docstring)."""

    def __init__(self, line: LineConfig) -> None:
        self.line: Final = line
        self.rts = False
        self.collisions = 0
        self.tx_at = 0.0  #: when the pending bytes may go
        self.rts_on_at: float | None = None
        self.rts_off_at: float | None = None
        self._out = bytearray()
        self._echo = bytearray()
        self._quiet_until = float("-inf")
        self._pending = b""

    def data_to_send(self) -> bytes:
        data = bytes(self._out)
        self._out.clear()
        return data

    def rts_deadlines(self) -> list[float]:
        return [t for t in (self.rts_on_at, self.rts_off_at) if t is not None]

    def heard(self, data: bytes, now: float, *, transmitting: bool) -> bytes:
        """``data`` read from the line, our own echo stripped; a byte heard makes the line busy
        (and pushes back bytes waiting to go, ``transmitting``)."""
        if self._echo:
            same = 0
            limit = min(len(data), len(self._echo))
            while same < limit and data[same] == self._echo[same]:
                same += 1
            if same < limit:  # our own bytes came back different: a collision
                self.collisions += 1
                self._echo.clear()
            else:
                del self._echo[:same]
            data = data[same:]
        if not data:
            return data
        self._quiet_until = max(self._quiet_until, now + self.line.pre_transmit_delay)
        if transmitting:
            self.tx_at = max(self.tx_at, self._quiet_until + self.line.rts_send_delay)
        return data

    def prepare(self, data: bytes, now: float) -> bool:
        """Hold ``data`` until the line is quiet and RTS is up; True when that is already so."""
        start = max(now, self._quiet_until)
        self._pending = data
        self.tx_at = start + self.line.rts_send_delay
        if start <= now:
            self.rts = True
            self.rts_off_at = None
        else:
            self.rts_on_at = start  # after the previous RTS off (start >= quiet_until >= it)
        return self.tx_at <= now

    def send(self, now: float) -> float:
        """The bytes held by :meth:`prepare` go out now, once; returns when their last byte has left."""
        data = self._pending
        self._pending = b""
        self._out += data
        if self.line.echo:
            self._echo += data
        end = now + len(data) * self.line.char_time
        self.rts_off_at = end + self.line.rts_off_delay
        self._quiet_until = max(self._quiet_until, self.rts_off_at)
        self.update_rts(now)
        return end

    def update_rts(self, now: float) -> None:
        if self.rts_off_at is not None and now >= self.rts_off_at:
            self.rts = False
            self.rts_off_at = None
        if self.rts_on_at is not None and now >= self.rts_on_at:
            self.rts = True
            self.rts_on_at = None
