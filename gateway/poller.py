"""Per link: read the plan's blocks in the order of its schedule (``gateway.schedule``), one at a time.

The schedule says which block is next (a block a waiting read asked for, then the urgent block
with the earliest deadline, then a wanted one; ``docs/guide/freshness.md``); the poller is the
loop around it: it folds the reads clients made (``DemandLog``) into demand before each pick,
reads the block through the driver, stores it in the cache, and sleeps only when nothing is due
(never when a class is read continuously).  Pollers of units that share one line (the stations
of a half-duplex line) share a :class:`LineShare`: a read that is only wanted waits while another
poller of the line has an urgent one, so one station's background does not take the line from
another's demanded blocks.

Every block is one request on the driver's queue at poll priority, so a write waits at most
for the one poll transaction already on the line.  A block that fails keeps its last value
in the cache and ages; it goes to the back of the order (a failure never holds the line), a
demanded one whose value is still served is tried again one transaction later (``Schedule._retry``).  A
block the controller refuses is tried again no sooner than ``min(slow_interval, 5 s)``.  While
the link is down (the driver's own verdict: several failures in a row, not one) the poller probes
it with one read every ``down_wait`` instead of spinning; the block a lost link interrupted is
read first when it comes back, then the demanded blocks (``Schedule.lost``).  Values read before a
loss are not served after it until their block is read again (``BlockCache.expire_before``): the
controller may have been replaced.

A *round* is as many read attempts as the plan has blocks (``scans`` counts them); a round also
ends when the link is lost.

Data availability (Home Assistant's ``DataUpdateCoordinator`` is the model): ``available`` is
whether the last round of polls read any block (False until the first one does),
``last_success`` the loop time of the last block read, ``last_error`` the last failure (kept
after recovery, for diagnosis).  A round that reads no block and fails at least one makes the
data unavailable; the first block read makes it available again.  Each change is logged once,
never per retry, and never twice with the driver's words:

* the link's own state is the driver's to log (``link X: down: ...`` after several failures in
  a row, ``link X: up`` at the first answer; ``gateway.line_driver``).  When the polls fail
  because of the link (``LinkError``: down, no answer), the poller's change is logged at DEBUG
  only: the driver's line is the one message the operator needs, and one unanswered round on
  a noisy line (not yet a link down) is no news for an operator;
* when the controller answers but no data comes (every read refused, as in program mode, or
  answered with bytes that break the protocol), the driver says the link is up, so only the
  poller can tell: ``link X: unavailable: <error>`` at WARNING once, and ``link X: back online``
  at INFO once the data comes back (also after a link loss in between).

When the line cannot refresh blocks within their stale limit (``stale_after`` plus their period)
in three rounds in a row, the poller says so once, at WARNING, with the refresh period it
achieves and what to change (:attr:`Poller.behind` keeps the words for the status page).

``stagger`` delays the first poll so that links do not all start, and then poll every
``fast_interval``, at the same instant: by default a share of ``fast_interval`` (at most
``MAX_STAGGER``) taken from the link's name, the same on every start; the application may pass
its own (e.g. link i of n: ``i / n`` of the interval), 0 to start at once.
"""

from __future__ import annotations

import asyncio
import logging
import math
import zlib
from collections.abc import Awaitable, Callable, Iterable, Sequence
from typing import Final

from gateway.cache import BlockCache
from gateway.errors import ControllerRefused, GatewayError, LinkDown, LinkError
from gateway.modbus.mapping import Block, Table
from gateway.schedule import DemandLog, Schedule

__all__ = ["MAX_STAGGER", "LineShare", "Poller", "default_stagger"]

log = logging.getLogger("gateway.poller")

ReadBlock = Callable[[Block], Awaitable[bytes]]

#: Seconds before a block the controller refused is tried again (at most the slow interval).
_REFUSED_RETRY = 5.0
#: Seconds the status page shows that the line could not keep up, after it was last seen.
_BEHIND_SHOWN = 60.0
#: Rounds in a row with a late read before the line is said not to keep up (not a start's burst).
_LATE_ROUNDS = 3
#: The most request keys whose blocks are remembered (a client scanning addresses cannot grow it).
_MAX_KEYS = 4096
#: Seconds a poller whose next read is only wanted waits at most for another's urgent reads to end.
_SHARE_WAIT = 1.0
#: Refused blocks logged one by one (program mode refuses every read: one line is enough).
_REFUSALS_LOGGED = 3
#: Seconds: the longest default start-up delay (a slow fast_interval must not hold the first data).
MAX_STAGGER: Final = 1.0


