"""The DF1 full-duplex responder as data (``gateway.protocols.df1.responder``): its inputs, actions
and :data:`TRANSITIONS`, ``(state, input) -> (action, next state)``; the states are the
transmitter's, :class:`~gateway.protocols.df1.full_duplex.TxState`.

The receiver's inputs (A-B 1770-6.5.16 p. 4-8) take the same action in every state and keep it:
receiver and transmitter work at the same time (p. 4-2).  The transmitter's follow the p. 4-6
flowchart.  Every pair that changes nothing is listed in :data:`IGNORED` with its reason; the
table holds every pair exactly once, checked at import.  Plain data, no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Final, NamedTuple

from gateway.protocols.df1.full_duplex import TxState
from gateway.protocols.df1.transitions import TableEnum, Transition

__all__ = [
    "IGNORED",
    "TRANSITIONS",
    "ResponderAction",
    "ResponderInput",
    "ResponderStep",
]


class ResponderInput(TableEnum):
    COMMAND = "a good frame with a new command, room in the sink"
    DUPLICATE = "a good frame with the SRC, CMD and TNS of the last command delivered"
    NOT_FOR_US = "a good frame whose DST is not our station (check_dst)"
    SINK_FULL = "a good frame with a new command, max_pending commands await their reply"
    BAD_FRAME = "a damaged frame: check, DLE sequence, fewer than 6 bytes, too long"
    ENQ_IN_FRAME = "DLE ENQ inside a frame: the frame is truncated"
    ENQ = "DLE ENQ"
    NOISE = "a byte or symbol outside a frame that starts nothing"
    REPLY = "a reply is queued"
    ACK = "DLE ACK"
    NAK = "DLE NAK, retransmissions left"
    NAK_LIMIT = "DLE NAK, no retransmission left"
    STALE = "DLE ACK / DLE NAK while our frame still waits in data_to_send()"
    TIMEOUT = "ACK timer expired, ENQs left"
    TIMEOUT_LIMIT = "ACK timer expired, no ENQ left"


class ResponderAction(TableEnum):
    DELIVER = "DLE ACK; CommandReceived; remember the header"
    ACK_DUPLICATE = "DLE ACK; DuplicateReceived; with resend_reply, queue the stored reply again if not on its way"
    ACK_ONLY = "DLE ACK; count the frame not for us"
    REFUSE = "DLE NAK: the sink is full"
    REJECT = "DLE NAK: the frame is damaged"
    ANSWER_ENQ = "send the last response symbol again"
    LAST_NAK = "the last response becomes DLE NAK"
    TRANSMIT = "send the next queued reply, start the ACK timer"
    COMPLETE = "ReplyDelivered; send the next queued reply"
    RETRANSMIT = "send the same frame again, restart the ACK timer"
    ENQUIRE = "send DLE ENQ, restart the ACK timer"
    LOSE_NAK = "ReplyLost(NAK_LIMIT); send the next queued reply"
    LOSE_NO_RESPONSE = "ReplyLost(NO_RESPONSE); send the next queued reply"
    IGNORE = "nothing"


S, K, A = TxState, ResponderInput, ResponderAction

#: The receiver's inputs: the same action in every state, and the state stays (p. 4-2).
_RECEIVER: Final[Mapping[ResponderInput, ResponderAction]] = {
    K.COMMAND: A.DELIVER,
    K.DUPLICATE: A.ACK_DUPLICATE,
    K.NOT_FOR_US: A.ACK_ONLY,
    K.SINK_FULL: A.REFUSE,
    K.BAD_FRAME: A.REJECT,
    K.ENQ_IN_FRAME: A.REJECT,
    K.ENQ: A.ANSWER_ENQ,
    K.NOISE: A.LAST_NAK,
}

#: The transmitter (p. 4-6).
_TRANSMITTER: Final[Mapping[tuple[TxState, ResponderInput], tuple[ResponderAction, TxState]]] = {
    (S.IDLE, K.REPLY): (A.TRANSMIT, S.AWAIT_ACK),
    (S.AWAIT_ACK, K.ACK): (A.COMPLETE, S.IDLE),
    (S.AWAIT_ACK, K.NAK): (A.RETRANSMIT, S.AWAIT_ACK),
    (S.AWAIT_ACK, K.NAK_LIMIT): (A.LOSE_NAK, S.IDLE),
    (S.AWAIT_ACK, K.TIMEOUT): (A.ENQUIRE, S.AWAIT_ACK),
    (S.AWAIT_ACK, K.TIMEOUT_LIMIT): (A.LOSE_NO_RESPONSE, S.IDLE),
}

#: Pairs that change nothing, each with its reason.
IGNORED: Final[Mapping[tuple[TxState, ResponderInput], str]] = MappingProxyType({
    (S.IDLE, K.ACK): "no reply on the line: a late or stray DLE ACK",
    (S.IDLE, K.NAK): "no reply on the line: a late or stray DLE NAK",
    (S.IDLE, K.NAK_LIMIT): "cannot happen: the NAK count belongs to the reply on the line",
    (S.IDLE, K.STALE): "cannot happen: no frame of ours waits in the output",
    (S.IDLE, K.TIMEOUT): "cannot happen: no ACK timer runs without a reply on the line",
    (S.IDLE, K.TIMEOUT_LIMIT): "cannot happen: no ACK timer runs without a reply on the line",
    (S.AWAIT_ACK, K.REPLY): "the reply waits in the queue: one reply on the line at a time",
    (S.AWAIT_ACK, K.STALE): "the peer cannot have seen our frame yet: the symbol answers an older one",
})


def _complete_table() -> Mapping[tuple[TxState, ResponderInput], Transition[ResponderAction, TxState]]:
    """Every (state, input) pair exactly once: the receiver's, the transmitter's, the ignored."""
    table = {(state, what): (action, state) for state in S for what, action in _RECEIVER.items()}
    for pair, step in (*_TRANSMITTER.items(), *((pair, (A.IGNORE, pair[0])) for pair in IGNORED)):
        if pair in table:
            raise RuntimeError(f"DF1 responder table: {pair} is listed twice")
        table[pair] = step
    missing = [(state, what) for state in S for what in K if (state, what) not in table]
    if missing:
        raise RuntimeError(f"DF1 responder table: no transition for {missing}")
    return MappingProxyType({pair: Transition(*step) for pair, step in table.items()})


#: (state, input) -> Transition(action, next state), complete: checked at import.
TRANSITIONS: Final = _complete_table()


class ResponderStep(NamedTuple):
    """One transition taken (the responder keeps the last ones in ``history``)."""

    state: TxState
    input: ResponderInput
    action: ResponderAction
    next_state: TxState
