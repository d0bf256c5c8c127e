"""What a publishing pass hands to the subscriptions for one link, decided without asyncua: sans-I/O,
the caller passes ``now``.

:class:`LinkWatch` keeps, per link, which points have a monitored item (``alive``), what was last
published of each, and the bytes of each run of points (``gateway.opcua.points.PointRun``) the
last pass read; :meth:`LinkWatch.changes` is what changed since:

* a block stored or patched since the last pass (the unit's cache tells: :meth:`LinkWatch.stored`)
  is judged (its quality from the one verdict) and, when its quality is the same as at its last
  judgment, its runs compared with what the last pass read: one comparison a run, then a step per
  changed point (``PointRun.changed``), not a step per point;
* at a check pass (``check``: what ages without a store, links going down, values going stale),
  every monitored block is judged again; one whose quality did not change costs the judgment
  only (its bytes cannot have changed without a store);
* a block whose quality changed: every monitored point of it is compared with what was published.

A change is ``(point, code, value, read_at)``: the value is None when the code carries none, and
``read_at`` the loop time of the block's read (``now`` for a block never read; for the status
values, ``now``).  The monitored items' demand is noted per block (:class:`gateway.opcua.quality.DemandBook`).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from gateway.freshness import LinkState, LinkVerdict
from gateway.opcua.points import OpcPoint, point_runs, point_value, points_by_block
from gateway.opcua.quality import Code, DemandBook, Reading, point_quality
from gateway.schedule import NEVER
from gateway.unit import Unit

__all__ = ["Change", "LinkWatch"]

#: (point, status code, value or None, read time)
Change = tuple[int, Code, bool | int | float | None, float]


class LinkWatch:
    """One link's points as the publishing passes see them (module docstring)."""

    def __init__(self, unit: Unit[Any, Any], points: list[OpcPoint]) -> None:
        self.unit = unit
        self.points = points
        self.by_block = points_by_block(points)
        #: per block: its points as runs of consecutive addresses of one table, each read at once
        self.runs = {block: point_runs(points, members) for block, members in self.by_block.items()}
        #: per block: the (table, address, count) its monitored items' demand is noted as (its first run)
        self.demand_keys = {block: (runs[0].table, runs[0].first, runs[0].count) for block, runs in self.runs.items()}
        self.status_points = [i for i, point in enumerate(points) if point.block is None]
        self.book = DemandBook({i: point.block for i, point in enumerate(points) if point.block is not None})
        #: points with a monitored item (:meth:`watch`; a new item adds its point at once: :meth:`created`)
        self.alive: set[int] = set()
        #: the blocks of those points (None: a status value's)
        self.live_blocks: set[int | None] = set()
        #: blocks stored or patched since the last pass
        self.dirty: set[int] = set()
        #: per block: what its quality depended on at the last pass that judged it, and that quality
        self.judgments: dict[int, tuple[tuple[object, ...], Reading]] = {}
        #: per point with a monitored item: the (status code, value: its bytes; a status value) last published
        self.published: dict[int, tuple[Code, object]] = {}
        #: per run (block, its position): the bytes the last pass read of it
        self.run_bytes: dict[tuple[int, int], bytes] = {}
        #: the link's verdict at the last pass that took it
        self._verdict: LinkVerdict | None = None

    def stored(self, block: int, _now: float | None) -> None:
        """A listener of the unit's cache: ``block`` was stored or patched."""
        self.dirty.add(block)

    def watch(self, alive: Iterable[int], now: float) -> None:
        """The points that have a monitored item now: the others stop demanding, and a point that lost its
        items is forgotten (a new item of it starts from a Read)."""
        found = set(alive)
        if found == self.alive and len(self.book) == len(found):
            return
        for gone in self.alive - found:
            self.published.pop(gone, None)
        self.alive = found
        self.live_blocks = {self.points[index].block for index in found}
        self.book.settle(found, now)

    def created(self, index: int, interval: float, now: float) -> None:
        """A monitored item of point ``index`` was created, sampling every ``interval`` s; its first value
        came from a Read (asyncua's), not from a pass."""
        self.book.watch(index, interval, now)
        self.published.pop(index, None)
        self.alive.add(index)
        self.live_blocks.add(self.points[index].block)

    def note_demand(self, now: float) -> None:
        """Note the demand of the monitored items whose sampling interval has come round."""
        for block in self.book.due(now):
            self.unit.note_demand(*self.demand_keys[block])

    def changes(self, now: float, check: bool) -> list[Change]:
        """What changed of the monitored points since the last pass (module docstring)."""
        if not self.live_blocks:
            self.dirty.clear()  # nobody monitors this link's data: nothing to judge
            return []
        found: list[Change] = []
        if check:
            self._judge(self.live_blocks, now, True, found)
            if None in self.live_blocks:
                self._status(now, found)
        elif self.dirty:
            self._judge(self.dirty, now, False, found)
        self.dirty.clear()
        return found

    def _judge(self, blocks: Iterable[int | None], now: float, check: bool, found: list[Change]) -> None:
        """Judge ``blocks``; the link's verdict is taken at a check pass, and at a pass between them only while
        the link is down or not known yet (a store then may be its first answer): a link that goes down is
        shown so by the next check pass, one that answers again by the next pass."""
        unit, dirty, live, judgments = self.unit, self.dirty, self.live_blocks, self.judgments
        alive, images, stamps, published, run_bytes = self.alive, unit.images, unit.cache.stamps, self.published, \
            self.run_bytes
        verdict = self._verdict
        if check or verdict is None or verdict.state is LinkState.DOWN or verdict.since is None:
            verdict = self._verdict = unit.verdict(now)
        known = verdict.since is not None
        refused = unit.poller.refused if unit.poller is not None else {}
        for block in blocks:
            if block is None or block not in live:
                continue
            read_at = stamps[block]
            fresh = unit.freshness.block_fresh(block, now)
            key = (verdict.state is LinkState.DOWN, known, fresh, block in refused, read_at != NEVER)
            prior = judgments.get(block)
            judged = prior is not None and prior[0] == key
            if prior is not None and judged:
                if block not in dirty:
                    continue  # the same quality, the same bytes
                reading = prior[1]
            else:
                reading = point_quality(state=verdict.state, known=known, fresh=fresh, read=key[4], refused=key[3],
                                        offline=unit.offline)
                judgments[block] = (key, reading)
            carries, code = reading.carries_value, reading.code
            if judged and not carries:
                continue  # the same status, and it carries no value: nothing to show
            stamp = now if read_at == NEVER else read_at
            for position, run in enumerate(self.runs.get(block, ())):
                data = images.held(run.table, run.first, run.count, None)
                last = run_bytes.get((block, position))
                if judged and last == data:
                    continue
                run_bytes[(block, position)] = data
                members = run.members
                picked = run.changed(last, data) if judged and last is not None else range(len(members))
                for member in picked:
                    index, at, size = members[member]
                    if index not in alive:
                        continue
                    raw = (data[at // 8] >> at % 8 & 1).to_bytes(1, "little") if run.bits else data[at : at + size]
                    shown = (code, raw if carries else None)
                    if published.get(index) != shown:
                        published[index] = shown
                        found.append((index, code, point_value(self.points[index], raw) if carries else None, stamp))

    def _status(self, now: float, found: list[Change]) -> None:
        values = self.unit.status_values(now)
        for index in self.status_points:
            if index in self.alive:
                shown = (Code.GOOD, values[self.points[index].status_key])
                if self.published.get(index) != shown:
                    self.published[index] = shown
                    found.append((index, Code.GOOD, shown[1], now))
