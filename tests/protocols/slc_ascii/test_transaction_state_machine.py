"""The SLC 100/150 transaction core against a model controller on a long, dense faulty line.

A hypothesis state machine: the core (:class:`SlcSession`, sans-I/O) runs reads and writes
against the simulator (:class:`SlcAsciiSimulator`, sans-I/O) under any combination of its variants
(every reading of the manual it has), through :class:`ModelLine`, a fake line with a fake clock.
The fault script is long and dense, and it never runs out: hundreds of reply fates (delivered,
dropped, garbled, truncated, late, delivered twice), fates for the frames we send (lost, delivered
twice: a line that repeats a frame), and power cycles (before any frame we send, ``;Z`` too, and
between a frame and the line's repeat of it), all repeated for as long as the machine runs, so a
transaction never gets the perfect line a short burst of faults ends in.

After every step, whatever the line did:

* no write is applied twice (each write carries a value no other write has);
* a write answered DONE was applied; one answered REFUSED or FAILED was not, and never is later;
* a write answered UNKNOWN was applied at most once;
* a read answered DONE returns a value the controller held at that address (its initial value or
  one a write applied);
* a write goes out only in an ID numbering begun with a barrier: an ID 00 resync sent on a quiet
  line (no reply to an earlier message could still come: ``late_bound`` after the message before
  it), or reads no earlier message's answer looks like; so no reply from before carries the
  write's ID, the only replies its verdict rests on;
* after a transaction ends UNKNOWN or FAILED the next one begins with an ID 00 resync: the
  controller's ID state is not known.

The default run is small enough for ``make test``.  More examples::

    SLC_CORE_EXAMPLES=5000 .venv/bin/python -m pytest tests/protocols/slc_ascii/test_transaction_state_machine.py
"""

from __future__ import annotations

import heapq
import itertools
import os
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.framing import NEED_DATA, CommandDecoder, CommandFrame, DataReply
from gateway.protocols.slc_ascii.transaction import Result, SlcSession, SlcVerdict
from gateway.sim.variants import variant_matrix

TIMEOUT = 0.3
ADDRESSES = (0x40, 0x42, 0x44)
VARIANTS = list(variant_matrix(SlcAsciiSimulator.VARIANTS))
#: a reply's fate on the line
REPLY_FAULTS = ("drop", "garble", "truncate", "late", "twice")
#: a frame we send: lost on the way, or delivered twice (a device server that repeats a frame)
COMMAND_FAULTS = ("lost", "twice")
EXAMPLES = int(os.environ.get("SLC_CORE_EXAMPLES", "200"))


@dataclass(frozen=True)
class Sent:
    """One frame the core put on the line."""

    time: float
    frame: CommandFrame | None  # None: ;Z


@dataclass
class ModelLine:
    """The simulator behind a line that keeps the order of the replies (a late one holds back
    those after it) and follows a fault script that repeats for ever."""

    sim: SlcAsciiSimulator
    session: SlcSession
    reply_fates: Iterator[str]
    command_fates: Iterator[str]
    power_cycles: Iterator[bool]
    late: float  # a late reply comes this long after the frame it answers (at most late_bound)
    now: float = 0.0
    sent: list[Sent] = field(default_factory=list)
    _queue: list[tuple[float, int, bytes]] = field(default_factory=list)
    _seq: Iterator[int] = field(default_factory=itertools.count)
    _line_free: float = 0.0
    _decoder: CommandDecoder = field(default_factory=CommandDecoder)

    def _to_controller(self, data: bytes) -> None:
        self._decoder.receive_data(data)
        while (event := self._decoder.next_event()) is not NEED_DATA:
            self.sent.append(Sent(self.now, event if isinstance(event, CommandFrame) else None))
        for frame in data.split(b"\r"):
            if not frame:
                continue
            frame += b"\r"
            fate = next(self.command_fates)
            deliveries = {"lost": 0, "twice": 2}.get(fate, 1)
            # the controller may power-cycle before any frame, ;Z included, and between a frame and
            # the line's repeat of it
            for _ in range(max(1, deliveries)):
                if next(self.power_cycles):
                    self.sim.power_cycle()
                if deliveries:
                    for out in self.sim.receive(frame, self.now):
                        self._reply(out.data, self.now + 0.001 + out.delay)

    def _reply(self, reply: bytes, arrival: float) -> None:
        fate = next(self.reply_fates)
        if fate == "drop":
            return
        if fate == "garble":
            middle = len(reply) // 2
            reply = reply[:middle] + bytes([reply[middle] ^ 0x01]) + reply[middle + 1 :]
        elif fate == "truncate":
            reply = reply[: max(1, len(reply) - 3)]
        elif fate == "late":
            arrival = self.now + self.late
        copies = 2 if fate == "twice" else 1
        for _ in range(copies):
            arrival = max(arrival, self._line_free)
            self._line_free = arrival
            heapq.heappush(self._queue, (arrival, next(self._seq), reply))

    def run(self, command: cmds.Command) -> Result:
        session = self.session
        session.start(command, self.now)
        steps = 0
        while session.result is None:
            steps += 1
            assert steps < 100_000, "the core does not finish"
            data = session.data_to_send()
            if data:
                self._to_controller(data)
                continue
            deadline = session.next_deadline()
            assert deadline is not None, "a running transaction always has a deadline"
            if self._queue and self._queue[0][0] <= deadline:
                arrival, _, reply = heapq.heappop(self._queue)
                self.now = max(self.now, arrival)
                session.receive_data(reply, self.now)
            else:
                self.now = max(self.now, deadline)
                session.handle_timeout(self.now)
        data = session.data_to_send()
        if data:
            self._to_controller(data)
        return session.take_result()

    def idle(self, seconds: float) -> None:
        """Time passes with no transaction; replies still on the line arrive."""
        end = self.now + seconds
        while self._queue and self._queue[0][0] <= end:
            arrival, _, reply = heapq.heappop(self._queue)
            self.now = max(self.now, arrival)
            self.session.receive_data(reply, self.now)
        self.now = end


