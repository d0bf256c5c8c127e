"""Transition tables of the protocol cores, as data: one mechanism for the DF1 and SLC 100/150 cores.

A core's table maps every (state, input) pair to a :class:`Transition`: the action to run and the
state it leads to.  A pair that changes nothing is an entry too (an ``IGNORE``-style action back
to the same state), so a pair missing from a table is a bug: the cores index their tables, and a
missing pair raises ``KeyError`` instead of being dropped.  :func:`require_complete` checks a
table when its module is imported; ``tests/protocols/test_transitions.py`` walks every table.

An action that must choose between next states (send again, or give up) names the states it may
choose besides ``next_state`` in ``or_states``; the core checks its choice with :meth:`Transition.allows`.

The states, inputs and actions of a table are :class:`TableEnum` members.

This module does no I/O.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Mapping
from typing import Any, Generic, NamedTuple, TypeVar

__all__ = ["Table", "TableEnum", "Transition", "require_complete", "stay"]

ActionT = TypeVar("ActionT")
StateT = TypeVar("StateT")
InputT = TypeVar("InputT")


class TableEnum(enum.Enum):
    """An enum whose members key or fill a transition table (states, inputs, actions).

    Members are singletons compared by identity; hashing them by identity too keeps the table
    look-up in C (``Enum.__hash__`` is Python code: 2.5x slower look-ups).
    """

    __hash__ = object.__hash__


class Transition(NamedTuple, Generic[ActionT, StateT]):
    """One table entry: run ``action``; the core is then in ``next_state`` (or in one of
    ``or_states``, when the action chooses)."""

    action: ActionT
    next_state: StateT
    or_states: frozenset[StateT] = frozenset()

    @property
    def allowed(self) -> frozenset[StateT]:
        """Every state this transition may end in."""
        return self.or_states | {self.next_state}

    def allows(self, state: StateT) -> bool:
        return state == self.next_state or state in self.or_states


#: A transition table: (state, input) -> :class:`Transition`; ``Table[State, Input, Action]``.
Table = dict[tuple[StateT, InputT], Transition[ActionT, StateT]]


def stay(action: ActionT, state: StateT, *inputs: InputT) -> Table[StateT, InputT, ActionT]:
    """The entries for ``inputs`` in ``state`` that run ``action`` (a table's IGNORE) and stay."""
    return {(state, what): Transition(action, state) for what in inputs}


def require_complete(
    table: Mapping[tuple[StateT, InputT], Transition[Any, StateT]],
    states: Iterable[StateT],
    inputs: Iterable[InputT],
    name: str,
) -> None:
    """Raise unless ``table`` has exactly the pairs of ``states`` x ``inputs``, and every state
    it leads to has its row."""
    states, inputs = list(states), list(inputs)
    pairs = {(state, what) for state in states for what in inputs}
    missing, extra = pairs - set(table), set(table) - pairs
    if missing or extra:
        raise RuntimeError(f"{name}: missing pairs {sorted(map(str, missing))}, extra pairs {sorted(map(str, extra))}")
    ends = {state for entry in table.values() for state in entry.allowed}
    if not ends <= set(states):
        raise RuntimeError(f"{name}: transitions lead to states without a row: {sorted(map(str, ends - set(states)))}")
