"""Every transition table of the protocol cores, walked: each (state, input) pair is an entry.

The cores (``gateway/protocols/``: DF1 and the SLC 100/150 session) keep their state machines as
data in one form: ``TRANSITIONS`` maps (state, input) to a
:class:`~gateway.protocols.transitions.Transition` (action, next state, and the other states an
action may choose).  One generic walk checks each table:

* every pair of its states x inputs is present, and nothing else;
* actions, next states and the states an action may choose are members of the table's enums;
* an ignored pair (the action that does nothing) stays where it is;
* every state is reachable from the initial one, and every state reached has its row;

and for each DF1 core, a pair taken out of its table raises when the core meets it, instead of being
dropped (the SLC session's are in ``slc_ascii/test_session_table.py``).
"""

from __future__ import annotations

import enum
import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

import gateway.protocols as protocols
from gateway.protocols.df1 import write_verdict
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.framing import decoder as frame_decoder
from gateway.protocols.df1.full_duplex import datalink, transaction
from gateway.protocols.df1.full_duplex import table as full_duplex_table
from gateway.protocols.df1.half_duplex import master as half_duplex
from gateway.protocols.df1.half_duplex.events import LineConfig, StationConfig
from gateway.protocols.df1.pccc import PcccHeader, ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite, decode_reply
from gateway.protocols.slc_ascii import session_table as slc_session
from gateway.protocols.transitions import Transition, require_complete


@dataclass(frozen=True)
class Table:
    name: str
    transitions: Mapping[tuple[Any, Any], Transition[Any, Any]]
    states: frozenset[Any]
    inputs: type[enum.Enum]
    actions: type[enum.Enum]
    initial: Any
    ignore: Any  #: the action of a pair that changes nothing (None: the table has none)


TABLES = [
    Table("full-duplex transmitter", full_duplex_table.TRANSITIONS, frozenset(full_duplex_table.TxState),
          full_duplex_table.TxInput, full_duplex_table.TxAction, full_duplex_table.TxState.IDLE,
          full_duplex_table.TxAction.IGNORE),
    Table("transaction", transaction.TRANSITIONS, frozenset(transaction.TxnState), transaction.TxnInput,
          transaction.TxnAction, transaction.TxnState.IDLE, transaction.TxnAction.IGNORE),
    Table("write_verdict", write_verdict.TRANSITIONS, frozenset(write_verdict.VerdictState), write_verdict.WriteInput,
          write_verdict.VerdictAction, write_verdict.VerdictState.SENT, write_verdict.VerdictAction.IGNORE),
    Table("half_duplex", half_duplex.TRANSITIONS, frozenset(half_duplex.LineState), half_duplex.MasterInput,
          half_duplex.MasterAction, half_duplex.LineState.IDLE, half_duplex.MasterAction.IGNORE),
    Table("decoder, full duplex", frame_decoder.FULL_DUPLEX_TRANSITIONS, frozenset(frame_decoder.FullDuplexState),
          frame_decoder.ByteClass, frame_decoder.DecoderAction, frame_decoder.DecoderState.IDLE, None),
    Table("decoder, half duplex", frame_decoder.HALF_DUPLEX_TRANSITIONS, frozenset(frame_decoder.DecoderState),
          frame_decoder.ByteClass, frame_decoder.DecoderAction, frame_decoder.DecoderState.IDLE, None),
    Table("slc_ascii session", slc_session.TRANSITIONS, frozenset(slc_session.SessionState), slc_session.SessionInput,
          slc_session.SessionAction, slc_session.SessionState.IDLE, slc_session.SessionAction.IGNORE),
]


def reachable(table: Table) -> set[Any]:
    seen = {table.initial}
    todo = [table.initial]
    while todo:
        state = todo.pop()
        for what in table.inputs:
            for end in table.transitions[state, what].allowed:
                if end not in seen:
                    seen.add(end)
                    todo.append(end)
    return seen


@pytest.mark.parametrize("table", TABLES, ids=lambda t: t.name)
def test_every_pair_is_an_entry(table: Table) -> None:
    pairs = {(state, what) for state in table.states for what in table.inputs}
    assert set(table.transitions) == pairs


@pytest.mark.parametrize("table", TABLES, ids=lambda t: t.name)
def test_entries_are_made_of_the_tables_enums(table: Table) -> None:
    for pair, entry in table.transitions.items():
        assert isinstance(entry, Transition), pair
        assert isinstance(entry.action, table.actions), pair
        assert entry.allowed <= table.states, pair
        assert entry.next_state not in entry.or_states, pair


