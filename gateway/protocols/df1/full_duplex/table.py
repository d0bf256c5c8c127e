"""The DF1 full-duplex station as data: one receiver table and one transmitter table.

Both full-duplex stations run them: the host's data link (``datalink.py``: commands out, replies
in) and the target's responder (``responder.py``: commands in, replies out).  Manual: A-B
1770-6.5.16 chapter 4 ("p. 4-x"); S4516-DF1 Program Development Manual §2.4 / §2.5.  The receiver
and the transmitter work at the same time (p. 4-2, Figure 4.1).

**Receiver** (p. 4-8, the RECEIVER program): each input has one action, whatever the transmitter
does (:data:`RECEIVER`)::

    good frame, new message          -> DLE ACK, deliver, remember SRC CMD TNS ("save last header")
    good frame, same SRC CMD TNS     -> DLE ACK, not delivered (duplicate_detect; p. 4-13, p. 6-3)
    good frame, DST not ours         -> DLE ACK, not delivered (the responder's check_dst)
    good frame, sink full            -> DLE NAK ("else if message sink is full send DLE NAK")
    damaged / < 6 bytes / too long   -> DLE NAK ("too small", "too large", BCC/CRC not valid)
    DLE ENQ inside a frame           -> DLE NAK for the truncated frame
    DLE ENQ                          -> the last response symbol again
    anything else outside a frame (noise, DLE ETX without DLE STX) -> last response := DLE NAK
                                        ("else LAST-RESPONSE = NAK"; p. 4-7 "a false control or
                                        data symbol occurs outside a message")

The manuals leave two receiver rules open (docs/develop/controller-variants.md), so the table is built by
:func:`receiver_table` from the station's reading: what a damaged frame gets
(:class:`BadFrameAnswer`) and what a DLE ENQ gets (:class:`EnqAnswer`).  The gateway's two
stations keep the defaults (the p. 4-8 program); a simulated controller picks a reading.

**Transmitter** (p. 4-6 flowchart), one frame on the line at a time (:data:`TRANSITIONS`)::

    IDLE --send--> AWAIT_ACK --DLE ACK--> IDLE (complete), the next queued frame
                   AWAIT_ACK --DLE NAK--> the same frame again                 (at most nak_limit times)
                   AWAIT_ACK --timeout--> DLE ENQ                              (at most enq_limit times)
                   then IDLE (failed), the next queued frame
                   AWAIT_ACK --confirm--> IDLE (complete): the data link saw the reply to its frame
                   AWAIT_ACK --DLE NAK for a frame that must not run twice--> IDLE (failed)

The data link's ``confirm`` and its frames that must not run twice are its own inputs; the
responder never makes them.  Plain data, no I/O.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from types import MappingProxyType
from typing import Final, NamedTuple

from gateway.protocols.transitions import Table, TableEnum, Transition, require_complete, stay

__all__ = [
    "RECEIVER",
    "TRANSITIONS",
    "BadFrameAnswer",
    "EnqAnswer",
    "RxAction",
    "RxInput",
    "StationStep",
    "TxAction",
    "TxInput",
    "TxState",
    "receiver_table",
]


class TxState(TableEnum):
    """The transmitter's state, one frame on the line at a time (p. 4-6)."""

    IDLE = "no frame of ours on the line"
    AWAIT_ACK = "our frame sent, waiting for its DLE ACK"


# ------------------------------------------------------------------------------------- receiver


class RxInput(TableEnum):
    MESSAGE = "a good frame with a new message, room in the sink"
    DUPLICATE = "a good frame with the SRC, CMD and TNS of the last message delivered (duplicate_detect)"
    NOT_FOR_US = "a good frame whose DST is not our station (the responder's check_dst)"
    SINK_FULL = "a good frame with a new message, the sink is full"
    BAD_FRAME = "a damaged frame: check, DLE sequence, fewer than 6 bytes, too long"
    ENQ_IN_FRAME = "DLE ENQ inside a frame: the frame is truncated"
    ENQ = "DLE ENQ"
    NOISE = "a byte or symbol outside a frame that starts nothing, DLE ETX without DLE STX included"


class RxAction(TableEnum):
    DELIVER = "DLE ACK; deliver the message; remember its header"
    ACK_DUPLICATE = "DLE ACK; the duplicate is not delivered"
    ACK_ONLY = "DLE ACK; the frame not for us is not delivered"
    REFUSE = "DLE NAK: the sink is full"
    REJECT = "DLE NAK: the frame is damaged"
    LAST_NAK = "no answer now; the last response becomes DLE NAK"
    ANSWER_ENQ = "send the last response symbol again"
    ANSWER_NAK = "send DLE NAK"
    IGNORE = "nothing: as if nothing arrived"


class BadFrameAnswer(enum.Enum):
    """What a receiver does with a damaged frame (p. 4-8 and S4516 §2.5 say NAK; some stay silent)."""

    NAK = "nak"  #: DLE NAK at once (p. 4-8)
    SILENCE = "silence"  #: no answer now; the last response becomes DLE NAK (answered on DLE ENQ)
    IGNORE = "ignore"  #: as if nothing arrived: no answer, the last response is unchanged


class EnqAnswer(enum.Enum):
    """How a receiver answers DLE ENQ."""

    LAST_RESPONSE = "last"  #: repeat the last response symbol (p. 4-8)
    NAK = "nak"  #: always DLE NAK, "a request for retransmission" (S4516-DF1 manual §2.1)


