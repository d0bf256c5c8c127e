"""Which block of a read plan to read next: deadlines and demand, sans-I/O (the caller passes ``now``).

The rule (``docs/guide/freshness.md`` states it for users):

* every block has its class period ``P`` (``fast_interval`` or ``slow_interval``) and a
  background period ``B = max(P, background_interval)``;
* a block is *demanded* for ``demand_hold`` seconds after a client read it (:meth:`Schedule.demand`);
* a block is *urgent* once ``P`` has passed since its last read when it is demanded, or once ``B``
  has passed when it is not; its deadline is then that time (last read + ``P`` or + ``B``);
* a block nobody demands is *wanted* once ``P`` has passed: it is read when nothing is urgent;
* the next read is: a bumped block (a client waits for it, :meth:`Schedule.bump`; not the block
  whose read is on the line: the client waits for that read), first bumped first; else the urgent
  block with the earliest deadline, unless a *read ahead* goes first (:meth:`Schedule._read_ahead`:
  a demanded block of a periodic class, read a little early while the continuous block it goes
  before is still young); else the wanted block with the earliest deadline; else nothing until
  :meth:`Schedule.next_due`;
* a block's first read after start or a loss sets its next due time at a share of ``P`` (its place
  in its class, 1/k .. k/k), not at ``P``: blocks read in one burst then come due spread over ``P``,
  not as one burst that would hold every other block up for as long as it takes to read them all.

So when the line has room every block is read at its class period (the fast class continuously
when ``fast_interval`` is 0); when it has not, what clients read goes first and every other block
is still read within ``B`` plus one read of every block (:meth:`Schedule.age_bound`): earliest
deadline first lets a block be overtaken by each other block at most once, and a read ahead
overtakes only a block younger than 70 % of its stale limit.  At start
(:meth:`Schedule.begin`) every block counts as read one class period ago: bumped and demanded
blocks first, then the fast class, then the slow one; a block nobody reads is read when the line
has room, and in any case first between ``B / 2`` and ``3 B / 2`` after start (spread evenly),
then within ``B``.  After a loss (:meth:`Schedule.lost`) the order goes on where it was, except
that a demanded block due later is due at once: no value read before a loss is served after it.

A failed read counts as a read for the order (the block goes to the back, it does not block the
line) but not for freshness, except for a demanded block whose value is still served: it is due
again one transaction (the mean measured) after the failure, as long as that comes before its
value's stale limit (:meth:`Schedule._retry`).  Its deadline is then later than every block's
already urgent, so it overtakes none of them and the age bound holds; but it is tried again
before its value goes stale, not a whole ``P`` later: with ``stale_after`` below ``P`` a read that
failed once would otherwise leave the block unserved for ``P - stale_after`` (a client reading 31
such blocks every second on a line failing 4 reads in 10 got data in under half of its reads:
``bench/schedule_faults.py``).  Its value gone stale, it goes to the back (a block that keeps
failing is tried at most until then, one transaction's time at least between two tries; a
client's read bumps it).

Each block's *stale limit* (the largest age at which it is served) is ``stale_after`` plus its
period as planned when it was read: ``P`` when demanded, ``B`` when not (:attr:`Schedule.max_age`,
shared with the image).  The schedule also measures what it achieves: the time of a transaction,
the share of the time the line spends reading, and the refresh period of each class and of the
demanded set (:meth:`Schedule.budget`).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Sequence
from typing import Final

from gateway.frozen import frozen
from gateway.modbus.mapping import Scan, Table

__all__ = [
    "DEFAULT_BACKGROUND_INTERVAL",
    "DEFAULT_DEMAND_HOLD",
    "DEFAULT_READ_WAIT",
    "MAX_READ_WAIT",
    "NEVER",
    "Budget",
    "DemandLog",
    "Schedule",
]

#: ``demand_hold``: a block stays demanded this many seconds after a client read it (longer than the
#: 1-30 s between two polls of a SCADA screen or a historian, so a polled block stays demanded).
DEFAULT_DEMAND_HOLD: Final = 60.0
#: ``background_interval``: blocks nobody reads are refreshed at least this often (``docs/guide/freshness.md``:
#: 56 blocks nobody reads on an SLC 150 cost 56 / 65 s = 0.9 of the 11 transactions/s of a 9600-baud line).
DEFAULT_BACKGROUND_INTERVAL: Final = 60.0
#: ``read_wait``: a read of data not yet read or stale may wait this long for its block (well
#: under the 1-3 s a SCADA client waits for an answer).
DEFAULT_READ_WAIT: Final = 0.5
#: The largest ``read_wait`` the config accepts.
MAX_READ_WAIT: Final = 5.0

#: A loop time before every other: the time of what has not happened yet (a block never read,
#: never due); the cache's and the images' stamps start at it too.
NEVER: Final = -math.inf
#: Seconds over which the line's use is measured (the last full window is shown).
USE_WINDOW: Final = 10.0
#: Weight of the newest transaction in the mean transaction time.
_EWMA: Final = 0.1
#: Spreads the first background reads (``begin``): ``k * _GOLDEN mod 1`` for k = 1, 2, ... places any
#: run of consecutive blocks evenly over the interval, so the blocks nobody reads, wherever they sit
#: in the plan, do not come due as one burst (then or any ``B`` later).
_GOLDEN: Final = (math.sqrt(5.0) - 1.0) / 2.0
#: Read ahead (``next``): a demanded block of a periodic class may go before a block read continuously
#: while that one's value is younger than this share of its stale limit (the rest, 30 %, absorbs the
#: spread of answer times), and only within half its period of coming due.
READ_AHEAD_AGE: Final = 0.7
READ_AHEAD_DUE: Final = 0.5


@frozen
class Budget:
    """What the schedule achieves at one moment (seconds; None: not known yet)."""

    blocks: int
    demanded: int
    transaction_time: float | None  #: mean seconds of a read transaction
    line_use: float | None  #: share of the last window the line spent reading
    refresh: dict[str, float | None]  #: achieved refresh period of "fast", "slow", "demanded", "all"
    age_bound: dict[str, float | None]  #: the bound on a block's age, per class and "demanded"


class DemandLog:
    """Requests read from the image since the last fold: noting one costs one dict store.

    Reads are answered inside the Modbus server's ``data_received``; each stores its request in
    ``keys`` and the poller folds the keys into block demand before each read.
    """

    __slots__ = ("keys",)

    def __init__(self) -> None:
        #: (table, address, count) -> the loop time of the last read
        self.keys: dict[tuple[Table, int, int], float] = {}

    def take(self) -> dict[tuple[Table, int, int], float]:
        """The keys noted since the last call, and when each was last noted."""
        keys, self.keys = self.keys, {}
        return keys


class Schedule:
    """The read order of one plan's blocks (module docstring)."""

    def __init__(
        self,
        scans: Sequence[Scan],
        *,
        fast_interval: float,
        slow_interval: float,
        stale_after: float,
        demand_hold: float = DEFAULT_DEMAND_HOLD,
        background_interval: float = DEFAULT_BACKGROUND_INTERVAL,
    ) -> None:
        periods = {Scan.FAST: fast_interval, Scan.SLOW: slow_interval}
        self.scans = list(scans)
        n = len(self.scans)
        self.stale_after = stale_after
        self.demand_hold = demand_hold
        #: per block: its class period P and its background period B
        self.period = [periods[scan] for scan in self.scans]
        self.background = [max(p, background_interval) for p in self.period]
        #: per block: when it is wanted again (its last read attempt plus P: the order), and the
        #: loop time of its last read (freshness)
        self.due = [NEVER] * n
        self.read_at = [NEVER] * n
        #: per block: the time its background period counts from (its last try, or its share of
        #: the first B at start)
        self.since = [NEVER] * n
        #: the block whose read is on the line, and its times before (:meth:`untry`)
        self._before = (-1, NEVER, NEVER)
        #: the block whose read is on the line (-1: none): a bump does not read it a second time
        self.on_line = -1
        #: per block: seconds between its last two reads (NaN: fewer than two since start or a loss)
        self.interval = [math.nan] * n
        #: per block: demanded until this loop time
        self.demanded_until = [NEVER] * n
        #: per block: not read before this loop time (:meth:`hold`)
        self.held_until = [NEVER] * n
        #: per block: the largest age at which it is served (shared with the image)
        self.max_age = [stale_after + p for p in self.period]
        #: per block: the stale limit its current value was read with
        self._stamped = list(self.max_age)
        #: blocks a waiting read asked for, first asked first
        self.bumped: dict[int, None] = {}
        #: reads that came after the block's stale limit (the line could not keep up)
        self.late_reads = 0
        self._tx_time = math.nan
        self._window_start = NEVER
        self._window_busy = 0.0
        self._line_use = math.nan
        #: per block: the share of its class period its first refresh comes after (its place in its class,
        #: 1/k .. k/k): blocks read together at start or after a loss come due spread over P, not as one
        #: burst that would hold every other block up for as long as it takes to read them all
        self._phase = [1.0] * n
        for period in set(self.period):
            members = [i for i in range(n) if self.period[i] == period]
            for place, i in enumerate(members):
                self._phase[i] = (place + 1) / len(members)
        self._tie = sorted(range(n), key=lambda i: (self.period[i], i))
        #: per block: its place among ties (blocks never read): the fast class first, then the plan's order
        self._rank = [0] * n
        for place, index in enumerate(self._tie):
            self._rank[index] = place
        #: heaps of (urgent time, 1 if not demanded, rank, block, version) and (wanted time, rank,
        #: block, version); an entry whose version is not the block's is stale
        self._version = [0] * n
        self._heap_cap = 2 * n + 16
        self._urgent: list[tuple[float, int, int, int, int]] = []
        self._wanted: list[tuple[float, int, int, int]] = []
        #: (due, rank, block, version) of the blocks of periodic classes, for reading ahead; an entry
        #: of a block nobody demands is dropped when it surfaces (:meth:`demand` pushes it again)
        self._ahead: list[tuple[float, int, int, int]] = []
        self._rebuild(NEVER)

    # --- inputs -----------------------------------------------------------------------------

    def begin(self, now: float) -> None:
        """The poller starts at ``now``: a block never read is wanted at once (as if read one class
        period ago; the fast class first) and urgent at once when demanded; the ones nobody reads
        get urgent spread evenly from ``B / 2`` to ``3 B / 2`` after ``now``: the first ``B / 2``
        leaves the line to the blocks clients wait for at start, and spread over a whole ``B`` they
        stay spread when each comes due again ``B`` after its read."""
        due, background = self.due, self.background
        never = [i for i in self._tie if due[i] == NEVER]
        for k, i in enumerate(never):
            due[i] = now
            self.since[i] = now - background[i] / 2 + background[i] * (((k + 1) * _GOLDEN) % 1.0)
        self._rebuild(now)

    def demand(self, blocks: Iterable[int], now: float) -> None:
        """A client read ``blocks`` at ``now``: they are demanded for ``demand_hold`` seconds."""
        until = now + self.demand_hold
        demanded = self.demanded_until
        for block in blocks:
            if demanded[block] < until:
                newly = demanded[block] <= now
                demanded[block] = until
                if newly:
                    self._push(block, now)  # urgent sooner now

    def bump(self, blocks: Iterable[int]) -> None:
        """A client waits for ``blocks``: read them before anything else, first asked first; not the
        block on the line (its read, under way, is the one the client waits for)."""
        for block in blocks:
            if block != self.on_line:
                self.bumped.setdefault(block, None)

    def started(self, block: int, now: float) -> None:
        """The read of ``block`` goes on the line: it goes to the back of the order; its stale limit
        is set from its period as planned now (the image stamps the read with it)."""
        self._before = (block, self.due[block], self.since[block])
        self.on_line = block
        first = self.read_at[block] == NEVER  # its first read since start or a loss: due spread over P
        self.due[block] = now + self.period[block] * (self._phase[block] if first else 1.0)
        self.since[block] = now
        self._push(block, now)
        self.bumped.pop(block, None)
        self.max_age[block] = self._limit_now(block, now)

    def done(self, block: int, started: float, now: float, ok: bool) -> bool:
        """The read of ``block`` that started at ``started`` ended at ``now`` (``ok``: data stored).

        True when it was late: its previous value had passed the stale limit it was read with.
        """
        self.on_line = -1
        elapsed = max(0.0, now - started)
        self._tx_time = elapsed if math.isnan(self._tx_time) else self._tx_time + _EWMA * (elapsed - self._tx_time)
        self._busy(started, now)
        if not ok:
            self._retry(block, now)
            return False
        last = self.read_at[block]
        late = False
        if last != NEVER:
            self.interval[block] = now - last
            late = now - last > self._stamped[block]
            self.late_reads += late
        self.read_at[block] = now
        self._stamped[block] = self.max_age[block]
        return late

    def _retry(self, block: int, now: float) -> None:
        """The read of ``block`` failed at ``now``: a demanded block whose value is still served is due
        again one transaction later (not a whole period: its value would go stale first), while that
        comes before its value goes stale (module docstring)."""
        if self.demanded_until[block] <= now or self.read_at[block] == NEVER:
            return
        retry = now + (0.0 if math.isnan(self._tx_time) else self._tx_time)
        if retry < self.read_at[block] + self._stamped[block] and retry < self.due[block]:
            self.due[block] = retry
            self._push(block, now)

    def lost(self, now: float) -> None:
        """The link was lost at ``now``: intervals restart (an outage is not a refresh period), and no
        value read before is served until its block is read again (``BlockCache.expire_before``), so a
        demanded block due later is due at ``now`` (the blocks a client reads are read again first)."""
        n = len(self.interval)
        self.interval = [math.nan] * n
        self.read_at = [NEVER] * n
        for block, until in enumerate(self.demanded_until):
            if until > now and self.due[block] > now:
                self.due[block] = now
                self._push(block, now)

    def _busy(self, started: float, now: float) -> None:
        if self._window_start == NEVER:
            self._window_start = started
        self._window_busy += now - started
        span = now - self._window_start
        if span >= USE_WINDOW:
            self._line_use = min(1.0, self._window_busy / span)
            self._window_start, self._window_busy = now, 0.0

    # --- the order --------------------------------------------------------------------------

    def next(self, now: float) -> int | None:
        """The block to read now (module docstring), or None: nothing is due before :meth:`next_due`.

        Ties (blocks never read) go to a demanded block first, then in the order of ``_rank``.
        Two heaps, of the urgent times and of the wanted times, with stale entries dropped as they
        come to the top: O(log n) a pick, not a look at every block.
        """
        if self.bumped:
            return next(iter(self.bumped))
        top = self._top_urgent(now)
        if top is not None and top[0] <= now:
            ahead = self._read_ahead(top[3], now)
            return top[3] if ahead is None else ahead
        wanted = self._top_wanted()
        if wanted is not None and wanted[0] <= now:
            return wanted[2]
        return None

    def _read_ahead(self, block: int, now: float) -> int | None:
        """The demanded periodic block to read before ``block``, the most urgent block, or None.

        Only when ``block`` is read continuously (period 0) and its value is younger than
        ``READ_AHEAD_AGE`` of its stale limit: the demanded block of a periodic class that comes due
        first, if it comes due within ``READ_AHEAD_DUE`` of its period, has been read before and is
        not held.  A continuous class takes every read nothing else is urgent for; without this, the
        periodic blocks read together at start would be read at the last moment together for ever,
        and the continuous class would age towards its stale limit each time they come due.  Read
        ahead while the continuous class has time to spare, they spread over the line.
        """
        last = self.read_at[block]
        if self.period[block] or last == NEVER or now - last >= READ_AHEAD_AGE * self._limit_now(block, now):
            return None
        heap, versions, demanded = self._ahead, self._version, self.demanded_until
        while heap and (heap[0][3] != versions[heap[0][2]] or demanded[heap[0][2]] <= now):
            heapq.heappop(heap)
        if not heap:
            return None
        due, _rank, candidate, _version = heap[0]
        if (due - now > READ_AHEAD_DUE * self.period[candidate] or self.held_until[candidate] > now
                or self.read_at[candidate] == NEVER):  # a first read keeps its place in the start order
            return None
        return candidate

    def _limit_now(self, block: int, now: float) -> float:
        """The stale limit ``block`` would be read with at ``now``: ``stale_after`` plus its period as
        planned now (``P`` when demanded, ``B`` when not)."""
        demanded = self.demanded_until[block] > now
        return self.stale_after + (self.period[block] if demanded else self.background[block])

    def _urgent_key(self, block: int, now: float) -> tuple[float, int]:
        """(the time ``block`` is urgent, 0 if demanded else 1) at ``now``."""
        if self.demanded_until[block] > now:
            return self.due[block], 0
        return self.since[block] + self.background[block], 1

    def _push(self, block: int, now: float) -> None:
        """``block``'s times changed: new heap entries (the old ones are dropped when they surface)."""
        version = self._version[block] = self._version[block] + 1
        rank = self._rank[block]
        urgent, demanded = self._urgent_key(block, now)
        heapq.heappush(self._urgent, (urgent, demanded, rank, block, version))
        heapq.heappush(self._wanted, (self.due[block], rank, block, version))
        if self.period[block]:
            heapq.heappush(self._ahead, (self.due[block], rank, block, version))
        if max(len(self._urgent), len(self._wanted), len(self._ahead)) > self._heap_cap:
            self._rebuild(now)  # drop the stale entries that have not surfaced (bounded memory)

    def _rebuild(self, now: float) -> None:
        self._urgent = []
        self._wanted = []
        self._ahead = []
        for block in range(len(self.scans)):
            urgent, demanded = self._urgent_key(block, now)
            rank, version = self._rank[block], self._version[block]
            self._urgent.append((urgent, demanded, rank, block, version))
            self._wanted.append((self.due[block], rank, block, version))
            if self.period[block]:
                self._ahead.append((self.due[block], rank, block, version))
        heapq.heapify(self._urgent)
        heapq.heapify(self._wanted)
        heapq.heapify(self._ahead)

    def _top_urgent(self, now: float) -> tuple[float, int, int, int, int] | None:
        heap, versions = self._urgent, self._version
        while heap:
            entry = heap[0]
            urgent, demanded, rank, block, version = entry
            if version != versions[block]:
                heapq.heappop(heap)
                continue
            key = self._urgent_key(block, now)
            if key != (urgent, demanded):  # its demand ran out: urgent later
                heapq.heapreplace(heap, (*key, rank, block, version))
                continue
            return entry
        return None

    def _top_wanted(self) -> tuple[float, int, int, int] | None:
        heap, versions = self._wanted, self._version
        while heap and heap[0][3] != versions[heap[0][2]]:
            heapq.heappop(heap)
        return heap[0] if heap else None

    def is_urgent(self, block: int, now: float) -> bool:
        """Whether ``block`` is bumped or urgent at ``now`` (not only wanted)."""
        if block in self.bumped:
            return True
        if self.demanded_until[block] > now:
            return self.due[block] <= now
        return self.since[block] + self.background[block] <= now

    def urgent_at(self, block: int) -> float:
        """When ``block`` gets urgent if nobody demands it (its background period passed)."""
        return self.since[block] + self.background[block]

    def hold(self, block: int, until: float) -> None:
        """Do not read ``block`` again before ``until`` (a block the controller refuses)."""
        self.due[block] = self.held_until[block] = until
        self.since[block] = until - self.period[block]
        self._push(block, until)

    def untry(self, block: int, now: float) -> None:
        """The read of ``block`` never reached the controller (the link was lost): its place back."""
        before, due, since = self._before
        self.on_line = -1
        if before == block:
            self.due[block], self.since[block] = due, since
            self._push(block, now)

    def next_due(self, now: float) -> float:
        """The loop time the next block falls due (``inf``: no blocks); at most ``now`` if one is due."""
        if self.bumped:
            return now
        wanted = self._top_wanted()
        return math.inf if wanted is None else wanted[0]

    # --- what is achieved -------------------------------------------------------------------

    def demanded(self, now: float) -> list[int]:
        return [i for i, until in enumerate(self.demanded_until) if until > now]

    def refresh_period(self, blocks: Iterable[int]) -> float | None:
        """The longest of the blocks' last refresh intervals (None: none measured yet)."""
        intervals = [self.interval[i] for i in blocks]
        known = [x for x in intervals if not math.isnan(x)]
        return max(known) if known else None

    def age_bound(self, blocks: Iterable[int], now: float) -> float | None:
        """The largest age a read of ``blocks`` is due at, plus one read of every block (the most an
        earliest-deadline-first order makes it wait); None before a transaction time is known."""
        if math.isnan(self._tx_time):
            return None
        round_time = len(self.scans) * self._tx_time
        demanded = self.demanded_until
        periods = [self.period[i] if demanded[i] > now else self.background[i] for i in blocks]
        return max(periods) + round_time if periods else None

    def budget(self, now: float) -> Budget:
        groups: dict[str, list[int]] = {
            "fast": [i for i, s in enumerate(self.scans) if s is Scan.FAST],
            "slow": [i for i, s in enumerate(self.scans) if s is Scan.SLOW],
            "demanded": self.demanded(now),
            "all": list(range(len(self.scans))),
        }
        return Budget(
            blocks=len(self.scans),
            demanded=len(groups["demanded"]),
            transaction_time=None if math.isnan(self._tx_time) else self._tx_time,
            line_use=None if math.isnan(self._line_use) else self._line_use,
            refresh={name: self.refresh_period(blocks) for name, blocks in groups.items()},
            age_bound={name: self.age_bound(blocks, now) for name, blocks in groups.items() if name != "all"},
        )
