"""Multi-packet writes of the DF1 target: word range write (0F 00) and typed write (0F 67) in pieces.

A PLC-5 MSG that writes more than one packet holds sends it as several commands with the same
address and TOTAL TRANSACTION, each with the PACKET OFFSET of its first word (word range) or
element (typed) in the whole transaction (S4516-DF1 manual §2.6.1: "PACKET OFFSET and TOTAL TNS
are in number of Elements"; 1756-PM020F p. 89: "[total transaction] 2 bytes, number of 16-bit
words in complete transaction"; 1770-KF2 p. 5-57).  The target applies such a write only when
its last packet has arrived, all of it at once, so the data table never holds half a transaction.

The rules (:class:`Transfers`):

* a transaction is the packets from one SRC node with the same FNC, address and total; several
  may be under way at once (one per key), at most ``limit`` (the oldest is dropped past that);
* a packet with offset 0 that is the whole transaction is written at once; one that is not starts
  the transaction, replacing (abandoning) one already under way under the same key;
* each further packet must start exactly where the packets so far end.  A packet that does not
  (a gap, a repeat, a packet of a transaction that is not under way) ends the transaction:
  nothing of it is applied and the packet is refused (STS F0, EXT STS 08 "cannot complete request,
  situation has changed since the start of the command", 1770-6.5.16 p. 8-4; p. 8-9 gives 08 to a
  multi-packet transaction that can no longer complete).  The PLC's MSG errors and its next try
  starts again at offset 0.  Repeated packets with the same TNS are the link layer's to drop
  (DF1 duplicate message detection); this layer sees a repeat as out of order;
* a transaction whose next packet does not come within ``timeout`` seconds of the last one is
  abandoned, nothing applied, when the target next runs (:meth:`Transfers.expire`).

No I/O, no clock: the caller passes ``now``.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.pccc.target_table import TableFile

__all__ = ["DEFAULT_TRANSFER_LIMIT", "DEFAULT_TRANSFER_TIMEOUT", "Transfer", "TransferOutcome", "Transfers"]

#: Seconds a multi-packet write may wait for its next packet.
DEFAULT_TRANSFER_TIMEOUT: Final = 30.0
#: Multi-packet writes under way at once.
DEFAULT_TRANSFER_LIMIT: Final = 8


@dataclass(slots=True)
class Transfer:
    """A multi-packet write under way: ``total`` units of ``unit_bytes`` bytes from ``start`` in ``file``."""

    key: Hashable
    file: TableFile
    start: int
    unit_bytes: int
    total: int
    last_at: float
    received: bytearray = field(default_factory=bytearray)

    @property
    def units(self) -> int:
        return len(self.received) // self.unit_bytes


@frozen
class TransferOutcome:
    """What a write packet did: ``complete`` carries the whole data when it is time to apply it."""

    complete: bytes | None = None
    out_of_order: bool = False
    abandoned: tuple[Transfer, ...] = ()


class Transfers:
    """The multi-packet writes under way (module docstring).  Not thread-safe."""

    def __init__(self, *, timeout: float = DEFAULT_TRANSFER_TIMEOUT, limit: int = DEFAULT_TRANSFER_LIMIT) -> None:
        if timeout <= 0 or limit < 1:
            raise ValueError("transfer timeout must be > 0 and the limit >= 1")
        self.timeout = timeout
        self.limit = limit
        self._open: dict[Hashable, Transfer] = {}

    @property
    def pending(self) -> tuple[Transfer, ...]:
        return tuple(self._open.values())

    def expire(self, now: float) -> tuple[Transfer, ...]:
        """Drop the transactions whose next packet is overdue; the ones dropped."""
        stale = tuple(t for t in self._open.values() if now - t.last_at > self.timeout)
        for transfer in stale:
            del self._open[transfer.key]
        return stale

    def packet(
        self,
        key: Hashable,
        file: TableFile,
        start: int,
        unit_bytes: int,
        offset: int,
        total: int,
        data: bytes,
        now: float,
    ) -> TransferOutcome:
        """One write packet of ``data`` at ``offset`` units of a ``total``-unit transaction (checked to fit)."""
        if offset == 0:
            replaced = self._open.pop(key, None)
            abandoned: tuple[Transfer, ...] = () if replaced is None else (replaced,)
            if len(data) == total * unit_bytes:
                return TransferOutcome(complete=data, abandoned=abandoned)
            if len(self._open) >= self.limit:
                oldest = min(self._open.values(), key=lambda t: t.last_at)
                del self._open[oldest.key]
                abandoned += (oldest,)
            self._open[key] = Transfer(key, file, start, unit_bytes, total, now, bytearray(data))
            return TransferOutcome(abandoned=abandoned)
        transfer = self._open.get(key)
        if transfer is None or transfer.units != offset:
            self._open.pop(key, None)
            return TransferOutcome(out_of_order=True, abandoned=() if transfer is None else (transfer,))
        transfer.received += data
        transfer.last_at = now
        if transfer.units < total:
            return TransferOutcome()
        del self._open[key]
        return TransferOutcome(complete=bytes(transfer.received))
