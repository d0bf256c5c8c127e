"""The one verdict on a unit's data: fresh or stale, and its link up, stale or down; sans-I/O.

Every face of the gateway reads this module's answers and decides nothing of its own: the Modbus
server (a value, or 0x0B), the status block (registers 1000, 1001 and 1011), ``/healthz``, the
status page, ``/metrics`` and Sparkplug (a value, or ``is_null`` with its ``Quality``; DDEATH).
``docs/guide/freshness.md`` states the rules for users; ``tests/test_freshness.py`` states them once
more, from the guide, and checks every face against them on random histories.

Inputs (nothing here reads a clock, a socket or a port: the caller passes ``now``):

* the *link state*: whether the controller answers, by the one up/down rule of every driver
  (``gateway.link_health.LinkHealth.available``: a few failures in a row, not one), and since when;
* the *schedule's limits*: per block, the largest age at which its value is served, set as the
  block's read goes on the line (``stale_after`` plus its period as planned then:
  ``gateway.schedule.Schedule.max_age``); ``inf`` for a unit that is not polled (its values do not
  age on their own);
* the *cache*: when each block was last read, and when the controller last answered.

**A block is fresh** at ``now`` when it was read at most its limit ago (:meth:`Freshness.deadline`,
the time the image stamps on its points), its value was not read before a link loss the link has
come back from (``BlockCache.expire_before``), and the controller is not *silent*: it has answered
a poll within the *silent limit* (``stale_after`` plus the shortest class period; a unit that is
not polled: ``stale_after`` since its peer was last heard).  No value outlives a silent controller
by more than ``stale_after``.

**A link** is, at ``now`` (:meth:`Freshness.verdict`):

* ``down`` when its link state says the controller does not answer;
* else ``stale`` when its *data age* (the age of the oldest fast-class value, 0 without a fast
  class; since its peer was last heard when not polled) is at or over its *stale limit*:
  ``stale_after`` plus the longest of the fast class's period and the refresh period the schedule
  achieves for it (the slow class's without a fast class): a healthy slow line is not stale, a
  silent one is;
* else ``up``.

``since`` is the loop time the link has been in that state (None: never known): down and up since
the link's last change, or, for up after stale, since the verdict first found it fresh again
(read times cannot tell when that was); stale since the oldest value passed the limit, or since the
link came up if that was later.

**Demand** (who reads, :class:`Source`): a read *serves* a client (Modbus, the status page's
register view: it counts as demand, ``gateway.schedule``, and the link's ``offline`` policy
applies to it) or the gateway's own faces *peek* (Sparkplug, the status page's summary, metrics:
no demand, and always the truth).  The ``offline`` policy (:class:`Offline`) says what a served
read of data that is not fresh gets: an exception (0x0B, the default), the last value read
(``hold``), or zero (``zero``); what is shown as stale stays stale on every face whatever the
policy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import Enum, StrEnum
from typing import TYPE_CHECKING, Final, Protocol

from gateway.frozen import frozen
from gateway.schedule import Schedule

if TYPE_CHECKING:
    from gateway.cache import BlockCache
    from gateway.image import Images

__all__ = ["OFFLINE_POLICIES", "Freshness", "LinkState", "LinkVerdict", "LinkView", "Offline", "Source"]


class LinkState(StrEnum):
    """A link's state, as every face shows it; its value is the status block's register 1011."""

    UP = "up"
    STALE = "stale"
    DOWN = "down"

    @property
    def number(self) -> int:
        """Register 1011 (``state``): 0 up, 1 stale, 2 down."""
        return _NUMBERS[self]


_NUMBERS: Final = {LinkState.UP: 0, LinkState.STALE: 1, LinkState.DOWN: 2}


class Source(Enum):
    """Who reads (module docstring): a client the gateway serves, or one of the gateway's own faces."""

    SERVE = "serve"  #: a client asked: counts as demand; the offline policy applies
    PEEK = "peek"  #: the gateway's own face: no demand, the truth


class Offline(StrEnum):
    """A link's ``offline`` policy: what a client's read of data that is not fresh gets."""

    EXCEPTION = "exception"  #: Modbus exception 0x0B (no value)
    HOLD = "hold"  #: the last value read (none read yet: 0x0B)
    ZERO = "zero"  #: 0 (and false for a bit)


#: the ``offline`` key's values, in the order the docs give them
OFFLINE_POLICIES: Final = tuple(policy.value for policy in Offline)


