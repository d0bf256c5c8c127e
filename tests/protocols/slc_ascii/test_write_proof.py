"""What an SLC 100/150 transaction's replies prove about a write (``slc_ascii/write_proof.py``).

From the manual (shared/docs/slc100-150-ascii-protocol.md, "Format of Transmission"):

* "If a command or <parameters> is illegal, the SLC will respond ... ;E [ID]": a refusal; the
  command did not run.
* "If a message contains an unexpected [ID], the controller will respond with ;I {id} where {id}
  is the last valid [ID]": a copy with the same ID as an accepted message is not run again
  ("the controller will verify that sequential order is maintained"), so a second copy under the
  same ID is safe, a copy under a new ID is not.
* ";Z ... retransmits its most recent acknowledge or data message": after a power cycle there is
  none ("Upon power up, the controller expects an [ID] of 00"), so a ``;E`` that follows a ``;Z``
  may be the controller's answer to the ``;Z`` itself, not a refusal of the command.

A write must never run twice and never be reported as not run when it may have run; a read may
always be asked again.
"""

from __future__ import annotations

import itertools

import pytest

from gateway.protocols.slc_ascii.write_proof import MismatchStep, RefusalStep, judge_id_mismatch, judge_refusal

BOOLS = (False, True)


# ------------------------------------------------------------------------------ ;E with our ID


def test_e_to_a_writes_only_copy_with_no_z_is_a_refusal() -> None:
    step = judge_refusal(is_write=True, era_trusted=True, refused_once=False, z_sent=False, copies=1)
    assert step is RefusalStep.REFUSED


def test_e_after_a_z_may_answer_the_z_so_a_write_is_unknown() -> None:
    for copies in (1, 2):
        step = judge_refusal(is_write=True, era_trusted=True, refused_once=False, z_sent=True, copies=copies)
        assert step is RefusalStep.UNKNOWN


def test_e_to_a_writes_second_copy_may_follow_a_first_copy_that_ran() -> None:
    step = judge_refusal(is_write=True, era_trusted=True, refused_once=False, z_sent=False, copies=2)
    assert step is RefusalStep.UNKNOWN


def test_e_to_a_read_is_a_refusal_and_after_a_z_the_read_asks_again() -> None:
    assert judge_refusal(is_write=False, era_trusted=True, refused_once=False, z_sent=False,
                         copies=2) is RefusalStep.REFUSED
    assert judge_refusal(is_write=False, era_trusted=True, refused_once=False, z_sent=True,
                         copies=1) is RefusalStep.ASK_AGAIN


def test_a_reads_first_e_in_an_untrusted_numbering_is_confirmed_once() -> None:
    """The numbering began without quiet: the ``;E`` may answer an earlier ``;Z`` with the same ID.
    The read asks again under a new numbering; a second ``;E`` is the controller's refusal."""
    assert judge_refusal(is_write=False, era_trusted=False, refused_once=False, z_sent=False,
                         copies=1) is RefusalStep.CONFIRM
    assert judge_refusal(is_write=False, era_trusted=False, refused_once=True, z_sent=False,
                         copies=1) is RefusalStep.REFUSED


@pytest.mark.parametrize(("era_trusted", "refused_once", "z_sent", "copies"),
                         list(itertools.product(BOOLS, BOOLS, BOOLS, (1, 2, 3))))
def test_a_write_is_never_called_not_run_when_it_may_have_run_nor_asked_again(
        era_trusted: bool, refused_once: bool, z_sent: bool, copies: int) -> None:
    step = judge_refusal(is_write=True, era_trusted=era_trusted, refused_once=refused_once, z_sent=z_sent,
                         copies=copies)
    if z_sent or copies > 1:
        assert step is RefusalStep.UNKNOWN
    else:
        assert step is RefusalStep.REFUSED


@pytest.mark.parametrize(("era_trusted", "refused_once", "z_sent", "copies"),
                         list(itertools.product(BOOLS, BOOLS, BOOLS, (1, 2, 3))))
def test_a_reads_e_never_leaves_its_outcome_unknown(era_trusted: bool, refused_once: bool, z_sent: bool,
                                                     copies: int) -> None:
    step = judge_refusal(is_write=False, era_trusted=era_trusted, refused_once=refused_once, z_sent=z_sent,
                         copies=copies)
    assert step is not RefusalStep.UNKNOWN


# ------------------------------------------------------------------------ ;I with another ID


def test_i_with_another_id_gets_one_second_copy_under_our_id() -> None:
    assert judge_id_mismatch(copies=1, may_resend=True, may_ask_z=True) is MismatchStep.SECOND_COPY


def test_after_the_second_copy_only_z_asks_and_then_the_outcome_is_unknown() -> None:
    assert judge_id_mismatch(copies=2, may_resend=True, may_ask_z=True) is MismatchStep.ASK_Z
    assert judge_id_mismatch(copies=2, may_resend=True, may_ask_z=False) is MismatchStep.UNKNOWN


def test_without_budget_for_a_copy_the_write_asks_z() -> None:
    assert judge_id_mismatch(copies=1, may_resend=False, may_ask_z=True) is MismatchStep.ASK_Z
    assert judge_id_mismatch(copies=1, may_resend=False, may_ask_z=False) is MismatchStep.UNKNOWN


@pytest.mark.parametrize(("copies", "may_resend", "may_ask_z"), list(itertools.product((1, 2, 3, 4), BOOLS, BOOLS)))
def test_a_write_meeting_stray_i_sends_at_most_two_copies(copies: int, may_resend: bool, may_ask_z: bool) -> None:
    step = judge_id_mismatch(copies=copies, may_resend=may_resend, may_ask_z=may_ask_z)
    if step is MismatchStep.SECOND_COPY:
        assert copies == 1 and may_resend
    if step is MismatchStep.ASK_Z:
        assert may_ask_z
