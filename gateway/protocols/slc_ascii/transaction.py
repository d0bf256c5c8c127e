"""SLC 100/150 transaction core, sans-I/O: ``;Z``, ``;I``, resend after proof, ID 00 resync, verdicts.

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

Readings the manual leaves open (``docs/controller-variants.md``), all handled here: after a
power cycle ``;I`` carries 00 or the pre-power-up ID, and ``;Z`` is not answered or answered
``;E``; replies may come just after the timeout; a ``;Z`` answer may be garbled again; ``;T``
may come between a command and its reply.

Rules:

* **Resends keep the ID.**  A copy with the same ID is never executed twice (the ID check).
* **ID 00 (resync) with a barrier.**  The controller's numbering restarts with a harmless read
  with ID 00 whose answer no earlier message can have: one byte at an address no ID 00 read
  asked for within the quiet time (its answer echoes the address).  The controller answers in
  order and the line keeps it, so that answer is a barrier: no reply of an earlier message
  follows it, and a reply with the same ID from before is never taken for an answer.  A write
  on a line where an earlier reply may still come (not *clean*) resyncs first.  Only when the
  controller refuses reads (program mode) does the resync wait for quiet (``late_bound``, 1.5 x
  the reply time, or more when replies were seen coming later) and read the FRN instead.
* **Timeouts adapt.**  The reply timeout is 2 x the slowest of the last 32 first replies (at
  least ``min_timeout``, at most the configured one); the waits that decide a verdict (the last
  resync read, a write's last ``;Z``) keep the configured time.  A frame whose next character
  does not come within ``char_gap`` is garbled at once.
* **Reads never fail for want of proof.**  A read that meets ``;I``, runs out of ``;Z`` retries
  or gets a ``;E`` that may answer a ``;Z`` resyncs and asks again (``max_resyncs`` times).
* **Writes are resent under a new ID only after proof of non-execution**: a ``;I`` to a copy of
  the command, in a transaction that began with no reply of an earlier message still due,
  that reports the ID before ours (not 00: a controller may report 00 after any power cycle),
  or a ``;I`` of another kind when only one copy was ever sent (it answers that copy: it was not
  executed).  A ``;I`` with the ID before ours to the first copy is not proof yet: it may answer
  a copy of the previous message that the line repeated (refused after the previous message ran),
  heard while ours is on its way; a second copy with our ID settles it (``;I`` with our ID: ours
  ran).  ``;I`` with our own ID proves an earlier copy was accepted: ``;Z`` fetches its
  answer (``;R`` or ``;E``).  Without proof, after the retries, the verdict is
  ``UNKNOWN`` (the gateway answers 0x0B); the command was applied at most once.
* **``;Z`` at once after a complete reply that fails its check**; the timeout is waited out
  only when nothing came.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from gateway.errors import format_seconds
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command, ReplyKind
from gateway.protocols.slc_ascii.framing import (
    MAX_ID,
    NEED_DATA,
    Ack,
    DataReply,
    Fault,
    Garbled,
    IdMismatch,
    Refused,
    ReplyDecoder,
    ReplyEvent,
    encode_command,
    encode_retransmit,
)
from gateway.protocols.slc_ascii.memory_map import is_readable

__all__ = ["Result", "SessionCounters", "SessionState", "SlcSession", "Verdict", "next_id"]

Answer = Ack | DataReply

#: How many times one transaction resends its command under the same ID (after a hint that the
#: controller did not get it) before it stops.
MAX_RESENDS: Final = 8
#: How many ID 00 resyncs one transaction may do (reads: each one asks again).
MAX_RESYNCS: Final = 8

_PROBE: Final = cmds.read_frn()
#: Bytes a barrier read may ask for (every readable byte of the "Reading Data" list).
_BARRIER_ADDRESSES: Final = tuple(a for a in range(0x113) if is_readable(a, 1))


def next_id(msg_id: int) -> int:
    """The ID after ``msg_id``: 01..7F, then 01 again ("roll over from 127D to 01")."""
    return 1 if msg_id >= MAX_ID else msg_id + 1


class Verdict(enum.Enum):
    DONE = "done"  # answered (;R or data)
    REFUSED = "refused"  # ;E to the command itself: not executed
    UNKNOWN = "unknown"  # a write without proof either way: executed at most once
    FAILED = "failed"  # no answer within the bounds (a read, or a write proved not executed)


@dataclass(frozen=True, slots=True)
class Result:
    verdict: Verdict
    answer: Answer | None = None
    reason: str = ""


class SessionState(enum.Enum):
    IDLE = "idle"
    QUIET = "quiet"  # waiting for the line to be quiet before a resync
    RESYNC = "resync"  # the ID 00 probe sent, waiting for its answer
    SENT = "sent"  # a copy of the command sent
    Z_SENT = "z_sent"  # ;Z sent, waiting for the controller's last reply
    PROVING = "proving"  # a write's proof of non-execution in, waiting until no reply to our copies can come


class _In(enum.Enum):
    """What happened, as the transition table sees it."""

    OURS = "answer with our ID that fits the command"
    OURS_REFUSED = ";E with our ID"
    OTHER = "an answer with another ID (or one that does not fit)"
    ID_OURS = ";I with our ID"
    ID_OTHER = ";I with another ID"
    GARBLED = "a complete reply that fails its check"
    PROBE_ANSWER = "the answer to the ID 00 probe"
    PROBE_REFUSED = ";E 00 to a barrier read (reads are refused: program mode)"
    TIMEOUT = "deadline passed"


_Handler = Callable[["SlcSession", float, ReplyEvent | None], None]


@dataclass
class SessionCounters:
    timeouts: int = 0
    crc_errors: int = 0
    retransmits: int = 0  # ;Z sent
    id_resyncs: int = 0  # ID 00 resyncs (the one after connecting included)
    handshakes: int = 0  # ... of which the first after connecting (not a recovery)
    id_mismatches: int = 0  # ;I received in a transaction
    resends: int = 0  # copies of a command sent again (same ID)
    faults: int = 0  # ;T received
    quiet_waits: int = 0


class SlcSession:
    """One SLC 100/150 link's message IDs and the transaction on it (one at a time)."""

    def __init__(
        self,
        *,
        timeout: float = 0.3,
        retries: int = 3,
        max_resends: int = MAX_RESENDS,
        max_resyncs: int = MAX_RESYNCS,
        late_bound: float | None = None,
        char_gap: float = 0.05,
        min_timeout: float = 0.05,
    ) -> None:
        self.timeout = timeout
        self.retries = retries
        self.max_resends = max_resends
        self.max_resyncs = max_resyncs
        #: a reply arrives at most this long after its message (replies "just after the timeout"; an
        #: assumption of the design, docs/controller-variants.md)
        self.late_bound = late_bound if late_bound is not None else 1.5 * timeout
        #: a frame whose next character does not come within this is cut short (garbled)
        self.char_gap = char_gap
        #: the reply timeout adapts to the controller's measured reply time (2 x the slowest of the
        #: last 32 replies), between min_timeout and the configured timeout ("Normally the SLC
        #: will respond within 0.3 seconds": an upper bound).  An early ;Z is harmless: it uses
        #: up no ID, and the controller handles it after the command it follows.
        self.min_timeout = min_timeout
        self._reply_times: deque[float] = deque(maxlen=32)
        #: how long after a copy of the command its answers came (an upper bound of their lateness)
        self._lateness: deque[float] = deque(maxlen=32)
        self._gap_deadline: float | None = None
        #: the current ID numbering began with a barrier sent after quiet (writes need it)
        self._era_trusted = False
        self.counters = SessionCounters()
        self.fault_pending = False
        self.result: Result | None = None
        self.state = SessionState.IDLE
        self._decoder = ReplyDecoder()
        self._out = bytearray()
        self._next = 0  # ID of the next command; 0: resync first
        self._handshake_due = True  # the next resync is the first after connecting
        self._last_sent = float("-inf")
        #: no reply of a command copy sent earlier can still come (a write's ;I proof needs it)
        self._clean = True
        self._deadline: float | None = None
        # the transaction
        self._command: Command = _PROBE
        #: the resync's ID 00 message: read FRN, or a barrier read (see _begin_resync)
        self._probe: Command = _PROBE
        #: every ID 00 message of this resync: an answer to any of them ends it
        self._probes_sent: list[Command] = []
        #: per barrier address, when it was last asked for; the next one to try
        self._barrier_sent: dict[int, float] = {}
        self._barrier_next = 0
        #: the controller answered a barrier read ;E (program mode): resync with read FRN
        self._barrier_refused = False
        self._is_write = False
        self._timeout = timeout
        self._msg_id = 0
        self._prev_id = 0
        self._last_taken = 0
        self._copies = 0
        self._z_sent = 0
        self._z_ever = False
        self._resends = 0
        self._resyncs = 0
        self._probes = 0
        self._messages = 0
        self._began_clean = True
        self._heard = False
        self._refused_once = False
        self._copy_sent = 0.0
        self._began = 0.0
        self._why = ""
        self._full_timeout = timeout
        self._until: float | None = None

    # --- API ------------------------------------------------------------------------------

    def connected(self) -> None:
        """A new stream: forget the decoder state; the first command resyncs."""
        self._last_sent = float("-inf")
        self._decoder = ReplyDecoder()
        self._out.clear()
        self._next = 0
        self._handshake_due = True
        self._clean = True
        self._era_trusted = False
        self._deadline = None
        self._gap_deadline = None
        self.state = SessionState.IDLE
        self.result = None

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
        self._is_write = command.is_write or command.code == cmds.CommandCode.UPLOAD
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
        if self._next == 0 or (self._is_write and not (self._era_trusted and self._clean)):
            self._begin_resync(now)
        else:
            self._send_first_copy(now)

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
            kind = self._classify(event)
            if kind is None:
                continue
            self._step(kind, now, event)

    def handle_timeout(self, now: float) -> None:
        if self._gap_deadline is not None and now >= self._gap_deadline:
            self._gap_deadline = None
            garbled = self._decoder.flush_partial()
            if garbled is not None:
                self.counters.crc_errors += 1
                kind = self._classify(garbled)
                if kind is not None:
                    self._step(kind, now, garbled)
            return
        if self._deadline is None or now < self._deadline:
            return
        self._step(_In.TIMEOUT, now, None)

    def next_deadline(self) -> float | None:
        if self._gap_deadline is not None and self.state is not SessionState.IDLE:
            if self._deadline is None or self._gap_deadline < self._deadline:
                return self._gap_deadline
        return self._deadline

    def data_to_send(self) -> bytes:
        data = bytes(self._out)
        self._out.clear()
        return data

    def take_result(self) -> Result:
        """The finished transaction's result; the session is then ready for the next one."""
        result = self.result
        if result is None:
            raise RuntimeError("no finished transaction")
        self.result = None
        return result

    # --- classification -------------------------------------------------------------------

    def _classify(self, event: ReplyEvent) -> _In | None:
        state = self.state
        if state in (SessionState.IDLE, SessionState.QUIET):
            return None  # late replies of finished transactions
        if isinstance(event, Garbled):
            return _In.GARBLED
        if state is SessionState.RESYNC:
            if isinstance(event, DataReply) and event.msg_id == 0 and any(
                    cmds.answers(probe, event.body_hex) for probe in self._probes_sent):
                return _In.PROBE_ANSWER
            if isinstance(event, Refused) and event.msg_id == 0 and self._probe is not _PROBE:
                return _In.PROBE_REFUSED
            if (not self._is_write and self._copies and isinstance(event, DataReply)
                    and event.msg_id == self._msg_id and self._fits(event)):
                return _In.OURS  # a read's answer held back on the line: a value it held, take it
            return None  # anything else answers an earlier message
        if isinstance(event, IdMismatch):
            self.counters.id_mismatches += 1
            return _In.ID_OURS if event.last_valid_id == self._msg_id else _In.ID_OTHER
        assert isinstance(event, (Ack, DataReply, Refused))
        if event.msg_id != self._msg_id:
            return _In.OTHER
        if isinstance(event, Refused):
            return _In.OURS_REFUSED
        return _In.OURS if self._fits(event) else _In.OTHER

    def _fits(self, answer: Ack | DataReply) -> bool:
        """Whether ``answer`` answers the command: ``;R`` for a write, else what its parser takes."""
        command = self._command
        if command.reply is ReplyKind.ACK:
            return isinstance(answer, Ack)
        return isinstance(answer, DataReply) and cmds.answers(command, answer.body_hex)

    def _step(self, kind: _In, now: float, event: ReplyEvent | None) -> None:
        if kind in (_In.OURS, _In.OURS_REFUSED, _In.ID_OURS, _In.ID_OTHER):
            self._lateness.append(now - self._copy_sent)
        if self.state in (SessionState.SENT, SessionState.RESYNC) and kind is not _In.TIMEOUT:
            # the first reply to a message we did not have to ask for again: its reply time
            self._reply_times.append(now - self._last_sent)
        handler = _TRANSITIONS.get((self.state, kind))
        if handler is not None:
            handler(self, now, event)

    # --- sending --------------------------------------------------------------------------

    def _send(self, frame: bytes, now: float, timeout: float) -> None:
        self._out += frame
        self._last_sent = now
        self._messages += 1
        self._deadline = now + timeout

    def _send_first_copy(self, now: float) -> None:
        self._prev_id = self._last_taken
        self._msg_id = self._last_taken = self._next
        self._next = next_id(self._next)
        self._copies = 0
        self._began_clean = self._clean
        self._send_copy(now)

    def _send_copy(self, now: float) -> None:
        self._copy_sent = now
        self._copies += 1
        self._z_sent = 0
        self._clean = False
        self.state = SessionState.SENT
        self._send(encode_command(self._command, self._msg_id), now, self._timeout)

    def _send_z(self, now: float) -> None:
        self._z_sent += 1
        self._z_ever = True
        self.counters.retransmits += 1
        self.state = SessionState.Z_SENT
        # a write's last ;Z waits the full reply time: its answer may be held back on the line
        last = self._is_write and not self._may_ask_again(now + self._timeout, self._z_sent, self.retries)
        self._send(encode_retransmit(self._msg_id), now, self._full_timeout if last else self._timeout)

    def _may_ask_again(self, now: float, asked: int, limit: int) -> bool:
        """Whether one more ``;Z`` / copy / probe may go: within the count, or the time budget."""
        if self._until is None:
            return asked < limit
        return now + self._timeout <= self._until

    def _quiet_time(self) -> float:
        """How long after our last message no reply to it can come: ``late_bound``, or more
        when answers were seen coming later than that (a controller slower than configured)."""
        return max(self.late_bound, 1.5 * max(self._lateness, default=0.0))

    def _enter_quiet(self, now: float) -> None:
        """Wait until no reply to our last message can still come, then resync with read FRN."""
        quiet_at = self._last_sent + self._quiet_time()
        if now >= quiet_at:
            self._after_quiet(now)
            return
        self.counters.quiet_waits += 1
        self.state = SessionState.QUIET
        self._deadline = quiet_at

    def _after_quiet(self, now: float) -> None:
        self._clean = True
        self._era_trusted = True
        self._barrier_refused = False  # the controller may take barrier reads again later
        self._probe = _PROBE
        self._send_probe(now)

    def _begin_resync(self, now: float) -> None:
        """Restart the numbering with an ID 00 message whose answer is a *barrier*: no reply to
        an earlier message can follow it (the controller answers in order, the line keeps it).

        It must be told from every earlier message's answer: a read of one byte at an address
        no earlier ID 00 read asked for within the quiet time (its answer echoes the address),
        so it needs no wait.  On a line quiet already, or when the controller refuses reads
        (program mode), read FRN after quiet instead.  A read may resync at once with read FRN
        when no barrier read is free (the numbering is then not trusted for writes).

        An answer to any ID 00 message of this resync ends it.  Only the answers to its later
        tries can still follow: data replies with ID 00, which no command (IDs 01-7F) and no
        later resync (other addresses) can take for its own.
        """
        self._resyncs += 1
        self.counters.id_resyncs += 1
        if self._handshake_due:
            self._handshake_due = False
            self.counters.handshakes += 1
        self._probes = 0
        self._probes_sent.clear()
        self._heard = False
        self._next = 0
        quiet = now >= self._last_sent + self._quiet_time()
        if not quiet and not self._barrier_refused and self._barrier_free(now):
            self._era_trusted = True
            self._send_probe(now)
        elif self._is_write or quiet:
            self._enter_quiet(now)
        else:
            self._era_trusted = False
            self._probe = _PROBE
            self._send_probe(now)

    def _barrier_free(self, now: float) -> bool:
        """Choose the next barrier read; False if its address was asked for too recently."""
        address = _BARRIER_ADDRESSES[self._barrier_next % len(_BARRIER_ADDRESSES)]
        if now - self._barrier_sent.get(address, float("-inf")) < self._quiet_time():
            return False
        self._barrier_next += 1
        self._barrier_sent[address] = now
        self._probe = cmds.read_bytes(address, 1)
        return True

    def _send_probe(self, now: float) -> None:
        if self._probe is not _PROBE and self._probes and not self._barrier_free(now):
            # a second try asks for another address (the first one's answer may still come);
            # none free: a write waits for quiet, a read takes read FRN at once
            if self._is_write:
                self._enter_quiet(now)
                return
            self._era_trusted = False
            self._probe = _PROBE
        self._probes += 1
        self.state = SessionState.RESYNC
        # the last try waits the full reply time: a reply held back on the line (one just after
        # the timeout) must not make a silent-line verdict
        last = not self._may_ask_again(now + self._timeout, self._probes, self.retries + 1)
        self._probes_sent.append(self._probe)
        self._send(encode_command(self._probe, 0), now, self._full_timeout if last else self._timeout)

    def _finish(self, verdict: Verdict, answer: Answer | None = None, reason: str = "") -> None:
        self.result = Result(verdict, answer, reason)
        self.state = SessionState.IDLE
        self._deadline = None
        if verdict in (Verdict.DONE, Verdict.REFUSED) and self._messages == 1 and self._era_trusted:
            # The one message of this transaction got its answer: the replies to every earlier
            # message came before it (or never will), so none can still come.
            self._clean = True
        if verdict in (Verdict.UNKNOWN, Verdict.FAILED):
            self._next = 0  # we no longer know the controller's ID state

    def _retry_read(self, now: float, why: str) -> None:
        """A read (or a write proved not executed): resync with ID 00 and ask again."""
        if not self._may_ask_again(now, self._resyncs, self.max_resyncs):
            self._finish(Verdict.FAILED, reason=f"{why}; gave up after {self._resyncs} resyncs")
            return
        self._begin_resync(now)

    # --- transitions ----------------------------------------------------------------------

    def _on_answer(self, now: float, event: ReplyEvent | None) -> None:
        assert isinstance(event, (Ack, DataReply))
        self._finish(Verdict.DONE, event)

    def _on_late_read_answer(self, now: float, event: ReplyEvent | None) -> None:
        assert isinstance(event, DataReply)
        self._finish(Verdict.DONE, event)
        self._next = 0  # our ID 00 read is still on its way: begin the next with a resync again

    def _on_refused(self, now: float, event: ReplyEvent | None) -> None:
        if not self._is_write and not self._era_trusted and not self._refused_once:
            self._refused_once = True
            # A read in a numbering begun without quiet: this ;E may answer an earlier ;Z with
            # the same ID (a controller that answers ;Z with ;E after a power cycle).  Ask again
            # under a new numbering; a second ;E is the controller's refusal.
            self._retry_read(now, ";E to be confirmed")
            return
        if not self._z_ever:
            self._finish(Verdict.REFUSED, reason="illegal command or parameters for the current mode")
            return
        # After a ;Z, a ;E with our ID may be the controller's ;E to the ;Z itself (a reading of
        # the manual: no last reply after a power cycle), not a refusal of our command.
        if self._is_write:
            self._finish(Verdict.UNKNOWN, reason=";E after ;Z: refused, or no reply kept after a power cycle")
        else:
            self._retry_read(now, ";E after ;Z")

    def _on_other_in_z(self, now: float, event: ReplyEvent | None) -> None:
        # The controller's last reply may be older than our command (it never got it), or this
        # is a late reply to an earlier message.  Resending with the same ID is safe either way.
        if not self._may_ask_again(now, self._resends, self.max_resends):
            if self._is_write:
                self._finish(Verdict.UNKNOWN, reason="the controller keeps answering an older message")
            else:
                self._retry_read(now, "the controller keeps answering an older message")
            return
        self._resends += 1
        self.counters.resends += 1
        self._send_copy(now)

    def _on_id_ours(self, now: float, event: ReplyEvent | None) -> None:
        # An earlier copy of this very message was accepted.
        if not self._is_write:
            self._retry_read(now, ";I: message ID out of step")
            return
        if not self._may_ask_again(now, self._z_sent, self.retries + 1):
            self._finish(Verdict.UNKNOWN, reason=";I with our ID, and no answer to ;Z")
            return
        self._send_z(now)

    def _on_id_other(self, now: float, event: ReplyEvent | None) -> None:
        assert isinstance(event, IdMismatch)
        if not self._is_write:
            self._retry_read(now, f";I{event.last_valid_id:02X}: message ID out of step")
            return
        last = event.last_valid_id
        if (self._began_clean and self._copies == 1 and last == self._prev_id and last != 0
                and self._may_ask_again(now, self._resends, self.max_resends)):
            # Ambiguous: this ;I may answer our only copy (not executed), or a copy of the previous
            # message that the line repeated, refused after that message ran and heard only now,
            # while ours is on its way (and runs).  A second copy with our ID is safe either way:
            # ;I with our ID (ours ran: ;Z fetches its answer) or ;I with the previous ID again.
            self._resends += 1
            self.counters.resends += 1
            self._send_copy(now)
            return
        proof = self._began_clean and (self._copies == 1 or (last == self._prev_id and last != 0))
        if proof and self._copies > 1:
            # ;I with the ID before ours to our second copy: proof, unless the line repeated the
            # stray ;I that made us send that copy (a line that repeats frames both ways).  Then
            # the answers to our copies are still on their way: wait until none can still come;
            # one with our ID settles it the other way.
            self._why = f";I{last:02X}: message ID out of step"
            self.state = SessionState.PROVING
            self._deadline = self._last_sent + self._quiet_time()
            return
        if proof:
            # No copy of the command was, or can still be, executed: a new ID is safe.
            self._retry_read(now, f";I{last:02X}: message ID out of step")
            return
        if not self._may_ask_again(now, self._z_sent, self.retries + 1):
            self._finish(Verdict.UNKNOWN, reason=f";I{last:02X} without proof that the command did not run")
            return
        self._send_z(now)

    def _on_proved(self, now: float, event: ReplyEvent | None) -> None:
        # No answer with our ID came while one still could: no copy ran, a new ID is safe.
        self._retry_read(now, self._why)

    def _on_garbled(self, now: float, event: ReplyEvent | None) -> None:
        # A complete reply failed its check: ask for it again at once.
        self._z_or_give_up(now, "garbled replies")

    def _on_timeout(self, now: float, event: ReplyEvent | None) -> None:
        self.counters.timeouts += 1
        if self.state is SessionState.Z_SENT and not self._is_write:
            # Silence after ;Z: power-cycled (no last reply to repeat) or lost again.  A read
            # need not find out which: ask again under a new numbering.
            self._retry_read(now, "no answer to ;Z")
            return
        self._z_or_give_up(now, "no valid answer")

    def _z_or_give_up(self, now: float, why: str) -> None:
        if self._may_ask_again(now, self._z_sent, self.retries):
            self._send_z(now)
            return
        what = f"{why} to {self._command.name} after {self._z_sent} retransmit requests"
        if self._until is not None:
            what += f" in {format_seconds(now - self._began)} s"
        if self._is_write:
            self._finish(Verdict.UNKNOWN, reason=what)
        else:
            self._retry_read(now, what)

    def _on_probe_answer(self, now: float, event: ReplyEvent | None) -> None:
        # The barrier: the controller expects 01 next, and no earlier reply can follow.
        self._next = 1
        self._last_taken = 0
        self._clean = self._era_trusted
        if self._clean:
            self._messages = 0  # nothing sent before the barrier can still be answered
        self._send_first_copy(now)

    def _on_probe_refused(self, now: float, event: ReplyEvent | None) -> None:
        # The controller refuses reads (program mode): resync with read FRN after quiet.
        self._barrier_refused = True
        self._enter_quiet(now)

    def _on_probe_garbled(self, now: float, event: ReplyEvent | None) -> None:
        # Perhaps the probe's answer: send the (harmless) probe again at once.
        self._on_probe_timeout(now, event, timed_out=False)

    def _on_probe_timeout(self, now: float, event: ReplyEvent | None, timed_out: bool = True) -> None:
        if timed_out:
            self.counters.timeouts += 1
        else:
            self._heard = True
        if not self._may_ask_again(now, self._probes, self.retries + 1):
            why = (f"no answer to {self._probe.name} with ID 00 (resync) within {format_seconds(self._full_timeout)} s "
                   f"after {self._probes} tries")
            if self._heard:
                self._retry_read(now, why)  # the controller is there, the line is bad: go on
                return
            self._next = 0
            self._finish(Verdict.FAILED, reason=why)  # silence: fail fast (a dead line)
            return
        self._send_probe(now)

    def _on_quiet(self, now: float, event: ReplyEvent | None) -> None:
        self._after_quiet(now)


