"""A half-duplex station's register table served as Modbus registers of its own unit.

Words a station writes to the gateway with an MSG instruction (report by exception) land in its
:class:`~gateway.protocols.df1.half_duplex.slave_messages.RegisterTable` (``gateway.kinds.df1.half.driver``; keys
``receive_file`` / ``receive_words``).  The station's unit serves that table, read-only, in
``receive_table`` ("input" or "holding") from ``receive_start`` on:

* ``receive_start + i`` (``i`` < ``receive_words``): word ``i`` (``N<receive_file>:i``) as the
  station wrote it, 0 until it does;
* ``receive_start + receive_words + i``: the age of word ``i``, in tenths of a second since the
  station last wrote it, 65535 when it never did or for 6553.5 s and more (as the status block's
  ``data_age``).

A read is answered from the table at the moment of the read (the age is as of the read, not of a
poll); it is never stale and needs no line I/O.  A read may span the window and mapped registers
around it: each part is answered by its own source.  Writes to the window are refused with 0x02
(no write target: the plan has no point there).
"""

from __future__ import annotations

from collections.abc import Iterator

from gateway.frozen import frozen
from gateway.modbus.mapping import Table
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable

__all__ = ["AGE_NEVER", "ReceiveWindow"]

#: The age register of a word never written, or written 6553.5 s or more ago.
AGE_NEVER = 0xFFFF


@frozen
class ReceiveWindow:
    """``table``'s words from ``start`` on, then their ages, in Modbus ``modbus_table``."""

    modbus_table: Table
    start: int
    table: RegisterTable

    @property
    def end(self) -> int:
        """One past the last address: ``start`` + words + ages."""
        return self.start + 2 * self.table.size

    def overlaps(self, table: Table, address: int, count: int) -> bool:
        return table is self.modbus_table and address < self.end and self.start < address + count

    def split(self, address: int, count: int) -> Iterator[tuple[int, int, bool]]:
        """``(first, count, inside)`` runs of ``address``.. (``count``): inside the window or not."""
        stop = address + count
        runs = ((address, self.start, False), (self.start, self.end, True), (self.end, stop, False))
        for low, high, inside in runs:
            first, last = max(low, address), min(high, stop)
            if first < last:
                yield first, last - first, inside

    def registers(self, address: int, count: int, now: float) -> bytes:
        """Registers ``address``.. (``count``, all inside the window) as big-endian bytes, ages as of ``now``."""
        size = self.table.size
        out = bytearray()
        for register in range(address - self.start, address - self.start + count):
            if register < size:
                value = self.table.value(register)
            else:
                age = self.table.age(register - size, now)
                value = AGE_NEVER if age is None else min(AGE_NEVER, int(max(0.0, age) * 10))
            out += value.to_bytes(2, "big")
        return bytes(out)
