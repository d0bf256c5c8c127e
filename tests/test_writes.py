"""The per-link write queue and the driver's write session (its lease), without a network or a controller."""

from __future__ import annotations

import asyncio
import contextlib
import gc
from collections.abc import AsyncIterator
from typing import Any

import pytest

from gateway.errors import GatewayError, LinkDown, LocalError, ModbusExceptionReply
from gateway.line_driver import LineDriver, LineLease, Priority
from gateway.writes import WriteQueue


class FakeLease(LineLease):
    """A lease that counts the bursts extended on it, in its driver."""

    __slots__ = ("driver",)

    def __init__(self, driver: FakeSessionDriver) -> None:
        self.driver = driver

    def extend_burst(self) -> None:
        self.driver.extended += 1


class FakeSessionDriver:
    """Only what WriteQueue uses: ``write_session``; ``down`` makes it fail like a lost link."""

    def __init__(self) -> None:
        self.down = False
        self.sessions = 0
        self.extended = 0
        self.leases: list[LineLease] = []

    @contextlib.asynccontextmanager
    async def write_session(self) -> AsyncIterator[LineLease]:
        if self.down:
            raise LinkDown("link fake is down")
        self.sessions += 1
        lease = FakeLease(self)
        self.leases.append(lease)
        yield lease


def queue(**kwargs: int) -> tuple[WriteQueue, FakeSessionDriver, list[str]]:
    driver = FakeSessionDriver()
    return WriteQueue(driver, "fake", **kwargs), driver, []  # type: ignore[arg-type]


def job(log: list[str], name: str, delay: float = 0.0) -> Any:
    async def run(line: LineLease) -> None:
        await asyncio.sleep(delay)
        log.append(name)

    return run


async def test_each_job_gets_the_lease_of_the_session_it_runs_in() -> None:
    q, driver, _ = queue()
    got: list[LineLease] = []

    async def run(line: LineLease) -> None:
        got.append(line)

    await asyncio.gather(*(q.submit(c, frozenset({c}), run) for c in "abc"))
    assert driver.sessions == 1 and got == driver.leases * 3


async def test_one_clients_jobs_run_in_arrival_order() -> None:
    q, _, log = queue()
    futures = [q.submit("a", frozenset({n % 2}), job(log, f"a{n}")) for n in range(5)]
    await asyncio.gather(*futures)
    assert log == ["a0", "a1", "a2", "a3", "a4"]


async def test_clients_are_served_round_robin_when_their_writes_do_not_overlap() -> None:
    q, _, log = queue()
    futures = [q.submit("flood", frozenset({("flood", n)}), job(log, f"f{n}")) for n in range(6)]
    futures.append(q.submit("polite", frozenset({"polite"}), job(log, "p")))
    await asyncio.gather(*futures)
    assert log.index("p") <= 2, log  # not behind the whole flood


async def test_a_write_never_overtakes_an_earlier_overlapping_one_of_another_client() -> None:
    q, _, log = queue()
    futures = [q.submit("a", frozenset({("a", n)}), job(log, f"a{n}")) for n in range(4)]
    futures.append(q.submit("a", frozenset({40, 41, 42, 43}), job(log, "a-fc16")))
    futures.append(q.submit("b", frozenset({43}), job(log, "b-fc6")))  # arrived after a-fc16, overlaps it
    futures.append(q.submit("c", frozenset({99}), job(log, "c")))
    await asyncio.gather(*futures)
    assert log.index("a-fc16") < log.index("b-fc6"), log
    assert log.index("c") < log.index("a-fc16"), log  # disjoint: round robin lets it in early


async def test_bounds_answer_0x06_at_once_and_queue_nothing() -> None:
    q, _, log = queue(per_client=2, per_link=3)
    futures = [q.submit("a", frozenset({1}), job(log, "a1", 0.01)), q.submit("a", frozenset({2}), job(log, "a2"))]
    await asyncio.sleep(0)  # a1 is running: it no longer counts as waiting
    futures.append(q.submit("a", frozenset({3}), job(log, "a3")))
    with pytest.raises(ModbusExceptionReply) as per_client:
        q.submit("a", frozenset({4}), job(log, "a4"))
    futures.append(q.submit("b", frozenset({5}), job(log, "b5")))
    with pytest.raises(ModbusExceptionReply) as per_link:
        q.submit("c", frozenset({6}), job(log, "c6"))
    assert per_client.value.code == per_link.value.code == 0x06
    assert "connection" in str(per_client.value) and "link" in str(per_link.value)
    await asyncio.gather(*futures)
    assert sorted(log) == ["a1", "a2", "a3", "b5"] and q.busy_refusals == 2


