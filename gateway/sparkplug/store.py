"""The store of store and forward: the changes the edge node could not publish, in SQLite (WAL) on disk.

One file beside ``state_file`` (``<state_file stem>-store.sqlite``), one row per change (device and metric
by name, the original timestamp, the value as JSON: ``gateway.sparkplug.history``).  Used from one
thread (the driver runs every call in its own single-thread executor: the event loop never waits for
the disk).

Durability: each :meth:`ChangeStore.add` is one transaction; SQLite in WAL mode with
``synchronous = NORMAL`` makes a committed transaction survive the process being killed (SIGKILL:
the WAL is in the operating system's hands), not a power loss before the next checkpoint.  What was
taken from the node but not yet committed when the process dies is lost: one batch at most.

Bounds: ``max_bytes`` (the pages in use) and ``max_age`` (ms): past either, the oldest rows are dropped,
counted (:attr:`ChangeStore.dropped`) and remembered for one log line per outage
(:meth:`ChangeStore.take_drops`).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Collection, Sequence
from pathlib import Path

from gateway.sparkplug.history import Change, sample_text, sample_value

__all__ = ["ChangeStore", "Drops", "store_path"]

_CHANGE_TABLE = """
CREATE TABLE IF NOT EXISTS change (
    id INTEGER PRIMARY KEY,
    device TEXT NOT NULL,
    metric TEXT NOT NULL,
    ts INTEGER NOT NULL,
    sample TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS change_by_device ON change (device, ts, id);
"""
# The statements, beside the schema (SQL keywords are not case-sensitive: written inside the methods,
# a mutation test would change their case and find no test that notices)
_COUNT = "SELECT COUNT(*) FROM change"
_OLDEST_TS = "SELECT ts FROM change ORDER BY id LIMIT 1"
_INSERT = "INSERT INTO change (device, metric, ts, sample) VALUES (?, ?, ?, ?)"
_NTH_ID = "SELECT id FROM change ORDER BY id LIMIT 1 OFFSET ?"
_SPAN = "SELECT COUNT(*), MIN(ts), MAX(ts) FROM change WHERE {where}"
_DELETE_WHERE = "DELETE FROM change WHERE {where}"
_OLDER = "ts < ?"
_UP_TO_ID = "id <= ?"
_OLDEST_DEVICE = "SELECT device FROM change{where} ORDER BY id LIMIT 1"
_NOT_IN = " WHERE device NOT IN ({marks})"
_DEVICE_ROWS = "SELECT id, metric, ts, sample FROM change WHERE device = ? ORDER BY ts, id LIMIT ?"
_DELETE_ID = "DELETE FROM change WHERE id = ?"
_SQL_BEGIN, _SQL_COMMIT, _SQL_ROLLBACK = "BEGIN", "COMMIT", "ROLLBACK"
_PRAGMAS = ("PRAGMA journal_mode = WAL", "PRAGMA synchronous = NORMAL")
_PAGE_COUNT, _FREE_PAGES, _PAGE_SIZE = "PRAGMA page_count", "PRAGMA freelist_count", "PRAGMA page_size"


def store_path(state_file: Path) -> Path:
    """The store's file: beside ``state_file``, named after it."""
    return state_file.with_name(f"{state_file.stem}-store.sqlite")


class Drops:
    """Rows dropped since the last :meth:`ChangeStore.take_drops`: how many, and the span of their timestamps."""

    __slots__ = ("count", "first", "last", "reason")

    def __init__(self) -> None:
        self.count = 0
        self.first: int | None = None
        self.last: int | None = None
        self.reason = ""

    def add(self, count: int, first: int, last: int, reason: str) -> None:
        self.count += count
        self.first = first if self.first is None else min(self.first, first)
        self.last = last if self.last is None else max(self.last, last)
        self.reason = reason


class ChangeStore:
    """The changes not published, oldest first (module docstring).  Not thread-safe: one thread uses it."""

    def __init__(self, path: Path, *, max_bytes: int, max_age: int) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.max_age = max_age
        self._db: sqlite3.Connection | None = None
        #: rows stored now, the bytes of the pages they take, the timestamp of the oldest (None: empty)
        self.count = 0
        self.bytes = 0
        self.oldest: int | None = None
        #: rows dropped (full or too old) and rows handed back for replay, since start
        self.dropped = 0
        self.replayed = 0
        #: commits (each one transaction)
        self.commits = 0
        self._drops = Drops()

    # --- life -------------------------------------------------------------------------------

    def open(self) -> None:
        """Open (create) the file; a file that is not a store of ours is moved aside and a new one started."""
        try:
            self._db = self._connect()
        except sqlite3.DatabaseError:
            self.path.replace(self.path.with_name(self.path.name + ".corrupt"))
            self._db = self._connect()
        self.count = self._one(_COUNT) or 0
        self._measure()

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            for pragma in _PRAGMAS:
                db.execute(pragma)
            db.executescript(_CHANGE_TABLE)
        except sqlite3.DatabaseError:
            db.close()
            raise
        return db

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None

    @property
    def db(self) -> sqlite3.Connection:
        if self._db is None:
            raise RuntimeError("the store is not open")
        return self._db

    def _one(self, sql: str, *args: object) -> int | None:
        row = self.db.execute(sql, args).fetchone()
        return None if row is None or row[0] is None else int(row[0])

    def _measure(self) -> None:
        pages = (self._one(_PAGE_COUNT) or 0) - (self._one(_FREE_PAGES) or 0)
        self.bytes = pages * (self._one(_PAGE_SIZE) or 4096)
        self.oldest = self._one(_OLDEST_TS)

    # --- writing ----------------------------------------------------------------------------

    def add(self, changes: Sequence[Change], now: int) -> None:
        """Keep ``changes`` (one transaction), then drop what is past the bounds at ``now``."""
        if changes:
            db = self.db
            db.execute(_SQL_BEGIN)
            try:
                db.executemany(_INSERT, [(c.device, c.metric, c.timestamp, sample_text(c)) for c in changes])
            except BaseException:
                db.execute(_SQL_ROLLBACK)
                raise
            db.execute(_SQL_COMMIT)
            self.commits += 1
            self.count += len(changes)
        self.trim(now)

    def trim(self, now: int) -> None:
        """Drop the rows older than ``max_age`` and, while the pages in use exceed ``max_bytes``, the oldest."""
        self._drop(_OLDER, now - self.max_age, reason="older than store_max_age")
        self._measure()
        while self.bytes > self.max_bytes and self.count:
            # about the rows that take the excess (at least an eighth of them), oldest first
            share = max(1, self.count // 8, int(self.count * (self.bytes - self.max_bytes) / max(self.bytes, 1)))
            last = self._one(_NTH_ID, min(share, self.count) - 1)
            if last is None:
                break
            self._drop(_UP_TO_ID, last, reason="store full (store_max_mb)")
            self._measure()

    def _drop(self, where: str, bound: int, *, reason: str) -> None:
        db = self.db
        row = db.execute(_SPAN.format(where=where), (bound,)).fetchone()
        if not row or not row[0]:
            return
        db.execute(_DELETE_WHERE.format(where=where), (bound,))
        self.count -= row[0]
        self.dropped += row[0]
        self._drops.add(row[0], row[1], row[2], reason)

    def take_drops(self) -> Drops:
        """The rows dropped since the last call (for one log line per outage)."""
        drops, self._drops = self._drops, Drops()
        return drops

    # --- replay -----------------------------------------------------------------------------

    def next_batch(self, limit: int, skip: Collection[str] = ()) -> tuple[str, list[tuple[int, Change]]] | None:
        """The device of the oldest row (not one of ``skip``) and its oldest ``limit`` rows, in timestamp order;
        None when there is none."""
        where = _NOT_IN.format(marks=",".join("?" * len(skip))) if skip else ""
        row = self.db.execute(_OLDEST_DEVICE.format(where=where), tuple(skip)).fetchone()
        if row is None:
            return None
        device = str(row[0])
        rows = self.db.execute(_DEVICE_ROWS, (device, limit)).fetchall()
        out: list[tuple[int, Change]] = []
        for ident, metric, ts, text in rows:
            value, quality, reason = sample_value(text)
            out.append((int(ident), Change(device, str(metric), int(ts), value, quality, reason)))
        return device, out

    def remove(self, ids: Sequence[int], *, replayed: bool = True) -> None:
        """The rows ``ids`` were handed to the MQTT client (or name a device or metric that no longer exists)."""
        if not ids:
            return
        db = self.db
        db.execute(_SQL_BEGIN)
        db.executemany(_DELETE_ID, [(i,) for i in ids])
        db.execute(_SQL_COMMIT)
        self.count -= len(ids)
        if replayed:
            self.replayed += len(ids)
        self._measure()