class LinkView(Protocol):
    """What the verdict takes of a link's state (``gateway.link_health.LinkHealth`` has it)."""

    @property
    def available(self) -> bool: ...

    @property
    def state_since(self) -> float | None: ...


@frozen
class LinkVerdict:
    """A link's state at one moment (module docstring)."""

    state: LinkState
    #: loop time it has been in ``state`` (None: not known)
    since: float | None
    #: data age: seconds since the oldest fast-class value was read (+inf: one never was)
    age: float
    #: the data age at and above which the link is stale
    limit: float

    @property
    def up(self) -> bool:
        """The controller answers (``link_up``): up or stale."""
        return self.state is not LinkState.DOWN

    @property
    def fresh(self) -> bool:
        """The link is up and its data younger than its limit."""
        return self.state is LinkState.UP


class Freshness:
    """The verdict of one unit (module docstring).

    ``schedule``: the polled unit's read order (None: not polled); ``link``: its link state.
    :meth:`watch` gives it the cache and images it judges once the unit has built them.
    """

    def __init__(self, *, stale_after: float, schedule: Schedule | None, link: LinkView, blocks: int) -> None:
        self.stale_after = stale_after
        self.schedule = schedule
        self.link = link
        #: per block: the largest age at which it is served (the schedule's limits; inf: not polled)
        self.limits: Sequence[float] = schedule.max_age if schedule is not None else [math.inf] * blocks
        #: the controller is silent after this long without an answer to a poll (the poller reads a
        #: block at least every shortest class period); a peer that is not polled, after stale_after
        self.silent_after = stale_after + min(schedule.period, default=0.0) if schedule is not None else stale_after
        #: the fast class (the slow one when the plan has no fast class): the data age's blocks
        self._age_blocks: list[int] = []
        if schedule is not None:
            self._age_blocks = [i for i, scan in enumerate(schedule.scans) if scan.value == "fast"] or list(
                range(len(schedule.scans)))
        self._cache: BlockCache | None = None
        self._images: Images | None = None
        #: the state of the last verdict, and since when the link has been fresh again after stale
        self._last: LinkState | None = None
        self._fresh_since: float | None = None

    def watch(self, cache: BlockCache, images: Images) -> None:
        """The unit's cache (read times) and images (each block's deadline) to judge."""
        self._cache = cache
        self._images = images

    @property
    def cache(self) -> BlockCache:
        if self._cache is None:
            raise RuntimeError("Freshness.watch was not called")
        return self._cache

    # --- blocks ---------------------------------------------------------------------------

    def deadline(self, block: int, read_at: float) -> float:
        """The loop time after which a value of ``block`` read at ``read_at`` is stale."""
        return read_at + self.limits[block]

    def silent(self, now: float) -> bool:
        """The controller has answered no poll (its peer was not heard) for the silent limit."""
        return now - self.cache.newest > self.silent_after

    def block_fresh(self, block: int, now: float) -> bool:
        """Whether the value of ``block`` is fresh at ``now`` (module docstring)."""
        images = self._images
        if images is None or self.silent(now):
            return False
        return images.block_deadline[block] >= now

    # --- the link -------------------------------------------------------------------------

    def data_age(self, now: float) -> float:
        """Seconds since the oldest fast-class value was read (0 without a fast class; not polled: since
        the peer was heard); +inf: never."""
        cache = self.cache
        if self.schedule is None:
            return max(0.0, now - cache.newest)
        return max(0.0, cache.oldest_fast_age(now))

    def stale_limit(self) -> float:
        """The data age at and above which the link is stale (module docstring)."""
        schedule = self.schedule
        if schedule is None:
            return self.stale_after
        blocks = self._age_blocks
        achieved = schedule.refresh_period(blocks) or 0.0
        return self.stale_after + max([achieved, *(schedule.period[i] for i in blocks)])

    def verdict(self, now: float) -> LinkVerdict:
        """The link's state at ``now`` (module docstring)."""
        link = self.link
        age = self.data_age(now)
        limit = self.stale_limit()
        since = link.state_since
        if not link.available:
            state = LinkState.DOWN
        elif age < limit:
            state = LinkState.UP
            if self._last is LinkState.STALE:
                self._fresh_since = now
            fresh = self._fresh_since
            if fresh is not None and (since is None or fresh > since):
                since = fresh
        else:
            state = LinkState.STALE
            if math.isfinite(age):
                crossed = now - (age - limit)
                since = crossed if since is None else max(since, crossed)
        self._last = state
        return LinkVerdict(state, since, age, limit)
