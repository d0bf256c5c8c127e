"""Per link: the Modbus writes waiting for the line, applied in arrival order and shared fairly.

Every write request (one FC5, FC6, FC15 or FC16, validated whole beforehand) becomes one *job*
queued here the moment it arrives: the server starts one task per request in arrival order and
nothing awaits before the queue, so queue order is arrival order, across all connections.
One worker per link runs the jobs one at a time inside a write session of the driver
(``LineDriver.write_session``): writes go ahead of polls, and after ``write_burst`` write
transactions in a row ``poll_burst`` poll transactions get the line.  A job is
``async def job(line)``: it gets the session's lease (``gateway.line_driver.LineLease``) as its
argument and hands it to its driver's requests, which run on the line the session holds.

Order.  Jobs of one client run in arrival order, always.  Between clients the worker serves
the least recently served first (round robin; a client with nothing queued counts as never
served), so one client's flood never makes another's write wait for one of its jobs; but a
job never overtakes an earlier-arrived job of another client whose *footprint* (the
controller words it writes) overlaps its own.  So any two writes that touch the same word
reach the controller in the order their requests arrived, whichever connections sent them,
and a write to 43 acknowledged after an FC16 over 40-43 arrived is never overwritten by it.
Two writes to disjoint words from two connections have no order a client could observe
besides their replies, which leave in any order, each with its own transaction id.

Bounds.  At most ``per_client`` jobs of one client and ``per_link`` jobs in all wait here;
beyond, the request is answered 0x06 (server device busy) and nothing of it is written (the
unit holds a busy answer 0.1 s, so that a master re-sending at once cannot make it spin).
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Awaitable, Callable, Hashable
from dataclasses import dataclass, field

from gateway.errors import LinkError, ModbusExceptionReply, modbus_exception
from gateway.line_driver import LineLease, UnitDriver, retrieve_outcome

__all__ = ["WriteQueue"]

log = logging.getLogger("gateway.writes")

#: A write job: run on the line of the session's lease, which it gets as its argument.
Job = Callable[[LineLease], Awaitable[None]]


@dataclass(eq=False, slots=True)
class _Entry:
    seq: int
    footprint: frozenset[Hashable]
    job: Job
    future: asyncio.Future[None] = field(repr=False)


class WriteQueue:
    """The write jobs of one link (module docstring)."""

    def __init__(self, driver: UnitDriver, name: str, *, per_client: int = 8, per_link: int = 32) -> None:
        if per_client < 1 or per_link < 1:
            raise ValueError("write queue bounds must be at least 1")
        self.driver = driver
        self.name = name
        self.per_client = per_client
        self.per_link = per_link
        #: per client, its waiting jobs in arrival order
        self._queues: dict[Hashable, deque[_Entry]] = {}
        #: per client with jobs waiting: when it was last served (round robin by least recent)
        self._served: dict[Hashable, int] = {}
        self._serves = 0
        #: the job picked last is of a client that was not being served (nothing queued before);
        #: set by _pick with the job it returns
        self._newcomer: bool
        self._waiting = 0
        self._seq = 0
        self._worker: asyncio.Task[None] | None = None
        self.busy_refusals = 0

    @property
    def waiting(self) -> int:
        return self._waiting

    def submit(self, client: Hashable, footprint: frozenset[Hashable], job: Job) -> asyncio.Future[None]:
        """Queue ``job`` now (call without awaiting first); its future ends as the job does.

        Raises ``ModbusExceptionReply`` 0x06 at once when a bound is reached.
        """
        queue = self._queues.get(client)
        if self._waiting >= self.per_link or (queue is not None and len(queue) >= self.per_client):
            self.busy_refusals += 1
            which = (f"{self.per_link} writes are waiting for link {self.name}" if self._waiting >= self.per_link
                     else f"this connection has {self.per_client} writes waiting for link {self.name}")
            raise ModbusExceptionReply(ModbusExceptionReply.SERVER_DEVICE_BUSY, f"busy: {which}; retry later")
        loop = asyncio.get_running_loop()
        entry = _Entry(self._seq, footprint, job, loop.create_future())
        self._seq += 1
        if queue is None:
            queue = self._queues[client] = deque()
        queue.append(entry)
        self._waiting += 1
        entry.future.add_done_callback(retrieve_outcome)  # its caller may give up
        if self._worker is None:
            self._worker = loop.create_task(self._work(), name=f"{self.name}-writes")
        return entry.future

    async def drain(self) -> None:
        """Return when every job taken so far has run (its verdict reached)."""
        while (worker := self._worker) is not None:
            await asyncio.shield(worker)

    def withdraw(self, future: asyncio.Future[None]) -> bool:
        """Take the job of ``future`` out of the queue if it has not started; True if it was
        (its future is then cancelled: nothing of it will be written)."""
        for client, queue in self._queues.items():
            for entry in queue:
                if entry.future is future:
                    queue.remove(entry)
                    self._waiting -= 1
                    if not queue:
                        del self._queues[client]
                        self._served.pop(client, None)
                    future.cancel()
                    return True
        return False

    def _pick(self) -> _Entry | None:
        """The next job: least recently served client first (one with nothing queued a moment
        ago counts as never served), never ahead of an earlier overlapping job of another."""
        served = self._served
        for client in sorted(self._queues, key=lambda c: served.get(c, -1)):
            queue = self._queues[client]
            head = queue[0]
            if head.footprint and any(
                other is not queue and other[0].seq < head.seq and any(
                    entry.seq < head.seq and not entry.footprint.isdisjoint(head.footprint) for entry in other
                )
                for other in self._queues.values()
            ):
                continue
            queue.popleft()
            self._waiting -= 1
            self._newcomer = client not in served
            if queue:
                served[client] = self._serves
                self._serves += 1
            else:
                del self._queues[client]
                served.pop(client, None)
            return head
        return None  # not reached while jobs wait: the earliest job overtakes nothing

    async def _work(self) -> None:
        try:
            while self._waiting:
                try:
                    async with self.driver.write_session() as line:
                        while (entry := self._pick()) is not None:
                            if self._newcomer:
                                line.extend_burst()
                            await self._run(entry, line)
                except LinkError as exc:
                    # No line for writes (the link is down): every waiting job fails at once.
                    error = modbus_exception(exc)  # 0x0B
                    while (entry := self._pick()) is not None:
                        if not entry.future.done():
                            entry.future.set_exception(error)
        finally:
            self._worker = None
            if self._waiting:  # cancelled (the gateway is stopping): nobody will run these
                error = ModbusExceptionReply(ModbusExceptionReply.GATEWAY_TARGET_FAILED, "the gateway is stopping")
                while (entry := self._pick()) is not None:
                    if not entry.future.done():
                        entry.future.set_exception(error)

    @staticmethod
    async def _run(entry: _Entry, line: LineLease) -> None:
        try:
            await entry.job(line)
        except asyncio.CancelledError:
            if not entry.future.done():
                entry.future.cancel()
            raise
        except BaseException as exc:  # the job's own failure is its caller's answer
            if not entry.future.done():
                entry.future.set_exception(exc)
        else:
            if not entry.future.done():
                entry.future.set_result(None)
