"""The SLC 100/150 session's transition table (``slc_ascii/session_table.py``) as the session uses it.

The table's form (every pair listed, entries of the table's enums, ignored pairs stay, every state
reachable) is walked with every other core's in ``tests/protocols/test_transitions.py``; here, what
is the session's own: unreachable pairs, its actions, and what it does when the table is broken.
"""

from __future__ import annotations

import pytest

from gateway.protocols.slc_ascii import session_table as slc
from gateway.protocols.slc_ascii import transaction as slc_transaction
from gateway.protocols.slc_ascii.commands import write_word
from gateway.protocols.slc_ascii.framing import encode_ack
from gateway.protocols.slc_ascii.session_table import (
    SessionAction,
    SessionInput,
    SessionState,
    SessionTableError,
)
from gateway.protocols.transitions import Transition


def test_slc_ignored_and_unreachable_pairs_lead_nowhere_but_back() -> None:
    for (state, _), entry in slc.TRANSITIONS.items():
        if entry.action in (SessionAction.IGNORE, SessionAction.UNREACHABLE):
            assert entry.allowed == {state}, (state, entry)


def test_slc_every_action_but_unreachable_has_its_method_and_is_used() -> None:
    runnable = set(SessionAction) - {SessionAction.UNREACHABLE}
    assert set(slc_transaction._ACTIONS) == runnable
    assert {entry.action for entry in slc.TRANSITIONS.values()} == set(SessionAction)


def test_slc_a_missing_pair_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    table = dict(slc.TRANSITIONS)
    del table[(SessionState.IDLE, SessionInput.START)]
    monkeypatch.setattr(slc, "TRANSITIONS", table)
    session = slc_transaction.SlcSession()
    with pytest.raises(SessionTableError, match="no transition for START in IDLE"):
        session.start(write_word(0x40, 1), 0.0)


def test_slc_an_unreachable_pair_raises() -> None:
    with pytest.raises(SessionTableError, match="TIMEOUT cannot happen in IDLE"):
        slc.transition(SessionState.IDLE, SessionInput.TIMEOUT)


def test_slc_a_state_outside_the_entry_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    table = dict(slc.TRANSITIONS)
    # the first command resyncs: RESYNC (or QUIET), which this entry no longer allows
    table[(SessionState.IDLE, SessionInput.START)] = Transition(SessionAction.BEGIN, SessionState.SENT)
    monkeypatch.setattr(slc, "TRANSITIONS", table)
    session = slc_transaction.SlcSession()
    with pytest.raises(SessionTableError, match="BEGIN on START in IDLE went to RESYNC"):
        session.start(write_word(0x40, 1), 0.0)


def test_slc_a_stale_reply_while_idle_is_an_explicit_ignore() -> None:
    session = slc_transaction.SlcSession()
    session.receive_data(encode_ack(5), 0.0)
    assert session.state is SessionState.IDLE
    assert session.result is None
    assert slc.TRANSITIONS[(SessionState.IDLE, SessionInput.STALE)].action is SessionAction.IGNORE
