"""What every link driver shares: the byte stream, reconnecting, one request at a time, state.

A driver owns one byte stream opened from a URL.  Requests are queued with a priority (writes
before polls) and run one at a time on the line by a worker task.  A reader task feeds the
protocol core with every byte that arrives.  When the stream is lost the driver reopens it by
itself with capped exponential backoff and jitter; meanwhile requests fail at once with
``LinkDown`` (never a hang).  The driver logs when the link goes down and when it recovers,
not every retry, by the rule of :class:`~gateway.link_health.LinkHealth` (its base).
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import heapq
import itertools
import logging
import random
from abc import abstractmethod
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import AbstractAsyncContextManager
from pathlib import Path
from typing import Any, Protocol, TypedDict, TypeVar

from gateway.errors import GatewayError, LinkDown, LinkError, LinkTimeout, LocalError, format_seconds
from gateway.link_health import DEFAULT_DOWN_AFTER, DownAfter, LineCounters, LineQuality, LinkHealth
from gateway.transport import ByteStream, SerialSettings, describe_url, open_stream

__all__ = [
    "LineCounters",  # defined in gateway.link_health, with the rule it counts for
    "LineDriver",
    "LineDriverOptions",
    "LineLease",
    "OpenStream",
    "Priority",
    "UnitDriver",
    "retrieve_outcome",
    "run_to_the_end",
]

log = logging.getLogger("gateway.link")

T = TypeVar("T")

#: A connection that lasted less than this (seconds) counts as a failed attempt for the backoff.
_STABLE_CONNECTION = 5.0
OpenStream = Callable[..., Awaitable[ByteStream]]


class LineLease:
    """The line as one run of writes has it: a write job's argument (``async def job(line)``).

    The write queue (``gateway.writes``) takes it from :meth:`UnitDriver.write_session` and hands
    it to each job it runs; the job hands it down, step by step, to its driver's requests
    (``LineDriver.submit(op, line=...)``), which then run on the line the session holds.  This one
    holds nothing: a station's handle on a half-duplex line gives it (the line's master core orders
    every request), and so does a unit with no line (the DF1 target's table).
    :meth:`LineDriver.write_session` gives a held one, with the burst accounting.
    """

    __slots__ = ()

    def extend_burst(self) -> None:
        """The next write may follow the burst before the polls it owes (a held line's, from
        ``LineDriver.write_session``); a lease that holds no line has no burst."""


class _HeldLine(LineLease):
    """The line held by ``LineDriver.write_session``: its state between two writes of the run."""

    __slots__ = ("driver", "extend", "held", "open", "writes")

    def __init__(self, driver: LineDriver) -> None:
        self.driver = driver
        #: the line is taken now (between bursts it is lent to the polls)
        self.held = False
        #: the session is on: a request with a lease whose session ended is refused
        self.open = True
        #: write transactions in a row since the line was last taken
        self.writes = 0
        #: the next write may follow the burst (``extend_burst``)
        self.extend = False

    def extend_burst(self) -> None:
        """For the write of a client with nothing else queued, so a flood ahead of it does not
        make it wait for a round of polls too; the polls still come after it, ``poll_burst``
        for every ``write_burst`` writes, so the share of the line writes take is unchanged."""
        self.extend = True


class Priority(enum.IntEnum):
    """Lower goes first: writes jump ahead of polls."""

    WRITE = 0
    POLL = 1


class _Line:
    """Exclusive use of the line, granted by priority (then arrival order).

    Free: the caller takes it at once and runs its request in its own task (no hand-over to a
    worker task, so a poller's next request leaves as soon as the previous answer is in).
    Busy: callers wait in a heap; ``release`` hands the line to the most urgent one.
    """

    __slots__ = ("_grant_waiters", "_seq", "_waiters", "busy", "grants")

    def __init__(self) -> None:
        self.busy = False
        self._waiters: list[tuple[int, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        #: how many times the line was granted (to anyone)
        self.grants = 0
        #: (grants to wait for, future): woken when the line was granted that often, or fell idle
        self._grant_waiters: list[tuple[int, asyncio.Future[None]]] = []

    async def acquire(self, priority: int) -> None:
        if not self.busy and not self._waiters:
            self.busy = True
            self._granted()
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._waiters, (priority, next(self._seq), future))
        try:
            await future
        except asyncio.CancelledError:
            if future.done() and not future.cancelled() and future.exception() is None:
                self.release()  # handed the line just as the caller gave up: pass it on
            raise

    def release(self) -> None:
        while self._waiters:
            _, _, future = heapq.heappop(self._waiters)
            if not future.done():
                future.set_result(None)  # the line stays busy: it is theirs now
                self._granted()
                return
        self.busy = False
        if self._grant_waiters:
            # Idle only if nobody takes it in the same step (a poller asks again at once).
            asyncio.get_running_loop().call_soon(self._idle_check)

    def _idle_check(self) -> None:
        if not self.busy:
            self._wake_grant_waiters(idle=True)

    def _granted(self) -> None:
        self.grants += 1
        if self._grant_waiters:
            self._wake_grant_waiters(idle=False)

    def _wake_grant_waiters(self, idle: bool) -> None:
        keep = []
        for target, future in self._grant_waiters:
            if future.done():
                continue
            if idle or self.grants >= target:
                future.set_result(None)
            else:
                keep.append((target, future))
        self._grant_waiters = keep

    async def wait_grants(self, target: int) -> None:
        """Until the line was granted ``target`` times in all, or nobody uses it."""
        if self.grants >= target or not self.busy:
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._grant_waiters.append((target, future))
        await future

    @property
    def waiting(self) -> bool:
        return any(not future.done() for _, _, future in self._waiters)

    def fail_waiting(self, exc: BaseException) -> None:
        self._wake_grant_waiters(idle=True)
        while self._waiters:
            _, _, future = heapq.heappop(self._waiters)
            if not future.done():
                future.set_exception(exc)


class UnitDriver(Protocol):
    """What a unit, its write queue, the metrics and the app use of the driver under a unit.

    A :class:`LineDriver` is one (one controller per port); so is a station's handle on a shared
    line (``gateway.kinds.df1.half.driver.Df1Station``), whose line is the runner instead.
    """

    name: str
    counters: LineCounters
    last_error: str
    #: loop time of the last change of ``available`` (None before the first verdict)
    state_since: float | None
    write_burst: int
    poll_burst: int

    @property
    def url(self) -> str: ...

    @property
    def available(self) -> bool: ...

    @property
    def connected(self) -> bool: ...

    def write_session(self) -> AbstractAsyncContextManager[LineLease]:
        """Hold the line for a run of writes; the lease it yields goes to each write job."""

    async def first_attempt(self) -> None:
        """Until the first attempt to open the port is over (opened or failed)."""

    def line_quality(self) -> LineQuality: ...


class LineDriverOptions(TypedDict, total=False):
    """The keyword arguments of :class:`LineDriver` that a kind's driver passes on as they are
    (``**line: Unpack[LineDriverOptions]``); their defaults are the base's."""

    name: str
    trace: Path | None
    reconnect_min: float
    reconnect_max: float
    connect_timeout: float
    opener: OpenStream
    down_after_failures: int
    down_after_seconds: float


class LineDriver(LinkHealth):
    """Base of the protocol drivers.  Subclasses implement the protocol hooks."""

    def __init__(
        self,
        url: str,
        *,
        name: str = "",
        settings: SerialSettings | None = None,
        trace: Path | None = None,
        reconnect_min: float = 0.5,
        reconnect_max: float = 1.0,
        connect_timeout: float = 5.0,
        opener: OpenStream = open_stream,
        down_after_failures: int = DEFAULT_DOWN_AFTER.failures,
        down_after_seconds: float = DEFAULT_DOWN_AFTER.seconds,
    ) -> None:
        super().__init__(name or describe_url(url), DownAfter(down_after_failures, down_after_seconds))
        self.url = url
        self.settings = settings or SerialSettings()
        #: seconds per character on the current stream's line (0 for an unpaced simulator)
        self.char_time = self.settings.char_time
        self._trace = trace
        self._reconnect_min = reconnect_min
        self._reconnect_max = reconnect_max
        self._connect_timeout = connect_timeout
        self._opener = opener
        self._stream: ByteStream | None = None
        self._line = _Line()
        self._connected = asyncio.Event()
        self._first_attempt_done = asyncio.Event()
        self._lost: asyncio.Future[None] | None = None
        self._run_task: asyncio.Task[None] | None = None
        self._closing = False
        self._timer: asyncio.TimerHandle | None = None  #: at the core's deadline (``follow_deadline``)
        #: in a write session: after ``write_burst`` write transactions in a row, up to
        #: ``poll_burst`` waiting poll transactions get the line
        self.write_burst = 1
        self.poll_burst = 2

    # --- public state -----------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._stream is not None

    def where(self) -> str:
        return describe_url(self.url)

    # --- life cycle -------------------------------------------------------------------------

    async def run(self) -> None:
        """Keep the link open until cancelled: connect, serve requests, reconnect on loss."""
        delay = self._reconnect_min
        attempt = 0
        while not self._closing:
            try:
                stream = await self._opener(
                    self.url,
                    self.settings,
                    connect_timeout=self._connect_timeout,
                    trace=self._trace,
                    link_name=self.name,
                )
            except LinkDown as exc:
                self._report(False, str(exc))
                self._first_attempt_done.set()
                attempt += 1
                await asyncio.sleep(delay * random.uniform(0.8, 1.2))
                delay = min(delay * 2, self._reconnect_max)
                continue
            if attempt or self.counters.transactions:
                self.counters.reconnects += 1
            self._failures_in_row = 0
            attempt = 0
            opened = asyncio.get_running_loop().time()
            await self._serve(stream)
            if self._closing:
                return
            if asyncio.get_running_loop().time() - opened < _STABLE_CONNECTION:
                # Opened, then lost at once (a device server that accepts and hangs up, a flaky
                # USB adapter): back off as for a failed open instead of reconnecting in a loop.
                await asyncio.sleep(delay * random.uniform(0.8, 1.2))
                delay = min(delay * 2, self._reconnect_max)
            else:
                delay = self._reconnect_min

    async def _serve(self, stream: ByteStream) -> None:
        loop = asyncio.get_running_loop()
        self._stream = stream
        self.char_time = stream.char_time(self.settings)
        self._lost = loop.create_future()
        self.on_connect()
        self._connected.set()
        self._first_attempt_done.set()
        # "up" is reported when the controller first answers, not when the port opens.
        reader: asyncio.Task[None] | None = None
        if not stream.start_push(self._bytes_in, self._connection_lost):
            reader = asyncio.create_task(self._read_loop(stream), name=f"{self.name}-reader")
        try:
            await self._lost
        finally:
            if reader is not None:
                reader.cancel()
            self._stream = None
            self._connected.clear()
            self._fail_pending(LinkDown(f"link {self.name} is down: {self.last_error or 'closed'}"))
            task = asyncio.current_task()
            if not self._closing and not (task is not None and task.cancelling()):  # stopped, not down
                self._report(False, self.last_error or "connection lost")
            try:
                # Not wrapped in suppress(CancelledError): a cancellation of this task must go on.
                if reader is not None:
                    await asyncio.wait([reader])
            finally:
                await stream.close()

    def _connection_lost(self, reason: str) -> None:
        self.last_error = reason
        if self._lost is not None and not self._lost.done():
            self._lost.set_result(None)

    async def _read_loop(self, stream: ByteStream) -> None:
        while True:
            try:
                data = await stream.read()
            except LinkDown as exc:
                self._connection_lost(str(exc))
                return
            self._bytes_in(data)

    def _bytes_in(self, data: bytes) -> None:
        """Bytes from the line, straight from the transport (push) or from the reader task."""
        self.counters.bytes_received += len(data)
        try:
            self.data_received(data)
        except Exception:  # a bug in a protocol core must not kill the transport's callback
            log.exception("link %s: error handling %d received bytes", self.name, len(data))

    def _fail_pending(self, exc: GatewayError) -> None:
        """The link is gone: the request on the line and every waiting one fail with ``exc``; the
        core's timer is stopped (a new connection gets a new core, or a reset one)."""
        self.follow_deadline(None)
        self.abort(exc)
        self._line.fail_waiting(exc)

    async def first_attempt(self) -> None:
        """Until :meth:`run` made its first attempt to open the port (opened or failed): before it the
        link is neither up nor down, and a request would fail with a "not connected" that is no error."""
        await self._first_attempt_done.wait()

    async def start(self, wait: float | None = None) -> None:
        """Run in the background and wait for the first connection attempt (for the CLI).

        Raises ``LinkDown`` when the first attempt failed.
        """
        self._run_task = asyncio.create_task(self.run(), name=f"{self.name}-run")
        await asyncio.wait_for(self._first_attempt_done.wait(), wait or self._connect_timeout + 1)
        if not self.connected:
            await self.close()
            raise LinkDown(self.last_error or f"{self.url}: cannot open")

    async def close(self) -> None:
        self._closing = True
        if self._run_task is not None:
            self._run_task.cancel()
            await asyncio.wait([self._run_task])  # a cancellation of close() itself still propagates
            self._run_task = None
        if self._stream is not None:
            await self._stream.close()
            self._stream = None
        self._fail_pending(LinkDown(f"link {self.name} is closed"))

    async def __aenter__(self) -> LineDriver:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # --- requests ---------------------------------------------------------------------------

    async def submit(
        self, op: Callable[[], Awaitable[T]], priority: Priority = Priority.POLL, line: LineLease | None = None
    ) -> T:
        """Run ``op`` with exclusive use of the line; fails at once with ``LinkDown`` when down.

        ``line``: the lease of a write session of this driver (:meth:`write_session`, passed down
        by the write job): ``op`` runs on the line the session holds, by its burst accounting.
        Without one, writes run in a task of their own, shielded: a write on the line goes on to
        its answer even when its caller gives up (a SCADA client that disconnects, a request
        cancelled), so the controller is never left with a write half done by us.
        """
        if line is not None:
            return await self._run_held(self._own(line), op)
        self._check_connected()
        await self._line.acquire(int(priority))
        if priority is Priority.WRITE:
            return await run_to_the_end(self._run_on_line(op))
        return await self._run_on_line(op)

    def _check_connected(self) -> None:
        """``LinkDown`` when the port is not open (requests fail at once, never hang)."""
        if self._stream is None:
            raise LinkDown(f"link {self.name} is down: {self.last_error or 'not connected'}")

    async def _run_on_line(self, op: Callable[[], Awaitable[T]]) -> T:
        """Run ``op`` holding the line; release it however ``op`` ends."""
        try:
            return await self._run_op(op)
        finally:
            self._line.release()

    async def _run_op(self, op: Callable[[], Awaitable[T]]) -> T:
        """Run ``op`` (the line is held); a bug in it fails the caller with ``LinkError``, the link lives on."""
        self._check_connected()
        try:
            return await op()
        except (GatewayError, asyncio.CancelledError):
            raise
        except Exception as exc:  # a bug: fail the caller, keep the link alive
            log.exception("link %s: unexpected error", self.name)
            raise LinkError(f"link {self.name}: internal error: {exc!r}") from exc

    @contextlib.asynccontextmanager
    async def write_session(self) -> AsyncIterator[LineLease]:
        """Hold the line for a run of writes: requests given the lease it yields run on it at once.

        The session takes the line at write priority and keeps it from one write to the next,
        so queued writes go ahead of polls; but after ``write_burst`` transactions in a row it
        lets waiting poll transactions have the line (``poll_burst`` of them, fewer if the poller
        stops asking), so the data age stays bounded under any write load: writes take at most
        ``write_burst * write / (write_burst * write + poll_burst * poll)`` of the line time.  A
        write is never interrupted: the line changes hands only between two.  The lease's
        ``extend_burst`` lets the next write follow the burst before the polls it owes.
        """
        self._check_connected()
        lease = _HeldLine(self)
        await self._line.acquire(int(Priority.WRITE))
        lease.held = True
        try:
            yield lease
        finally:
            lease.open = False
            if lease.held:
                lease.held = False
                self._line.release()

    def _own(self, line: LineLease) -> _HeldLine:
        """``line`` as a lease of this driver's open write session; ``LocalError`` for any other."""
        if not (isinstance(line, _HeldLine) and line.driver is self and line.open):
            raise LocalError(f"link {self.name}: a request on a line lease that is not of this link's open "
                             "write session: nothing sent")
        return line

    async def _run_held(self, lease: _HeldLine, op: Callable[[], Awaitable[T]]) -> T:
        """Run ``op`` in the write session of ``lease``: the burst accounting (:meth:`write_session`)."""
        limit = self.write_burst + lease.extend
        lease.extend = False
        if lease.held and lease.writes >= limit and self._line.waiting:
            owed = -(-self.poll_burst * lease.writes // self.write_burst)
            lease.held = False
            lease.writes = 0
            target = self._line.grants + owed
            self._line.release()  # to the waiting poll
            # Let the poller's next requests have the line too, as many as the writes owe; the
            # last one's release hands the line back here (queued at write priority meanwhile).
            await self._line.wait_grants(target)
        if not lease.held:
            self._check_connected()
            await self._line.acquire(int(Priority.WRITE))  # LinkDown when the link fails meanwhile
            lease.held = True
        lease.writes += 1
        return await self._run_op(op)

    def send(self, data: bytes) -> None:
        """Write bytes to the line (from inside an ``op``)."""
        stream = self._stream
        if stream is None:
            raise LinkDown(f"link {self.name} is down")
        self.counters.bytes_sent += len(data)
        stream.write(data)

    # --- the core's timer -------------------------------------------------------------------

    def follow_deadline(self, deadline: float | None) -> None:
        """Keep the one timer of the protocol core at ``deadline`` (loop time; None: no timer).

        A driver calls it with ``core.next_deadline()`` after each step of its core; when the
        deadline comes (the port still open), :meth:`on_deadline` runs.
        """
        timer = self._timer
        if timer is not None:
            if deadline is not None and timer.when() == deadline:
                return
            timer.cancel()
            self._timer = None
        if deadline is not None and self.connected:
            self._timer = asyncio.get_running_loop().call_at(deadline, self._deadline_reached)

    def _deadline_reached(self) -> None:
        self._timer = None
        if self.connected:
            self.on_deadline(asyncio.get_running_loop().time())

    # --- protocol hooks ---------------------------------------------------------------------

    def on_deadline(self, now: float) -> None:
        """The deadline given to :meth:`follow_deadline` has come: ``core.handle_timeout(now)`` and
        act on what the core does then.  A driver whose core has no timers never gets here."""

    @abstractmethod
    def on_connect(self) -> None:
        """A new stream is open: reset the protocol state (e.g. message IDs)."""

    @abstractmethod
    def data_received(self, data: bytes) -> None:
        """Bytes from the controller."""

    @abstractmethod
    def abort(self, exc: GatewayError) -> None:
        """The link is gone: make the request on the line (waiting for an answer) fail with ``exc``."""


def retrieve_outcome(future: asyncio.Future[Any]) -> None:
    """Retrieve a future's outcome, so one whose caller gave up logs no 'exception was never retrieved'.

    A done callback (``future.add_done_callback(retrieve_outcome)``).
    """
    if not future.cancelled():
        future.exception()


async def run_to_the_end(work: Awaitable[T]) -> T:
    """Await ``work`` in a task of its own, shielded: it goes on to its end even when the caller is
    cancelled (a write on the line reaches its verdict), and its outcome is retrieved either way."""
    task = asyncio.ensure_future(work)
    task.add_done_callback(retrieve_outcome)
    return await asyncio.shield(task)


def timeout_error(name: str, what: str, seconds: float, tries: int) -> LinkTimeout:
    return LinkTimeout(f"link {name}: no valid answer to {what} within {format_seconds(seconds)} s after {tries} tries")