def default_stagger(name: str, fast_interval: float) -> float:
    """A link's start-up delay: a share of ``fast_interval`` (at most ``MAX_STAGGER``) from its name.

    CRC-32 of the name, not ``hash()`` (salted per process): the same delay on every start.
    """
    share = zlib.crc32(name.encode("utf-8")) / 2**32
    return share * min(max(fast_interval, 0.0), MAX_STAGGER)




class LineShare:
    """The pollers of the units that share one line (module docstring): those whose next read is urgent.

    A poller marks itself when it picks an urgent read and unmarks when it picks one that is only
    wanted, sleeps or stops; a wanted read waits while another poller is marked.
    """

    def __init__(self) -> None:
        self._urgent: set[int] = set()
        self._calm: asyncio.Event | None = None

    def _event(self) -> asyncio.Event:
        if self._calm is None:
            self._calm = asyncio.Event()
            self._calm.set()
        return self._calm

    def mark(self, poller: object, urgent: bool) -> None:
        key = id(poller)
        if urgent:
            self._urgent.add(key)
            self._event().clear()
        else:
            self._urgent.discard(key)
            if not self._urgent:
                self._event().set()

    def others(self, poller: object) -> bool:
        """Whether another poller of the line has urgent reads."""
        return bool(self._urgent) and self._urgent != {id(poller)}

    async def calm(self, seconds: float) -> None:
        """Until no poller of the line has urgent reads, at most ``seconds``."""
        if self._urgent:
            try:
                async with asyncio.timeout(max(0.0, seconds)):
                    await self._event().wait()
            except TimeoutError:
                pass


