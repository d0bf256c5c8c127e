"""``persist = "file.db"`` of a DF1 target link: the data table on disk, committed before each answer.

Every write to the table (a PLC's MSG write, a Modbus client's write) is one SQLite transaction,
committed before the write is acknowledged: the PCCC reply goes out, or the Modbus answer, only
after :meth:`TargetStore.save` returned.  A process killed at any moment therefore loses no write
that was acknowledged; a write killed before its commit was never acknowledged, and its sender
sends it again (a PLC's MSG errors out and is retried by its ladder; a Modbus client sees no
answer).

SQLite from the standard library, in WAL mode with ``synchronous=FULL``: a commit is on disk when
it returns (WAL with ``NORMAL`` may lose the last commits on power loss, not on a process kill; FULL
holds for both).  One row per element: ``(file, element, value, written_at)``, where ``value`` is
the element's words as they are on the wire (little-endian bytes, 2 per word) and ``written_at``
the wall-clock time (Unix seconds) of the write.

Nothing here knows PCCC; the table is ``file number -> element -> bytes``.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable, Iterator
from pathlib import Path

from gateway.frozen import frozen

__all__ = ["StoredElement", "TargetStore"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS element (
    file INTEGER NOT NULL,
    element INTEGER NOT NULL,
    value BLOB NOT NULL,
    written_at REAL NOT NULL,
    PRIMARY KEY (file, element)
) WITHOUT ROWID
"""
# The statements, stated once beside the schema they work on.  ``isolation_level=None`` at connect:
# the transactions are these statements' own, not ones the ``sqlite3`` module would open for us.
_WAL = "PRAGMA journal_mode=WAL"
_FULL_SYNC = "PRAGMA synchronous=FULL"
_LOAD = "SELECT file, element, value, written_at FROM element ORDER BY file, element"
_BEGIN = "BEGIN IMMEDIATE"
_UPSERT = "INSERT OR REPLACE INTO element (file, element, value, written_at) VALUES (?, ?, ?, ?)"
_COMMIT = "COMMIT"
_ROLLBACK = "ROLLBACK"


@frozen
class StoredElement:
    file: int
    element: int
    value: bytes
    written_at: float


class TargetStore:
    """The persisted data table of one target link, used by the thread that opened it (the event loop's;
    ``sqlite3`` refuses a connection used from another thread)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(path, isolation_level=None)
            for statement in (_WAL, _FULL_SYNC, _SCHEMA):
                self._db.execute(statement)
        except sqlite3.Error as exc:
            raise OSError(f"persist = {str(path)!r}: cannot open the database ({exc}); check the path "
                          "and that the directory is writable") from exc

    def load(self) -> Iterator[StoredElement]:
        """Every element written before, in file and element order."""
        rows = self._db.execute(_LOAD)
        for file, element, value, written_at in rows:
            yield StoredElement(int(file), int(element), bytes(value), float(written_at))

    def save(self, elements: Iterable[StoredElement]) -> None:
        """Write ``elements`` in one transaction; on disk when this returns (else it raises)."""
        rows = [(e.file, e.element, e.value, e.written_at) for e in elements]
        if not rows:
            return
        db = self._db
        db.execute(_BEGIN)
        try:
            db.executemany(_UPSERT, rows)
            db.execute(_COMMIT)
        except BaseException:
            # After some errors (SQLITE_FULL, SQLITE_IOERR) SQLite has rolled back already; a COMMIT
            # that failed may leave the transaction open, and the next save must not commit its rows.
            if db.in_transaction:
                db.execute(_ROLLBACK)
            raise

    def close(self) -> None:
        self._db.close()