_BAD_FRAME: Final = {
    BadFrameAnswer.NAK: RxAction.REJECT,
    BadFrameAnswer.SILENCE: RxAction.LAST_NAK,
    BadFrameAnswer.IGNORE: RxAction.IGNORE,
}
_ENQ_ANSWER: Final = {EnqAnswer.LAST_RESPONSE: RxAction.ANSWER_ENQ, EnqAnswer.NAK: RxAction.ANSWER_NAK}


def receiver_table(
    bad_frame: BadFrameAnswer = BadFrameAnswer.NAK, enq_answer: EnqAnswer = EnqAnswer.LAST_RESPONSE
) -> Mapping[RxInput, RxAction]:
    """The receiver's action for each input, under the station's reading (module docstring)."""
    table = {
        RxInput.MESSAGE: RxAction.DELIVER,
        RxInput.DUPLICATE: RxAction.ACK_DUPLICATE,
        RxInput.NOT_FOR_US: RxAction.ACK_ONLY,
        RxInput.SINK_FULL: RxAction.REFUSE,
        RxInput.BAD_FRAME: _BAD_FRAME[bad_frame],
        RxInput.ENQ_IN_FRAME: RxAction.REJECT,
        RxInput.ENQ: _ENQ_ANSWER[enq_answer],
        RxInput.NOISE: RxAction.LAST_NAK,
    }
    missing = set(RxInput) - set(table)
    if missing:
        raise RuntimeError(f"DF1 receiver table: no action for {sorted(map(str, missing))}")
    return MappingProxyType(table)


#: The receiver of the p. 4-8 program: the gateway's data link and responder.
RECEIVER: Final = receiver_table()


# ------------------------------------------------------------------------------------ transmitter


class TxInput(TableEnum):
    SEND = "a frame is queued"
    ACK = "DLE ACK received"
    NAK = "DLE NAK received, retransmissions left"
    NAK_LIMIT = "DLE NAK received, no retransmission left"
    TIMEOUT = "ACK timer expired, ENQs left"
    TIMEOUT_LIMIT = "ACK timer expired, no ENQ left"
    NAK_NOT_PROOF = "DLE NAK for a frame that must not run twice (not resent: the NAK is no proof)"
    CONFIRM = "the application layer saw the reply to the frame"
    STALE = "DLE ACK / DLE NAK before our frame left data_to_send(): an answer to an older frame"
    RESET = "the line was reset (port reopened)"


class TxAction(TableEnum):
    TRANSMIT = "send the next queued frame, start the ACK timer"
    COMPLETE = "the frame is delivered; the next queued frame goes"
    RETRANSMIT = "send the same frame again, restart the ACK timer"
    ENQUIRE = "send DLE ENQ, restart the ACK timer"
    FAIL_NAK = "the frame is given up (NAK_LIMIT); the next queued frame goes"
    FAIL_NO_RESPONSE = "the frame is given up (NO_RESPONSE); the next queued frame goes"
    FAIL_AMBIGUOUS = "the frame is given up (AMBIGUOUS_NAK); the next queued frame goes"
    RESET = "forget the line; every frame on the line or queued is given up (LINK_RESET)"
    IGNORE = "nothing (a stray symbol, or nothing to do)"


def _tx_table() -> Table[TxState, TxInput, TxAction]:
    T, In, A, IDLE, AWAIT = Transition, TxInput, TxAction, TxState.IDLE, TxState.AWAIT_ACK
    return {
        (IDLE, In.SEND): T(A.TRANSMIT, AWAIT),
        # nothing awaits an answer: a stray or late symbol, a confirm of a frame already done; the
        # NAK count, the output and the timer belong to a frame on the line, so NAK_LIMIT, STALE
        # and the timeouts cannot happen here
        **stay(A.IGNORE, IDLE, In.ACK, In.NAK, In.NAK_LIMIT, In.NAK_NOT_PROOF, In.STALE, In.CONFIRM, In.TIMEOUT,
               In.TIMEOUT_LIMIT),
        (IDLE, In.RESET): T(A.RESET, IDLE),
        (AWAIT, In.SEND): T(A.IGNORE, AWAIT),  # queued: it goes when the frame on the line is done
        (AWAIT, In.STALE): T(A.IGNORE, AWAIT),  # the peer cannot have seen our frame yet
        (AWAIT, In.ACK): T(A.COMPLETE, IDLE),
        (AWAIT, In.NAK): T(A.RETRANSMIT, AWAIT),
        (AWAIT, In.NAK_LIMIT): T(A.FAIL_NAK, IDLE),
        (AWAIT, In.TIMEOUT): T(A.ENQUIRE, AWAIT),
        (AWAIT, In.TIMEOUT_LIMIT): T(A.FAIL_NO_RESPONSE, IDLE),
        (AWAIT, In.NAK_NOT_PROOF): T(A.FAIL_AMBIGUOUS, IDLE),
        (AWAIT, In.CONFIRM): T(A.COMPLETE, IDLE),
        (AWAIT, In.RESET): T(A.RESET, IDLE),
    }


#: The transmitter's state machine: (state, input) -> (action, next state).
TRANSITIONS: Final = _tx_table()
require_complete(TRANSITIONS, TxState, TxInput, "full-duplex transmitter")


class StationStep(NamedTuple):
    """One step a station took (its ``history`` keeps the last ones): a receiver input leaves the
    transmitter's state as it is."""

    state: TxState
    input: RxInput | TxInput
    action: RxAction | TxAction
    next_state: TxState
