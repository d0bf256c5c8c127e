"""The transition tables of the protocol cores: every (state, input) pair is listed.

A core exposes its table as a mapping ``(state, input) -> entry`` (``TRANSITIONS``) with its state
enum and its input enum; a pair missing from a table is a pair the core would meet with no
decision, so the walk below fails on it.  Add each core's table to :data:`ALL_TABLES`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

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
    SessionTransition,
)


@dataclass(frozen=True)
class Table:
    """One core's transition table and the axes its keys range over."""

    name: str
    transitions: Mapping[Any, Any]
    states: type[Enum]
    inputs: type[Enum]
    #: further key components after (state, input), e.g. ``(False, True)`` for a table keyed by a flag
    more: tuple[Iterable[Any], ...] = ()
    #: the states an entry may lead to, when the entry says (checked to be states of the table)
    next_states: Callable[[Any], Iterable[Any]] | None = None

    def pairs(self) -> list[tuple[Any, ...]]:
        return list(itertools.product(self.states, self.inputs, *self.more))


ALL_TABLES: list[Table] = [
    Table("slc_ascii session", slc.TRANSITIONS, slc.SessionState, slc.SessionInput,
          next_states=lambda entry: entry.next_states),
    # The DF1 cores' tables go here, e.g.
    # Table("df1 transaction", df1.TRANSITIONS, df1.TxnState, df1.TxnInput, more=((False, True),)),
]


@pytest.mark.parametrize("table", ALL_TABLES, ids=lambda table: table.name)
def test_every_state_and_input_pair_is_in_the_table(table: Table) -> None:
    missing = [pair for pair in table.pairs() if pair not in table.transitions]
    assert not missing, f"{table.name}: no entry for {missing}"


@pytest.mark.parametrize("table", ALL_TABLES, ids=lambda table: table.name)
def test_the_table_has_no_other_keys(table: Table) -> None:
    assert set(table.transitions) <= set(table.pairs())


@pytest.mark.parametrize("table", [t for t in ALL_TABLES if t.next_states is not None], ids=lambda table: table.name)
def test_every_next_state_is_a_state(table: Table) -> None:
    assert table.next_states is not None
    for key, entry in table.transitions.items():
        assert set(table.next_states(entry)) <= set(table.states), (table.name, key)


def test_the_walk_finds_a_missing_pair() -> None:
    class State(Enum):
        A = "a"
        B = "b"

    class Input(Enum):
        X = "x"

    table = Table("two states", {(State.A, Input.X): "go"}, State, Input)
    assert [pair for pair in table.pairs() if pair not in table.transitions] == [(State.B, Input.X)]


# --- the SLC 100/150 session table ---------------------------------------------------------


def test_slc_ignored_pairs_stay_and_unreachable_ones_lead_nowhere() -> None:
    for (state, _), entry in slc.TRANSITIONS.items():
        if entry.action is SessionAction.IGNORE:
            assert entry.next_states == {state}
        elif entry.action is SessionAction.UNREACHABLE:
            assert entry.next_states == frozenset()
        else:
            assert entry.next_states, (state, entry)


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
    table[(SessionState.IDLE, SessionInput.START)] = SessionTransition(
        SessionAction.BEGIN, frozenset({SessionState.SENT}))
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