class Poller:
    """Reads a plan's blocks in the order of its :class:`~gateway.schedule.Schedule` (module docstring)."""

    def __init__(
        self,
        name: str,
        blocks: Sequence[Block],
        cache: BlockCache,
        read_block: ReadBlock,
        *,
        fast_interval: float = 0.0,
        slow_interval: float = 10.0,
        down_wait: float = 0.2,
        stagger: float | None = None,
        responding: Callable[[], bool] | None = None,
        ready: Callable[[], Awaitable[None]] | None = None,
        schedule: Schedule | None = None,
        demand: DemandLog | None = None,
        share: LineShare | None = None,
    ) -> None:
        self.name = name
        self.blocks = list(blocks)
        self.cache = cache
        self._read_block = read_block
        self.fast_interval = fast_interval
        self.slow_interval = slow_interval
        #: the read order; without one given, a schedule of the plan's classes and nothing served
        #: from an image (the stale limits are the unit's)
        self.schedule = schedule or Schedule([b.scan for b in self.blocks], fast_interval=fast_interval,
                                             slow_interval=slow_interval, stale_after=math.inf)
        self.fast = [i for i, scan in enumerate(self.schedule.scans) if scan.value == "fast"]
        self.slow = [i for i, scan in enumerate(self.schedule.scans) if scan.value == "slow"]
        #: the requests clients read, ``(table, address, count)``; the image knows their blocks
        self.demand = demand
        self._keys: dict[tuple[Table, int, int], tuple[int, ...]] = {}
        self._share = share
        self._down_wait = down_wait
        #: seconds before the first poll (module docstring)
        self.stagger = default_stagger(name, fast_interval) if stagger is None else max(0.0, stagger)
        self._responding = responding
        #: awaited before the first poll: the driver's first attempt to open its port (a poll before it
        #: would fail with "not connected", an error of nobody's)
        self._ready = ready
        self.scans = 0
        self.block_errors = 0
        #: reads that waited for their blocks (``read_wait``)
        self.read_waits = 0
        #: blocks the controller refuses to read (a file too short, program mode ...): the
        #: refusal and when it came; retried every min(slow_interval, 5 s), not every round
        self.refused: dict[int, tuple[ControllerRefused, float]] = {}
        #: the last round of polls read a block (False until the first one does)
        self.available = False
        #: loop time of the last block read, None before the first
        self.last_success: float | None = None
        #: the last failure of a block read (kept after recovery, for diagnosis)
        self.last_error: GatewayError | None = None
        #: loop time of ``last_error`` (the end of the round it came in), None before the first
        self.last_error_at: float | None = None
        #: changes of ``available`` (the first data included)
        self.availability_changes = 0
        #: the words of the last warning that the line cannot keep up, and when it was last true
        self.behind_text: str | None = None
        self._behind_at = -math.inf
        self._late_block = -1  # the last block read late in this round (-1: none)
        self._late_rounds = 0  # rounds in a row with a late read
        self._warned = False  # the current unavailability was logged at WARNING
        self._round_tries = 0  # read attempts in this round
        self._round_read = 0  # blocks read in this round
        self._round_error: GatewayError | None = None  # the last failure of this round
        self._lost_at: float | None = None  # loop time the link was lost, until a block is read again
        #: reads waiting for blocks: (the blocks not read yet, the future to resolve)
        self._waits: list[tuple[set[int], asyncio.Future[None]]] = []
        self._wake: asyncio.Event | None = None
        #: the loop runs (a read may wait for a block only then)
        self.running = False

    # --- what clients read ------------------------------------------------------------------

    def _fold(self, now: float) -> None:
        """Turn the requests clients read since the last pick into block demand."""
        images = self.cache.images
        if self.demand is None or images is None or not self.demand.keys:
            return
        keys = self._keys
        for key, when in self.demand.take().items():
            blocks = keys.get(key)
            if blocks is None:
                if len(keys) >= _MAX_KEYS:
                    keys.clear()
                table, address, count = key
                blocks = keys[key] = images.blocks_in(table, address, count)
            self.schedule.demand(blocks, when)

    def wait_for(self, blocks: Iterable[int]) -> asyncio.Future[None]:
        """Read ``blocks`` before anything else; the future is done when each was read or failed,
        or the link was lost."""
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        pending = set(blocks)
        self.read_waits += 1
        if not pending:
            future.set_result(None)
            return future
        self.schedule.bump(pending)
        self._waits.append((pending, future))
        if self._wake is not None:
            self._wake.set()
        return future

    def _answered(self, block: int | None) -> None:
        """Block ``block`` was read or failed (None: the link was lost: every wait ends)."""
        if not self._waits:
            return
        keep = []
        for pending, future in self._waits:
            if block is not None:
                pending.discard(block)
            if (block is None or not pending) and not future.done():
                future.set_result(None)
            elif not future.done():
                keep.append((pending, future))
        self._waits = keep

    @property
    def behind(self) -> str | None:
        """The warning that the line cannot keep up, while it holds (None: it keeps up)."""
        if self.behind_text is None or asyncio.get_running_loop().time() - self._behind_at > _BEHIND_SHOWN:
            return None
        return self.behind_text

    def _behind(self, block: int, now: float) -> None:
        """Reads came after their block's stale limit in ``_LATE_ROUNDS`` rounds in a row: say once
        what the line achieves and what to change (``block``: the last one late)."""
        schedule = self.schedule
        demanded = schedule.demanded_until[block] > now
        group = schedule.demanded(now) if demanded else range(len(self.blocks))
        period = schedule.refresh_period(group) or schedule.interval[block]
        what = f"{len(group)} demanded blocks" if demanded else f"{len(group)} blocks"
        fix = "raise stale_after, or read fewer addresses" if demanded else "raise stale_after, or map fewer addresses"
        text = (f"link {self.name} refreshes its {what} every {period:.1f} s; "
                f"stale_after is {schedule.stale_after:g} s: {fix}")
        self._behind_at = now
        if self.behind_text is None:
            log.warning("%s", text)
        self.behind_text = text

    # --- one read -----------------------------------------------------------------------------

    async def _read(self, index: int) -> bool:
        """Read block ``index``; False when the link is lost (or reported down)."""
        loop = asyncio.get_running_loop()
        schedule = self.schedule
        block = self.blocks[index]
        started = loop.time()
        schedule.started(index, started)
        try:
            data = await self._read_block(block)
        except LinkDown as exc:
            self._round_error = exc
            schedule.untry(index, loop.time())
            return False
        except ControllerRefused as exc:
            self._round_error = exc
            self.block_errors += 1
            if index not in self.refused and len(self.refused) < _REFUSALS_LOGGED:
                log.warning("link %s: the controller refuses to read %s: %s", self.name, block.label, exc)
            elif index not in self.refused and len(self.refused) == _REFUSALS_LOGGED:
                log.warning("link %s: more blocks refused; not logging each", self.name)
            now = loop.time()
            self.refused[index] = (exc, now)
            schedule.done(index, started, now, ok=False)
            schedule.hold(index, now + min(self.slow_interval, _REFUSED_RETRY))
            self._answered(index)
            return True
        except GatewayError as exc:
            self._round_error = exc
            self.block_errors += 1
            log.debug("link %s: block %s failed: %s", self.name, block.label, exc)
            schedule.done(index, started, loop.time(), ok=False)
            self._answered(index)
            # The driver reports the link down (several failures in a row): probe it with one
            # block every down_wait instead of waiting out the retries of every block.
            return self._responding is None or self._responding()
        if index in self.refused:
            del self.refused[index]
            log.info("link %s: %s is read again", self.name, block.label)
        now = loop.time()
        if self._lost_at is not None:
            # The first answer after a loss: what was read before it is not served any more.
            self.cache.expire_before(self._lost_at)
            self._lost_at = None
        late = schedule.done(index, started, now, ok=True)
        self.cache.store(index, data, now)
        self._answered(index)
        if late:
            self._late_block = index
        self._round_read += 1
        self.last_success = now
        if not self.available:
            self._went_available()
        return True

    # --- data availability (module docstring) -----------------------------------------------

    def _went_available(self) -> None:
        self.available = True
        self.availability_changes += 1
        if self._warned:
            log.info("link %s: back online", self.name)
        else:
            log.debug("link %s: data available", self.name)
        self._warned = False

    def _end_round(self) -> None:
        """After a round of polls: no block read and one failed -> unavailable (logged once)."""
        error, self._round_error = self._round_error, None
        read, self._round_read = self._round_read, 0
        self._round_tries = 0
        if error is None:
            return
        self.last_error = error
        self.last_error_at = asyncio.get_running_loop().time()
        if read:
            return
        changed = self.available or self.availability_changes == 0  # (the first round too)
        if changed:
            self.available = False
            self.availability_changes += 1
        if isinstance(error, LinkError):
            # The link's trouble: the driver logs it (down after several failures in a row).
            if changed:
                log.debug("link %s: unavailable: %s", self.name, error)
        elif not self._warned:
            log.warning("link %s: unavailable: %s (the controller answers, but no block of the map could "
                        "be read)", self.name, error)
            self._warned = True

    # --- the loop -----------------------------------------------------------------------------

    async def _sleep_until(self, when: float) -> None:
        """Sleep until loop time ``when``, or until a client waits for a block."""
        loop = asyncio.get_running_loop()
        if self._wake is None:
            self._wake = asyncio.Event()
        self._wake.clear()
        delay = when - loop.time()
        if delay <= 0 or self.schedule.bumped:
            return
        try:
            async with asyncio.timeout(delay if math.isfinite(delay) else None):
                await self._wake.wait()
        except TimeoutError:
            pass

    async def _wait_share(self, share: LineShare, seconds: float) -> None:
        """Until the other pollers of the line have no urgent reads, a client waits for a block of
        this one, or ``seconds`` passed."""
        if self._wake is None:
            self._wake = asyncio.Event()
        self._wake.clear()
        if self.schedule.bumped:
            return
        waits = {asyncio.ensure_future(share.calm(seconds)), asyncio.ensure_future(self._wake.wait())}
        try:
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for wait in waits:
                wait.cancel()

    async def run(self) -> None:
        self.running = True
        try:
            await self._run()
        finally:
            self.running = False
            if self._share is not None:
                self._share.mark(self, False)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        if self.stagger > 0:
            await asyncio.sleep(self.stagger)
        if self._ready is not None:
            await self._ready()
        schedule = self.schedule
        schedule.begin(loop.time())
        share = self._share
        rounds = max(1, len(self.blocks))
        while True:
            now = loop.time()
            self._fold(now)
            index = schedule.next(now)
            if share is not None:
                share.mark(self, index is not None and schedule.is_urgent(index, now))
                if index is not None and share.others(self) and not schedule.is_urgent(index, now):
                    # Only wanted: the line is the other stations' while they have urgent reads;
                    # wait at most until this one's own work gets urgent.
                    await self._wait_share(share, min(_SHARE_WAIT, schedule.urgent_at(index) - now))
                    continue
            if index is None:
                await self._sleep_until(schedule.next_due(now))
                continue
            ok = await self._read(index)
            self._round_tries += 1
            if not ok:
                self._end_round()
                if self._lost_at is None:
                    self._lost_at = loop.time()
                    schedule.lost(self._lost_at)
                self._answered(None)
                if share is not None:
                    share.mark(self, False)  # a station that does not answer holds no one up
                await asyncio.sleep(self._down_wait)
                continue
            if self._round_tries >= rounds:
                self._late_rounds = self._late_rounds + 1 if self._late_block >= 0 else 0
                if self._late_rounds >= _LATE_ROUNDS:
                    self._behind(self._late_block, loop.time())
                self._late_block = -1
                self._end_round()
                self.scans += 1
                await asyncio.sleep(0)  # let other links and the server run
