"""DF1 half-duplex transactions: a read's value comes from its own transaction.

The station's N7:5 changes before every read and after every command it hears.  Its replies come
late (held back and sent at a later poll, after replies to later commands: out of order), twice,
or never; some commands are not heard at all.  Every value a read is answered with must have been
held by the station at some time after that read began: never one already replaced when it began
(the reply to an earlier read, taken for this one, would be such a value).  The station is played
as in ``test_transactions.py`` (its :class:`Line`): each command is answered with
the value the station holds when it hears it.
"""

from __future__ import annotations

import itertools

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.protocols.df1.full_duplex.transaction import TransactionDone, TransactionFailed
from gateway.protocols.df1.pccc import PcccCommand

from .test_transactions import READ, Line, ok

#: what a station does with one command, and where a held-back reply goes among those owed
FATES = ["ok", "ok", "ok", "late", "twice", "lost", "unheard"]
Fate = tuple[str, int]


def run(fates: list[Fate], gaps: list[float]) -> None:
    values = itertools.count(1)
    changes: list[tuple[float, int]] = []
    held_back: list[bytes] = []
    fate_of = iter(fates)
    line: Line

    def change() -> None:
        changes.append((line.now, next(values)))

    def answer(command: PcccCommand) -> bytes | str | None:
        fate, position = next(fate_of, ("ok", 0))
        owed = line.owed[1]
        while held_back:  # the replies held back go out now, among those owed
            owed.insert(position % (len(owed) + 1), held_back.pop())
        if fate == "unheard":
            return None
        reply = ok(command, changes[-1][1].to_bytes(2, "little"))
        change()
        if fate == "lost":
            return "ack"
        if fate == "late":
            held_back.append(reply)
            return "ack"
        if fate == "twice":
            held_back.append(reply)
        return reply

    line = Line(answer)
    change()
    for gap in gaps:
        line.now += gap
        change()
        line.now += 0.001
        began = line.now
        line.start(READ, write=False)
        line.run()
        verdict = line.verdicts()[-1]
        if isinstance(verdict, TransactionDone):
            value = int.from_bytes(verdict.reply.data, "little")
            index = [v for _, v in changes].index(value)
            replaced = changes[index + 1][0] if index + 1 < len(changes) else float("inf")
            assert replaced >= began, (value, began, changes[-8:])
        else:
            assert isinstance(verdict, TransactionFailed), verdict


@settings(max_examples=200, deadline=None)
@given(fates=st.lists(st.tuples(st.sampled_from(FATES), st.integers(0, 3)), max_size=80),
       gaps=st.lists(st.sampled_from([0.0, 0.5, 5.0]), min_size=1, max_size=12))
def test_every_read_is_answered_with_a_value_held_after_it_began(fates: list[Fate], gaps: list[float]) -> None:
    run(fates, gaps)


def test_every_reply_held_back_and_sent_again() -> None:
    """Each read's first reply comes only after the next command, ahead of that command's own."""
    run([("late", 0), ("twice", 0)] * 20, [0.0] * 10)
