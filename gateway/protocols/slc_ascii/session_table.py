"""The SLC 100/150 session's transition table, as data.

:class:`~gateway.protocols.slc_ascii.transaction.SlcSession` runs one transaction at a time and
is always in one :class:`SessionState`.  What happens to it is a :class:`SessionInput`: the
caller's start, a reply as the session classifies it against the running transaction, or a
deadline.  :data:`TRANSITIONS` maps every (state, input) pair to a
:class:`~gateway.protocols.transitions.Transition`, the one table entry of every protocol core: the
:class:`SessionAction` to run and the states the session may be in after it (``next_state``, and
``or_states`` when the action chooses).  An action that can end in more than one state (a resend,
a resync, a verdict) returns the one it chose, and the session checks that the entry allows it.

Every pair is listed (:func:`~gateway.protocols.transitions.require_complete` checks it on import).
A pair that changes nothing is an ``IGNORE`` entry, whose next state is the state itself; a pair
the session's classification never produces is an ``UNREACHABLE`` entry, which leads nowhere but
back.  :func:`transition` raises :class:`SessionTableError` for an unreachable pair and for one
missing from the table, so neither can be dropped unnoticed.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Final

from gateway.protocols.transitions import Table, TableEnum, Transition, require_complete, stay

__all__ = [
    "TRANSITIONS",
    "SessionAction",
    "SessionInput",
    "SessionState",
    "SessionTableError",
    "transition",
]


class SessionState(TableEnum):
    IDLE = "idle"
    QUIET = "quiet"  # waiting for the line to be quiet before a resync
    RESYNC = "resync"  # the ID 00 probe sent, waiting for its answer
    SENT = "sent"  # a copy of the command sent
    Z_SENT = "z_sent"  # ;Z sent, waiting for the controller's last reply


class SessionInput(TableEnum):
    """What happened, as the transition table sees it."""

    START = "the caller starts a transaction"
    OURS = "answer with our ID that fits the command"
    OURS_REFUSED = ";E with our ID"
    OTHER = "an answer with another ID (or one that does not fit)"
    ID_OURS = ";I with our ID"
    ID_OTHER = ";I with another ID"
    GARBLED = "a complete reply that fails its check"
    PROBE_ANSWER = "the answer to the ID 00 probe"
    PROBE_REFUSED = ";E 00 to a barrier read (reads are refused: program mode)"
    STALE = "a reply of no use here: a late one of a finished transaction, or an answer to an earlier message"
    TIMEOUT = "deadline passed"


class SessionAction(TableEnum):
    """What the session does; each is one method of :class:`SlcSession`."""

    BEGIN = "resync first, or send the first copy of the command"
    ANSWER = "DONE with the answer"
    LATE_READ_ANSWER = "DONE with a read's answer held back on the line; the next transaction resyncs"
    REFUSED = ("a ;E with our ID: REFUSED, or a read asks again to confirm it; after ;Z (or to a write's later copy) "
               "a write is UNKNOWN, a read asks again")
    RESEND = "after ;Z the controller answers an older message: resend the command with the same ID"
    ID_OURS = "an earlier copy was accepted: ;Z fetches its answer"
    ID_OTHER = "a ;I with another ID: a read resyncs; a write sends a second copy with its ID, or ;Z, or ends UNKNOWN"
    GARBLED = "ask for the reply again with ;Z at once, or give up"
    TIMEOUT = "ask for the reply with ;Z, or give up"
    Z_TIMEOUT = "silence after ;Z: a read resyncs and asks again, a write asks again or gives up"
    PROBE_ANSWER = "the barrier: the numbering restarts, send the first copy"
    PROBE_REFUSED = "the controller refuses reads (program mode): read FRN after quiet"
    PROBE_GARBLED = "perhaps the probe's answer: send the probe again at once, or give up"
    PROBE_TIMEOUT = "send the probe again, or give up"
    QUIET_OVER = "the line is quiet: resync with read FRN"
    IGNORE = "nothing changes"
    UNREACHABLE = "the session's classification never gives this input in this state"


class SessionTableError(RuntimeError):
    """A (state, input) pair the table does not allow, or a next state outside an entry's: a bug
    in the session, never a fault of the line."""


def transition(state: SessionState, what: SessionInput) -> Transition[SessionAction, SessionState]:
    """The table's entry for ``what`` in ``state``; raises :class:`SessionTableError` for a pair
    that is missing or ``UNREACHABLE``."""
    entry = TRANSITIONS.get((state, what))
    if entry is None:
        raise SessionTableError(f"no transition for {what.name} in {state.name}")
    if entry.action is SessionAction.UNREACHABLE:
        raise SessionTableError(f"{what.name} cannot happen in {state.name}")
    return entry


#: a verdict: the transaction is over
_ENDS: Final = (SessionState.IDLE,)
#: a resync: the ID 00 probe goes out, or the session waits for quiet before it
_RESYNCS: Final = (SessionState.RESYNC, SessionState.QUIET)
#: a verdict, or a resync to ask again (a read; a write only before its first copy)
_ENDS_OR_RESYNCS: Final = (*_ENDS, *_RESYNCS)
#: ;Z, a verdict or a resync
_Z_ENDS_OR_RESYNCS: Final = (SessionState.Z_SENT, *_ENDS_OR_RESYNCS)
#: a copy of the command, a verdict or a resync
_COPY_ENDS_OR_RESYNCS: Final = (SessionState.SENT, *_ENDS_OR_RESYNCS)
#: anything a ;I with another ID may call for: a write's second copy or ;Z, a verdict, a read's resync
_AFTER_ID_OTHER: Final = (SessionState.SENT, *_Z_ENDS_OR_RESYNCS)

_Entry = Transition[SessionAction, SessionState]
_SessionTable = Table[SessionState, SessionInput, SessionAction]


def _entry(action: SessionAction, states: tuple[SessionState, ...]) -> _Entry:
    """The action and the states it may end in, the first of them its ``next_state``."""
    return Transition(action, states[0], frozenset(states[1:]))


def _stay(state: SessionState) -> _SessionTable:
    """``IGNORE``: stale replies change nothing."""
    return stay(SessionAction.IGNORE, state, SessionInput.STALE)


def _never(state: SessionState, *inputs: SessionInput) -> _SessionTable:
    """``UNREACHABLE`` entries: the session's classification never gives these inputs in ``state``
    (:func:`transition` raises on them; they lead back to the state, nowhere else)."""
    return stay(SessionAction.UNREACHABLE, state, *inputs)


#: (state, input) -> (action, the states it may lead to), for every pair.
TRANSITIONS: Final[Mapping[tuple[SessionState, SessionInput], _Entry]] = MappingProxyType({
    # No transaction: start() begins one; replies are late ones of finished transactions; there is
    # no deadline.
    (SessionState.IDLE, SessionInput.START): _entry(SessionAction.BEGIN, (*_RESYNCS, SessionState.SENT)),
    **_stay(SessionState.IDLE),
    **_never(
        SessionState.IDLE,
        SessionInput.OURS, SessionInput.OURS_REFUSED, SessionInput.OTHER, SessionInput.ID_OURS, SessionInput.ID_OTHER,
        SessionInput.GARBLED, SessionInput.PROBE_ANSWER, SessionInput.PROBE_REFUSED, SessionInput.TIMEOUT,
    ),
    # Waiting for quiet: every reply is a late one of an earlier message.
    (SessionState.QUIET, SessionInput.TIMEOUT): _entry(SessionAction.QUIET_OVER, (SessionState.RESYNC,)),
    **_stay(SessionState.QUIET),
    **_never(
        SessionState.QUIET,
        SessionInput.START, SessionInput.OURS, SessionInput.OURS_REFUSED, SessionInput.OTHER, SessionInput.ID_OURS,
        SessionInput.ID_OTHER, SessionInput.GARBLED, SessionInput.PROBE_ANSWER, SessionInput.PROBE_REFUSED,
    ),
    # The ID 00 probe is out: its answer, its refusal, a read's answer held back on the line, a
    # garbled reply; any other reply answers an earlier message (STALE).
    (SessionState.RESYNC, SessionInput.PROBE_ANSWER): _entry(SessionAction.PROBE_ANSWER, (SessionState.SENT,)),
    (SessionState.RESYNC, SessionInput.PROBE_REFUSED): _entry(SessionAction.PROBE_REFUSED, _RESYNCS),
    (SessionState.RESYNC, SessionInput.OURS): _entry(SessionAction.LATE_READ_ANSWER, _ENDS),
    (SessionState.RESYNC, SessionInput.GARBLED): _entry(SessionAction.PROBE_GARBLED, _ENDS_OR_RESYNCS),
    (SessionState.RESYNC, SessionInput.TIMEOUT): _entry(SessionAction.PROBE_TIMEOUT, _ENDS_OR_RESYNCS),
    **_stay(SessionState.RESYNC),
    **_never(
        SessionState.RESYNC,
        SessionInput.START, SessionInput.OURS_REFUSED, SessionInput.OTHER, SessionInput.ID_OURS, SessionInput.ID_OTHER,
    ),
    # A copy of the command is out.
    (SessionState.SENT, SessionInput.OURS): _entry(SessionAction.ANSWER, _ENDS),
    (SessionState.SENT, SessionInput.OURS_REFUSED): _entry(SessionAction.REFUSED, _ENDS_OR_RESYNCS),
    # a late reply to an earlier message
    (SessionState.SENT, SessionInput.OTHER): Transition(SessionAction.IGNORE, SessionState.SENT),
    (SessionState.SENT, SessionInput.ID_OURS): _entry(SessionAction.ID_OURS, _Z_ENDS_OR_RESYNCS),
    (SessionState.SENT, SessionInput.ID_OTHER): _entry(SessionAction.ID_OTHER, _AFTER_ID_OTHER),
    (SessionState.SENT, SessionInput.GARBLED): _entry(SessionAction.GARBLED, _Z_ENDS_OR_RESYNCS),
    (SessionState.SENT, SessionInput.TIMEOUT): _entry(SessionAction.TIMEOUT, _Z_ENDS_OR_RESYNCS),
    **_never(
        SessionState.SENT,
        SessionInput.START, SessionInput.PROBE_ANSWER, SessionInput.PROBE_REFUSED, SessionInput.STALE,
    ),
    # ;Z is out.
    (SessionState.Z_SENT, SessionInput.OURS): _entry(SessionAction.ANSWER, _ENDS),
    (SessionState.Z_SENT, SessionInput.OURS_REFUSED): _entry(SessionAction.REFUSED, _ENDS_OR_RESYNCS),
    (SessionState.Z_SENT, SessionInput.OTHER): _entry(SessionAction.RESEND, _COPY_ENDS_OR_RESYNCS),
    (SessionState.Z_SENT, SessionInput.ID_OURS): _entry(SessionAction.ID_OURS, _Z_ENDS_OR_RESYNCS),
    (SessionState.Z_SENT, SessionInput.ID_OTHER): _entry(SessionAction.ID_OTHER, _AFTER_ID_OTHER),
    (SessionState.Z_SENT, SessionInput.GARBLED): _entry(SessionAction.GARBLED, _Z_ENDS_OR_RESYNCS),
    (SessionState.Z_SENT, SessionInput.TIMEOUT): _entry(SessionAction.Z_TIMEOUT, _Z_ENDS_OR_RESYNCS),
    **_never(
        SessionState.Z_SENT,
        SessionInput.START, SessionInput.PROBE_ANSWER, SessionInput.PROBE_REFUSED, SessionInput.STALE,
    ),
})

require_complete(TRANSITIONS, SessionState, SessionInput, "SLC 100/150 session")
