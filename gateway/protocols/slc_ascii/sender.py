"""The sending side of the SLC 100/150 session: message IDs, copies, ``;Z`` and the ID 00 resync.

:class:`SlcSender` is the base of :class:`~gateway.protocols.slc_ascii.transaction.SlcSession`:
it keeps the link's message ID numbering and puts the transaction's frames on the line with
their deadlines; the session decides, from what comes back, which one goes next.  Each method
that sends returns the :class:`SessionState` the session is in after it (the session's
transition table checks it).

Rules:

* **Resends keep the ID.**  A copy with the same ID is never executed twice (the ID check).
* **ID 00 (resync) with a barrier.**  The controller's numbering restarts with a harmless read
  with ID 00 whose answer no earlier message can have: one byte at an address no ID 00 read
  asked for within the quiet time (its answer echoes the address).  The controller answers in
  order and the line keeps it, so that answer is a barrier: no reply of an earlier message
  follows it, and a reply with the same ID from before is never taken for an answer.  A write
  on a line where an earlier reply may still come (not *clean*) resyncs first, so that the
  replies it meets are answers to its own copies (a stray one proves nothing, but costs it a
  copy or a ``;Z``).  Only when the controller refuses reads (program mode) does the resync wait
  for quiet (``late_bound``, 1.5 x the reply time, or more when replies were seen coming later)
  and read the FRN instead.
* **Timeouts adapt.**  The reply timeout is 2 x the slowest of the last 32 first replies (at
  least ``min_timeout``, at most the configured one); the waits that decide a verdict (the last
  resync read, a write's last ``;Z``) keep the configured time.  A frame whose next character
  does not come within ``char_gap`` is garbled at once.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Final

from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command
from gateway.protocols.slc_ascii.framing import MAX_ID, ReplyDecoder, encode_retransmit, frame_command
from gateway.protocols.slc_ascii.memory_map import MAP_SIZE, is_readable
from gateway.protocols.slc_ascii.session_table import SessionState
from gateway.protocols.slc_ascii.write_proof import Result

__all__ = ["MAX_RESENDS", "MAX_RESYNCS", "SessionCounters", "SlcSender", "next_id"]

#: How many times one transaction resends its command under the same ID (after a hint that the
#: controller did not get it) before it stops.
MAX_RESENDS: Final = 8
#: How many ID 00 resyncs one transaction may do (reads: each one asks again).
MAX_RESYNCS: Final = 8

_PROBE: Final = cmds.read_frn()
#: when nothing was ever sent: every quiet time has passed since
_LONG_AGO: Final = float("-inf")
#: Bytes a barrier read may ask for (every readable byte of the "Reading Data" list).
_BARRIER_ADDRESSES: Final = tuple(a for a in range(MAP_SIZE) if is_readable(a, 1))


def next_id(msg_id: int) -> int:
    """The ID after ``msg_id``: 01..7F, then 01 again ("roll over from 127D to 01")."""
    return 1 if msg_id >= MAX_ID else msg_id + 1


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


class SlcSender:
    """One SLC 100/150 link's message IDs and the frames of its transaction (one at a time)."""

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
        #: assumption of the design, docs/develop/controller-variants.md)
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
        self._next = 0  # ID of the next transaction's command; 0: resync first (a resync's answer sets 1)
        self._handshake_due = True  # the next resync is the first after connecting
        self._last_sent = _LONG_AGO
        #: no reply of a command copy sent earlier can still come (a write begins only then);
        #: decided by a resync's answer and by a transaction's end
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
        self._timeout = timeout
        self._full_timeout = timeout
        self._until: float | None = None
        # Set before anything reads them: by start (a transaction), _send_first_copy and _send_copy
        # (a copy of the command), _begin_resync (a resync).
        self._is_write: bool
        self._began: float
        self._resends: int
        self._resyncs: int
        self._probes: int
        self._messages: int
        self._copies: int
        self._z_ever: bool
        self._refused_once: bool
        self._msg_id: int
        self._z_sent: int
        self._copy_sent: float
        self._heard: bool

    def connected(self) -> None:
        """A new stream: forget the decoder state; the first command resyncs.  Nothing was sent on
        the stream, so that resync is one after quiet, which begins a trusted, clean numbering."""
        self._last_sent = _LONG_AGO
        self._decoder = ReplyDecoder()
        self._out.clear()
        self._next = 0
        self._handshake_due = True
        self._deadline = None
        self._gap_deadline = None
        self.state = SessionState.IDLE
        self.result = None

    def next_deadline(self) -> float | None:
        if self._gap_deadline is not None and self.state is not SessionState.IDLE:
            if self._deadline is None or self._gap_deadline < self._deadline:
                return self._gap_deadline
        return self._deadline

    def data_to_send(self) -> bytes:
        data = bytes(self._out)
        self._out.clear()
        return data

    # --- sending --------------------------------------------------------------------------

    def _send(self, frame: bytes, now: float, timeout: float) -> None:
        self._out += frame
        self._last_sent = now
        self._messages += 1
        self._deadline = now + timeout

    def _send_first_copy(self, now: float) -> SessionState:
        self._msg_id = self._next
        self._next = next_id(self._next)
        self._copies = 0
        return self._send_copy(now)

    def _send_copy(self, now: float) -> SessionState:
        self._copy_sent = now
        self._copies += 1
        self._z_sent = 0
        self._clean = False
        self._send(frame_command(self._command, self._msg_id), now, self._timeout)
        return SessionState.SENT

    def _send_z(self, now: float) -> SessionState:
        self._z_sent += 1
        self._z_ever = True
        self.counters.retransmits += 1
        # a write's last ;Z waits the full reply time: its answer may be held back on the line
        last = self._is_write and not self._may_ask_again(now + self._timeout, self._z_sent, self.retries)
        self._send(encode_retransmit(self._msg_id), now, self._full_timeout if last else self._timeout)
        return SessionState.Z_SENT

    def _may_ask_again(self, now: float, asked: int, limit: int) -> bool:
        """Whether one more ``;Z`` / copy / probe may go: within the count, or the time budget."""
        if self._until is None:
            return asked < limit
        return now + self._timeout <= self._until

    def _quiet_time(self) -> float:
        """How long after our last message no reply to it can come: ``late_bound``, or more
        when answers were seen coming later than that (a controller slower than configured)."""
        return max(self.late_bound, 1.5 * max(self._lateness, default=0.0))

    # --- the ID 00 resync -----------------------------------------------------------------

    def _enter_quiet(self, now: float) -> SessionState:
        """Wait until no reply to our last message can still come, then resync with read FRN."""
        quiet_at = self._last_sent + self._quiet_time()
        if now >= quiet_at:
            return self._after_quiet(now)
        self.counters.quiet_waits += 1
        self._deadline = quiet_at
        return SessionState.QUIET

    def _after_quiet(self, now: float) -> SessionState:
        self._era_trusted = True
        self._probe = _PROBE
        return self._send_probe(now)

    def _begin_resync(self, now: float) -> SessionState:
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
        quiet = now >= self._last_sent + self._quiet_time()
        if not quiet and self._barrier_free(now):
            self._era_trusted = True
            return self._send_probe(now)
        if self._is_write or quiet:
            return self._enter_quiet(now)
        self._era_trusted = False
        self._probe = _PROBE
        return self._send_probe(now)

    def _barrier_free(self, now: float) -> bool:
        """Choose the next barrier read; False if its address was asked for too recently."""
        address = _BARRIER_ADDRESSES[self._barrier_next % len(_BARRIER_ADDRESSES)]
        if now - self._barrier_sent.get(address, _LONG_AGO) < self._quiet_time():
            return False
        self._barrier_next += 1
        self._barrier_sent[address] = now
        self._probe = cmds.read_bytes(address, 1)
        return True

    def _probing_with_barrier(self) -> bool:
        """Whether the resync's ID 00 message is a barrier read (not read FRN)."""
        return self._probe is not _PROBE

    def _send_probe(self, now: float) -> SessionState:
        if self._probing_with_barrier() and self._probes and not self._barrier_free(now):
            # a second try asks for another address (the first one's answer may still come);
            # none free: a write waits for quiet, a read takes read FRN at once
            if self._is_write:
                return self._enter_quiet(now)
            self._era_trusted = False
            self._probe = _PROBE
        self._probes += 1
        # the last try waits the full reply time: a reply held back on the line (one just after
        # the timeout) must not make a silent-line verdict
        last = not self._may_ask_again(now + self._timeout, self._probes, self.retries + 1)
        self._probes_sent.append(self._probe)
        self._send(frame_command(self._probe, 0), now, self._full_timeout if last else self._timeout)
        return SessionState.RESYNC