async def test_a_job_failure_is_its_callers_answer_and_the_queue_goes_on() -> None:
    q, _, log = queue()

    async def refused(line: LineLease) -> None:
        raise ModbusExceptionReply(0x04, "refused")

    bad = q.submit("a", frozenset({1}), refused)
    good = q.submit("a", frozenset({1}), job(log, "next"))
    with pytest.raises(ModbusExceptionReply):
        await bad
    await good
    assert log == ["next"]


async def test_link_down_fails_every_waiting_write_with_0x0B() -> None:
    q, driver, log = queue()
    driver.down = True
    futures = [q.submit(c, frozenset({n}), job(log, c)) for n, c in enumerate("abc")]
    results = await asyncio.gather(*futures, return_exceptions=True)
    assert all(isinstance(r, ModbusExceptionReply) and r.code == 0x0B for r in results), results
    assert log == [] and q.waiting == 0


# --------------------------------------------------------------------------------------------
# The write session: writes ahead of polls, write_burst writes then poll_burst polls


class LineDriver(LineDriver):
    """A driver whose 'transactions' are sleeps, logged in the order they held the line."""

    def __init__(self) -> None:
        super().__init__("socket://127.0.0.1:1", name="line")
        self._stream = object()  # type: ignore[assignment]  # "connected": no I/O is done
        self.line_log: list[str] = []

    def on_connect(self) -> None: ...

    def data_received(self, data: bytes) -> None: ...

    def abort(self, exc: GatewayError) -> None: ...

    async def transaction(self, name: str, priority: Priority, line: LineLease | None = None) -> None:
        async def op() -> None:
            self.line_log.append(name)
            await asyncio.sleep(0.002)

        await self.submit(op, priority, line)


@pytest.mark.parametrize(("write_burst", "poll_burst"), [(1, 1), (1, 2), (3, 1), (2, 3)])
async def test_a_write_session_lets_polls_through_after_each_burst(write_burst: int, poll_burst: int) -> None:
    driver = LineDriver()
    driver.write_burst, driver.poll_burst = write_burst, poll_burst
    stop = asyncio.Event()

    async def poller() -> None:
        n = 0
        while not stop.is_set():
            await driver.transaction(f"P{n}", Priority.POLL)
            n += 1

    poll_task = asyncio.create_task(poller())
    await asyncio.sleep(0.01)
    async with driver.write_session() as line:
        for n in range(12):
            await driver.transaction(f"W{n}", Priority.WRITE, line)
    stop.set()
    await poll_task
    kinds = "".join(name[0] for name in driver.line_log)
    during = kinds[kinds.index("W") : kinds.rindex("W") + 1]
    expected = ("W" * write_burst + "P" * poll_burst) * 12
    assert during == expected[: len(during)], during
    assert during.count("W") == 12


async def test_an_extended_burst_still_owes_its_polls() -> None:
    """A newcomer's write may follow a burst at once; the polls come after, two per write."""
    driver = LineDriver()
    stop = asyncio.Event()

    async def poller() -> None:
        n = 0
        while not stop.is_set():
            await driver.transaction(f"P{n}", Priority.POLL)
            n += 1

    poll_task = asyncio.create_task(poller())
    await asyncio.sleep(0.01)
    async with driver.write_session() as line:
        for n in range(4):
            if n == 1:
                line.extend_burst()
            await driver.transaction(f"W{n}", Priority.WRITE, line)
    stop.set()
    await poll_task
    kinds = "".join(name[0] for name in driver.line_log)
    assert kinds[kinds.index("W") : kinds.rindex("W") + 1] == "WWPPPPWPPW"


async def test_the_queue_extends_the_burst_for_a_client_with_nothing_else_queued() -> None:
    q, driver, log = queue()
    futures = [q.submit("flood", frozenset({("flood", n)}), job(log, f"f{n}")) for n in range(4)]
    await asyncio.sleep(0)
    futures.append(q.submit("polite", frozenset({"polite"}), job(log, "p")))
    await asyncio.gather(*futures)
    assert driver.extended == 2  # the flood's first job (nothing queued before it) and the polite one


