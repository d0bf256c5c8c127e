"""SLC 100/150 transaction core, sans-I/O: ``;Z``, ``;I``, copies with the same ID, ID 00 resync, verdicts.

Manual: "SLC Programmable Controller Communications Protocol", *Format of Transmission* ([ID],
``;I``, ``;Z``, ``;E``, ``;T``).  The caller owns the port and the clock::

    session = SlcSession(timeout=0.3)
    session.start(command, now)
    port.write(session.data_to_send())
    while session.result is None:
        ... bytes arrive:        session.receive_data(data, now)
        ... next_deadline() due: session.handle_timeout(now)
        port.write(session.data_to_send())
    result = session.result            # Result(verdict, answer, reason)

Facts of the manual the rules rest on:

* the controller handles messages in the order they arrive and answers each at most once;
  the line keeps the order, so replies come back in the order of their messages (some lost,
  garbled or late);
* a message with an unexpected ID is not executed and is answered ``;I <last valid ID>``; the
  controller checks "sequential order", so a second copy of an accepted message is refused;
* ``;Z`` repeats the most recent reply with its ID and does not use up an ID;
* ID 00 "is always accepted": a copy of a command sent with ID 00 is not protected.

Readings the manual leaves open (``docs/develop/controller-variants.md``), all handled here: after a
power cycle ``;I`` carries 00 or the pre-power-up ID, and ``;Z`` is not answered or answered
``;E``; replies may come just after the timeout; a ``;Z`` answer may be garbled again; ``;T``
may come between a command and its reply.

The parts: :mod:`sender` keeps the message IDs and sends (copies with the same ID, ``;Z``, the
ID 00 resync with its barrier; the timeouts); :mod:`write_proof` says what a reply proves about
a write and holds the verdicts; :mod:`session_table` is the transition table.  This module
classifies each reply against the transaction and runs the table's action for it.  Rules of
its own:

* **Reads never fail for want of proof.**  A read that meets ``;I``, runs out of ``;Z`` retries
  or gets a ``;E`` that may answer a ``;Z`` resyncs and asks again (``max_resyncs`` times).
* **A write goes under one ID only** (:mod:`write_proof`): copies with its ID and ``;Z`` until a
  reply with its ID settles it, else ``UNKNOWN`` (applied at most once).  Only a write none of
  whose copies went out resyncs again (and may end ``FAILED``).
* **``;Z`` at once after a complete reply that fails its check**; the timeout is waited out
  only when nothing came.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Final

from gateway.errors import format_seconds
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command, ReplyKind
from gateway.protocols.slc_ascii.framing import (
    NEED_DATA,
    Ack,
    DataReply,
    Fault,
    Garbled,
    IdMismatch,
    Refused,
    ReplyEvent,
)
from gateway.protocols.slc_ascii.sender import MAX_RESENDS, MAX_RESYNCS, SessionCounters, SlcSender, next_id
from gateway.protocols.slc_ascii.session_table import (
    SessionAction,
    SessionInput,
    SessionState,
    SessionTableError,
    transition,
)
from gateway.protocols.slc_ascii.write_proof import (
    Answer,
    MismatchStep,
    RefusalStep,
    Result,
    SlcVerdict,
    judge_id_mismatch,
    judge_refusal,
)

__all__ = [
    "MAX_RESENDS",
    "MAX_RESYNCS",
    "Result",
    "SessionCounters",
    "SessionState",
    "SlcSession",
    "SlcVerdict",
    "next_id",
]

#: the inputs that answer a copy of the command (their delay is its lateness)
_ANSWERS: Final = frozenset({SessionInput.OURS, SessionInput.OURS_REFUSED, SessionInput.ID_OURS,
                             SessionInput.ID_OTHER})


class SlcSession(SlcSender):
    """One SLC 100/150 link's message IDs and the transaction on it (one at a time)."""

    # --- API ------------------------------------------------------------------------------

    def start(self, command: Command, now: float, timeout: float | None = None, *,
              until: float | None = None) -> None:
        """Begin ``command``.  ``until``: a write's time budget (an absolute time) in place of
        the counts of ``;Z`` and resends: it asks again while a further wait fits before
        ``until``, so a write on a line that answers at all gets its verdict; ``UNKNOWN`` only
        when the budget is spent.  Without it, ``retries`` ``;Z`` and ``max_resends`` copies."""
        if self.state is not SessionState.IDLE:
            raise RuntimeError("a transaction is already running")
        self.result = None
        self._command = command
        self._is_write = not command.repeatable
        self._until = until if self._is_write else None
        self._timeout = timeout if timeout is not None else self.timeout
        #: the configured reply time: the last wait before a verdict is never shorter
        self._full_timeout = self._timeout
        if self._timeout <= self.timeout and len(self._reply_times) >= 8:
            self._timeout = min(self._timeout, max(self.min_timeout, 2 * max(self._reply_times)))
        self._resends = self._resyncs = self._probes = self._messages = self._copies = 0
        self._z_ever = False
        self._refused_once = False
        self._began = now
        self._step(SessionInput.START, now, None)

    def receive_data(self, data: bytes, now: float) -> None:
        if data and self.state is SessionState.RESYNC:
            self._heard = True
        self._decoder.receive_data(data)
        self._events(now)
        self._gap_deadline = now + self.char_gap if self._decoder.partial else None

    def _events(self, now: float) -> None:
        while True:
            event = self._decoder.next_event()
            if event is NEED_DATA:
                return
            if isinstance(event, Fault):
                # ;T: unsolicited, "the ID is meaningless"; the caller reads 84H-85H afterwards.
                self.counters.faults += 1
                self.fault_pending = True
                continue
            if isinstance(event, Garbled):
                self.counters.crc_errors += 1
            self._step(self._classify(event), now, event)

    def handle_timeout(self, now: float) -> None:
        if self._gap_deadline is not None and now >= self._gap_deadline:
            self._gap_deadline = None
            garbled = self._decoder.flush_partial()
            if garbled is not None:
                self.counters.crc_errors += 1
                self._step(self._classify(garbled), now, garbled)
            return
        if self._deadline is None or now < self._deadline:
            return
        self._step(SessionInput.TIMEOUT, now, None)

    def take_result(self) -> Result:
        """The finished transaction's result; the session is then ready for the next one."""
        result = self.result
        if result is None:
            raise RuntimeError("no finished transaction")
        self.result = None
        return result

    # --- classification -------------------------------------------------------------------

    def _classify(self, event: ReplyEvent) -> SessionInput:
        state = self.state
        if state in (SessionState.IDLE, SessionState.QUIET):
            return SessionInput.STALE  # late replies of finished transactions
        if isinstance(event, Garbled):
            return SessionInput.GARBLED
        if state is SessionState.RESYNC:
            if isinstance(event, DataReply) and event.msg_id == 0 and any(
                    cmds.answers(probe, event.body_hex) for probe in self._probes_sent):
                return SessionInput.PROBE_ANSWER
            if isinstance(event, Refused) and event.msg_id == 0 and self._probing_with_barrier():
                return SessionInput.PROBE_REFUSED
            if (not self._is_write and self._copies and isinstance(event, DataReply)
                    and event.msg_id == self._msg_id and self._fits(event)):
                return SessionInput.OURS  # a read's answer held back on the line: a value it held, take it
            return SessionInput.STALE  # anything else answers an earlier message
        if isinstance(event, IdMismatch):
            self.counters.id_mismatches += 1
            return SessionInput.ID_OURS if event.last_valid_id == self._msg_id else SessionInput.ID_OTHER
        assert isinstance(event, (Ack, DataReply, Refused))
        if event.msg_id != self._msg_id:
            return SessionInput.OTHER
        if isinstance(event, Refused):
            return SessionInput.OURS_REFUSED
        return SessionInput.OURS if self._fits(event) else SessionInput.OTHER

    def _fits(self, answer: Ack | DataReply) -> bool:
        """Whether ``answer`` answers the command: ``;R`` for a write, else what its parser takes."""
        command = self._command
        if command.reply is ReplyKind.ACK:
            return isinstance(answer, Ack)
        return isinstance(answer, DataReply) and cmds.answers(command, answer.body_hex)

    def _step(self, what: SessionInput, now: float, event: ReplyEvent | None) -> None:
        """Run the table's action for ``what`` and go to the state it chose (one the table allows)."""
        if what in _ANSWERS:
            self._lateness.append(now - self._copy_sent)
        if (self.state in (SessionState.SENT, SessionState.RESYNC)
                and what not in (SessionInput.START, SessionInput.STALE, SessionInput.TIMEOUT)):
            # the first reply to a message we did not have to ask for again: its reply time
            self._reply_times.append(now - self._last_sent)
        entry = transition(self.state, what)
        next_state = _ACTIONS[entry.action](self, now, event)
        if not entry.allows(next_state):
            raise SessionTableError(f"{entry.action.name} on {what.name} in {self.state.name} "
                                    f"went to {next_state.name}, not one of the table's")
        self.state = next_state

    # --- ending ---------------------------------------------------------------------------

    def _finish(self, verdict: SlcVerdict, answer: Answer | None = None, reason: str = "") -> SessionState:
        self.result = Result(verdict, answer, reason)
        self._deadline = None
        if verdict in (SlcVerdict.DONE, SlcVerdict.REFUSED) and self._messages == 1 and self._era_trusted:
            # The one message of this transaction got its answer: the replies to every earlier
            # message came before it (or never will), so none can still come.
            self._clean = True
        if verdict in (SlcVerdict.UNKNOWN, SlcVerdict.FAILED):
            self._next = 0  # we no longer know the controller's ID state
        return SessionState.IDLE

    def _retry_read(self, now: float, why: str) -> SessionState:
        """A read, or a write none of whose copies went out: resync with ID 00 and ask again."""
        assert not (self._is_write and self._copies), (
            "a write whose copy went out never goes under a new ID")
        if not self._may_ask_again(now, self._resyncs, self.max_resyncs):
            return self._finish(SlcVerdict.FAILED, reason=f"{why}; gave up after {self._resyncs} resyncs")
        return self._begin_resync(now)

    def _z_or_give_up(self, now: float, why: str) -> SessionState:
        if self._may_ask_again(now, self._z_sent, self.retries):
            return self._send_z(now)
        what = f"{why} to {self._command.name} after {self._z_sent} retransmit requests"
        if self._until is not None:
            what += f" in {format_seconds(now - self._began)} s"
        if self._is_write:
            return self._finish(SlcVerdict.UNKNOWN, reason=what)
        return self._retry_read(now, what)

    # --- actions (one per SessionAction) --------------------------------------------------

    def _begin(self, now: float, event: ReplyEvent | None) -> SessionState:
        if self._next == 0 or (self._is_write and not (self._era_trusted and self._clean)):
            return self._begin_resync(now)
        return self._send_first_copy(now)

    def _ignore(self, now: float, event: ReplyEvent | None) -> SessionState:
        return self.state

    def _on_answer(self, now: float, event: ReplyEvent | None) -> SessionState:
        assert isinstance(event, (Ack, DataReply))
        return self._finish(SlcVerdict.DONE, event)

    def _on_late_read_answer(self, now: float, event: ReplyEvent | None) -> SessionState:
        assert isinstance(event, DataReply)
        state = self._finish(SlcVerdict.DONE, event)
        self._next = 0  # our ID 00 read is still on its way: begin the next with a resync again
        return state

    def _on_refused(self, now: float, event: ReplyEvent | None) -> SessionState:
        step = judge_refusal(is_write=self._is_write, era_trusted=self._era_trusted,
                             refused_once=self._refused_once, z_sent=self._z_ever, copies=self._copies)
        if step is RefusalStep.CONFIRM:
            self._refused_once = True
            return self._retry_read(now, why=";E to be confirmed")
        if step is RefusalStep.REFUSED:
            return self._finish(SlcVerdict.REFUSED, reason="illegal command or parameters for the current mode")
        if step is RefusalStep.UNKNOWN:
            return self._finish(SlcVerdict.UNKNOWN, reason=";E after ;Z or to a later copy: refused, or an earlier "
                                                           "copy ran")
        return self._retry_read(now, why=";E after ;Z")

    def _on_other_in_z(self, now: float, event: ReplyEvent | None) -> SessionState:
        # The controller's last reply may be older than our command (it never got it), or this
        # is a late reply to an earlier message.  Resending with the same ID is safe either way.
        if not self._may_ask_again(now, self._resends, self.max_resends):
            if self._is_write:
                return self._finish(SlcVerdict.UNKNOWN, reason="the controller keeps answering an older message")
            return self._retry_read(now, why="the controller keeps answering an older message")
        self._resends += 1
        self.counters.resends += 1
        return self._send_copy(now)

    def _on_id_ours(self, now: float, event: ReplyEvent | None) -> SessionState:
        # An earlier copy of this very message was accepted.
        if not self._is_write:
            return self._retry_read(now, why=";I: message ID out of step")
        if not self._may_ask_again(now, self._z_sent, self.retries + 1):
            return self._finish(SlcVerdict.UNKNOWN, reason=";I with our ID, and no answer to ;Z")
        return self._send_z(now)

    def _on_id_other(self, now: float, event: ReplyEvent | None) -> SessionState:
        assert isinstance(event, IdMismatch)
        last = event.last_valid_id
        if not self._is_write:
            return self._retry_read(now, why=f";I{last:02X}: message ID out of step")
        # A power-cycled controller's answer to a copy, or a stale or repeated reply: no proof
        # either way, and never a new ID.
        step = judge_id_mismatch(
            copies=self._copies,
            may_resend=self._may_ask_again(now, self._resends, self.max_resends),
            may_ask_z=self._may_ask_again(now, self._z_sent, self.retries + 1))
        if step is MismatchStep.SECOND_COPY:
            self._resends += 1
            self.counters.resends += 1
            return self._send_copy(now)
        if step is MismatchStep.UNKNOWN:
            return self._finish(SlcVerdict.UNKNOWN, reason=f";I{last:02X} and no answer with our ID: the controller "
                                                           f"may have power-cycled after the command ran")
        return self._send_z(now)

    def _on_garbled(self, now: float, event: ReplyEvent | None) -> SessionState:
        # A complete reply failed its check: ask for it again at once.
        return self._z_or_give_up(now, why="garbled replies")

    def _on_timeout(self, now: float, event: ReplyEvent | None) -> SessionState:
        self.counters.timeouts += 1
        return self._z_or_give_up(now, why="no valid answer")

    def _on_z_timeout(self, now: float, event: ReplyEvent | None) -> SessionState:
        self.counters.timeouts += 1
        if not self._is_write:
            # Silence after ;Z: power-cycled (no last reply to repeat) or lost again.  A read
            # need not find out which: ask again under a new numbering.
            return self._retry_read(now, why="no answer to ;Z")
        return self._z_or_give_up(now, why="no valid answer")

    def _on_probe_answer(self, now: float, event: ReplyEvent | None) -> SessionState:
        # The barrier: the controller expects 01 next, and no earlier reply can follow.
        self._next = 1
        self._clean = self._era_trusted
        if self._clean:
            self._messages = 0  # nothing sent before the barrier can still be answered
        return self._send_first_copy(now)

    def _on_probe_refused(self, now: float, event: ReplyEvent | None) -> SessionState:
        # The controller refuses reads (program mode): resync with read FRN after quiet.
        return self._enter_quiet(now)

    def _on_probe_garbled(self, now: float, event: ReplyEvent | None) -> SessionState:
        # Perhaps the probe's answer: send the (harmless) probe again at once.
        self._heard = True
        return self._probe_again(now)

    def _on_probe_timeout(self, now: float, event: ReplyEvent | None) -> SessionState:
        self.counters.timeouts += 1
        return self._probe_again(now)

    def _probe_again(self, now: float) -> SessionState:
        if not self._may_ask_again(now, self._probes, self.retries + 1):
            why = (f"no answer to {self._probe.name} with ID 00 (resync) within {format_seconds(self._full_timeout)} s "
                   f"after {self._probes} tries")
            if self._heard:
                return self._retry_read(now, why)  # the controller is there, the line is bad: go on
            return self._finish(SlcVerdict.FAILED, reason=why)  # silence: fail fast (a dead line)
        return self._send_probe(now)

    def _on_quiet_over(self, now: float, event: ReplyEvent | None) -> SessionState:
        return self._after_quiet(now)


