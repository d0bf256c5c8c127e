"""The read order of a plan's blocks (``gateway.schedule``), on a fake clock.

The rule, as ``docs/guide/freshness.md`` states it: a bumped block first; else the urgent block
with the earliest deadline (demanded: its class period P passed; not demanded: its background
period B = max(P, background_interval) passed); else the wanted block with the earliest deadline
(not demanded, P passed); else nothing.  Never-read blocks: demanded first, then fast, then slow.
"""

from __future__ import annotations

import importlib.util
import math
import random
import sys
from collections.abc import Callable, Collection, Sequence
from itertools import pairwise
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.modbus.mapping import Scan
from gateway.schedule import NEVER, Schedule

F, S = Scan.FAST, Scan.SLOW


def schedule(scans: Sequence[Scan], *, fast: float = 0.0, slow: float = 10.0, stale_after: float = 5.0,
             hold: float = 60.0, background: float = 30.0) -> Schedule:
    return Schedule(scans, fast_interval=fast, slow_interval=slow, stale_after=stale_after, demand_hold=hold,
                    background_interval=background)


def read(s: Schedule, block: int, at: float, took: float = 0.0, ok: bool = True) -> bool:
    s.started(block, at)
    return s.done(block, at, at + took, ok)


# --- which block is next: one table row per situation -------------------------------------------

# (case, scans, reads done as (block, time), demanded blocks at 100, bumped, now, expected next)
ORDER = [
    ("start: fast class before slow, plan order", [S, F, S, F], [], [], [], 0.0, 1),
    ("start: a demanded slow block before any fast one", [F, S, F], [], [1], [], 0.0, 1),
    ("bumped first, even before a never-read block", [F, S], [(1, 99.0)], [], [1], 100.0, 1),
    ("first bumped first", [F, F, F], [(0, 99), (1, 99), (2, 99)], [], [2, 0], 100.0, 2),
    ("demanded fast (P=0) is urgent at once; undemanded wanted waits",
     [F, F], [(0, 90.0), (1, 99.0)], [1], [], 100.0, 1),
    ("nobody demands: the wanted block with the earliest deadline (a slow one due at 90)", [F, F, S],
     [(0, 95), (1, 94), (2, 80)], [], [], 100.0, 2),
    ("a slow block due (P=10) goes before a fast block read after its deadline", [F, S],
     [(0, 99.5), (1, 89.0)], [], [], 100.0, 1),
    ("a slow block not due: the fast one", [F, S], [(0, 99.5), (1, 95.0)], [], [], 100.0, 0),
    ("undemanded, B passed: urgent, ahead of a demanded block with a later deadline", [F, F],
     [(0, 68.0), (1, 99.0)], [1], [], 100.0, 0),
    ("undemanded, B not passed: the demanded block", [F, F], [(0, 71.0), (1, 99.0)], [1], [], 100.0, 1),
    ("a tie of deadlines: the demanded block", [F, F], [(0, 69.0), (1, 99.0)], [1], [], 100.0, 1),
    # the k-th block never read gets urgent at B / 2 + B * (k * 0.618... mod 1): for the first of
    # two, 15 + 30 * 0.618 = 33.54 s; for the second, 15 + 30 * 0.236 = 22.08 s
    ("start: a block nobody reads is urgent only at its place, B / 2 to 3 B / 2", [F, F], [(1, 33.5)], [1], [],
     33.5, 1),
    ("start: ... and then ahead of the demanded one", [F, F], [(1, 33.6)], [1], [], 33.6, 0),
    ("start: the second of two nobody reads comes first (22.08 s)", [F, F], [(0, 22.1)], [0], [], 22.1, 1),
    ("read ahead: a demanded slow block within half its period of due, before a young continuous one",
     [F, S], [(0, 99.0), (1, 94.0)], [0, 1], [], 100.0, 1),
    ("no read ahead: the slow block is not within half its period of due", [F, S], [(0, 99.0), (1, 95.5)],
     [0, 1], [], 100.0, 0),
    ("no read ahead: the continuous block is past 70 % of its stale limit (5 s)", [F, S], [(0, 96.4), (1, 94.0)],
     [0, 1], [], 100.0, 0),
    ("no read ahead for a slow block nobody demands", [F, S], [(0, 99.0), (1, 94.0)], [0], [], 100.0, 0),
    ("demanded slow (P=10) not due: the wanted fast block", [F, S], [(0, 99.0), (1, 95.0)], [1], [], 100.0, 0),
    ("nothing due when every period is positive", [S, S], [(0, 85.0), (1, 86.0), (0, 95.0), (1, 96.0)], [], [], 100.0,
     None),
]


