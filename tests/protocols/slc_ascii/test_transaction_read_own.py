"""SLC 100/150 transaction core: a read's value comes from its own transaction.

The controller's word changes between reads (and each time a frame reaches it), and its replies
come late, twice, out of order, or not at all.  Every value a read is answered with must have
been held by the controller at some time after that read was started (the controller answers a
frame the instant it gets it, then its word changes): never a value that had already been replaced
when the read began (a late reply to an earlier read, taken for this one,
would be such a value).

The controller is the simulator (:class:`SlcAsciiSimulator`, sans-I/O), the clock is fake, and
the line is this test's: each reply the controller gives gets a delay (0 to 4 reply timeouts),
may be delivered a second time, or is lost.  A point-to-point serial line keeps the order of the
bytes (the fact the core rests on: "replies come back in the order of their messages"), so a late
reply holds back the replies after it and a repeated one comes right behind itself.  Reordered
replies are outside that model: with them the core can take a late reply to an earlier message
that had the same ID (IDs start again at 01 after an ID 00 resync) for this read's.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterator

from hypothesis import example, given, settings
from hypothesis import strategies as st

from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.replies import parse_read_reply
from gateway.protocols.slc_ascii.transaction import SlcSession, SlcVerdict

TIMEOUT = 0.3
ADDRESS = 0x40
READ = cmds.read_bytes(ADDRESS, 2)

#: one reply's fate: delay in reply timeouts, delivered twice, lost
Fate = tuple[float, bool, bool]
FATE = st.tuples(st.sampled_from([0.0, 0.0, 0.0, 0.5, 1.2, 2.5, 4.0]), st.booleans(),
                 st.sampled_from([False] * 5 + [True]))


class ChangingLine:
    """The core, the simulator, a word that changes, and a line that reorders (module doc)."""

    def __init__(self, fates: list[Fate]) -> None:
        self.sim = SlcAsciiSimulator(ladder=False)
        self.session = SlcSession(timeout=TIMEOUT, retries=3)
        self.fates: Iterator[Fate] = iter(fates)
        self.now = 0.0
        self.values = itertools.count(1)
        #: (time set, value) of the word at ADDRESS, oldest first; every value is new
        self.history: list[tuple[float, int]] = []
        self._queue: list[tuple[float, int, bytes]] = []
        self._seq = itertools.count()
        self._line_free = 0.0
        self.change()

    def change(self) -> None:
        value = next(self.values)
        self.sim.set_word(ADDRESS, value)
        self.history.append((self.now, value))

    def replaced_at(self, value: int) -> float:
        """When the controller stopped holding ``value`` (inf: it still holds it)."""
        times = [t for t, v in self.history]
        index = [v for t, v in self.history].index(value)
        return times[index + 1] if index + 1 < len(times) else float("inf")

    def _to_controller(self, data: bytes) -> None:
        for frame in data.split(b"\r"):
            if not frame:
                continue
            for out in self.sim.receive(frame + b"\r", self.now):
                delay, twice, lost = next(self.fates, (0.0, False, False))
                if lost:
                    continue
                arrival = max(self.now + 0.001 + out.delay + delay * TIMEOUT, self._line_free)
                heapq.heappush(self._queue, (arrival, next(self._seq), out.data))
                if twice:
                    arrival += 0.001
                    heapq.heappush(self._queue, (arrival, next(self._seq), out.data))
                self._line_free = arrival
            self.change()  # the controller's scan moves on after each message

    def _arrive(self, until: float) -> bool:
        if not self._queue or self._queue[0][0] > until:
            return False
        arrival, _, reply = heapq.heappop(self._queue)
        self.now = max(self.now, arrival)
        self.session.receive_data(reply, self.now)
        return True

    def read(self) -> int | None:
        """One read transaction: the value it was answered with (None: it failed)."""
        session = self.session
        session.start(READ, self.now)
        for _ in range(10_000):
            if session.result is not None:
                break
            data = session.data_to_send()
            if data:
                self._to_controller(data)
                continue
            deadline = session.next_deadline()
            assert deadline is not None
            if not self._arrive(deadline):
                self.now = max(self.now, deadline)
                session.handle_timeout(self.now)
        else:
            raise AssertionError("the core does not finish")
        self._to_controller(session.data_to_send())
        result = session.take_result()
        if result.verdict is not SlcVerdict.DONE:
            return None
        assert result.answer is not None and hasattr(result.answer, "body_hex")
        return int.from_bytes(parse_read_reply(ADDRESS, 2, result.answer.body_hex), "big")

    def idle(self, seconds: float) -> None:
        end = self.now + seconds
        while self._arrive(end):
            pass
        self.now = end


@settings(max_examples=300, deadline=None)
@given(fates=st.lists(FATE, max_size=80), gaps=st.lists(st.sampled_from([0.0, 0.05, 0.5, 2.0]), min_size=1,
                                                          max_size=25))
@example(fates=[(4.0, False, False)] * 12, gaps=[0.0] * 4)
# the first read's reply 2.5 timeouts late, twice: the second read begins with a resync, and a read
# in resync may take only a reply to a copy of its own (not the first read's, with the same ID)
@example(fates=[(0.0, False, False), (2.5, True, False)], gaps=[0.0, 0.0])
def test_every_read_is_answered_with_a_value_held_after_it_began(fates: list[Fate], gaps: list[float]) -> None:
    line = ChangingLine(fates)
    for gap in gaps:
        line.idle(gap * TIMEOUT)
        line.change()  # between two reads
        line.now += 0.001
        began = line.now
        value = line.read()
        if value is not None:
            assert line.replaced_at(value) >= began, (value, began, line.history[-6:])
