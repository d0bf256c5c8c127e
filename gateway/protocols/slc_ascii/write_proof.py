"""What an SLC 100/150 transaction's replies prove about a write, and the verdict it ends with.

A write must never run twice and must never be reported as not run when it did.  A copy sent
again with the same ID is safe: the controller refuses a second copy of an accepted message
("sequential order"), and after a power cycle it accepts nothing but ID 00.  A copy under a new
ID would be safe only once no copy ran or can still run, and nothing on this line proves that:
so a write is never sent under a second ID.  Its verdict rests only on replies that carry its
own ID (within a numbering begun with a barrier, no earlier message's reply has that ID):

* **``;R`` with our ID**: a copy ran (``DONE``).
* **``;E`` with our ID** (:func:`judge_refusal`) to the write's only copy, with no ``;Z`` sent:
  the controller refused it, nothing ran (``REFUSED``).  After a ``;Z`` it may be the
  controller's ``;E`` to the ``;Z`` (no last reply kept after a power cycle); after a second copy
  it may be the refusal of that copy by a controller that checks the command before the ID (the
  manual does not say which check comes first) while an earlier copy ran: ``UNKNOWN`` either way.
* **``;I`` with our ID**: a copy was accepted; ``;Z`` fetches its answer.
* **``;I`` with another ID** (:func:`judge_id_mismatch`) proves nothing.  It may answer one of our
  copies (a power-cycled controller: ``;I00``, or ``;I`` with the last ID it accepted before the
  power cycle), or be a stale or repeated reply to an earlier message: a line that repeats frames
  makes the controller refuse the repeat of the previous message, and may repeat that ``;I`` too,
  and may drop the replies with our ID that would tell the two apart.  It is also what a
  controller answers to the line's repeat of our own copy when it power-cycled in between, after
  that copy ran.  So a second copy with our ID (``;I`` with our ID or its ack if ours ran; it runs
  if ours never got there), then ``;Z``; never a new ID.
* Without an answer with our ID, after the retries, the verdict is ``UNKNOWN`` (the gateway
  answers 0x0B): the command ran at most once.  ``FAILED`` is for a write only when none of its
  copies went out (its resync got no answer).
"""

from __future__ import annotations

import enum

from gateway.frozen import frozen
from gateway.protocols.slc_ascii.framing import Ack, DataReply

__all__ = ["Answer", "MismatchStep", "RefusalStep", "Result", "SlcVerdict", "judge_id_mismatch", "judge_refusal"]

Answer = Ack | DataReply


class SlcVerdict(enum.Enum):
    DONE = "done"  # answered (;R or data)
    REFUSED = "refused"  # ;E to the command itself: not executed
    UNKNOWN = "unknown"  # a write without an answer with its ID: executed at most once
    FAILED = "failed"  # no answer within the bounds (a read, or a write none of whose copies went out)


@frozen
class Result:
    verdict: SlcVerdict
    answer: Answer | None = None
    reason: str = ""


class MismatchStep(enum.Enum):
    """What a write does on a ``;I`` with another ID than ours (never proof of anything)."""

    SECOND_COPY = "send a second copy with our ID: refused with our ID if ours ran, run if none got there"
    ASK_Z = "ask for the controller's last reply (;Z): our ack if a copy ran and it kept it"
    UNKNOWN = "no more asking: outcome unknown"


def judge_id_mismatch(*, copies: int, may_resend: bool, may_ask_z: bool) -> MismatchStep:
    """A write's step on ``;I`` with another ID than ours.

    ``copies``: copies of the command sent; ``may_resend`` / ``may_ask_z``: a copy / a ``;Z`` may
    still go (count or time budget).  One more copy with our ID after the first: it settles a
    stray ``;I`` on a controller in step (``;I`` with our ID, or our ack, if ours ran; it runs if
    ours was lost).  Past that (a power-cycled controller answers every copy so), ``;Z``: it
    fetches our ack if a copy ran and the controller still has it, an older reply (the command
    then goes again, same ID) if none ran.
    """
    if copies == 1 and may_resend:
        return MismatchStep.SECOND_COPY
    return MismatchStep.ASK_Z if may_ask_z else MismatchStep.UNKNOWN


class RefusalStep(enum.Enum):
    """What a transaction does on a ``;E`` with our ID."""

    CONFIRM = "a read in a numbering begun without quiet: ask again under a new numbering"
    REFUSED = "the controller refused the command: it did not run"
    UNKNOWN = "a write's ;E after ;Z or to a later copy: refused, or an earlier copy ran"
    ASK_AGAIN = "a read's ;E after ;Z: ask again under a new numbering"


def judge_refusal(*, is_write: bool, era_trusted: bool, refused_once: bool, z_sent: bool,
                  copies: int) -> RefusalStep:
    """The step on ``;E`` with our ID.

    ``era_trusted``: the numbering began with a barrier sent after quiet; ``refused_once``: this
    transaction already asked again after a ``;E``; ``z_sent``: a ``;Z`` went out in it;
    ``copies``: copies of the command sent.
    """
    if not is_write and not era_trusted and not refused_once:
        # A read in a numbering begun without quiet: this ;E may answer an earlier ;Z with the
        # same ID (a controller that answers ;Z with ;E after a power cycle).  Ask again under a
        # new numbering; a second ;E is the controller's refusal.
        return RefusalStep.CONFIRM
    if not z_sent and (copies == 1 or not is_write):
        return RefusalStep.REFUSED
    # After a ;Z, a ;E with our ID may be the controller's ;E to the ;Z itself (a reading of the
    # manual: no last reply after a power cycle), not a refusal of our command.  A write's later
    # copy may be refused by a controller that checks the command before its ID (the mode changed)
    # after an earlier copy ran.
    return RefusalStep.UNKNOWN if is_write else RefusalStep.ASK_AGAIN