@pytest.mark.parametrize(("case", "scans", "reads", "demanded", "bumped", "now", "expected"), ORDER,
                         ids=[row[0] for row in ORDER])
def test_next_block(case: str, scans: list[Scan], reads: list[tuple[int, float]], demanded: list[int],
                    bumped: list[int], now: float, expected: int | None) -> None:
    s = schedule(scans)
    s.begin(0.0)
    for block, at in reads:
        read(s, block, at)
    s.demand(demanded, now)
    s.bump(bumped)
    assert s.next(now) == expected, case


def test_next_due_is_the_earliest_class_deadline_and_now_when_bumped() -> None:
    s = schedule([S, S], slow=10.0)
    for at in (85.0, 95.0):  # the second read: due one class period after it (the first: a share of it)
        read(s, 0, at)
        read(s, 1, at + 1.0)
    assert s.next_due(100.0) == 105.0
    s.bump([1])
    assert s.next_due(100.0) == 100.0


def test_blocks_read_together_first_come_due_spread_over_their_class_period() -> None:
    """The slow class read in one burst at start: its next reads are due 10/4, 20/4, 30/4 and 40/4 s
    after, not all 10 s after (a burst of them would hold the fast class up for the whole burst); from
    then on each block is due one class period after its last read."""
    s = schedule([F, S, S, S, S], slow=10.0)
    s.begin(0.0)
    for block in (1, 2, 3, 4):
        read(s, block, 1.0)
    assert [s.due[b] for b in (1, 2, 3, 4)] == [3.5, 6.0, 8.5, 11.0]
    read(s, 1, 3.5)
    assert s.due[1] == 13.5
    s.lost(15.0)  # after a loss the first reads spread again
    read(s, 2, 20.0)
    assert s.due[2] == 25.0


def test_demand_lasts_demand_hold() -> None:
    s = schedule([F, F], hold=60.0)
    s.demand([0], 10.0)
    assert s.demanded(69.9) == [0]
    assert s.demanded(70.0) == []


def test_a_read_that_never_reached_the_controller_keeps_its_place() -> None:
    s = schedule([F, F, F])
    for block in range(3):
        read(s, block, float(block))
    s.started(0, 10.0)
    s.untry(0, 10.0)  # the link was lost under it
    assert s.next(10.0) == 0
    read(s, 0, 10.0, ok=False)  # a failed read: to the back
    assert s.next(10.0) == 1


def test_a_held_block_is_not_read_before_its_time() -> None:
    s = schedule([F, F])
    read(s, 0, 0.0)
    read(s, 1, 0.0)
    s.hold(0, 5.0)
    assert [s.next(t) for t in (1.0, 4.9)] == [1, 1]
    read(s, 1, 5.0)
    assert s.next(5.0) == 0


# --- stale limits and lateness ------------------------------------------------------------------


def test_the_stale_limit_is_stale_after_plus_the_period_planned_at_the_read() -> None:
    s = schedule([F, S], stale_after=5.0, slow=10.0, background=30.0)
    assert s.max_age == [5.0, 15.0]  # before any read: the class periods
    s.demand([0], 0.0)
    s.started(0, 1.0)
    s.started(1, 1.0)
    assert s.max_age == [5.0 + 0.0, 5.0 + 30.0]  # demanded: P; nobody reads it: B