async def test_without_waiting_polls_a_session_keeps_the_line() -> None:
    driver = LineDriver()
    async with driver.write_session() as line:
        for n in range(5):
            await driver.transaction(f"W{n}", Priority.WRITE, line)
    assert driver.line_log == [f"W{n}" for n in range(5)]


async def test_a_request_without_the_lease_waits_for_the_session_like_any_other() -> None:
    """Only a request given the lease runs on the session's line; another write waits for the line
    (within the burst: after it, the session lends the line to whoever waits)."""
    driver = LineDriver()
    driver.write_burst = 10
    async with driver.write_session() as line:
        other = asyncio.create_task(driver.transaction("other", Priority.WRITE))
        for n in range(3):
            await driver.transaction(f"W{n}", Priority.WRITE, line)
            await asyncio.sleep(0)
        assert not other.done()
    await other
    assert driver.line_log == ["W0", "W1", "W2", "other"]


async def test_a_lease_of_another_link_or_of_an_ended_session_is_refused_and_nothing_is_sent() -> None:
    driver, other = LineDriver(), LineDriver()
    async with other.write_session() as foreign:
        with pytest.raises(LocalError, match="not of this link's open write session"):
            await driver.transaction("W", Priority.WRITE, foreign)
    with pytest.raises(LocalError):
        await other.transaction("W", Priority.WRITE, foreign)  # its session is over
    with pytest.raises(LocalError):
        await driver.transaction("W", Priority.WRITE, LineLease())  # holds no line
    assert driver.line_log == other.line_log == []
    async with driver.write_session() as line:  # the line was released each time
        await driver.transaction("W", Priority.WRITE, line)
    assert driver.line_log == ["W"]


async def test_a_session_on_a_lost_link_fails_its_writes_with_link_down() -> None:
    driver = LineDriver()
    driver._stream = None
    with pytest.raises(LinkDown):
        async with driver.write_session():
            pass




# --------------------------------------------------------------------------------------------
# Bounds, stopping, and the order of several clients (mutants of writes.py that survived)


async def test_default_bounds_are_8_writes_per_connection_and_32_per_link() -> None:
    q, _, log = queue()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()

    running = q.submit("x", frozenset(), held)
    await asyncio.sleep(0)  # running: no longer waiting
    futures = [q.submit("a", frozenset({("a", n)}), job(log, f"a{n}")) for n in range(8)]
    with pytest.raises(ModbusExceptionReply, match="this connection has 8 writes waiting for link fake"):
        q.submit("a", frozenset({"a9"}), job(log, "a9"))
    futures += [q.submit(c, frozenset({(c, n)}), job(log, f"{c}{n}")) for c in "bcd" for n in range(8)]
    assert q.waiting == 32
    with pytest.raises(ModbusExceptionReply, match="32 writes are waiting for link fake"):
        q.submit("e", frozenset({"e"}), job(log, "e"))
    gate.set()
    await asyncio.gather(running, *futures)
    assert len(log) == 32 and q.waiting == 0 and q.busy_refusals == 2


@pytest.mark.parametrize(("per_client", "per_link"), [(1, 1), (1, 5), (5, 1)])
async def test_bounds_of_one_are_allowed_and_hold(per_client: int, per_link: int) -> None:
    q, _, log = queue(per_client=per_client, per_link=per_link)
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()

    running = q.submit("x", frozenset(), held)
    await asyncio.sleep(0)
    first = q.submit("a", frozenset({1}), job(log, "a1"))
    for client, word in [("a", 2), ("b", 3)]:
        if q.waiting >= per_link or (client == "a" and per_client == 1):
            with pytest.raises(ModbusExceptionReply):
                q.submit(client, frozenset({word}), job(log, f"{client}{word}"))
        else:
            q.submit(client, frozenset({word}), job(log, f"{client}{word}"))
    gate.set()
    await asyncio.gather(running, first)


@pytest.mark.parametrize("bounds", [{"per_client": 0}, {"per_link": 0}, {"per_client": -1, "per_link": 4}])
def test_bounds_below_one_are_refused(bounds: dict[str, int]) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        queue(**bounds)


