"""The store of store and forward (gateway.sparkplug.store): real SQLite files in a temporary directory.

Issue 43: item 1 (the store, its bounds: the oldest dropped, counted, the span kept for the log), item 3
(oldest first per device), item 4 (what was committed survives SIGKILL).
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gateway.sparkplug.history import Change
from gateway.sparkplug.store import ChangeStore, store_path

T0 = 1_700_000_000_000
DAY = 86_400_000


def change(k: int, device: str = "press", metric: str = "N7:0", ts: int | None = None) -> Change:
    return Change(device, metric, T0 + k if ts is None else ts, k, 192)


def opened(path: Path, max_bytes: int = 10**8, max_age: int = DAY) -> ChangeStore:
    store = ChangeStore(path, max_bytes=max_bytes, max_age=max_age)
    store.open()
    return store


def test_the_store_lives_beside_the_state_file() -> None:
    assert store_path(Path("/var/lib/gw/sparkplug-bdseq.json")) == Path("/var/lib/gw/sparkplug-bdseq-store.sqlite")


def test_batches_are_one_device_at_a_time_oldest_first_in_timestamp_order(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite")
    store.add([change(1), change(2, "oven"), change(0, ts=T0 - 5), change(3)], T0)
    assert (store.count, store.oldest) == (4, T0 + 1)
    device, rows = store.next_batch(10) or ("", [])
    assert device == "press" and [c.timestamp for _, c in rows] == [T0 - 5, T0 + 1, T0 + 3]
    assert store.next_batch(10, skip=["press"]) is not None
    store.remove([ident for ident, _ in rows])
    assert (store.count, store.replayed) == (1, 3)
    device, rows = store.next_batch(10) or ("", [])
    assert device == "oven" and [c.value for _, c in rows] == [2]
    assert store.next_batch(10, skip=["oven"]) is None


def test_a_full_store_drops_the_oldest_counts_them_and_keeps_their_span(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite", max_bytes=64 * 1024)
    for batch in range(40):
        store.add([change(batch * 100 + k) for k in range(100)], T0)
        assert store.bytes <= 64 * 1024
    assert store.dropped > 0 and store.count + store.dropped == 4000
    drops = store.take_drops()
    assert drops.count == store.dropped and drops.first == T0 and drops.reason.startswith("store full")
    assert drops.last is not None and drops.last < T0 + 4000 - store.count + 1
    # what is left is the newest, oldest first
    _, rows = store.next_batch(5) or ("", [])
    assert [c.value for _, c in rows] == list(range(4000 - store.count, 4000 - store.count + 5))
    assert store.take_drops().count == 0


def test_changes_older_than_max_age_are_dropped_and_counted(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite", max_age=60_000)
    store.add([change(0, ts=T0), change(1, ts=T0 + 50_000)], T0 + 50_000)
    assert store.count == 2
    store.add([], T0 + 100_000)
    assert (store.count, store.dropped) == (1, 1)
    assert store.take_drops().reason == "older than store_max_age"


def test_what_was_committed_is_there_after_a_reopen(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    store = opened(path)
    store.add([change(k) for k in range(10)], T0)
    store.close()
    again = opened(path)
    assert again.count == 10 and again.oldest == T0


def test_what_was_committed_survives_sigkill(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    script = textwrap.dedent(f"""
        import os, signal
        from pathlib import Path
        from gateway.sparkplug.history import Change
        from gateway.sparkplug.store import ChangeStore
        store = ChangeStore(Path({str(path)!r}), max_bytes=10**8, max_age=10**12)
        store.open()
        for batch in range(5):
            store.add([Change("press", "N7:0", {T0} + batch * 10 + k, k, 192) for k in range(10)], {T0})
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    done = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).resolve().parents[2], check=False)
    assert done.returncode == -signal.SIGKILL
    store = opened(path)
    assert store.count == 50


def test_a_file_that_is_not_a_store_is_moved_aside(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    path.write_bytes(os.urandom(8192))
    store = opened(path)
    assert store.count == 0
    assert (tmp_path / "s.sqlite.corrupt").exists()


def test_each_add_of_changes_is_one_commit_and_an_empty_one_none(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite")
    store.add([change(1), change(2)], T0)
    store.add([change(3)], T0)
    store.add([], T0)
    assert (store.commits, store.count) == (2, 3)


def test_a_failed_insert_is_rolled_back_whole(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite")
    bad = Change("press", None, T0, 1, 192)  # type: ignore[arg-type]  # metric NOT NULL
    with pytest.raises(sqlite3.IntegrityError):
        store.add([change(1), bad], T0)
    store.add([change(2)], T0)  # the store takes the next batch (no transaction left open)
    assert (store.count, store.commits) == (1, 1)
    store.close()
    assert opened(tmp_path / "s.sqlite").count == 1  # the first row of the failed batch is not there


def test_every_row_past_the_age_bound_is_dropped_whatever_its_timestamp(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite", max_age=60_000)
    store.add([change(0, ts=0), change(1, ts=5), change(2, ts=T0)], T0)  # 0: the oldest row's timestamp
    assert (store.count, store.dropped) == (1, 2)
    drops = store.take_drops()
    assert (drops.count, drops.first, drops.last) == (2, 0, 5)


def test_batches_skip_every_device_named(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite")
    store.add([change(1, "a"), change(2, "b"), change(3, "c")], T0)
    assert (store.next_batch(10, skip=["a", "b"]) or ("", []))[0] == "c"
    assert (store.next_batch(10, skip=["a"]) or ("", []))[0] == "b"
    assert store.next_batch(10, skip=["a", "b", "c"]) is None
    _, rows = store.next_batch(1) or ("", [])
    assert len(rows) == 1


def test_a_store_not_opened_holds_nothing(tmp_path: Path) -> None:
    """What the status shows of a store that could not be opened."""
    store = ChangeStore(tmp_path / "s.sqlite", max_bytes=10**8, max_age=DAY)
    assert (store.count, store.bytes, store.oldest, store.dropped, store.replayed) == (0, 0, None, 0, 0)
    drops = store.take_drops()
    assert (drops.count, drops.first, drops.last, drops.reason) == (0, None, None, "")


def test_the_bytes_are_the_pages_in_use(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite"
    store = opened(path)
    store.add([change(k) for k in range(50)], T0)
    reader = sqlite3.connect(path)
    pages, free, size = (reader.execute(f"PRAGMA {name}").fetchone()[0]
                         for name in ("page_count", "freelist_count", "page_size"))
    reader.close()
    assert store.bytes == (pages - free) * size > 0


def test_replay_hands_back_each_change_whole_and_counts_every_removal(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite")
    store.add([Change("press", "N7:0", T0, None, 500, "no fresh data"), change(1), change(2)], T0)
    _, rows = store.next_batch(10) or ("", [])
    assert rows[0][1] == Change("press", "N7:0", T0, None, 500, "no fresh data")
    store.remove([rows[0][0]])
    store.remove([ident for ident, _ in rows[1:]])
    assert (store.replayed, store.count) == (3, 0)


def test_the_span_of_what_was_dropped_is_its_oldest_and_newest_timestamp(tmp_path: Path) -> None:
    store = opened(tmp_path / "s.sqlite", max_age=1_000)
    store.add([change(0, ts=100)], 2_000)  # too old: dropped
    store.add([change(1, ts=50)], 2_000)  # an older one stored later: dropped too
    drops = store.take_drops()
    assert (drops.count, drops.first, drops.last) == (2, 50, 100)