def test_a_read_after_the_stale_limit_is_late() -> None:
    s = schedule([F], stale_after=5.0)
    s.demand([0], 0.0)
    assert not read(s, 0, 0.0)
    assert not read(s, 0, 4.9)
    assert read(s, 0, 10.0)  # 5.1 s after the last read, limit 5 s
    assert s.late_reads == 1
    s.lost(11.0)
    assert not read(s, 0, 60.0)  # an outage is not a refresh period


def test_lateness_is_judged_against_the_limit_the_value_was_read_with() -> None:
    # Nobody demands the block: it was read with the background limit, stale_after + B = 5 + 30, not
    # the class period's 5 + 0.  A read 20 s later is on time (no "raise stale_after" warning); one
    # 36 s later is late.
    s = schedule([F], stale_after=5.0, background=30.0)
    assert not read(s, 0, 0.0)
    assert not read(s, 0, 20.0)
    assert s.late_reads == 0
    assert read(s, 0, 56.0)
    assert s.late_reads == 1


def test_a_held_block_comes_due_when_its_hold_ends_not_a_period_later() -> None:
    # A refused block is held (not read) until 5; it is read at 5, when nothing else is due, whether
    # demanded or not: its hold ends at 5, not 5 + P.
    for demanded in (False, True):
        s = schedule([S, S], slow=10.0, background=10.0)
        s.begin(0.0)
        if demanded:
            s.demand([0, 1], 0.0)
        read(s, 0, 0.0, ok=False)
        s.hold(0, 5.0)
        read(s, 1, 0.1)
        assert s.next(4.9) is None
        assert s.next(5.0) == 0, demanded
        assert s.next_due(4.0) == 5.0


def test_a_failed_read_of_a_demanded_block_is_tried_again_before_its_value_goes_stale() -> None:
    # slow_interval 10, stale_after 4: the value read at 0.5 is served until 14.5.  Its read at 10
    # fails: it is tried again one transaction (0.5 s) later, behind the block already urgent, not
    # a whole period later (at 20: 5.5 s of 0x0B to every client on a line that failed once).
    s = schedule([S, S], slow=10.0, stale_after=4.0)
    s.begin(0.0)
    s.demand([0, 1], 0.0)
    read(s, 0, 0.0, took=0.5)  # due again at 5 (its share of P: the first of 2), then every 10 s
    read(s, 0, 5.0, took=0.5)  # due at 15; its value, read at 5.5, served until 19.5
    read(s, 1, 5.5, took=0.5)  # due at 15.5
    read(s, 0, 15.0, took=0.5, ok=False)  # ends at 15.5: tried again at 16
    assert s.next(15.5) == 1  # already urgent: first
    read(s, 1, 15.5, took=0.5)
    for at in (16.0, 17.0, 18.0):  # fails again and again: one retry a transaction after each failure
        assert s.next(at) == 0
        read(s, 0, at, took=0.5, ok=False)
        assert s.next(at + 0.5) is None  # the line is free a transaction for other reads
    assert s.next(19.0) == 0
    read(s, 0, 19.0, took=0.5, ok=False)  # no time left before 19.5: to the back, due at 29
    assert s.due[0] == 29.0
    assert s.next_due(19.5) == 25.5  # block 1, read at 15.5, comes due first


def test_a_failed_read_of_a_block_nobody_reads_goes_to_the_back_of_the_order() -> None:
    s = schedule([S], slow=10.0, stale_after=4.0)
    read(s, 0, 0.0, took=0.5)
    read(s, 0, 10.0, took=0.5, ok=False)
    assert s.due[0] == 20.0


def test_a_client_waiting_for_the_block_on_the_line_does_not_have_it_read_twice() -> None:
    s = schedule([F, F])
    read(s, 0, 0.0)
    read(s, 1, 0.0)
    s.started(0, 1.0)
    s.bump([0, 1])  # a client waits for both; block 0's read is under way: it is the one awaited
    assert list(s.bumped) == [1]
    s.done(0, 1.0, 1.1, True)
    assert s.next(1.1) == 1
    read(s, 1, 1.1)
    assert not s.bumped
    s.started(0, 2.0)
    s.untry(0, 2.0)  # the link was lost under it: bumped again, it is read again
    s.bump([0])
    assert list(s.bumped) == [0]


