"""The one verdict (``gateway.freshness``): the rule stated once, from ``docs/guide/freshness.md``
("One verdict for every face"), and every face checked against it on random histories.

The reference below is written from the guide, not from the module: a value is fresh while it is
younger than the limit it was read with (``stale_after`` plus its class period when it was demanded
as its read started, its background period when not), was not read before a link loss the link has
since answered after, and the controller has answered within ``stale_after`` plus the shortest class
period.  A link is down when its controller does not answer; else stale when its oldest fast-class
value is at least ``stale_after`` plus the longest of the fast period and the fast blocks' last
refresh intervals old; else up.

Faces: a Modbus read (value or 0x0B), a peek (what Sparkplug publishes: a value or STALE), the
status block (1000 link up, 1011 state), ``/healthz``, the status page's row and ``/metrics``'
``link_up``.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_register_image import FakeDriver, MemoryUnit

from gateway.errors import ModbusExceptionReply
from gateway.freshness import Freshness, LinkState, Offline, Source
from gateway.health import health
from gateway.link_health import LineQuality
from gateway.modbus.mapping import Table
from gateway.status import StatusPage

#: per block of ``memory_plan``: a holding register in it (block 0 fast, block 1 slow)
PROBE = {0: 0, 1: 8}
FAST, SLOW = 0, 1


class Reference:
    """The guide's rule, kept from the events alone."""

    def __init__(self, stale_after: float, fast: float, slow: float, background: float) -> None:
        self.stale_after = stale_after
        self.period = {FAST: fast, SLOW: slow}
        self.background = {b: max(p, background) for b, p in self.period.items()}
        self.read_at: dict[int, float] = {}
        self.limit: dict[int, float] = {}
        self.interval: dict[int, float] = {}
        #: the blocks read since the last loss (a refresh interval counts from their last read)
        self.since_loss: set[int] = set()
        self.expired: set[int] = set()
        self.demanded_until = {FAST: -math.inf, SLOW: -math.inf}
        self.lost_at: float | None = None
        self.answers = True

    def demand(self, block: int, now: float, hold: float) -> None:
        self.demanded_until[block] = max(self.demanded_until[block], now + hold)

    def read(self, block: int, started: float, now: float) -> None:
        if self.lost_at is not None:  # the first answer after a loss: what was read before it is not served
            self.expired |= {b for b, at in self.read_at.items() if at < self.lost_at}
            self.lost_at = None
        demanded = self.demanded_until[block] > started
        self.limit[block] = self.stale_after + (self.period[block] if demanded else self.background[block])
        if block in self.since_loss:
            self.interval[block] = now - self.read_at[block]
        self.read_at[block] = now
        self.since_loss.add(block)
        self.expired.discard(block)

    def lose(self, now: float) -> None:
        if self.lost_at is None:
            self.lost_at = now
        self.interval.clear()  # an outage is not a refresh period
        self.since_loss.clear()

    def fresh(self, block: int, now: float) -> bool:
        if block not in self.read_at or block in self.expired:
            return False
        if now - max(self.read_at.values()) > self.stale_after + min(self.period.values()):
            return False  # the controller is silent
        return now - self.read_at[block] <= self.limit[block]

    def state(self, now: float) -> LinkState:
        if not self.answers:
            return LinkState.DOWN
        age = now - self.read_at[FAST] if FAST in self.read_at else math.inf
        limit = self.stale_after + max(self.period[FAST], self.interval.get(FAST, 0.0))
        return LinkState.STALE if age >= limit else LinkState.UP


class PageDriver(FakeDriver):
    """A fake driver the status page can show (its line quality too)."""

    def line_quality(self) -> LineQuality:
        return LineQuality(check_errors=0, timeouts=0)


def _served(unit: MemoryUnit, block: int, source: Source) -> bool:
    try:
        unit.read_register_bytes(Table.HOLDING, PROBE[block], 1, source)
    except ModbusExceptionReply as exc:
        assert exc.code == ModbusExceptionReply.GATEWAY_TARGET_FAILED
        return False
    return True


events = st.lists(st.tuples(st.sampled_from(["read", "fail", "demand", "down", "up", "lose", "wait"]),
                            st.sampled_from([FAST, SLOW]), st.floats(0.0, 4.0)), min_size=1, max_size=40)


