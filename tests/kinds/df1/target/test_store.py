"""``persist`` of a DF1 target link (``gateway/kinds/df1/target/store.py``): the data table on disk.

What the user guide promises (docs/guide/target-mode.md, "Persistence and the simulator"): each write
is committed before its answer goes out, and "after a restart, even after ``kill -9``, the table
comes back with its values and write times".  A write that cannot be committed is answered STS 40
(the table of refusals there), so a save that fails must leave nothing of itself behind.  These
tests use the store alone, on a real SQLite file; the unit and the driver around it are tested in
``test_persist_faults.py``.
"""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gateway.kinds.df1.target.store import StoredElement, TargetStore

ROOT = Path(__file__).resolve().parents[4]

N7_0 = StoredElement(7, 0, b"\x34\x12", 1_700_000_000.25)  # N7:0 = 0x1234, low byte first on the wire
N7_1 = StoredElement(7, 1, b"\xff\xff", 1_700_000_001.5)  # N7:1 = -1
F8_2 = StoredElement(8, 2, b"\x00\x00\x80\x3f", 1_700_000_002.0)  # F8:2 = 1.0, two words


def reopened(path: Path) -> list[StoredElement]:
    """What a restarted gateway loads from ``path``."""
    store = TargetStore(path)
    try:
        return list(store.load())
    finally:
        store.close()


def test_a_new_file_holds_nothing(tmp_path: Path) -> None:
    assert reopened(tmp_path / "line3.db") == []


def test_the_table_comes_back_after_a_restart_with_values_and_write_times(tmp_path: Path) -> None:
    path = tmp_path / "line3.db"
    store = TargetStore(path)
    store.save([F8_2, N7_1])
    store.save([N7_0])
    store.close()
    # in file and element order, whatever the order of the writes
    assert reopened(path) == [N7_0, N7_1, F8_2]


def test_a_later_write_of_an_element_replaces_it(tmp_path: Path) -> None:
    path = tmp_path / "line3.db"
    store = TargetStore(path)
    store.save([N7_0, N7_1])
    later = StoredElement(7, 0, b"\x05\x00", 1_700_000_010.0)
    store.save([later])
    assert list(store.load()) == [later, N7_1]
    store.close()
    assert reopened(path) == [later, N7_1]


def test_an_empty_save_changes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "line3.db"
    store = TargetStore(path)
    store.save([N7_0, N7_1, F8_2])
    store.save([])
    store.close()
    assert reopened(path) == [N7_0, N7_1, F8_2]


def test_a_failed_save_leaves_none_of_its_rows_and_the_next_save_only_its_own(tmp_path: Path) -> None:
    """A save that fails part-way (here its second row breaks the table's rules) is answered STS 40:
    nothing of it may be on disk, and the next save must not commit the failed one's first row."""
    path = tmp_path / "line3.db"
    store = TargetStore(path)
    store.save([N7_0])
    broken = StoredElement(7, 2, b"\x00\x00", float("nan"))  # SQLite binds NaN as NULL: NOT NULL refuses it
    with pytest.raises(sqlite3.Error):
        store.save([N7_1, broken])
    assert list(store.load()) == [N7_0]
    store.save([F8_2])
    store.close()
    assert reopened(path) == [N7_0, F8_2]


def test_a_write_saved_is_on_disk_when_the_process_is_killed_at_once(tmp_path: Path) -> None:
    """``kill -9`` right after a save returned (no close, no exit handlers): the write is there."""
    path = tmp_path / "line3.db"
    child = textwrap.dedent(f"""
        import os, signal
        from pathlib import Path
        from gateway.kinds.df1.target.store import StoredElement, TargetStore
        store = TargetStore(Path({str(path)!r}))
        store.save([StoredElement(7, 0, b"\\x34\\x12", 1700000000.25)])
        store.save([StoredElement(8, 2, b"\\x00\\x00\\x80\\x3f", 1700000002.0)])
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    done = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == -9, done.stderr
    assert reopened(path) == [N7_0, F8_2]


def test_a_path_that_cannot_be_a_database_is_a_clear_error(tmp_path: Path) -> None:
    """``persist`` naming a directory: an OSError that names the setting and the path, and what to check."""
    with pytest.raises(OSError, match=r"persist = .*cannot open the database.*check the path") as caught:
        TargetStore(tmp_path)
    assert str(tmp_path) in str(caught.value)


def test_the_directory_of_the_file_is_made(tmp_path: Path) -> None:
    path = tmp_path / "var" / "lib" / "slc-gateway" / "line3.db"
    store = TargetStore(path)
    store.save([N7_0])
    store.close()
    assert reopened(path) == [N7_0]
