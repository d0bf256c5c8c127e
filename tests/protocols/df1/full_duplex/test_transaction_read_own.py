"""DF1 full-duplex transaction core: a read's value comes from its own transaction.

The controller (:class:`Slc500Simulator`, sans-I/O) holds N7:0, which changes before every read
and each time a chunk reaches the controller; what the controller sends comes late (up to three
reply timeouts), twice, out of order, or not at all.  Every value a read is answered with must have
been held by the controller at some time after that read began: never one already replaced when it
began (a late reply to an earlier read, taken for this one, would be such a value).  A reply
answers a command by its TNS (1770-6.5.16 p. 6-3: SRC, CMD and TNS identify a message; the reply
carries the command's TNS), and the TNS runs on across transactions, so the late reply of an
earlier read never matches a later one.
"""

from __future__ import annotations

import heapq
import itertools

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.kinds.df1.sim.slc500 import Slc500Options, Slc500Simulator
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import NEED_DATA, Checksum
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import Df1Transactions, TransactionDone, TransactionFailed
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead

REPLY_TIMEOUT = 0.1
LINE_DELAY = 0.002

#: what happens to one chunk the controller sends: delay in reply timeouts, sent twice, lost
Fate = tuple[float, bool, bool]
FATE = st.tuples(st.sampled_from([0.0, 0.0, 0.0, 0.4, 1.1, 3.0]), st.sampled_from([False] * 4 + [True]),
                 st.sampled_from([False] * 6 + [True]))


class History:
    """The values N7:0 held, each new, with the time it was set."""

    def __init__(self) -> None:
        self.values = itertools.count(1)
        self.changes: list[tuple[float, int]] = []

    def change(self, sim: Slc500Simulator, now: float) -> None:
        value = next(self.values)
        sim.set_word("N7", 0, value)
        self.changes.append((now, value))

    def replaced_at(self, value: int) -> float:
        index = [v for _, v in self.changes].index(value)
        return self.changes[index + 1][0] if index + 1 < len(self.changes) else float("inf")


def run(fates: list[Fate], gaps: list[float]) -> None:
    sim = Slc500Simulator(Slc500Options(checksum=Checksum.CRC, link_ack_timeout=0.05), ladder=False)
    link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.05, enq_limit=2, nak_limit=2)
    core = Df1Transactions(link, station=1, source=0, reply_timeout=REPLY_TIMEOUT, retries=2, first_tns=7)
    history = History()
    fate_of = iter(fates)
    queue: list[tuple[float, int, str, bytes]] = []
    seq = itertools.count()
    now = 0.0

    def to_sim(data: bytes) -> None:
        if data:
            heapq.heappush(queue, (now + LINE_DELAY, next(seq), "sim", data))

    def to_host(data: bytes) -> None:
        delay, twice, lost = next(fate_of, (0.0, False, False))
        if lost:
            return
        arrival = now + LINE_DELAY + delay * REPLY_TIMEOUT  # no order kept: a later chunk may overtake it
        heapq.heappush(queue, (arrival, next(seq), "host", data))
        if twice:
            heapq.heappush(queue, (arrival + 0.5 * REPLY_TIMEOUT, next(seq), "host", data))

    history.change(sim, now)
    for gap in gaps:
        now += gap * REPLY_TIMEOUT
        history.change(sim, now)
        now += 0.001
        began = now
        handle = core.start(ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2), now, write=False)
        to_sim(core.data_to_send())
        verdict = None
        for _ in range(10_000):
            event = core.next_event()
            if event is not NEED_DATA:
                assert event.handle == handle
                verdict = event
                break
            times = [queue[0][0]] if queue else []
            times += [d for d in (core.next_deadline(), sim.next_deadline()) if d is not None]
            assert times, "nothing left to happen and no verdict"
            now = max(now, min(times))
            while queue and queue[0][0] <= now:
                _, _, to, data = heapq.heappop(queue)
                if to == "sim":
                    for output in sim.receive(data, now):
                        to_host(output.data)
                    history.change(sim, now)
                else:
                    core.receive_data(data, now)
                    to_sim(core.data_to_send())
            core.handle_timeout(now)
            to_sim(core.data_to_send())
            for output in sim.poll(now):
                to_host(output.data)
        assert verdict is not None, "no verdict"
        if isinstance(verdict, TransactionDone):
            value = int.from_bytes(verdict.reply.data, "little")
            assert history.replaced_at(value) >= began, (value, began, history.changes[-8:])
        else:
            assert isinstance(verdict, TransactionFailed), verdict


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fates=st.lists(FATE, max_size=120), gaps=st.lists(st.sampled_from([0.0, 0.3, 1.0, 5.0]), min_size=1,
                                                           max_size=12))
def test_every_read_is_answered_with_a_value_held_after_it_began(fates: list[Fate], gaps: list[float]) -> None:
    run(fates, gaps)


def test_late_and_repeated_replies_of_every_read() -> None:
    """Every reply of the controller two reply timeouts late and sent twice: later reads meet the
    replies of earlier ones first."""
    run([(2.0, True, False)] * 400, [0.0] * 10)