_S = SessionState
#: (state, input) -> handler.  Missing pairs are ignored (a stale reply, an event of no use).
_TRANSITIONS: Final[dict[tuple[SessionState, _In], _Handler]] = {
    (_S.SENT, _In.OURS): SlcSession._on_answer,
    (_S.Z_SENT, _In.OURS): SlcSession._on_answer,
    (_S.SENT, _In.OURS_REFUSED): SlcSession._on_refused,
    (_S.Z_SENT, _In.OURS_REFUSED): SlcSession._on_refused,
    # SENT, OTHER: a late reply to an earlier message: ignored
    (_S.Z_SENT, _In.OTHER): SlcSession._on_other_in_z,
    (_S.SENT, _In.ID_OURS): SlcSession._on_id_ours,
    (_S.Z_SENT, _In.ID_OURS): SlcSession._on_id_ours,
    (_S.SENT, _In.ID_OTHER): SlcSession._on_id_other,
    (_S.Z_SENT, _In.ID_OTHER): SlcSession._on_id_other,
    (_S.SENT, _In.GARBLED): SlcSession._on_garbled,
    (_S.Z_SENT, _In.GARBLED): SlcSession._on_garbled,
    (_S.SENT, _In.TIMEOUT): SlcSession._on_timeout,
    (_S.Z_SENT, _In.TIMEOUT): SlcSession._on_timeout,
    (_S.RESYNC, _In.PROBE_ANSWER): SlcSession._on_probe_answer,
    (_S.RESYNC, _In.PROBE_REFUSED): SlcSession._on_probe_refused,
    (_S.RESYNC, _In.OURS): SlcSession._on_late_read_answer,
    (_S.RESYNC, _In.GARBLED): SlcSession._on_probe_garbled,
    (_S.RESYNC, _In.TIMEOUT): SlcSession._on_probe_timeout,
    (_S.QUIET, _In.TIMEOUT): SlcSession._on_quiet,
    # PROVING, ID_OTHER / OTHER: another stray reply of the repeated message: ignored
    (_S.PROVING, _In.OURS): SlcSession._on_answer,
    (_S.PROVING, _In.OURS_REFUSED): SlcSession._on_refused,
    (_S.PROVING, _In.ID_OURS): SlcSession._on_id_ours,
    (_S.PROVING, _In.GARBLED): SlcSession._on_garbled,
    (_S.PROVING, _In.TIMEOUT): SlcSession._on_proved,
}