@settings(max_examples=150, deadline=None)
@given(events=events, stale_after=st.floats(0.5, 5.0), fast=st.sampled_from([0.0, 0.5, 2.0]),
       slow=st.sampled_from([1.0, 5.0]), background=st.sampled_from([0.0, 3.0, 20.0]))
def test_every_face_says_what_the_rule_says(events: list[tuple[str, int, float]], stale_after: float, fast: float,
                                            slow: float, background: float) -> None:
    hold = 10.0
    driver = PageDriver()
    unit = MemoryUnit(stale_after=stale_after, fast_interval=fast, slow_interval=slow,
                      background_interval=background, demand_hold=hold, driver=driver)
    assert unit.schedule is not None
    ref = Reference(stale_after, fast, slow, background)
    view: Any = SimpleNamespace(units=[unit], servers=[], sparkplug=None, opcua=None)
    page = StatusPage(view)
    now = 100.0
    for kind, block, step in events:
        now += step
        unit.now = now
        if kind == "read":
            started = now - 0.05
            unit.schedule.started(block, started)
            unit.schedule.done(block, started, now, ok=True)
            if ref.lost_at is not None:
                unit.cache.expire_before(ref.lost_at)
            unit.cache.store(block, bytes(unit.plan.blocks[block].size), now)
            ref.read(block, started, now)
        elif kind == "fail":
            unit.schedule.started(block, now - 0.05)
            unit.schedule.done(block, now - 0.05, now, ok=False)
        elif kind == "demand":
            unit.schedule.demand([block], now)
            ref.demand(block, now, hold)
        elif kind in ("down", "up"):
            driver.available = ref.answers = kind == "up"
        elif kind == "lose":
            unit.schedule.lost(now)
            ref.lose(now)
        for b in (FAST, SLOW):
            expected = ref.fresh(b, now)
            assert unit.freshness.block_fresh(b, now) is expected, (b, now)
            assert _served(unit, b, Source.SERVE) is expected, ("modbus", b, now)
            assert _served(unit, b, Source.PEEK) is expected, ("peek (sparkplug)", b, now)
        state = ref.state(now)
        assert unit.verdict(now).state is state
        assert unit.read_registers(Table.INPUT, 1011, 1) == [state.number]
        assert unit.read_registers(Table.INPUT, 1000, 1) == [int(state is not LinkState.DOWN)]
        healthy, body = health(view, now)
        assert healthy is (state is LinkState.UP)
        assert body["links"]["mem"]["up"] is (state is not LinkState.DOWN)  # type: ignore[index]
        row = page.status(now, 0.0)["links"][0]  # type: ignore[index]
        assert row["state"] == state.value


def test_the_state_register_numbers() -> None:
    """docs/reference/status-block.md: 1011 is 0 up, 1 stale, 2 down."""
    assert [LinkState.UP.number, LinkState.STALE.number, LinkState.DOWN.number] == [0, 1, 2]


# --- the offline policy -------------------------------------------------------------------


def _stale_unit(offline: Offline) -> MemoryUnit:
    """A unit whose fast block was read at 100 with 0x1234 in holding 0, seen at 200 (long stale)."""
    unit = MemoryUnit(stale_after=2.0, offline=offline)
    data = bytearray(20)
    data[0:2] = b"\x12\x34"
    data[18] = 0b1  # coil 0 on
    unit.cache.store(0, bytes(data), 100.0)
    unit.now = 200.0
    return unit


@pytest.mark.parametrize(("offline", "holding", "coil"), [(Offline.HOLD, 0x1234, True), (Offline.ZERO, 0, False)])
def test_hold_and_zero_serve_a_value_where_exception_answers_0x0b(offline: Offline, holding: int, coil: bool) -> None:
    unit = _stale_unit(offline)
    assert unit.read_registers(Table.HOLDING, 0, 1) == [holding]
    assert unit.read_bits(Table.COIL, 0, 1) == [coil]
    # the truth stays on every other face: a peek (Sparkplug, the page's state) and register 1011
    with pytest.raises(ModbusExceptionReply) as info:
        unit.read_register_bytes(Table.HOLDING, 0, 1, Source.PEEK)
    assert info.value.code == ModbusExceptionReply.GATEWAY_TARGET_FAILED
    assert unit.read_registers(Table.INPUT, 1011, 1) == [LinkState.STALE.number]


