"""What an SLC 100/150 transaction's replies prove, and the verdict it ends with.

A write must never run twice and must never be reported as not run when it did.  A copy sent
again with the same ID is safe (the controller refuses a second copy of an accepted message:
"sequential order"); a copy under a new ID is safe only once no copy of the command ran or can
still run.  The rules, which :class:`~gateway.protocols.slc_ascii.transaction.SlcSession` applies:

* **A ``;I`` with another ID** (:func:`judge_id_mismatch`) is proof of non-execution when the
  transaction began with no reply of an earlier message still due and it reports the ID before
  ours (not 00: a controller may report 00 after any power cycle), or is of another kind when
  only one copy was ever sent (it answers that copy: it was not executed).  A ``;I`` with the ID
  before ours to the first copy is not proof yet: it may answer a copy of the previous message
  that the line repeated (refused after the previous message ran), heard while ours is on its
  way; a second copy with our ID settles it (``;I`` with our ID: ours ran).  The same ``;I`` to
  a later copy is proof only once no answer to our copies can still come (``late_bound`` after
  the last): the line may have repeated the stray ``;I`` too, and an answer with our ID settles
  it the other way.
* **A ``;I`` with our own ID** proves an earlier copy was accepted: ``;Z`` fetches its answer
  (``;R`` or ``;E``).
* **A ``;E`` with our ID** (:func:`judge_refusal`) is a refusal, unless it may answer a ``;Z``
  (a controller that answers ``;Z`` with ``;E`` after a power cycle, no last reply kept).
* Without proof, after the retries, the verdict is ``UNKNOWN`` (the gateway answers 0x0B): the
  command was applied at most once.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from gateway.protocols.slc_ascii.framing import Ack, DataReply

__all__ = ["Answer", "MismatchStep", "RefusalStep", "Result", "SlcVerdict", "judge_id_mismatch", "judge_refusal"]

Answer = Ack | DataReply


class SlcVerdict(enum.Enum):
    DONE = "done"  # answered (;R or data)
    REFUSED = "refused"  # ;E to the command itself: not executed
    UNKNOWN = "unknown"  # a write without proof either way: executed at most once
    FAILED = "failed"  # no answer within the bounds (a read, or a write proved not executed)


@dataclass(frozen=True, slots=True)
class Result:
    verdict: SlcVerdict
    answer: Answer | None = None
    reason: str = ""


class MismatchStep(enum.Enum):
    """What a write does on a ``;I`` with another ID than ours."""

    SECOND_COPY = "send a second copy with our ID: its answer settles it either way"
    AWAIT_PROOF = "proof once no answer to our copies can still come"
    PROVED = "no copy ran or can still run: a new ID is safe"
    ASK_Z = "no proof: ask for the controller's last reply (;Z)"
    UNKNOWN = "no proof, and no more asking"


def judge_id_mismatch(*, last_valid_id: int, prev_id: int, copies: int, began_clean: bool,
                      may_resend: bool, may_ask_z: bool) -> MismatchStep:
    """A write's step on ``;I<last_valid_id>`` (not our ID).

    ``prev_id``: the ID before ours; ``copies``: copies of the command sent; ``began_clean``: no
    reply of an earlier message could still come when the transaction began; ``may_resend`` /
    ``may_ask_z``: a copy / a ``;Z`` may still go (count or time budget).
    """
    previous = last_valid_id == prev_id and last_valid_id != 0
    if began_clean and copies == 1 and previous and may_resend:
        # Ambiguous: this ;I may answer our only copy (not executed), or a copy of the previous
        # message that the line repeated, refused after that message ran and heard only now,
        # while ours is on its way (and runs).  A second copy with our ID is safe either way:
        # ;I with our ID (ours ran: ;Z fetches its answer) or ;I with the previous ID again.
        return MismatchStep.SECOND_COPY
    proof = began_clean and (copies == 1 or previous)
    if proof and copies > 1:
        # ;I with the ID before ours to our second copy: proof, unless the line repeated the
        # stray ;I that made us send that copy (a line that repeats frames both ways).  Then
        # the answers to our copies are still on their way: wait until none can still come;
        # one with our ID settles it the other way.
        return MismatchStep.AWAIT_PROOF
    if proof:
        return MismatchStep.PROVED
    return MismatchStep.ASK_Z if may_ask_z else MismatchStep.UNKNOWN


class RefusalStep(enum.Enum):
    """What a transaction does on a ``;E`` with our ID."""

    CONFIRM = "a read in a numbering begun without quiet: ask again under a new numbering"
    REFUSED = "the controller refused the command: it did not run"
    UNKNOWN = "a write's ;E after ;Z: refused, or no reply kept after a power cycle"
    ASK_AGAIN = "a read's ;E after ;Z: ask again under a new numbering"


def judge_refusal(*, is_write: bool, era_trusted: bool, refused_once: bool, z_sent: bool) -> RefusalStep:
    """The step on ``;E`` with our ID.

    ``era_trusted``: the numbering began with a barrier sent after quiet; ``refused_once``: this
    transaction already asked again after a ``;E``; ``z_sent``: a ``;Z`` went out in it.
    """
    if not is_write and not era_trusted and not refused_once:
        # A read in a numbering begun without quiet: this ;E may answer an earlier ;Z with the
        # same ID (a controller that answers ;Z with ;E after a power cycle).  Ask again under a
        # new numbering; a second ;E is the controller's refusal.
        return RefusalStep.CONFIRM
    if not z_sent:
        return RefusalStep.REFUSED
    # After a ;Z, a ;E with our ID may be the controller's ;E to the ;Z itself (a reading of the
    # manual: no last reply after a power cycle), not a refusal of our command.
    return RefusalStep.UNKNOWN if is_write else RefusalStep.ASK_AGAIN