async def test_stopping_the_gateway_fails_the_waiting_writes_with_0x0B_and_runs_none_of_them() -> None:
    """The gateway stops by cancelling its tasks: the write running is cancelled, and every write
    still waiting is answered 0x0B (nothing of it reaches the controller)."""
    q, _, log = queue()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()

    running = q.submit("a", frozenset({1}), held)
    waiting = [q.submit(c, frozenset({n}), job(log, c)) for n, c in enumerate("abc", start=2)]
    await asyncio.sleep(0)
    workers = [t for t in asyncio.all_tasks() if t.get_name() == "fake-writes"]
    assert len(workers) == 1
    workers[0].cancel()
    results = await asyncio.gather(running, *waiting, return_exceptions=True)
    assert isinstance(results[0], asyncio.CancelledError)
    for result in results[1:]:
        assert isinstance(result, ModbusExceptionReply) and result.code == 0x0B, result
        assert str(result) == "the gateway is stopping"
    assert log == [] and q.waiting == 0
    # a write submitted afterwards starts a new worker
    await q.submit("d", frozenset({9}), job(log, "d"))
    assert log == ["d"]


async def test_three_clients_take_turns_and_a_client_whose_queue_emptied_counts_as_never_served() -> None:
    """Round robin by least recently served; clients with nothing served since their queue was
    last empty go first, in the order their first waiting write arrived."""
    q, _, log = queue()
    futures = [q.submit(c, frozenset({(c, n)}), job(log, f"{c}{n}")) for c in "abc" for n in range(3)]
    await asyncio.gather(*futures)
    assert log == ["a0", "b0", "c0", "a1", "b1", "c1", "a2", "b2", "c2"]
    log.clear()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()
        log.append("held")

    futures = [q.submit("a", frozenset({"a"}), held)]
    await asyncio.sleep(0)  # "a" is being served
    futures += [q.submit("a", frozenset({("a", n)}), job(log, f"a{n}")) for n in range(2)]
    futures += [q.submit("b", frozenset({("b", n)}), job(log, f"b{n}")) for n in range(2)]
    futures.append(q.submit("c", frozenset({"c"}), job(log, "c")))
    gate.set()
    await asyncio.gather(*futures)
    assert log == ["held", "a0", "b0", "c", "a1", "b1"]


async def test_an_overlapping_write_waits_for_an_earlier_one_behind_another_clients_head() -> None:
    q, _, log = queue()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()
        log.append("held")

    futures = [q.submit("z", frozenset({"z"}), held)]
    await asyncio.sleep(0)
    futures.append(q.submit("a", frozenset({1}), job(log, "a-1")))
    futures.append(q.submit("a", frozenset({2}), job(log, "a-2")))
    futures.append(q.submit("b", frozenset({2}), job(log, "b-2")))  # overlaps a's second job
    futures.append(q.submit("b", frozenset(), job(log, "b-none")))  # overlaps nothing
    gate.set()
    await asyncio.gather(*futures)
    assert log == ["held", "a-1", "a-2", "b-2", "b-none"]


async def test_a_job_that_fails_after_its_caller_gave_up_is_not_reported_as_never_retrieved(
    caplog: pytest.LogCaptureFixture,
) -> None:
    q, _, _ = queue()

    async def fails(line: LineLease) -> None:
        raise ModbusExceptionReply(0x04, "refused")

    future = q.submit("a", frozenset({1}), fails)
    cancelled = q.submit("a", frozenset({2}), fails)
    cancelled.cancel()  # its caller gave up before it ran
    await asyncio.wait([future])  # done, its exception not retrieved by anyone
    del future, cancelled
    gc.collect()
    await asyncio.sleep(0)
    assert not [r for r in caplog.records if "never retrieved" in r.getMessage()]


async def test_a_client_whose_queue_emptied_is_a_newcomer_again_whatever_it_was_served_before() -> None:
    q, driver, log = queue()
    futures = [q.submit(c, frozenset({(c, n)}), job(log, f"{c}{n}")) for c in "ab" for n in range(2)]
    await asyncio.gather(*futures)
    assert log == ["a0", "b0", "a1", "b1"]  # "a" was served before "b"
    log.clear()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()

    futures = [q.submit("c", frozenset({"c"}), held)]
    await asyncio.sleep(0)
    futures.append(q.submit("b", frozenset({"b"}), job(log, "b2")))
    futures.append(q.submit("a", frozenset({"a"}), job(log, "a2")))
    extended = driver.extended
    gate.set()
    await asyncio.gather(*futures)
    assert log == ["b2", "a2"]  # both newcomers: in arrival order, not by how long ago they were served
    assert driver.extended - extended == 2  # and each a newcomer's write extends the burst