def test_exception_answers_0x0b_and_hold_has_nothing_to_hold_before_the_first_read() -> None:
    unit = _stale_unit(Offline.EXCEPTION)
    with pytest.raises(ModbusExceptionReply) as info:
        unit.read_registers(Table.HOLDING, 0, 1)
    assert info.value.code == ModbusExceptionReply.GATEWAY_TARGET_FAILED
    never = MemoryUnit(offline=Offline.HOLD)
    never.now = 10.0
    with pytest.raises(ModbusExceptionReply):
        never.read_registers(Table.HOLDING, 8, 1)  # block 1 never read: no last value
    zero = MemoryUnit(offline=Offline.ZERO)
    zero.now = 10.0
    assert zero.read_registers(Table.HOLDING, 8, 2) == [0, 0]


def test_zero_keeps_the_fresh_values_of_a_range_that_is_partly_stale() -> None:
    unit = MemoryUnit(stale_after=2.0, offline=Offline.ZERO)
    unit.cache.store(0, b"\x00\x07" + bytes(18), 100.0)
    unit.now = 101.0
    # holding 0 (block 0, fresh) and 8 (block 1, never read) are not one segment: read each
    assert unit.read_registers(Table.HOLDING, 0, 1) == [7]
    assert unit.read_registers(Table.HOLDING, 8, 1) == [0]


# --- demand: who reads -----------------------------------------------------------------------


def test_a_peek_is_no_demand_and_a_served_read_is() -> None:
    unit = MemoryUnit()
    unit.now = 5.0
    with pytest.raises(ModbusExceptionReply):
        unit.read_register_bytes(Table.HOLDING, 0, 1, Source.PEEK)
    assert unit.demand.take() == {}
    with pytest.raises(ModbusExceptionReply):
        unit.read_register_bytes(Table.HOLDING, 0, 1)
    assert unit.demand.take() == {(Table.HOLDING, 0, 1): 5.0}
    unit.note_demand(Table.COIL, 0, 3)  # a face that peeks but demands ([sparkplug] demand = true)
    assert unit.demand.take() == {(Table.COIL, 0, 3): 5.0}


def test_a_value_is_fresh_up_to_its_deadline_inclusive() -> None:
    """Fresh when read at most its limit ago: at the deadline the image stamped on it, still fresh."""
    link = SimpleNamespace(available=True, state_since=0.0)
    freshness = Freshness(stale_after=5.0, schedule=None, link=link, blocks=1)
    freshness.watch(SimpleNamespace(newest=99.0), SimpleNamespace(block_deadline=[100.0]))  # type: ignore[arg-type]
    assert freshness.block_fresh(0, 100.0)
    assert not freshness.block_fresh(0, 100.001)


def test_the_verdict_says_since_when_the_link_is_in_its_state() -> None:
    """``since`` (the module docstring, docs/guide/freshness.md): down and up since the link's last
    change; stale since the oldest value passed the limit (``stale_after`` for a unit not polled), or
    since the link came up if that was later; up after stale since the verdict found it fresh again.
    Stale at and over the limit."""
    link = SimpleNamespace(available=False, state_since=3.0)
    cache = SimpleNamespace(newest=0.0)
    freshness = Freshness(stale_after=5.0, schedule=None, link=link, blocks=1)
    freshness.watch(cache, SimpleNamespace(block_deadline=[0.0]))  # type: ignore[arg-type]

    def verdict(now: float) -> tuple[LinkState, float | None]:
        result = freshness.verdict(now)
        return result.state, result.since

    assert verdict(4.0) == (LinkState.DOWN, 3.0)
    link.available, link.state_since, cache.newest = True, 10.0, 12.0
    assert verdict(14.0) == (LinkState.UP, 10.0)
    assert verdict(17.0) == (LinkState.STALE, 17.0)  # age 5: at the limit
    assert verdict(20.0) == (LinkState.STALE, 17.0)  # still since the value passed the limit
    link.state_since = 30.0  # the link went down and came back at 30, the data older still
    assert verdict(32.0) == (LinkState.STALE, 30.0)
    cache.newest = 31.0
    assert verdict(33.0) == (LinkState.UP, 33.0)  # fresh again: since the verdict found it so
    assert verdict(34.0) == (LinkState.UP, 33.0)
