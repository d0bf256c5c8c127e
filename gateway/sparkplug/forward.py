"""Store and forward on the event loop: the node's unsent changes into the store, and back out as replay.

The session rules are the core's (``gateway.sparkplug.node``, ``gateway.sparkplug.history``); the disk is
the store's (``gateway.sparkplug.store``), which runs in one thread of its own, so the event loop (the
Modbus answers) never waits for SQLite.

* :meth:`Forwarder.keep` (for the life of the node): every :data:`KEEP_INTERVAL` the changes the core could
  not publish are committed, one transaction; the bounds are applied; a store that starts dropping is
  logged once per outage, and when the session is back the span lost is logged (:meth:`session_up`).
* :meth:`Forwarder.replay` (in each session, after the births): the oldest stored changes of one device
  at a time, up to :data:`REPLAY_METRICS` per DDATA, marked historical, at most ``replay_rate`` messages a
  second, each only once everything queued before it is written (live DDATA goes first); its rows are
  removed once the MQTT client wrote it.  A message lost with the connection afterwards is still in the
  core's window (2 x keepalive + 2 s) and is stored again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from typing import Final, ParamSpec, TypeVar

from gateway.sparkplug.node import EdgeNode, Publish
from gateway.sparkplug.store import ChangeStore

__all__ = ["KEEP_INTERVAL", "REPLAY_METRICS", "Forwarder"]

log = logging.getLogger("gateway.sparkplug")

#: seconds between commits of the unsent changes (what a SIGKILL can lose: one batch)
KEEP_INTERVAL: Final = 0.25
#: stored changes in one historical DDATA, at most
REPLAY_METRICS: Final = 64

P = ParamSpec("P")
T = TypeVar("T")


class _Closed(Exception):
    """The store was closed (the node is stopping): the replay ends."""


def _when(ms: int | None) -> str:
    return "-" if ms is None else datetime.fromtimestamp(ms / 1000, UTC).isoformat(timespec="milliseconds")


class Forwarder:
    """The driver's side of store and forward (module docstring)."""

    def __init__(self, core: EdgeNode, store: ChangeStore, *, replay_rate: float, now_ms: Callable[[], int]) -> None:
        self.core = core
        self.store = store
        self.replay_rate = replay_rate
        self._now_ms = now_ms
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="sparkplug-store")
        self._stored = asyncio.Event()
        self._drop_logged = False
        self._dropped_seen = 0
        self._closed = False
        self._lock = asyncio.Lock()
        #: the store could not be opened or written: store and forward is off (logged)
        self.failed = ""

    async def _call(self, function: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._executor, lambda: function(*args, **kwargs))

    async def _replay_call(self, function: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        """A store call of the replay: under the lock :meth:`close` takes, so it never reaches a closed store
        (a node replaced by a reload closes its store while its session's replay may be between two calls);
        :class:`_Closed` once it is closed."""
        async with self._lock:
            if self._closed or self.failed:
                raise _Closed
            return await self._call(function, *args, **kwargs)

    async def open(self) -> None:
        try:
            await self._call(self.store.open)
        except Exception as exc:
            self._fail(exc)
            return
        if self.store.count:
            log.info("sparkplug: %d stored changes since %s wait to be replayed (store %s)", self.store.count,
                     _when(self.store.oldest), self.store.path)
            self._stored.set()

    def _fail(self, exc: BaseException) -> None:
        self.failed = f"{type(exc).__name__}: {exc}"
        self.core.storing = False
        log.error("sparkplug: store and forward is off: the store %s cannot be used (%s)", self.store.path, exc)

    async def commit(self) -> None:
        """The changes the core recorded since the last commit, into the store (one transaction)."""
        async with self._lock:
            if self._closed or self.failed:
                return
            changes = self.core.take_unsent()
            try:
                await self._call(self.store.add, changes, self._now_ms())
            except Exception as exc:
                self._fail(exc)
                return
            if changes:
                self._stored.set()
            if self.store.dropped > self._dropped_seen:
                self._dropped_seen = self.store.dropped
                if not self._drop_logged:
                    self._drop_logged = True
                    log.warning("sparkplug: store and forward: dropping the oldest stored changes (the store holds "
                                "%d, %d bytes; store_max_mb, store_max_age); the span lost is logged when the "
                                "session is back", self.store.count, self.store.bytes)

    async def keep(self) -> None:
        """Commit every :data:`KEEP_INTERVAL`, for the life of the node."""
        while not self._closed:
            await asyncio.sleep(KEEP_INTERVAL)
            await self.commit()

    async def session_up(self) -> None:
        """The births of a session are out: log what the outage cost, once."""
        if self.failed or self._closed:
            return
        drops = await self._call(self.store.take_drops)
        self._drop_logged = False
        if drops.count:
            log.warning("sparkplug: store and forward: %d changes from %s to %s were dropped (%s); the rest are "
                        "replayed", drops.count, _when(drops.first), _when(drops.last), drops.reason)

    async def replay(self, send: Callable[[list[Publish]], None], drained: Callable[[], Awaitable[None]]) -> None:
        """Replay the store in this session (module docstring); returns only when cancelled or closed."""
        with contextlib.suppress(_Closed):
            await self._replay(send, drained)

    async def _replay(self, send: Callable[[list[Publish]], None], drained: Callable[[], Awaitable[None]]) -> None:
        interval = 1.0 / self.replay_rate
        core, store = self.core, self.store
        while not self._closed and not self.failed:
            if not store.count:
                self._stored.clear()
                await self._stored.wait()
                continue
            await drained()  # live DDATA first
            skip = [device.name for device in core.devices if not device.born]
            batch = await self._replay_call(store.next_batch, REPLAY_METRICS, skip)
            if batch is None:  # only devices that are down now: wait for them
                await asyncio.sleep(1.0)
                continue
            name, rows = batch
            ids = [ident for ident, _ in rows]
            index = core.by_device.get(name)
            message = None if index is None else core.historical(index, [change for _, change in rows],
                                                                 self._now_ms())
            if message is None:
                if index is None or (core.online and not core.unborn and core.devices[index].born):
                    # a device or metrics this node no longer has (the store is older than the config)
                    core.unknown_history += len(rows) if index is None else 0
                    await self._replay_call(store.remove, ids, replayed=False)
                else:
                    await asyncio.sleep(interval)
                continue
            send([message])
            await drained()  # written to the socket: from now on the core's window covers it
            await self._replay_call(store.remove, ids)
            await asyncio.sleep(interval)

    async def close(self) -> None:
        """Commit what is left, close the store."""
        await self.commit()
        async with self._lock:
            self._closed = True
            self._stored.set()
            if not self.failed:
                await self._call(self.store.close)
        self._executor.shutdown(wait=False)

    def status(self) -> dict[str, object]:
        store = self.store
        return {
            "path": str(store.path),
            "failed": self.failed or None,
            "messages": store.count,
            "bytes": store.bytes,
            "oldest": _when(store.oldest) if store.oldest is not None else None,
            "oldest_ms": store.oldest,
            "dropped": store.dropped,
            "replayed": store.replayed,
            "unknown": self.core.unknown_history,
            "commits": store.commits,
        }