def test_after_a_loss_the_demanded_blocks_are_read_first() -> None:
    # No value read before a loss is served after it (BlockCache.expire_before): a demanded block
    # due later is due at the loss, before the blocks nobody reads.
    s = schedule([F, S, S], slow=10.0)
    s.begin(0.0)
    s.demand([2], 0.0)
    assert s.next(0.0) == 2
    read(s, 2, 0.0)  # due at 10
    assert s.next(5.0) == 0  # the fast block, wanted
    s.lost(5.0)
    assert s.next(5.0) == 2
    assert s.due[1] == 0.0  # a block nobody reads keeps its place


def test_background_interval_zero_reads_every_block_at_its_class_period() -> None:
    s = schedule([F, S], background=0.0)
    assert s.background == s.period == [0.0, 10.0]


# --- what the order achieves, simulated: each read takes T seconds ------------------------------


def simulate(s: Schedule, seconds: float, took: float | Callable[[], float],
             demanded: Collection[int] = ()) -> list[list[float]]:
    """Run the order for ``seconds`` of fake time, reads of ``took`` each (or as long as each call of
    it says), ``demanded`` read by a client all along; the read times of each block."""
    times: list[list[float]] = [[] for _ in s.scans]
    now = 0.0
    s.begin(now)
    while now < seconds:
        s.demand(demanded, now)
        block = s.next(now)
        if block is None:
            now = max(now + 1e-3, s.next_due(now))
            continue
        duration = took() if callable(took) else took
        read(s, block, now, duration)
        now += duration
        times[block].append(now)
    return times


def longest_gap(times: list[float], until: float) -> float:
    """The longest time without a read, from the first read to ``until``."""
    return max(b - a for a, b in zip(times, [*times[1:], until], strict=True))


def stale_share(times: list[float], until: float, limit: float) -> float:
    """The share of ``until`` seconds a value read at ``times`` was older than ``limit``."""
    edges = [0.0, *times, until]
    return sum(max(0.0, b - a - limit) for a, b in pairwise(edges)) / until


# 120 blocks (55 fast, 65 slow) as the SLC 150 plan; a client reads 32 fast and 32 slow blocks, as
# the accumulators and presets screen does (holding 0-31 and 32-63).
PLAN = [F] * 55 + [S] * 65
SCREEN = set(range(32)) | set(range(55, 87))


@pytest.mark.parametrize(("took", "settled", "share"), [(0.066, 30.0, 0.0), (0.09, 300.0, 0.01)],
                         ids=["15 reads per s", "11 reads per s"])
def test_a_working_set_that_fits_the_line_stays_fresh_and_nothing_starves(
    took: float, settled: float, share: float
) -> None:
    # Fits: 32 / 5 s + 32 / 15 s + 56 / 65 s = 9.4 reads/s are enough (stale_after 5, slow 10, B 60:
    # docs/guide/freshness.md)
    s = schedule(PLAN, background=60.0)
    times = simulate(s, 600.0, took, SCREEN)
    fast = range(32)
    # the first reads of 64 blocks take a few seconds at start; then the set stays fresh
    assert max(stale_share(times[b], 600.0, 5.0) for b in fast) <= share
    assert max(longest_gap([t for t in times[b] if t > settled], 600.0) for b in fast) < 5.0
    # stale_after + slow_interval
    assert max(longest_gap([t for t in times[b] if t > settled], 600.0) for b in range(55, 87)) < 15.0
    bound = 60.0 + len(PLAN) * took  # B plus one read of every block
    others = max(longest_gap(times[b], 600.0) for b in range(120) if b not in SCREEN)
    assert others <= bound, (others, bound)
    assert s.age_bound(range(32, 55), 600.0) == pytest.approx(bound)


