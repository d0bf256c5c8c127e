"""The one up/down rule of every link (``gateway.link_health.LinkHealth``), on a bare link with no driver.

Down after ``down_after_failures`` failed transactions *in a row* (an answer in between starts the
count again), or ``down_after_seconds`` without an answer while transactions fail; up at the first
answer; a controller that never answered is not available.
"""

from __future__ import annotations

import asyncio

import pytest

from gateway.link_health import DownAfter, LineQuality, LinkHealth


class Link(LinkHealth):
    """A link whose port is open (or not, as the test sets it)."""

    def __init__(self, down_after: DownAfter) -> None:
        super().__init__("test", down_after)
        self.port_open = True

    @property
    def connected(self) -> bool:
        return self.port_open

    def where(self) -> str:
        return "nowhere"


async def test_failures_between_answers_never_make_the_link_down() -> None:
    link = Link(DownAfter(failures=3, seconds=3600.0))
    link.note_result(True)
    assert link.available
    for _ in range(10):  # a line with an occasional timeout: two failures, then an answer, again and again
        link.note_result(False, "timeout")
        link.note_result(False, "timeout")
        assert link.available
        link.note_result(True)
    assert link.available and link.state_changes == 1
    assert link.counters.errors == 20 and link.counters.transactions == 11


async def test_the_third_failure_in_a_row_makes_it_down_and_an_answer_makes_it_up() -> None:
    link = Link(DownAfter(failures=3, seconds=3600.0))
    link.note_result(True)
    link.note_result(False, "timeout")
    link.note_result(False, "timeout")
    assert link.available
    link.note_result(False, "no answer")
    assert not link.available and link.last_error == "no answer"
    link.note_result(True)
    assert link.available and link.state_changes == 3  # up, down, up
    # after coming back, the count starts again: two more failures are not three in a row
    link.note_result(False, "timeout")
    link.note_result(False, "timeout")
    assert link.available


async def test_a_controller_that_never_answered_is_not_available() -> None:
    link = Link(DownAfter(failures=3, seconds=5.0))
    assert link.connected
    assert not link.available  # the port is open, no answer yet: no verdict, and not available
    assert link.state_since is None
    link.note_result(False, "timeout")
    assert not link.available  # the very first verdict is taken at once
    assert link.state_changes == 1
    link.note_result(True)
    assert link.available


async def test_an_answer_does_not_make_a_closed_port_available() -> None:
    link = Link(DownAfter())
    link.note_result(True)
    link.port_open = False
    assert not link.available


async def test_down_after_seconds_without_an_answer_while_transactions_fail() -> None:
    loop = asyncio.get_running_loop()
    link = Link(DownAfter(failures=1000, seconds=0.05))
    link.note_result(True)
    answered = loop.time()
    while loop.time() - answered < 0.05:  # noqa: ASYNC110 (the loop's own clock, no timed assertion)
        await asyncio.sleep(0.01)
    link.note_result(False, "timeout")
    assert not link.available and link.state_changes == 2


async def test_a_bare_links_line_quality_is_its_check_errors_and_timeouts_only() -> None:
    """The counters every link has; NAKs, retransmissions and resyncs are a kind's (None: not counted)."""
    link = Link(DownAfter())
    link.counters.crc_errors = 4
    link.counters.timeouts = 7
    assert link.line_quality() == LineQuality(check_errors=4, timeouts=7, naks=None, retransmits=None, resyncs=None)


@pytest.mark.looptime
async def test_the_state_says_since_when_and_up_clears_the_error() -> None:
    loop = asyncio.get_running_loop()
    link = Link(DownAfter(failures=1000, seconds=5.0))
    link.note_result(True)
    assert link.state_since == loop.time()
    await asyncio.sleep(5.0)  # exactly down_after_seconds without an answer: down
    link.note_result(False, "timeout")
    assert not link.available and link.state_since == loop.time() and link.last_error == "timeout"
    link.note_result(False)  # a failure that gives no reason keeps the last one
    assert link.last_error == "timeout"
    await asyncio.sleep(1.0)
    link.note_result(True)
    assert link.available and link.state_since == loop.time() and link.last_error == ""