# --------------------------------------------------------------------------------------------
# Withdrawing a job that has not started (a write still waiting at write_timeout), and drain


async def test_a_withdrawn_write_is_cancelled_and_never_runs_and_the_others_do() -> None:
    q, _, log = queue()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()
        log.append("held")

    running = q.submit("z", frozenset({"z"}), held)
    await asyncio.sleep(0)  # "z" is on the line: no longer waiting
    a = [q.submit("a", frozenset({("a", n)}), job(log, f"a{n}")) for n in range(3)]
    b = q.submit("b", frozenset({"b"}), job(log, "b"))  # b's only job
    assert q.waiting == 4
    assert q.withdraw(a[1]) and a[1].cancelled()
    assert q.withdraw(b) and b.cancelled()  # b's queue is now empty: b is gone from the queue
    assert q.waiting == 2
    assert not q.withdraw(a[1])  # not waiting any more
    assert not q.withdraw(running)  # started: it can no longer be taken back
    gate.set()
    async with asyncio.timeout(1):
        await asyncio.gather(running, a[0], a[2])
    assert log == ["held", "a0", "a2"] and q.waiting == 0
    assert not q.withdraw(a[0])  # done


async def test_a_withdrawn_write_frees_its_place_in_the_bounds() -> None:
    q, _, log = queue(per_client=2, per_link=2)
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()

    running = q.submit("z", frozenset({"z"}), held)
    await asyncio.sleep(0)
    first = q.submit("a", frozenset({1}), job(log, "a1"))
    q.submit("a", frozenset({2}), job(log, "a2"))
    with pytest.raises(ModbusExceptionReply):
        q.submit("a", frozenset({3}), job(log, "a3"))  # both bounds reached
    assert q.withdraw(first)
    third = q.submit("a", frozenset({3}), job(log, "a3"))  # its place is free again
    gate.set()
    async with asyncio.timeout(1):
        await asyncio.gather(running, third)
    assert log == ["a2", "a3"]


async def test_a_client_whose_last_waiting_write_was_withdrawn_is_a_newcomer_again() -> None:
    """Served once with more queued, then its last waiting job withdrawn: its next write counts
    as never served (ahead of a client that arrived after it, and extending the burst)."""
    q, driver, log = queue()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()
        log.append("held")

    running = q.submit("a", frozenset({("a", 0)}), held)
    waiting = q.submit("a", frozenset({("a", 1)}), job(log, "a1"))
    await asyncio.sleep(0)  # a0 on the line, a1 still queued: "a" was just served
    assert q.withdraw(waiting)
    futures = [q.submit("a", frozenset({("a", 2)}), job(log, "a2")), q.submit("b", frozenset({"b"}), job(log, "b"))]
    extended = driver.extended
    gate.set()
    async with asyncio.timeout(1):
        await asyncio.gather(running, *futures)
    assert log == ["held", "a2", "b"]  # both newcomers, in arrival order
    assert driver.extended - extended == 2


async def test_drain_returns_when_every_job_taken_has_run() -> None:
    q, _, log = queue()
    await q.drain()  # nothing taken: at once
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()
        log.append("held")

    futures = [q.submit("a", frozenset({1}), held), q.submit("b", frozenset({2}), job(log, "b"))]
    drained = asyncio.create_task(q.drain())
    for _ in range(5):
        await asyncio.sleep(0)
    assert not drained.done()
    gate.set()
    async with asyncio.timeout(1):
        await drained
    assert log == ["held", "b"] and all(f.done() for f in futures)


async def test_a_cancelled_drain_leaves_the_jobs_running() -> None:
    q, _, log = queue()
    gate = asyncio.Event()

    async def held(line: LineLease) -> None:
        await gate.wait()
        log.append("held")

    future = q.submit("a", frozenset({1}), held)
    drained = asyncio.create_task(q.drain())
    await asyncio.sleep(0)
    drained.cancel()
    with pytest.raises(asyncio.CancelledError):
        await drained
    gate.set()
    async with asyncio.timeout(1):
        await future
    assert log == ["held"]