def test_a_client_reading_everything_gets_every_block_in_turn() -> None:
    scans = [F] * 55 + [S] * 65
    s = schedule(scans)
    times = simulate(s, 120.0, 0.05, set(range(120)))
    fast = [longest_gap(times[b], 120.0) for b in range(55)]
    # the fast class (P = 0) goes round; each slow block joins it every P = 10 s plus a round
    assert max(fast) < 0.05 * 120, max(fast)
    assert max(longest_gap(times[b], 120.0) for b in range(55, 120)) < 10.0 + 0.05 * 120


def test_a_line_with_room_reads_every_block_at_its_class_period() -> None:
    # fast_interval 1 s: 10 blocks of 0.01 s fit with room; nobody reads anything
    s = schedule([F] * 5 + [S] * 5, fast=1.0, slow=10.0)
    times = simulate(s, 60.0, 0.01)
    assert all(longest_gap(times[b], 60.0) < 1.0 + 0.2 for b in range(5))
    assert all(longest_gap(times[b], 60.0) < 10.0 + 0.2 for b in range(5, 10))


def test_budget_reports_what_is_achieved() -> None:
    s = schedule([F, F, S], background=0.0)
    assert s.budget(0.0).transaction_time is None
    simulate(s, 30.0, 0.1, {0})
    budget = s.budget(30.0)
    assert budget.blocks == 3 and budget.demanded == 1
    assert budget.transaction_time == pytest.approx(0.1)
    assert budget.line_use == pytest.approx(1.0)
    assert budget.refresh["demanded"] is not None and budget.refresh["demanded"] < 0.5
    assert budget.refresh["slow"] is not None and budget.refresh["slow"] == pytest.approx(10.0, abs=0.5)
    assert math.isfinite(budget.age_bound["slow"] or math.inf)


@pytest.mark.parametrize("seed", range(8))
def test_a_working_set_stays_fresh_when_answer_times_spread(seed: int) -> None:
    # The SLC 150 screen on a 9600-baud line whose controller answers within 0-100 ms: a read takes
    # 40 ms of characters plus uniform(0, 100) ms, 11.1 reads/s on average; the screen needs 9.4
    # (docs/guide/freshness.md). Answers that come late and early in runs must not age the fast
    # class past stale_after (5 s) nor the slow blocks past stale_after + slow_interval (15 s).
    rng = random.Random(seed)
    s = schedule(PLAN, background=60.0)
    times = simulate(s, 300.0, lambda: 0.040 + rng.uniform(0.0, 0.1), SCREEN)
    settled = 12.0  # the first reads of every block a client waits for, at start
    assert max(longest_gap([t for t in times[b] if t > settled], 300.0) for b in range(32)) < 5.0
    assert max(longest_gap([t for t in times[b] if t > settled], 300.0) for b in range(55, 87)) < 15.0