@pytest.mark.parametrize("table", [t for t in TABLES if t.ignore is not None], ids=lambda t: t.name)
def test_an_ignored_pair_stays_where_it_is(table: Table) -> None:
    ignored = {pair: entry for pair, entry in table.transitions.items() if entry.action is table.ignore}
    assert ignored, "the table lists the pairs it ignores"
    for (state, _), entry in ignored.items():
        assert entry.allowed == {state}


@pytest.mark.parametrize("table", TABLES, ids=lambda t: t.name)
def test_every_state_is_reachable_and_has_its_row(table: Table) -> None:
    assert reachable(table) == table.states


def test_require_complete_names_what_is_missing() -> None:
    require_complete(datalink.TRANSITIONS, datalink.TxState, datalink.TxInput, "probe")  # leads to every state
    table = dict(datalink.TRANSITIONS)
    del table[datalink.TxState.IDLE, datalink.TxInput.SEND]
    with pytest.raises(RuntimeError, match="missing pairs"):
        require_complete(table, datalink.TxState, datalink.TxInput, "probe")
    table = dict(datalink.TRANSITIONS)
    table[datalink.TxState.IDLE, datalink.TxInput.SEND] = Transition(datalink.TxAction.TRANSMIT, "nowhere")
    with pytest.raises(RuntimeError, match="without a row"):
        require_complete(table, datalink.TxState, datalink.TxInput, "probe")


# ---------------------------------------------------------------------- a missing pair raises


def _link() -> datalink.Df1DataLink:
    return datalink.Df1DataLink(checksum=Checksum.BCC)


def _send_on_link() -> None:
    _link().send(b"\x01\x00\x0f\x00\x01\x00", 0.0)


def _start_read() -> None:
    core = transaction.Df1Transactions(_link(), station=1, source=0, reply_timeout=1.0)
    core.start(ProtectedTypedLogicalRead(0x89, 7, 0, 0, 2), 0.0, write=False)


def _reply_to_write() -> None:
    verdict = write_verdict.WriteVerdict(ProtectedTypedLogicalWrite(0x89, 7, 0, 0, b"\x01\x00"), retries=1, now=0.0)
    verdict.reply(decode_reply(PcccHeader(0, 1, 0x4F, 0, 1).encode()), 0.0)


def _start_master() -> None:
    half_duplex.HalfDuplexMaster(LineConfig(Checksum.BCC), [StationConfig(1)]).start(0.0)


MISSING: list[tuple[Mapping[Any, Any], tuple[Any, Any], Callable[[], None]]] = [
    (datalink.TRANSITIONS, (datalink.TxState.IDLE, datalink.TxInput.SEND), _send_on_link),
    (transaction.TRANSITIONS, (transaction.TxnState.IDLE, transaction.TxnInput.START_READ), _start_read),
    (write_verdict.TRANSITIONS, (write_verdict.VerdictState.SENT, write_verdict.WriteInput.REPLY), _reply_to_write),
    (half_duplex.TRANSITIONS, (half_duplex.LineState.IDLE, half_duplex.MasterInput.SCHEDULE), _start_master),
]


@pytest.mark.parametrize(("transitions", "pair", "run"), MISSING, ids=lambda v: getattr(v, "__name__", ""))
def test_a_missing_pair_raises(
    monkeypatch: pytest.MonkeyPatch, transitions: dict[Any, Any], pair: tuple[Any, Any], run: Callable[[], None]
) -> None:
    run()  # the pair is met, and handled
    monkeypatch.delitem(transitions, pair)
    with pytest.raises(KeyError):
        run()


def test_the_walk_covers_every_table() -> None:
    """Every module-level ``TRANSITIONS`` / ``*_TRANSITIONS`` table under gateway/protocols/ (keyed by
    (state, input)) is walked here.  The program transfer's ``_TRANSITIONS`` (``slc_ascii/transfer.py``)
    is no such table: it lists the moves each state allows, which its core asserts as it moves."""
    walked = {id(t.transitions) for t in TABLES}
    found: dict[int, str] = {}  # a table imported into another module is the same table
    root = Path(protocols.__file__).parent
    for path in sorted(root.rglob("*.py")):  # slc_ascii/ is a namespace package: walked by file
        parts = path.relative_to(root.parent.parent).with_suffix("").parts
        module_name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        module = importlib.import_module(module_name)
        for name, value in vars(module).items():
            if name.endswith("TRANSITIONS") and isinstance(value, Mapping) and isinstance(next(iter(value)), tuple):
                found.setdefault(id(value), f"{module_name}.{name}")
                assert id(value) in walked, f"{module_name}.{name} is not walked"
    assert len(found) == len(TABLES)