def _script(fates: list[str], ok_share: int) -> Iterator[str]:
    """The fates, each fault among ``ok_share`` deliveries, repeated for ever."""
    return itertools.cycle(list(itertools.chain.from_iterable(["ok"] * ok_share + [f] for f in fates)) or ["ok"])


class SlcCoreOnAFaultyLine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.line: ModelLine | None = None
        self.values = itertools.count(1)
        self.outcome: dict[tuple[int, int], SlcVerdict] = {}  # write -> its verdict
        self.initial: dict[int, int] = {}
        self.checked_frames = 0
        self.after_unknown_from = -1  # index in line.sent of the first frame after an UNKNOWN/FAILED

    @initialize(
        variants=st.sampled_from(VARIANTS),
        reply_faults=st.lists(st.sampled_from(REPLY_FAULTS), min_size=100, max_size=400),
        reply_ok_share=st.integers(0, 4),
        command_faults=st.lists(st.sampled_from(COMMAND_FAULTS), min_size=1, max_size=60),
        command_ok_share=st.integers(1, 12),
        power_every=st.integers(3, 60),
        power_phase=st.integers(0, 59),
        late=st.floats(1.0, 1.45),
    )
    def connect(self, variants: dict[str, str], reply_faults: list[str], reply_ok_share: int,
                command_faults: list[str], command_ok_share: int, power_every: int, power_phase: int,
                late: float) -> None:
        sim = SlcAsciiSimulator(faults=FaultPlan(late_delay=1.2 * TIMEOUT), ladder=False, variants=variants)
        session = SlcSession(timeout=TIMEOUT, retries=3)
        power = itertools.cycle([n == power_phase % power_every for n in range(power_every)])
        self.line = ModelLine(sim, session, _script(reply_faults, reply_ok_share),
                              _script(command_faults, command_ok_share), power, late * TIMEOUT)
        self.initial = {a: sim.word(a) for a in ADDRESSES}

    def _line(self) -> ModelLine:
        assert self.line is not None
        return self.line

    def _ended(self, result: Result) -> None:
        if result.verdict in (SlcVerdict.UNKNOWN, SlcVerdict.FAILED):
            self.after_unknown_from = len(self._line().sent)

    @precondition(lambda self: self.line is not None)
    @rule(address=st.sampled_from(ADDRESSES))
    def write(self, address: int) -> None:
        value = next(self.values)
        result = self._line().run(cmds.write_word(address, value))
        self.outcome[(address, value)] = result.verdict
        self._ended(result)

    @precondition(lambda self: self.line is not None)
    @rule(address=st.sampled_from(ADDRESSES))
    def read(self, address: int) -> None:
        line = self._line()
        result = line.run(cmds.read_bytes(address, 2))
        if result.verdict is SlcVerdict.DONE:
            assert isinstance(result.answer, DataReply)
            got = int.from_bytes(cmds.parse_read_reply(address, 2, result.answer.body_hex), "big")
            held = {self.initial[address]} | {v for kind, a, v in line.sim.applied_writes if a == address}
            assert got in held, f"read 0x{address:02X} = {got}: the controller never held it ({sorted(held)})"
        else:
            assert result.verdict is SlcVerdict.FAILED, result
        self._ended(result)

    @precondition(lambda self: self.line is not None)
    @rule(seconds=st.sampled_from([0.0, 0.05, 0.2, 0.5, 2.0]))
    def idle(self, seconds: float) -> None:
        self._line().idle(seconds)

    @invariant()
    def writes_land_at_most_once_and_as_reported(self) -> None:
        if self.line is None:
            return
        applied = Counter((a, v) for kind, a, v in self.line.sim.applied_writes if kind == "word")
        twice = {w: n for w, n in applied.items() if n > 1}
        assert not twice, f"writes applied more than once: {twice} ({self._outcomes(twice)})"
        for write, verdict in self.outcome.items():
            if verdict is SlcVerdict.DONE:
                assert applied[write] == 1, f"write {write} acknowledged, but never applied"
            elif verdict in (SlcVerdict.REFUSED, SlcVerdict.FAILED):
                assert applied[write] == 0, f"write {write} answered {verdict.name}, but applied"
        unreported = set(applied) - set(self.outcome)
        assert not unreported, f"writes applied that were never asked for: {unreported}"

    def _outcomes(self, writes: dict[tuple[int, int], int]) -> dict[tuple[int, int], str]:
        return {w: self.outcome[w].name if w in self.outcome else "running" for w in writes}

    @invariant()
    def writes_go_out_only_in_a_numbering_begun_with_a_barrier(self) -> None:
        """The resync before a write is a barrier: sent on a quiet line, or every ID 00 frame of
        it a read of an address no ID 00 frame asked for within ``late_bound`` before it (its
        answer then echoes what no earlier message's answer does)."""
        if self.line is None:
            return
        sent = self.line.sent
        late_bound = self.line.session.late_bound
        for n in range(self.checked_frames, len(sent)):
            frame = sent[n].frame
            if frame is None or frame.msg_id == 0 or frame.code != cmds.CommandCode.WRITE:
                continue
            # the last run of ID 00 frames before this write: one resync, or several back to back
            last = max(i for i in range(n) if (f := sent[i].frame) is not None and f.msg_id == 0)
            first = last
            while first > 0 and (before := sent[first - 1].frame) is not None and before.msg_id == 0:
                first -= 1
            if first == 0:
                continue  # the session's first resync: nothing was sent before it
            gaps = [sent[i].time - sent[i - 1].time for i in range(first, last + 1)]
            if max(gaps) >= late_bound - 1e-9:
                continue

            def unique(i: int) -> bool:
                probe = sent[i].frame
                assert probe is not None
                return probe.code == cmds.CommandCode.READ and not any(
                    (other := sent[j].frame) is not None and other.msg_id == 0 and other.params == probe.params
                    and sent[i].time - sent[j].time < late_bound for j in range(i))

            assert all(unique(i) for i in range(first, last + 1)), (
                f"write with ID {frame.msg_id:02X} at {sent[n].time:.3f} s in a numbering whose resync "
                f"(ID 00 frames at {[round(sent[i].time, 3) for i in range(first, last + 1)]}) was neither sent "
                f"on a quiet line (late_bound {late_bound:.3f} s) nor a read no earlier answer looks like"
            )
        self.checked_frames = len(sent)

    @invariant()
    def after_an_unknown_outcome_the_next_transaction_resyncs(self) -> None:
        if self.line is None or self.after_unknown_from < 0:
            return
        sent = self.line.sent
        if len(sent) > self.after_unknown_from:
            first = sent[self.after_unknown_from].frame
            assert first is not None and first.msg_id == 0, (
                f"after an UNKNOWN or FAILED outcome the next transaction began with {first}, not an ID 00 resync"
            )
            self.after_unknown_from = -1


SlcCoreOnAFaultyLine.TestCase.settings = settings(
    max_examples=EXAMPLES,
    stateful_step_count=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
test_slc_core_on_a_long_dense_faulty_line = SlcCoreOnAFaultyLine.TestCase