def harsh_line_model() -> ModuleType:
    """``bench/schedule_faults.py``: the read order on a faulty line, on a fake clock."""
    path = Path(__file__).resolve().parent.parent / "bench" / "schedule_faults.py"
    spec = importlib.util.spec_from_file_location("schedule_faults", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("seed", range(2))
def test_a_demanded_set_that_fits_a_faulty_line_is_answered_with_data(seed: int) -> None:
    # Issue 39: the SLC 150 plan, the 31 presets read every second by a client that writes one every
    # fifth read; 4 reads in 10 fail, a read takes 0.05-0.2 s.  By the sizing rule, with the time a
    # read that stored data costs (its failures included) and the line's time on writes, the set
    # fits; each failed read of a demanded block used to wait a whole slow_interval (10 s), past
    # its stale limit (14 s): 40-50 % of the reads had data.
    model = harsh_line_model()
    line = model.Line(tx=(0.05, 0.2), fail=0.4, loss_every=0, period=1.0)
    result = model.simulate(line, 600.0, seed)
    assert model.sizing(line, result.tx_time / result.ok_share) + result.write_share < 0.9
    assert result.with_data >= 0.9


# --- the order, checked against the rule as the docs state it, on random histories -------------


def rule(s: Schedule, now: float) -> int | None:
    """The next block by the rule of ``docs/guide/freshness.md``, looking at every block."""
    if s.bumped:
        return next(iter(s.bumped))
    tie = sorted(range(len(s.scans)), key=lambda i: (s.period[i], i))  # the fast class first, then plan order
    urgent: list[tuple[float, int, int, int]] = []
    wanted: list[tuple[float, int, int]] = []
    for place, i in enumerate(tie):
        demanded = s.demanded_until[i] > now
        due = s.due[i]
        if demanded and due <= now:
            urgent.append((due, 0, place, i))
        elif not demanded and s.since[i] + s.background[i] <= now:
            urgent.append((s.since[i] + s.background[i], 1, place, i))
        elif not demanded and due <= now:
            wanted.append((due, place, i))
    if urgent:
        pick = min(urgent)[3]
        # read ahead: before a block read continuously whose value is younger than 70 % of its stale
        # limit, the demanded periodic block that comes due first, within half its period, unless held
        limit = 5.0 + (s.period[pick] if s.demanded_until[pick] > now else s.background[pick])  # stale_after 5
        if s.period[pick] == 0 and s.read_at[pick] != NEVER and now - s.read_at[pick] < 0.7 * limit:
            periodic = [(s.due[i], place, i) for place, i in enumerate(tie)
                        if s.period[i] > 0 and s.demanded_until[i] > now]
            if periodic:
                due, _place, first = min(periodic)
                if due - now <= 0.5 * s.period[first] and s.held_until[first] <= now and s.read_at[first] != NEVER:
                    return first
        return pick
    if wanted:
        return min(wanted)[2]
    return None


@settings(max_examples=200, deadline=None)
@given(
    scans=st.lists(st.sampled_from([F, S]), min_size=1, max_size=12),
    steps=st.lists(st.tuples(st.sampled_from(["read", "fail", "demand", "hold", "lost", "bump"]),
                             st.integers(0, 11), st.floats(0.0, 3.0)), max_size=60),
    fast=st.sampled_from([0.0, 0.5]),
    background=st.sampled_from([0.0, 2.0, 30.0]),
)
def test_the_order_is_the_rule(scans: list[Scan], steps: list[tuple[str, int, float]], fast: float,
                               background: float) -> None:
    s = schedule(scans, fast=fast, slow=1.5, hold=4.0, background=background)
    now = 0.0
    s.begin(now)
    for action, block, dt in steps:
        now += dt
        block %= len(scans)
        if action == "demand":
            s.demand([block], now)
        elif action == "hold":
            s.hold(block, now + dt)
        elif action == "bump":
            s.bump([block])
        else:
            pick = s.next(now)
            assert pick == rule(s, now), (action, now)
            if pick is None:
                continue
            s.started(pick, now)
            if action == "lost":
                s.untry(pick, now)
            else:
                s.done(pick, now, now + 0.01, action == "read")
        assert s.next(now) == rule(s, now)
        assert s.next_due(now) == (now if s.bumped else min(s.due))


# --- edges of the rule (mutation testing) -------------------------------------------------------


def test_after_a_read_that_never_reached_the_controller_no_block_is_on_the_line() -> None:
    s = schedule([F, F, F])
    s.started(0, 1.0)
    s.untry(0, 1.0)
    s.bump([1, 0])  # nothing is on the line: a client waits for the read of either
    assert list(s.bumped) == [1, 0]


def test_a_block_is_urgent_at_its_deadline_and_demanded_until_its_hold_ends() -> None:
    s = schedule([S, S], slow=10.0, background=30.0, hold=60.0)
    for block in (0, 1, 0, 1):  # read twice: the first read after start comes due early (spread over P)
        read(s, block, 0.0)
    s.demand([0], 0.0)
    assert s.is_urgent(0, 10.0) and not s.is_urgent(0, 9.9)  # demanded: at its due time, P after its read
    assert not s.is_urgent(1, 10.0) and s.is_urgent(1, 30.0)  # nobody reads it: B after its read
    s2 = schedule([S], slow=10.0, background=100.0, hold=60.0)
    read(s2, 0, 0.0)
    read(s2, 0, 0.0)
    s2.demand([0], 0.0)  # demanded until 60 (not at 60)
    assert s2.is_urgent(0, 59.9)
    assert not s2.is_urgent(0, 60.0)  # demand over: urgent only B (100) after its read


def test_a_loss_when_a_demand_ends_leaves_that_block_in_its_place() -> None:
    s = schedule([S, S], slow=10.0, hold=5.0)
    s.begin(0.0)
    for block in (0, 1, 0, 1):  # read twice: due a whole P after the second read
        read(s, block, 0.0)
    s.demand([0], 0.0)  # demanded until 5
    s.demand([1], 1.0)  # demanded until 6
    s.lost(5.0)
    assert s.due[0] == 10.0  # no longer demanded at the loss: its place kept
    assert s.due[1] == 5.0  # demanded: due at the loss


def test_a_held_block_nobody_reads_is_urgent_a_background_period_after_it_counts_as_read() -> None:
    """A held block counts as read one class period before its hold ends (so it is wanted when the hold
    ends): nobody reading it, it is urgent ``B - P`` after the hold ends, not ``B + P``."""
    s = schedule([S, S], slow=10.0, background=30.0)
    read(s, 0, 0.0, ok=False)
    s.hold(0, 5.0)
    assert s.urgent_at(0) == 25.0
    assert not s.is_urgent(0, 24.9) and s.is_urgent(0, 25.0)


def test_the_budget_names_its_classes() -> None:
    s = schedule([F, S, S], fast=1.0, slow=10.0, background=0.0)
    for t in range(3):  # the fast block read every 1 s, the slow ones every 10 s
        read(s, 0, float(t))
    read(s, 1, 0.0)
    read(s, 1, 9.0)
    read(s, 2, 0.0)
    read(s, 2, 9.0)
    budget = s.budget(9.0)
    assert budget.refresh == {"fast": 1.0, "slow": 9.0, "demanded": None, "all": 9.0}
    assert set(budget.age_bound) == {"fast", "slow", "demanded"}
    assert budget.line_use is None  # no full window (10 s) measured yet


def test_a_failed_read_as_its_demand_ends_is_not_tried_again_early() -> None:
    s = schedule([S, S], slow=10.0, hold=10.0, background=30.0)
    for block in (0, 1, 0, 1):
        read(s, block, 0.0)
    s.demand([0], 0.0)  # demanded until 10, not at 10
    read(s, 0, 10.0, ok=False)
    assert s.due[0] == 20.0  # to the back: a whole period


def test_a_retry_that_would_come_at_the_stale_limit_is_not_made() -> None:
    """Tried again one transaction later only while that comes *before* the value's stale limit."""
    s = schedule([S, S], slow=10.0, stale_after=5.0, hold=100.0)
    s.demand([0, 1], 0.0)
    for block in (0, 1, 0, 1):
        read(s, block, 0.0, took=1.0)  # every transaction takes 1 s; each block read at 1, its limit 1 + 15
    read(s, 0, 14.0, took=1.0, ok=False)  # failed at 15: a retry at 16 is at the limit
    assert s.due[0] == 24.0
    read(s, 1, 13.0, took=1.0, ok=False)  # block 1 (read at 1, limit 16) failed at 14: retry at 15
    assert s.due[1] == 15.0


def test_the_age_bound_of_a_demanded_block_is_its_class_period_else_its_background() -> None:
    s = schedule([F, S], fast=1.0, slow=10.0, background=30.0, hold=10.0)
    read(s, 0, 0.0, took=0.5)
    read(s, 1, 0.5, took=0.5)  # transactions of 0.5 s: one round of both blocks takes 1 s
    s.demand([1], 0.0)  # demanded until 10
    assert s.age_bound([1], 5.0) == 11.0  # P + a round
    assert s.age_bound([1], 10.0) == 31.0  # the demand is over: B + a round
    assert s.age_bound([0], 5.0) == 31.0
