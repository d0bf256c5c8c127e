"""The exactly-once verdict of one DF1 write, shared by full and half duplex (sans-I/O).

A write is sent once.  When its answer does not come, it may have run (a controller without
duplicate detection would run a second copy again, S4516-DF1 manual §4.2 / §5.2), so it is never
resent: the target is read back.  :class:`WriteVerdict` decides, from what the caller saw, what
to do next - send a read-back, or give the verdict - and the callers (the full-duplex transaction
core, the half-duplex transaction layer) only carry frames.

The rule for read-backs: a write whose outcome is open is read back at most ``retries + 1``
times (:func:`read_back_tries`), the tries a read gets on the same link, where ``retries`` is the
link's ``retries`` key (default :data:`DEFAULT_RETRIES`).  Each read-back is one command: what the
link below does to deliver it (DLE ENQ on full duplex, identical copies on half duplex) is that
link's business.

Verdicts (:class:`VerdictKind`)::

    DONE      the reply, STS 0; or a read-back showed the written value (``verified``)
    REFUSED   the reply, STS != 0: nothing was written
    FAILED    the write provably never reached the controller (it was never sent)
    UNKNOWN   it may have run and no read-back proved it: a read-back showed another value, was
              refused, never answered ``retries + 1`` times, the write has no read-back, or the
              link went away

States and transitions (:data:`TRANSITIONS`; the pairs whose action is IGNORE change nothing)::

    SENT --reply OK--> SETTLED (DONE)          --reply STS!=0--> SETTLED (REFUSED)
    SENT --never arrived--> SETTLED (FAILED)   --lost (may have run)--> VERIFYING (read-back) | UNKNOWN
    VERIFYING --read-back holds--> SETTLED (DONE, verified)   --differs / refused--> SETTLED (UNKNOWN)
    VERIFYING --read-back lost--> VERIFYING (another read-back, tries left) | SETTLED (UNKNOWN)
    VERIFYING --late reply to the write--> SETTLED (DONE | REFUSED)
    SENT / VERIFYING --abandoned (link gone)--> SETTLED (UNKNOWN)

The caller passes ``now`` (its clock) with every input; the verdict carries the seconds from
the start.  This module does no I/O.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Final

from gateway.errors import format_seconds
from gateway.frozen import frozen
from gateway.protocols.df1.pccc import (
    PcccReply,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadModifyWriteRequest,
    WordRangeRead,
    WordRangeWrite,
)
from gateway.protocols.transitions import Table, TableEnum, Transition, require_complete, stay
from gateway.retries import DEFAULT_RETRIES

__all__ = [
    "DEFAULT_RETRIES",
    "TRANSITIONS",
    "ReadBack",
    "SendReadBack",
    "Verdict",
    "VerdictAction",
    "VerdictKind",
    "VerdictState",
    "VerdictStep",
    "WriteInput",
    "WriteVerdict",
    "read_back_for",
    "read_back_tries",
]



def read_back_tries(retries: int) -> int:
    """Read-backs of one write at most: the tries a read gets on the same link."""
    return retries + 1


# ------------------------------------------------------------------------------------ read-back


@frozen
class ReadBack:
    """How to verify a write: the read to send and whether its data shows the write applied."""

    request: ProtectedTypedLogicalRead | WordRangeRead
    holds: Callable[[bytes], bool]


def read_back_for(request: object) -> ReadBack | None:
    """The read-back of a protected typed logical (masked) write, a PLC-5 word range write or a
    one-word read-modify-write; None for other commands."""
    if isinstance(request, ProtectedTypedLogicalWrite):
        data = request.data
        read = ProtectedTypedLogicalRead(
            request.file_type, request.file_number, request.element, request.sub_element, len(data)
        )
        return ReadBack(read, lambda got: got == data)
    if isinstance(request, ProtectedTypedLogicalMaskedWrite):
        data, mask = request.data, request.mask.to_bytes(2, "little")
        read = ProtectedTypedLogicalRead(
            request.file_type, request.file_number, request.element, request.sub_element, len(data)
        )
        # the mask's low byte applies to even bytes, its high byte to odd ones (notes §4.36)

        def holds(got: bytes) -> bool:
            return len(got) == len(data) and all(
                (got[i] & mask[i % 2]) == (data[i] & mask[i % 2]) for i in range(len(data))
            )

        return ReadBack(read, holds)
    if isinstance(request, WordRangeWrite) and request.packet_offset == 0:
        # PLC-5 word range write: read the same words back with a word range read
        words = request.data
        return ReadBack(WordRangeRead(request.address, len(words)), lambda got: got == words)
    if isinstance(request, ReadModifyWriteRequest) and len(request.sets) == 1:
        # PLC-5 coil write: the bits the masks force (AND 0 or OR 1) hold the OR mask's value (p. 7-20)
        address, and_mask, or_mask = request.sets[0]
        forced = (~and_mask | or_mask) & 0xFFFF

        def forced_bits_hold(got: bytes) -> bool:
            return len(got) == 2 and int.from_bytes(got, "little") & forced == or_mask & forced

        return ReadBack(WordRangeRead(address, 2), forced_bits_hold)
    return None


# ---------------------------------------------------------------------------------- the steps


class VerdictKind(enum.Enum):
    DONE = "done"
    REFUSED = "refused"
    FAILED = "failed"
    UNKNOWN = "unknown"


@frozen
class Verdict:
    """The outcome of a write; ``reply`` is the write's reply, or the read-back's when ``verified``."""

    kind: VerdictKind
    reason: str = ""
    reply: PcccReply | None = None
    verified: bool = False
    seconds: float = 0.0  #: from the start to the verdict, on the caller's clock
    #: UNKNOWN after a read-back that answered with another value: the data it gave (what the
    #: controller held after the write).  On a full-duplex link, where the read-back runs after the
    #: write, data equal to the value before the write proves it was not applied (``gateway.unit``).
    shown: bytes | None = None


@frozen
class SendReadBack:
    """Send this read-back now (``attempt`` counts from 1)."""

    request: ProtectedTypedLogicalRead | WordRangeRead
    attempt: int


#: What to do after an input: send a read-back, the verdict, or None (the input changed nothing).
VerdictStep = SendReadBack | Verdict | None


# ---------------------------------------------------------------------------------------- table


class VerdictState(TableEnum):
    SENT = "the write is on its way; no answer yet"
    VERIFYING = "the write may have run; a read-back is on its way"
    SETTLED = "the verdict is given"


class WriteInput(TableEnum):
    REPLY = "the reply to the write (STS 0 or not)"
    NEVER_ARRIVED = "the write provably never reached the controller"
    LOST = "no answer to the write; it may have run"
    READ_BACK_REPLY = "the reply to the read-back"
    READ_BACK_LOST = "no answer to the read-back"
    ABANDONED = "the link is gone"


class VerdictAction(TableEnum):
    ANSWERED = "DONE if STS 0, else REFUSED"
    FAIL = "FAILED"
    READ_BACK = "send a read-back if the write has one and tries are left, else UNKNOWN"
    CHECK = "DONE (verified) if the read-back shows the written value, else UNKNOWN"
    UNKNOWN = "UNKNOWN"
    IGNORE = "nothing: the input changes nothing"


S, K, A = VerdictState, WriteInput, VerdictAction

#: (state, input) -> (action, next state); an action that gives a verdict ends in SETTLED.
TRANSITIONS: Final[Table[VerdictState, WriteInput, VerdictAction]] = {
    (S.SENT, K.REPLY): Transition(A.ANSWERED, S.SETTLED),
    (S.SENT, K.NEVER_ARRIVED): Transition(A.FAIL, S.SETTLED),
    # a read-back, or UNKNOWN at once when the write has none
    (S.SENT, K.LOST): Transition(A.READ_BACK, S.VERIFYING, frozenset({S.SETTLED})),
    (S.SENT, K.ABANDONED): Transition(A.UNKNOWN, S.SETTLED),
    (S.SENT, K.READ_BACK_REPLY): Transition(A.IGNORE, S.SENT),  # no read-back was sent
    (S.SENT, K.READ_BACK_LOST): Transition(A.IGNORE, S.SENT),  # no read-back was sent
    (S.VERIFYING, K.READ_BACK_REPLY): Transition(A.CHECK, S.SETTLED),
    # another read-back while tries are left, else UNKNOWN
    (S.VERIFYING, K.READ_BACK_LOST): Transition(A.READ_BACK, S.VERIFYING, frozenset({S.SETTLED})),
    (S.VERIFYING, K.REPLY): Transition(A.ANSWERED, S.SETTLED),  # a late reply to the write settles it
    (S.VERIFYING, K.ABANDONED): Transition(A.UNKNOWN, S.SETTLED),
    (S.VERIFYING, K.NEVER_ARRIVED): Transition(A.IGNORE, S.VERIFYING),  # it was known to be on the line
    (S.VERIFYING, K.LOST): Transition(A.IGNORE, S.VERIFYING),  # it was known to be lost
    **stay(A.IGNORE, S.SETTLED, *WriteInput),  # the verdict is given
}
require_complete(TRANSITIONS, VerdictState, WriteInput, "write verdict")


# ---------------------------------------------------------------------------------------- the machine


class WriteVerdict:
    """The verdict of one write (module docstring).  Feed it what happened; follow its steps."""

    def __init__(self, request: object, *, retries: int, now: float) -> None:
        if retries < 0:
            raise ValueError("retries must not be negative")
        self.read_back: Final = read_back_for(request)
        self.max_read_backs: Final = read_back_tries(retries)
        self.read_backs = 0  #: read-backs asked for so far
        self.started: Final = now
        self._state = VerdictState.SENT
        self._why = ""

    @property
    def state(self) -> VerdictState:
        return self._state

    @property
    def settled(self) -> bool:
        return self._state is VerdictState.SETTLED

    def reply(self, reply: PcccReply, now: float) -> VerdictStep:
        """The write's own reply (matched by the caller), in time or late."""
        return self._input(WriteInput.REPLY, now, reply=reply)

    def lost(self, why: str, now: float, *, may_have_executed: bool = True) -> VerdictStep:
        """No answer to the write; ``may_have_executed`` False: it never reached the controller."""
        self._why = why
        return self._input(WriteInput.LOST if may_have_executed else WriteInput.NEVER_ARRIVED, now)

    def read_back_reply(self, reply: PcccReply, now: float) -> VerdictStep:
        return self._input(WriteInput.READ_BACK_REPLY, now, reply=reply)

    def read_back_lost(self, why: str, now: float) -> VerdictStep:
        self._why = why
        return self._input(WriteInput.READ_BACK_LOST, now)

    def abandon(self, why: str, now: float) -> VerdictStep:
        self._why = why
        return self._input(WriteInput.ABANDONED, now)

    # ------------------------------------------------------------------------------- internals

    def _input(self, what: WriteInput, now: float, *, reply: PcccReply | None = None) -> VerdictStep:
        entry = TRANSITIONS[self._state, what]
        if entry.action is VerdictAction.IGNORE:
            return None
        self._state = entry.next_state
        step = self._act(entry.action, now, reply)
        assert entry.allows(self._state), f"{entry.action.name} ended in {self._state.name}"
        return step

    def _act(self, action: VerdictAction, now: float, reply: PcccReply | None) -> VerdictStep:
        match action:
            case VerdictAction.ANSWERED:
                assert reply is not None
                return self._verdict(VerdictKind.DONE if reply.ok else VerdictKind.REFUSED, now, reply=reply)
            case VerdictAction.FAIL:
                return self._verdict(VerdictKind.FAILED, now, f"{self._why}; the write was never sent")
            case VerdictAction.READ_BACK:
                if self.read_back is not None and self.read_backs < self.max_read_backs:
                    self.read_backs += 1
                    return SendReadBack(self.read_back.request, self.read_backs)
                return self._unknown(now)
            case VerdictAction.CHECK:
                assert reply is not None and self.read_back is not None
                if reply.ok and self.read_back.holds(reply.data):
                    return self._verdict(VerdictKind.DONE, now, reply=reply, verified=True)
                self._why = (
                    f"the read-back was refused ({reply.error()})" if not reply.ok
                    else f"the read-back gave {reply.data.hex(' ')}, not the value written"
                )
                return self._unknown(now, shown=reply.data if reply.ok else None)
            case VerdictAction.UNKNOWN:
                return self._unknown(now)
        return None  # IGNORE: _input never acts on it

    def _unknown(self, now: float, *, shown: bytes | None = None) -> Verdict:
        if self.read_back is None:
            proof = ""
        elif self.read_backs >= self.max_read_backs and self._state is VerdictState.VERIFYING:
            proof = f"; {self.read_backs} read-backs got no answer"
        else:
            proof = "; the read-back did not prove it applied"
        return self._verdict(
            VerdictKind.UNKNOWN, now, f"{self._why}{proof}: the write may or may not have been applied", shown=shown
        )

    def _verdict(self, kind: VerdictKind, now: float, reason: str = "", *, reply: PcccReply | None = None,
                 verified: bool = False, shown: bytes | None = None) -> Verdict:
        self._state = VerdictState.SETTLED
        seconds = now - self.started
        if reason:
            reason = f"{reason} (after {format_seconds(seconds)} s)"
        return Verdict(kind, reason, reply, verified, seconds, shown)