_Action = Callable[[SlcSession, float, ReplyEvent | None], SessionState]

#: The method that runs each action of the table (UNREACHABLE never runs: the lookup raises).
_ACTIONS: Final[Mapping[SessionAction, _Action]] = {
    SessionAction.BEGIN: SlcSession._begin,
    SessionAction.ANSWER: SlcSession._on_answer,
    SessionAction.LATE_READ_ANSWER: SlcSession._on_late_read_answer,
    SessionAction.REFUSED: SlcSession._on_refused,
    SessionAction.RESEND: SlcSession._on_other_in_z,
    SessionAction.ID_OURS: SlcSession._on_id_ours,
    SessionAction.ID_OTHER: SlcSession._on_id_other,
    SessionAction.GARBLED: SlcSession._on_garbled,
    SessionAction.TIMEOUT: SlcSession._on_timeout,
    SessionAction.Z_TIMEOUT: SlcSession._on_z_timeout,
    SessionAction.PROBE_ANSWER: SlcSession._on_probe_answer,
    SessionAction.PROBE_REFUSED: SlcSession._on_probe_refused,
    SessionAction.PROBE_GARBLED: SlcSession._on_probe_garbled,
    SessionAction.PROBE_TIMEOUT: SlcSession._on_probe_timeout,
    SessionAction.QUIET_OVER: SlcSession._on_quiet_over,
    SessionAction.IGNORE: SlcSession._ignore,
}
