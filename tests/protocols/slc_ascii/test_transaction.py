"""The SLC 100/150 transaction core (sans-I/O) under every reading of the manual.

Driven with a fake clock and the simulator through random fault scripts (hypothesis): no write
applied twice, no acknowledged write lost, every unacknowledged write applied at most once (and
reported UNKNOWN, which the gateway answers 0x0B), no value the controller never held; reads
never fail for want of proof.
"""

from __future__ import annotations

import itertools
from collections import Counter

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.framing import (
    MAX_ID,
    CommandDecoder,
    CommandFrame,
    DataReply,
    encode_ack,
    encode_data_reply,
    encode_fault,
    encode_id_mismatch,
    encode_refused,
    encode_retransmit,
    frame_command,
)
from gateway.protocols.slc_ascii.transaction import SessionCounters, SessionState, SlcSession, SlcVerdict, next_id
from gateway.sim.variants import pairwise_cover

from .core_harness import FATES, FakeLine

#: every reading of every variant, and every pair of readings of two variants, at least once
VARIANTS = pairwise_cover(SlcAsciiSimulator.VARIANTS)
ADDRESSES = (0x40, 0x42, 0x44)
TIMEOUT = 0.3

fates = st.lists(st.sampled_from(FATES), max_size=300)
cycles = st.lists(st.booleans(), max_size=120)
operations = st.lists(st.tuples(st.sampled_from(("read", "write")), st.sampled_from(ADDRESSES)), min_size=1,
                      max_size=25)


def _fresh(variants: dict[str, str]) -> tuple[SlcAsciiSimulator, SlcSession]:
    sim = SlcAsciiSimulator(faults=FaultPlan(late_delay=1.2 * TIMEOUT), ladder=False, variants=variants)
    return sim, SlcSession(timeout=TIMEOUT, retries=3)


def _check_run(variants: dict[str, str], fate_list: list[str], cycle_list: list[bool],
               ops: list[tuple[str, int]], lost: list[bool] = ()) -> None:  # type: ignore[assignment]
    sim, session = _fresh(variants)
    line = FakeLine(sim, session, iter(fate_list), iter(cycle_list), iter(lost))
    held = {a: {sim.word(a)} for a in ADDRESSES}  # every value each address ever held
    acknowledged: list[tuple[int, int]] = []
    unknown: list[tuple[int, int]] = []
    refused_or_failed: list[tuple[int, int]] = []
    values = itertools.count(1)
    for kind, address in ops:
        if kind == "write":
            value = next(values)
            result = line.run(cmds.write_word(address, value))
            # the controller may have applied it: it may hold it from now on
            held[address].add(value)
            if result.verdict is SlcVerdict.DONE:
                acknowledged.append((address, value))
            elif result.verdict is SlcVerdict.UNKNOWN:
                unknown.append((address, value))
            else:
                refused_or_failed.append((address, value))
        else:
            result = line.run(cmds.read_bytes(address, 2))
            if result.verdict is SlcVerdict.DONE:
                assert isinstance(result.answer, DataReply)
                got = int.from_bytes(cmds.parse_read_reply(address, 2, result.answer.body_hex), "big")
                assert got in held[address], f"read 0x{address:02X} = {got}: never held {sorted(held[address])}"
            else:
                # reads never fail for want of proof: only when the line stays bad past the bounds
                assert result.verdict is SlcVerdict.FAILED
    applied = Counter((a, v) for kind, a, v in sim.applied_writes if kind == "word")
    assert all(n == 1 for n in applied.values()), f"a write applied twice: {applied}"
    for write in acknowledged:
        assert applied[write] == 1, f"acknowledged write {write} not applied"
    for write in refused_or_failed:
        assert applied[write] == 0, f"write {write} reported not executed, but applied"
    assert set(applied) <= set(acknowledged) | set(unknown)


@pytest.mark.parametrize("variants", VARIANTS, ids=lambda v: ",".join(f"{k}={x}" for k, x in sorted(v.items())))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fate_list=fates, cycle_list=cycles, ops=operations, lost=cycles)
def test_correct_under_random_faults(variants: dict[str, str], fate_list: list[str], cycle_list: list[bool],
                                     ops: list[tuple[str, int]], lost: list[bool]) -> None:
    _check_run(variants, fate_list, cycle_list, ops, lost)


@pytest.mark.parametrize("variants", VARIANTS,
                         ids=lambda v: ",".join(f"{k}={x}" for k, x in sorted(v.items())))
def test_reads_succeed_on_a_harsh_line(variants: dict[str, str]) -> None:
    """1 in 4 garbled, 1 in 6 dropped, a power cycle every 25 commands: every read answers."""
    sim, session = _fresh(variants)
    fate_cycle = itertools.cycle(["ok", "garble", "ok", "drop", "ok", "ok", "garble", "ok", "ok", "ok", "drop", "late"])
    power = itertools.cycle([False] * 24 + [True])
    line = FakeLine(sim, session, fate_cycle, power)
    for n in range(200):
        address = 0x40 + 2 * (n % 32)
        result = line.run(cmds.read_bytes(address, 2))
        assert result.verdict is SlcVerdict.DONE, result.reason
        got = int.from_bytes(cmds.parse_read_reply(address, 2, result.answer.body_hex), "big")  # type: ignore[union-attr]
        assert got == sim.word(address)


# --- byte scripts --------------------------------------------------------------------------------


def _started(command: cmds.Command | None = None, *, msg_id: int = 5) -> SlcSession:
    """A session in step with the controller: the next command goes with ``msg_id``."""
    session = SlcSession(timeout=TIMEOUT)
    session._next = msg_id  # as after msg_id - 1 messages, numbering begun after quiet
    session._era_trusted = True
    session.start(command or cmds.read_bytes(0x40, 2), 0.0)
    return session


READ = cmds.read_bytes(0x40, 2)
WRITE = cmds.write_word(0x40, 1234)


def _barrier(frame: bytes) -> tuple[int, bytes]:
    """``frame`` is a barrier read (one byte, ID 00): (its address, the controller's answer)."""
    decoder = CommandDecoder()
    decoder.receive_data(frame)
    event = decoder.next_event()
    assert isinstance(event, CommandFrame), frame
    assert event.code == cmds.CommandCode.READ and event.msg_id == 0, frame
    count, address = int.from_bytes(event.params[:2], "big"), int.from_bytes(event.params[2:], "big")
    assert count == 1, frame
    return address, encode_data_reply(f"01{address:04X}00", 0)


def test_clean_read_whole_byte_by_byte_and_with_trailing_garbage() -> None:
    for chunks in ("whole", "bytes", "garbage"):
        session = _started()
        assert session.data_to_send() == frame_command(READ, 5)
        reply = encode_data_reply("00020040" + "04D2", 5)
        if chunks == "whole":
            session.receive_data(reply, 0.01)
        elif chunks == "bytes":
            for i in range(len(reply)):
                session.receive_data(reply[i : i + 1], 0.01)
        else:
            session.receive_data(b"\x00~" + reply + b"\r\n\x7f", 0.01)
        result = session.take_result()
        assert result.verdict is SlcVerdict.DONE
        assert result.reason == ""  # the answer says it all; reasons explain the other verdicts
        assert session.data_to_send() == b""


def test_a_garbled_complete_reply_gets_z_at_once_a_missing_one_after_the_timeout() -> None:
    session = _started()
    session.data_to_send()
    bad = bytearray(encode_data_reply("000200400064", 5))
    bad[5] ^= 1
    session.receive_data(bytes(bad), 0.01)
    assert session.data_to_send() == encode_retransmit(5)  # at once, not at 0.3 s
    assert session.next_deadline() == pytest.approx(0.01 + TIMEOUT)
    session.handle_timeout(0.2)  # early: nothing happens
    assert session.data_to_send() == b""
    session.receive_data(encode_data_reply("000200400064", 5), 0.05)
    assert session.take_result().verdict is SlcVerdict.DONE

    # nothing at all: the timeout is waited out, then ;Z
    session.start(READ, 1.0)
    assert session.data_to_send() == frame_command(READ, 6)
    session.handle_timeout(1.0 + TIMEOUT / 2)
    assert session.data_to_send() == b""
    session.handle_timeout(1.0 + TIMEOUT)
    assert session.data_to_send() == encode_retransmit(6)
    # silence after ;Z (a power cycle leaves nothing to repeat): a read resyncs and asks again
    session.handle_timeout(1.0 + 2 * TIMEOUT)
    _, answer = _barrier(session.data_to_send())
    session.receive_data(answer, 1.7)
    assert session.data_to_send() == frame_command(READ, 1)
    session.receive_data(encode_data_reply("000200400064", 1), 1.71)
    assert session.take_result().verdict is SlcVerdict.DONE


def test_a_reply_cut_short_gets_z_after_the_character_gap_not_the_timeout() -> None:
    session = _started()
    session.data_to_send()
    reply = encode_data_reply("000200400064", 5)
    session.receive_data(reply[:7], 0.01)  # the rest (and its CR) is lost
    assert session.next_deadline() == pytest.approx(0.01 + session.char_gap)
    session.handle_timeout(0.01 + session.char_gap)
    assert session.data_to_send() == encode_retransmit(5)
    assert session.counters.crc_errors == 1
    session.receive_data(reply, 0.1)
    assert session.take_result().verdict is SlcVerdict.DONE


def test_a_frame_in_pieces_is_not_cut_short() -> None:
    session = _started()
    session.data_to_send()
    reply = encode_data_reply("000200400064", 5)
    now = 0.0
    for i in range(len(reply)):
        now += session.char_gap / 2
        session.handle_timeout(now)
        session.receive_data(reply[i : i + 1], now)
    assert session.take_result().verdict is SlcVerdict.DONE
    assert session.counters.crc_errors == 0


def test_a_write_answered_by_its_z_is_done_once() -> None:
    session = _started(WRITE)
    session.data_to_send()
    session.handle_timeout(TIMEOUT)
    assert session.data_to_send() == encode_retransmit(5)
    session.receive_data(encode_ack(5), 0.35)
    assert session.take_result().verdict is SlcVerdict.DONE


def test_a_write_with_no_answer_is_unknown_never_resent() -> None:
    session = _started(WRITE)
    sent = [session.data_to_send()]
    now = 0.0
    while session.result is None:
        now = session.next_deadline() or now
        session.handle_timeout(now)
        sent.append(session.data_to_send())
    assert session.take_result().verdict is SlcVerdict.UNKNOWN
    assert sent.count(frame_command(WRITE, 5)) == 1
    assert sent[1:] == [encode_retransmit(5)] * 3 + [b""]
    assert session.counters.timeouts == 4  # the copy's wait and each ;Z's


def test_a_refusal_after_z_is_not_taken_for_a_refusal_of_the_write() -> None:
    # z_after_power_up=error: a controller power-cycled after executing the write answers the ;Z
    # with ;E: the write may have run, so the verdict is UNKNOWN, not REFUSED.
    session = _started(WRITE)
    session.data_to_send()
    session.handle_timeout(TIMEOUT)
    session.receive_data(encode_refused(5), 0.35)
    assert session.take_result().verdict is SlcVerdict.UNKNOWN


def test_a_refusal_of_the_command_itself_is_refused() -> None:
    session = _started(WRITE)
    session.data_to_send()
    session.receive_data(encode_refused(5), 0.01)
    assert session.take_result().verdict is SlcVerdict.REFUSED


def test_t_between_command_and_reply_is_noted_and_does_not_disturb() -> None:
    session = _started()
    session.data_to_send()
    session.receive_data(encode_fault(0) + encode_data_reply("000200400064", 5), 0.01)
    assert session.fault_pending
    assert session.take_result().verdict is SlcVerdict.DONE


@pytest.mark.parametrize("reported", [4, 0], ids=["retained", "zero"])
def test_i_after_power_up_is_no_proof_the_write_stays_under_its_id(reported: int) -> None:
    """The controller power-cycled before our write (ID 05): ``;I04`` (retained) or ``;I00``.  The
    same bytes come from a stray ``;I`` of a repeated earlier message, or from the line's repeat of
    our copy refused after a power cycle that followed its run: no proof that it did not run.  A
    second copy with ID 05 and ``;Z`` (unanswered: nothing kept since the power cycle), then
    UNKNOWN; never a resync and a new ID."""
    session = _started(WRITE)
    sent = session.data_to_send()
    session.receive_data(encode_id_mismatch(reported), 0.01)
    assert session.data_to_send() == sent  # a second copy, the same ID
    session.receive_data(encode_id_mismatch(reported), 0.02)
    frames = [session.data_to_send()]
    now = 0.02
    while session.result is None:
        now = session.next_deadline() or now
        session.handle_timeout(now)
        frames.append(session.data_to_send())
    assert session.take_result().verdict is SlcVerdict.UNKNOWN
    assert set(frames) == {encode_retransmit(5), b""}, frames


def test_stray_i_of_a_repeated_previous_message_never_makes_a_write_run_twice() -> None:
    """The line repeated the previous message (ID 04): the controller ran it, refused the copy with
    ``;I04``, and that ``;I`` comes after its ack, while our write (ID 05) is on its way and runs.
    Taking the ``;I04`` as proof would resend the write under a new ID (run twice): a second copy
    with ID 05 is refused ``;I05`` (ours ran), and ``;Z`` fetches its ack.  (Long soak, 9be0bdd.)"""
    session = _started(WRITE)
    sent = session.data_to_send()
    session.receive_data(encode_id_mismatch(4), 0.01)
    assert session.data_to_send() == sent  # the same ID again, never a new one
    session.receive_data(encode_ack(5), 0.02)  # the ack of the first copy, which ran
    result = session.take_result()
    assert result.verdict is SlcVerdict.DONE
    # and when the ack of the first copy is lost: the second copy is refused with our ID
    session = _started(WRITE)
    sent = session.data_to_send()
    session.receive_data(encode_id_mismatch(4), 0.01)
    assert session.data_to_send() == sent
    session.receive_data(encode_id_mismatch(5), 0.02)
    assert session.data_to_send() == encode_retransmit(5)
    session.receive_data(encode_ack(5), 0.03)
    assert session.take_result().verdict is SlcVerdict.DONE


def test_a_write_after_id_rollover_goes_with_01_and_keeps_it() -> None:
    """Our write goes with ID 01 after 7F ("roll over from 127D to 01"), and every copy of it keeps
    01: also after ``;I7F`` (a retained-ID controller power-cycled, or a stray reply), which is no
    proof that it did not run."""
    session = SlcSession(timeout=TIMEOUT)
    session._next = MAX_ID
    session._era_trusted = True
    session.start(cmds.read_bytes(0x40, 2), 0.0)
    assert session.data_to_send() == frame_command(cmds.read_bytes(0x40, 2), MAX_ID)
    session.receive_data(encode_data_reply("000200400064", MAX_ID), 0.01)
    assert session.take_result().verdict is SlcVerdict.DONE
    session.start(WRITE, 0.02)
    assert session.data_to_send() == frame_command(WRITE, 1)  # 7F rolls over to 01, never 80 or 00
    session.handle_timeout(0.02 + TIMEOUT)  # reply lost
    assert session.data_to_send() == encode_retransmit(1)
    session.receive_data(encode_data_reply("000200400064", MAX_ID), 0.4)  # ;Z: an older reply
    assert session.data_to_send() == frame_command(WRITE, 1)  # resent with the same ID
    session.receive_data(encode_id_mismatch(MAX_ID), 0.41)
    assert session.data_to_send() == encode_retransmit(1)  # no proof: ;Z, never a resync
    session.receive_data(encode_ack(1), 0.42)
    assert session.take_result().verdict is SlcVerdict.DONE


def test_i_00_after_two_copies_is_no_proof() -> None:
    """Zero reading: ``;I00`` after a power cycle says nothing of an earlier copy: UNKNOWN."""
    session = _started(WRITE)
    session.data_to_send()
    session.handle_timeout(TIMEOUT)
    session.data_to_send()
    session.receive_data(encode_ack(4), 0.35)  # ;Z answered with the previous reply
    assert session.data_to_send() == frame_command(WRITE, 5)
    session.receive_data(encode_id_mismatch(0), 0.36)
    now = 0.36
    while session.result is None:
        assert session.data_to_send() in (b"", encode_retransmit(5))
        now = session.next_deadline() or now
        session.handle_timeout(now)
    assert session.take_result().verdict is SlcVerdict.UNKNOWN


def test_i_with_our_id_fetches_the_answer_with_z() -> None:
    session = _started(WRITE)
    session.data_to_send()
    session.receive_data(encode_id_mismatch(5), 0.01)
    assert session.data_to_send() == encode_retransmit(5)
    session.receive_data(encode_ack(5), 0.02)
    assert session.take_result().verdict is SlcVerdict.DONE


def test_next_id_rolls_over_from_7f_to_01() -> None:
    assert next_id(0) == 1
    assert next_id(0x7E) == 0x7F
    assert next_id(0x7F) == 1


def test_the_ids_after_a_resync_run_01_to_7f_and_never_return_to_00() -> None:
    ids = [0]
    for _ in range(0x7F + 3):
        ids.append(next_id(ids[-1]))
    assert ids == [0, *range(1, 0x80), 1, 2, 3]


def test_ids_run_through_a_rollover_against_the_simulator() -> None:
    sim, session = _fresh(VARIANTS[0])
    line = FakeLine(sim, session, iter(()), iter(()))
    for _ in range(300):
        assert line.run(READ).verdict is SlcVerdict.DONE
    assert sim.counters.id_mismatches == 0
    assert session.counters.id_resyncs == 1  # only the one after connecting


def test_a_read_refused_in_a_numbering_begun_without_quiet_is_asked_again() -> None:
    """``;E01`` may be a controller's answer to an earlier ``;Z01`` (after a power cycle): a read
    in a numbering begun without quiet resyncs and asks again; a second ``;E`` is a refusal."""
    session = _started(msg_id=1)
    session._era_trusted = False
    session.data_to_send()
    session.receive_data(encode_refused(1), 0.01)
    assert session.result is None
    _, answer = _barrier(session.data_to_send())
    session.receive_data(answer, 0.02)
    assert session.data_to_send() == frame_command(READ, 1)
    session.receive_data(encode_refused(1), 0.03)
    assert session.take_result().verdict is SlcVerdict.REFUSED


# --- barrier resyncs ---------------------------------------------------------------------------


def test_a_write_on_an_unclean_line_resyncs_with_a_barrier_at_once() -> None:
    """After a read that needed ``;Z`` (its first reply may still come) a write does not wait for
    quiet: a barrier read (ID 00) goes at once, and its answer proves every earlier reply came."""
    session = _started()
    session.data_to_send()
    session.handle_timeout(TIMEOUT)  # reply lost (or late)
    assert session.data_to_send() == encode_retransmit(5)
    session.receive_data(encode_data_reply("0200400064", 5), 0.35)
    assert session.take_result().verdict is SlcVerdict.DONE
    session.start(WRITE, 0.36)
    assert session.state is SessionState.RESYNC  # no QUIET wait
    _, answer = _barrier(session.data_to_send())
    session.receive_data(encode_data_reply("0200400064", 5), 0.37)  # the late first reply: ignored
    assert session.data_to_send() == b""
    session.receive_data(answer, 0.38)
    assert session.data_to_send() == frame_command(WRITE, 1)
    session.receive_data(encode_ack(1), 0.39)
    assert session.take_result().verdict is SlcVerdict.DONE
    session.start(WRITE, 0.40)  # one message, answered after the barrier: clean, no resync
    assert session.data_to_send() == frame_command(WRITE, 2)


def test_an_earlier_resyncs_barrier_answer_never_ends_a_resync() -> None:
    """The answer to an earlier resync's barrier read (a repeated frame, a late reply) echoes
    another address: taken for this resync's, a reply of an earlier message could follow it."""
    session = _started()
    session.data_to_send()
    session.receive_data(encode_id_mismatch(9), 0.01)  # a read meeting ;I resyncs
    first, first_answer = _barrier(session.data_to_send())
    session.receive_data(first_answer, 0.02)
    assert session.data_to_send() == frame_command(READ, 1)
    session.receive_data(encode_id_mismatch(9), 0.03)  # again
    second, second_answer = _barrier(session.data_to_send())
    assert second != first
    session.receive_data(first_answer, 0.04)  # the line repeats the first barrier's answer
    assert session.state is SessionState.RESYNC and session.data_to_send() == b""
    session.receive_data(second_answer, 0.05)
    assert session.data_to_send() == frame_command(READ, 1)


def test_a_refused_barrier_read_falls_back_to_read_frn_after_quiet() -> None:
    """Program mode refuses reads (``;E00``): the resync waits for quiet and reads the FRN,
    which every mode answers."""
    session = _started()
    session.data_to_send()
    session.receive_data(encode_id_mismatch(0), 0.01)  # power-cycled: a read resyncs at once
    _barrier(session.data_to_send())
    session.receive_data(encode_refused(0), 0.02)
    assert session.state is SessionState.QUIET
    session.handle_timeout(session.next_deadline() or 0)
    assert session.data_to_send() == frame_command(cmds.read_frn(), 0)
    session.receive_data(encode_data_reply("021FFE1547", 0), 0.7)
    assert session.data_to_send() == frame_command(READ, 1)


# --- scripts from a fresh session: connecting, counters, budgets, timeouts ----------------------

FRN_REPLY = encode_data_reply("021FFE1547", 0)
READ_REPLY_BODY = "000200400064"


class Script:
    """One session from its start, driven by the test: the frames it sends, the bytes it gets, a
    fake clock that moves only when the test says."""

    def __init__(self, *, retries: int = 3, max_resends: int = 8, max_resyncs: int = 8,
                 late_bound: float | None = None, min_timeout: float = 0.05) -> None:
        self.session = SlcSession(timeout=TIMEOUT, retries=retries, max_resends=max_resends, max_resyncs=max_resyncs,
                                  late_bound=late_bound, min_timeout=min_timeout)
        self.now = 0.0

    def start(self, command: cmds.Command, timeout: float | None = None, until: float | None = None) -> bytes:
        self.session.start(command, self.now, timeout, until=until)
        return self.session.data_to_send()

    def reply(self, data: bytes, dt: float = 0.01) -> bytes:
        """``data`` arrives ``dt`` later: what the session sends at once."""
        self.now += dt
        self.session.receive_data(data, self.now)
        return self.session.data_to_send()

    def read_answered(self, msg_id: int, *, dt: float) -> None:
        """A read as message ``msg_id``, its data reply ``dt`` later."""
        assert self.start(READ) == frame_command(READ, msg_id)
        self.reply(encode_data_reply(READ_REPLY_BODY, msg_id), dt=dt)
        assert self.verdict() is SlcVerdict.DONE

    def read_answered_after_retransmit(self, msg_id: int, *, dt: float) -> None:
        """A read as message ``msg_id`` whose reply is lost; the ``;Z`` brings it ``dt`` later."""
        assert self.start(READ) == frame_command(READ, msg_id)
        assert self.wait() == encode_retransmit(msg_id)
        self.reply(encode_data_reply(READ_REPLY_BODY, msg_id), dt=dt)
        assert self.verdict() is SlcVerdict.DONE

    def waits_until_verdict(self) -> list[float]:
        """Let each wait pass until the transaction ends; how long each was (to the millisecond)."""
        waits = []
        while self.session.result is None:
            deadline = self.session.next_deadline()
            assert deadline is not None
            waits.append(round(deadline - self.now, 3))
            self.wait()
        return waits

    def wait(self) -> bytes:
        """Nothing arrives until the session's deadline: what it sends then."""
        deadline = self.session.next_deadline()
        assert deadline is not None
        self.now = max(self.now, deadline)
        self.session.handle_timeout(self.now)
        return self.session.data_to_send()

    def verdict(self) -> SlcVerdict:
        return self.session.take_result().verdict

    def handshake_read(self) -> None:
        """The first read after connecting: read FRN with ID 00 (the line is quiet), then ID 01."""
        assert self.start(READ) == frame_command(cmds.read_frn(), 0)
        assert self.reply(FRN_REPLY) == frame_command(READ, 1)
        self.reply(encode_data_reply(READ_REPLY_BODY, 1))
        assert self.verdict() is SlcVerdict.DONE


def test_the_first_command_after_a_reconnect_resyncs_and_counts_as_a_handshake() -> None:
    """A new stream (``connected``): the controller's numbering is unknown, so the next command
    begins with an ID 00 resync, at once (nothing was sent on this stream yet); it is the
    connection's handshake, not a recovery (the driver reports resyncs less handshakes)."""
    script = Script()
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)  # in step: no resync
    script.session.connected()  # the stream drops with the read on its way
    assert script.session.state is SessionState.IDLE and script.session.result is None
    assert script.session.next_deadline() is None
    assert script.start(READ) == frame_command(cmds.read_frn(), 0)
    assert script.reply(FRN_REPLY) == frame_command(READ, 1)
    counters = script.session.counters
    assert (counters.id_resyncs, counters.handshakes) == (2, 2)


def test_a_reconnect_forgets_a_frame_cut_short_and_unsent_frames() -> None:
    """Bytes of the old stream never join the new one's: a partial reply is forgotten and
    frames not yet taken by the caller are dropped."""
    script = Script()
    script.handshake_read()
    script.session.start(READ, script.now)  # the frame is not taken before the stream drops
    script.session.receive_data(encode_data_reply(READ_REPLY_BODY, 2)[:6], script.now)
    script.session.connected()
    assert script.session.data_to_send() == b""
    assert script.session.next_deadline() is None
    assert script.start(READ) == frame_command(cmds.read_frn(), 0)
    # the new stream's FRN reply is not glued to the old partial frame
    assert script.reply(FRN_REPLY) == frame_command(READ, 1)
    assert script.session.counters.crc_errors == 0


def test_a_transaction_runs_one_at_a_time_and_a_result_is_taken_once() -> None:
    script = Script()
    with pytest.raises(RuntimeError):
        script.session.take_result()
    script.start(READ)
    with pytest.raises(RuntimeError):
        script.session.start(READ, script.now)
    script.reply(FRN_REPLY)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1))
    assert script.verdict() is SlcVerdict.DONE
    assert script.session.result is None
    with pytest.raises(RuntimeError):
        script.session.take_result()


def test_counters_count_what_the_line_did() -> None:
    """The driver reports the core's counters (timeouts, CRC errors, ;Z, resyncs less handshakes,
    ;T): each counts its event once."""
    script = Script()
    script.handshake_read()
    counters = script.session.counters
    assert counters == SessionCounters(id_resyncs=1, handshakes=1)
    assert script.start(READ) == frame_command(READ, 2)
    assert script.reply(encode_fault(0)) == b""  # ;T: noted for the caller, no answer
    assert script.session.fault_pending
    bad = bytearray(encode_data_reply(READ_REPLY_BODY, 2))
    bad[5] ^= 1
    assert script.reply(bytes(bad)) == encode_retransmit(2)
    assert script.reply(encode_ack(1)) == frame_command(READ, 2)  # ;Z met an older reply: resend
    first = script.reply(encode_id_mismatch(7))  # a read meeting ;I resyncs at once
    _barrier(first)
    second, answer = _barrier(script.wait())  # the barrier read is lost: another address
    assert second != _barrier(first)[0]
    assert script.reply(answer) == frame_command(READ, 1)
    assert script.wait() == encode_retransmit(1)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1))
    assert script.verdict() is SlcVerdict.DONE
    assert counters == SessionCounters(timeouts=2, crc_errors=1, retransmits=2, id_resyncs=2, handshakes=1,
                                       id_mismatches=1, resends=1, faults=1)
    # a write after a read of two messages resyncs; the controller refuses the barrier read
    # (program mode): quiet, then read FRN
    _barrier(script.start(WRITE))
    assert script.reply(encode_refused(0)) == b""
    assert script.session.state is SessionState.QUIET
    assert script.wait() == frame_command(cmds.read_frn(), 0)
    assert script.reply(FRN_REPLY) == frame_command(WRITE, 1)
    script.reply(encode_ack(1))
    assert script.verdict() is SlcVerdict.DONE
    assert counters == SessionCounters(timeouts=2, crc_errors=1, retransmits=2, id_resyncs=3, handshakes=1,
                                       id_mismatches=1, resends=1, faults=1, quiet_waits=1)


def test_a_write_whose_copy_was_accepted_asks_for_its_answer_a_bounded_number_of_times() -> None:
    """``;I`` with the write's own ID: a copy ran, so no copy goes again; ``;Z`` asks for its
    answer, ``retries`` times after the first (the controller may keep repeating the ``;I``),
    then UNKNOWN."""
    script = Script(retries=3)
    script.handshake_read()
    assert script.start(WRITE) == frame_command(WRITE, 2)
    asked = [script.reply(encode_id_mismatch(2)) for _ in range(5)]
    assert asked == [encode_retransmit(2)] * 4 + [b""]
    assert script.verdict() is SlcVerdict.UNKNOWN


def test_a_write_with_a_time_budget_asks_again_while_a_wait_fits_and_says_how_long_it_tried() -> None:
    """``until``: in place of the counts, a write asks again while one more wait fits before
    it; a read ignores it (reads are bounded by their resyncs)."""
    script = Script(retries=1)
    script.handshake_read()
    began = script.now
    assert script.start(WRITE, until=began + 1.0) == frame_command(WRITE, 2)
    asked = []
    for _ in range(3):
        frame = script.wait()
        asked.append((round(script.now - began, 3), frame))
    assert asked == [(0.3, encode_retransmit(2)), (0.6, encode_retransmit(2)), (0.9, b"")]
    result = script.session.take_result()
    assert result.verdict is SlcVerdict.UNKNOWN
    assert result.reason.endswith("after 2 retransmit requests in 0.9 s"), result.reason
    # without a budget: ``retries`` requests, and the reason gives no time
    _, answer = _barrier(script.start(READ))  # after UNKNOWN: a resync
    assert script.reply(answer) == frame_command(READ, 1)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1))
    assert script.verdict() is SlcVerdict.DONE
    assert script.start(WRITE) == frame_command(WRITE, 2)
    assert [script.wait() for _ in range(2)] == [encode_retransmit(2), b""]
    result = script.session.take_result()
    assert result.verdict is SlcVerdict.UNKNOWN and result.reason.endswith("after 1 retransmit requests"), result
    # a read with a budget: the budget is not its bound
    _, answer = _barrier(script.start(READ, until=script.now))
    assert script.reply(answer) == frame_command(READ, 1)
    assert script.wait() == encode_retransmit(1)


def test_the_reply_timeout_adapts_to_the_controller_and_verdicts_wait_the_full_time() -> None:
    """After 8 first replies the timeout is 2 x the slowest of them, at least ``min_timeout``;
    a longer timeout given for a command is kept; a reply fetched by ``;Z`` is no first reply;
    a write's last ``;Z`` waits the configured time (its answer may be held back on the line)."""
    script = Script(retries=3, min_timeout=0.05)
    script.handshake_read()  # two first replies, 10 ms each
    for n in range(2, 8):  # six more: 8 in all, measured when the eighth transaction starts
        assert script.start(READ) == frame_command(READ, n)
        assert script.session.next_deadline() == pytest.approx(script.now + TIMEOUT)
        script.reply(encode_data_reply(READ_REPLY_BODY, n), dt=0.01)
        assert script.verdict() is SlcVerdict.DONE
    script.start(READ)
    assert script.session.next_deadline() == pytest.approx(script.now + 0.05)  # 2 x 10 ms, raised to 50 ms
    assert script.wait() == encode_retransmit(8)
    script.reply(encode_data_reply(READ_REPLY_BODY, 8), dt=0.2)  # after ;Z: not a reply time
    assert script.verdict() is SlcVerdict.DONE
    assert script.start(READ, timeout=0.2) == frame_command(READ, 9)
    assert script.session.next_deadline() == pytest.approx(script.now + 0.05)
    script.reply(encode_data_reply(READ_REPLY_BODY, 9), dt=0.04)  # a slower first reply: 40 ms
    assert script.verdict() is SlcVerdict.DONE
    script.start(READ, timeout=1.0)  # a slow command's longer timeout is its own
    assert script.session.next_deadline() == pytest.approx(script.now + 1.0)
    script.reply(encode_data_reply(READ_REPLY_BODY, 10), dt=0.01)
    assert script.verdict() is SlcVerdict.DONE
    began = script.now
    assert script.start(WRITE) == frame_command(WRITE, 11)
    waits = script.waits_until_verdict()
    assert waits == [0.08, 0.08, 0.08, TIMEOUT]  # 2 x 40 ms; the last ;Z waits the full time
    assert script.verdict() is SlcVerdict.UNKNOWN
    assert script.now - began == pytest.approx(3 * 0.08 + TIMEOUT)


def test_with_no_barrier_address_free_a_read_resyncs_untrusted_and_a_refusal_there_is_confirmed_once() -> None:
    """Every barrier address asked for within the quiet time: a read resyncs at once with read
    FRN, a numbering no earlier ``;E`` is told apart in.  A ``;E`` to the read there is asked
    again once under a new numbering; the second ``;E`` is the controller's refusal."""
    script = Script(late_bound=100.0)  # nothing is quiet within this test
    script.handshake_read()
    used: list[int] = []
    while True:
        assert script.start(READ) == frame_command(READ, 2)
        resync = script.reply(encode_id_mismatch(0x55))  # ;I: the read resyncs at once
        if resync == frame_command(cmds.read_frn(), 0):
            break  # no barrier address free
        address, answer = _barrier(resync)
        used.append(address)
        assert script.reply(answer) == frame_command(READ, 1)
        script.reply(encode_data_reply(READ_REPLY_BODY, 1))
        assert script.verdict() is SlcVerdict.DONE
    assert len(used) > 200 and len(set(used)) == len(used)  # every readable byte, each once
    assert script.reply(FRN_REPLY) == frame_command(READ, 1)
    assert script.reply(encode_refused(1)) == frame_command(cmds.read_frn(), 0)  # to be confirmed
    assert script.reply(FRN_REPLY) == frame_command(READ, 1)
    script.reply(encode_refused(1))
    assert script.verdict() is SlcVerdict.REFUSED


def test_a_resync_that_heard_the_controller_goes_on_one_that_heard_nothing_fails_fast() -> None:
    """A resync whose tries run out: if anything came back (a garbled frame, perhaps the
    answer), the controller is there and the line is bad: a read resyncs again.  Silence is a
    dead line: FAILED at once, and the next command resyncs."""
    script = Script(retries=1)
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)
    # ;I (the read resyncs) and the start of a frame whose rest never comes
    _barrier(script.reply(encode_id_mismatch(0x55) + encode_data_reply(READ_REPLY_BODY, 0)[:6]))
    _barrier(script.wait())  # cut short after char_gap: garbled, perhaps the answer: a new try
    assert script.session.counters.crc_errors == 1
    _barrier(script.wait())  # the tries run out, the controller was heard: a new resync
    assert script.session.result is None
    assert script.session.counters.id_resyncs == 3
    # silence from here on: the tries of this resync run out, FAILED
    _barrier(script.wait())  # its second try
    assert script.wait() == b""
    result = script.session.take_result()
    assert result.verdict is SlcVerdict.FAILED
    assert script.session.counters.id_resyncs == 3
    _barrier(script.start(READ))


def _fast_controller() -> Script:
    """A session whose reply timeout adapted to a controller that answers in 10 ms (50 ms)."""
    script = Script(retries=3, min_timeout=0.05)
    script.handshake_read()
    for n in range(2, 10):
        script.read_answered(n, dt=0.01)
    return script


def test_a_silent_resync_fails_after_its_tries_and_the_last_try_waits_the_full_time() -> None:
    """The resync's tries go at the adapted timeout, the last waits the configured one (a reply
    held back on the line must not make a silent-line verdict); silence then: FAILED, no
    further resync (a dead line fails fast)."""
    script = _fast_controller()
    assert script.start(READ) == frame_command(READ, 10)
    addresses = [_barrier(script.reply(encode_id_mismatch(0x55)))[0]]
    waits = []
    while script.session.result is None:
        deadline = script.session.next_deadline()
        assert deadline is not None
        waits.append(round(deadline - script.now, 3))
        frame = script.wait()
        if frame:
            addresses.append(_barrier(frame)[0])
    assert waits == [0.05, 0.05, 0.05, TIMEOUT]
    assert len(set(addresses)) == 4  # each try asks for another address
    result = script.session.take_result()
    assert result.verdict is SlcVerdict.FAILED and "after 4 tries" in result.reason, result
    assert script.session.counters.id_resyncs == 2  # the handshake and this one
    assert script.session.counters.timeouts == 4  # each try's


def test_a_controller_seen_answering_late_lengthens_the_quiet_wait() -> None:
    """The quiet wait before a read FRN resync is ``late_bound`` after our last message, or 1.5 x
    the latest an answer was seen coming after its copy, if that is longer."""
    script = Script()
    script.handshake_read()
    script.read_answered_after_retransmit(2, dt=0.2)  # 0.5 s after the copy
    _barrier(script.start(WRITE))  # two messages: a write resyncs
    sent = script.now
    assert script.reply(encode_refused(0)) == b""  # program mode: quiet, then read FRN
    assert script.session.next_deadline() == pytest.approx(sent + 1.5 * 0.5)
    assert script.wait() == frame_command(cmds.read_frn(), 0)


def test_after_a_quiet_time_a_resync_reads_the_frn_at_once() -> None:
    """A command after the line was quiet for ``late_bound`` needs no barrier: no reply of an
    earlier message can still come, so the resync reads the FRN at once (a trusted numbering)."""
    script = Script()
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)
    while script.session.result is None:  # every reply lost: FAILED (a read after its resyncs)
        script.wait()
    assert script.verdict() is SlcVerdict.FAILED
    script.now += script.session.late_bound
    assert script.start(WRITE) == frame_command(cmds.read_frn(), 0)
    assert script.reply(FRN_REPLY) == frame_command(WRITE, 1)


def test_a_frame_cut_short_just_before_the_reply_timeout_waits_for_the_timeout_first() -> None:
    """The next deadline is the earlier of the reply timeout and the character gap; a partial
    frame while no transaction runs sets none."""
    script = Script()
    script.handshake_read()
    script.session.receive_data(encode_data_reply(READ_REPLY_BODY, 1)[:5], script.now)
    assert script.session.next_deadline() is None
    script.session.receive_data(b"\r", script.now)  # the garbled rest, still idle
    assert script.start(READ) == frame_command(READ, 2)
    sent = script.now
    script.session.receive_data(encode_data_reply(READ_REPLY_BODY, 2)[:5], sent + TIMEOUT - 0.01)
    assert script.session.next_deadline() == pytest.approx(sent + TIMEOUT)


def test_a_write_whose_z_keeps_meeting_an_older_reply_is_resent_under_its_id_a_bounded_number_of_times() -> None:
    """``;Z`` answered with an older reply: the controller never got the copy, or that reply is
    a late one; the copy goes again with the same ID, ``max_resends`` times, then UNKNOWN."""
    script = Script(max_resends=2)
    script.handshake_read()
    copy = frame_command(WRITE, 2)
    assert script.start(WRITE) == copy
    frames = []
    for _ in range(3):
        frames.append(script.wait())  # the reply is lost: ;Z
        frames.append(script.reply(encode_ack(1)))  # the ;Z fetches the previous reply
    assert frames == [encode_retransmit(2), copy] * 2 + [encode_retransmit(2), b""]
    assert script.verdict() is SlcVerdict.UNKNOWN
    assert script.session.counters.resends == 2


def test_a_write_meeting_only_i_with_other_ids_asks_z_a_bounded_number_of_times_then_unknown() -> None:
    """``;I`` with another ID proves nothing: one second copy with the write's ID, then ``;Z``
    (``retries`` times after the first) while every answer is such a ``;I``, then UNKNOWN."""
    script = Script(retries=3)
    script.handshake_read()
    copy = frame_command(WRITE, 2)
    assert script.start(WRITE) == copy
    frames = [script.reply(encode_id_mismatch(0)) for _ in range(6)]
    assert frames == [copy] + [encode_retransmit(2)] * 4 + [b""]
    assert script.verdict() is SlcVerdict.UNKNOWN
    assert script.session.counters.resends == 1


def test_e_to_a_writes_second_copy_is_no_proof_that_it_did_not_run() -> None:
    """A controller that checks the command before its ID refuses the second copy with ``;E``
    (its mode changed) while the first copy ran: UNKNOWN, never REFUSED."""
    script = Script()
    script.handshake_read()
    copy = frame_command(WRITE, 2)
    assert script.start(WRITE) == copy
    assert script.reply(encode_id_mismatch(1)) == copy
    assert script.reply(encode_refused(2)) == b""
    assert script.verdict() is SlcVerdict.UNKNOWN


# --- each occurrence counted; bounds and budgets at their edge; what a resync hears -------------


def test_every_fault_garbled_frame_and_i_counts_once() -> None:
    """The counters are the link's metrics: each ``;T``, each frame that fails its check (whole
    or cut short) and each ``;I`` adds one."""
    script = Script(retries=8)
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)
    assert script.reply(encode_fault(0)) == b""
    assert script.reply(encode_fault(0)) == b""
    bad = bytearray(encode_data_reply(READ_REPLY_BODY, 2))
    bad[5] ^= 1
    assert script.reply(bytes(bad)) == encode_retransmit(2)
    assert script.reply(bytes(bad)) == encode_retransmit(2)
    for _ in range(2):  # cut short: garbled when the character gap passes
        assert script.reply(encode_data_reply(READ_REPLY_BODY, 2)[:6]) == b""
        assert script.wait() == encode_retransmit(2)
    _, answer = _barrier(script.reply(encode_id_mismatch(0x55)))
    assert script.reply(answer) == frame_command(READ, 1)
    _, answer = _barrier(script.reply(encode_id_mismatch(0x55)))
    assert script.reply(answer) == frame_command(READ, 1)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1))
    assert script.verdict() is SlcVerdict.DONE
    counters = script.session.counters
    assert (counters.faults, counters.crc_errors, counters.id_mismatches) == (2, 4, 2)


def test_every_quiet_wait_counts_once() -> None:
    """Two writes, each after a read of two messages, each resync refused (program mode): two
    quiet waits."""
    script = Script()
    script.handshake_read()
    for _ in range(2):
        assert script.start(READ) == frame_command(READ, 2)
        assert script.wait() == encode_retransmit(2)
        script.reply(encode_data_reply(READ_REPLY_BODY, 2))
        assert script.verdict() is SlcVerdict.DONE
        _barrier(script.start(WRITE))
        assert script.reply(encode_refused(0)) == b""
        assert script.wait() == frame_command(cmds.read_frn(), 0)
        assert script.reply(FRN_REPLY) == frame_command(WRITE, 1)
        script.reply(encode_ack(1))
        assert script.verdict() is SlcVerdict.DONE
    assert script.session.counters.quiet_waits == 2


def test_a_writes_second_copy_after_i_counts_as_a_resend_and_toward_its_bound() -> None:
    """The second copy a ``;I`` with another ID sends is one of the write's ``max_resends``
    resends (and counted): with 2, one more copy after it when ``;Z`` meets an older reply,
    then UNKNOWN."""
    script = Script(max_resends=2)
    script.handshake_read()
    copy = frame_command(WRITE, 2)
    assert script.start(WRITE) == copy
    frames = [script.reply(encode_id_mismatch(0))]
    for _ in range(2):
        frames.append(script.wait())  # the copy's reply is lost: ;Z
        frames.append(script.reply(encode_ack(1)))  # the ;Z fetches the previous reply
    assert frames == [copy, encode_retransmit(2), copy, encode_retransmit(2), b""]
    assert script.verdict() is SlcVerdict.UNKNOWN
    assert script.session.counters.resends == 2
    _, answer = _barrier(script.start(WRITE))  # after UNKNOWN: a resync
    assert script.reply(answer) == frame_command(WRITE, 1)
    assert script.reply(encode_id_mismatch(0)) == frame_command(WRITE, 1)
    script.reply(encode_ack(1))
    assert script.verdict() is SlcVerdict.DONE
    assert script.session.counters.resends == 3


def test_a_read_that_keeps_meeting_i_fails_after_max_resyncs() -> None:
    """Each ``;I`` sends a read through another resync, ``max_resyncs`` of them; then FAILED."""
    script = Script(max_resyncs=3)
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)
    barriers = 0
    for _ in range(10):
        frame = script.reply(encode_id_mismatch(0x55))
        if script.session.result is not None:
            break
        _, answer = _barrier(frame)
        barriers += 1
        assert script.reply(answer) == frame_command(READ, 1)
    result = script.session.take_result()
    assert result.verdict is SlcVerdict.FAILED and result.reason.endswith("gave up after 3 resyncs"), result
    assert barriers == 3
    assert script.session.counters.id_resyncs == 4  # the handshake and these


def test_a_wait_that_ends_exactly_at_the_budget_still_fits() -> None:
    """``until``: a write asks again while the next wait ends at or before it."""
    session = SlcSession(timeout=0.25, retries=1)
    session.start(WRITE, 0.0, until=1.0)
    assert session.data_to_send() == frame_command(cmds.read_frn(), 0)  # nothing sent yet: quiet
    session.receive_data(FRN_REPLY, 0.0)
    assert session.data_to_send() == frame_command(WRITE, 1)
    for now in (0.25, 0.5, 0.75):
        session.handle_timeout(now)
        assert session.data_to_send() == encode_retransmit(1)
    assert session.next_deadline() == 1.0
    session.handle_timeout(1.0)
    result = session.take_result()
    assert result.verdict is SlcVerdict.UNKNOWN and result.reason.endswith("after 3 retransmit requests in 1 s"), result


def test_under_a_budget_the_last_resync_try_and_the_last_z_wait_the_full_time() -> None:
    """With a time budget as with the counts, the waits that decide a verdict (a silent
    resync's last try, a write's last ``;Z``) keep the configured reply time; the others go at
    the adapted one."""
    script = _fast_controller()
    assert script.start(READ) == frame_command(READ, 10)
    assert script.wait() == encode_retransmit(10)
    script.reply(encode_data_reply(READ_REPLY_BODY, 10))
    assert script.verdict() is SlcVerdict.DONE  # two messages: a write resyncs
    for verdict in (SlcVerdict.FAILED, SlcVerdict.UNKNOWN):
        began = script.now
        first = _barrier(script.start(WRITE, until=began + 0.52))
        if verdict is SlcVerdict.UNKNOWN:  # the barrier's answer comes, the write's never
            assert script.reply(first[1]) == frame_command(WRITE, 1)
        waits = script.waits_until_verdict()
        assert waits[-1] == TIMEOUT and set(waits[:-1]) == {0.05} and len(waits) > 5, waits
        assert script.verdict() is verdict


def test_before_any_answer_was_seen_the_quiet_wait_is_late_bound() -> None:
    """With no answer's lateness measured, the quiet wait before a read FRN resync is
    ``late_bound`` after the last message."""
    script = Script()
    assert script.start(READ) == frame_command(cmds.read_frn(), 0)
    assert script.reply(FRN_REPLY) == frame_command(READ, 1)  # the FRN answers no copy
    assert script.wait() == encode_retransmit(1)
    _barrier(script.wait())  # silence after ;Z: the read resyncs
    sent = script.now
    assert script.reply(encode_refused(0)) == b""  # program mode: quiet, then read FRN
    assert script.session.next_deadline() == pytest.approx(sent + script.session.late_bound)


def test_a_command_exactly_late_bound_after_the_last_message_reads_the_frn_at_once() -> None:
    """At ``late_bound`` after the last message no reply to it can come any more: the line is
    quiet, so the resync reads the FRN at once, with no barrier and no wait."""
    script = Script(late_bound=0.5)
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)
    assert script.wait() == encode_retransmit(2)
    last = script.now
    script.reply(encode_data_reply(READ_REPLY_BODY, 2))
    assert script.verdict() is SlcVerdict.DONE  # two messages: a write resyncs
    script.now = last + 0.5
    assert script.start(WRITE) == frame_command(cmds.read_frn(), 0)
    assert script.session.counters.quiet_waits == 0


def _resync_with_a_barrier(script: Script) -> int:
    """A read meets ``;I`` and resyncs with a barrier read: its address."""
    assert script.start(READ) == frame_command(READ, 2)
    address, answer = _barrier(script.reply(encode_id_mismatch(0x55), dt=0.0))
    assert script.reply(answer) == frame_command(READ, 1)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1))
    assert script.verdict() is SlcVerdict.DONE
    return address


def test_a_barrier_address_is_free_again_exactly_the_quiet_time_after_it_was_asked_for() -> None:
    """An address asked for ``late_bound`` ago can have no answer on the way any more: a barrier
    read may ask for it again (the resync needs no read FRN fallback)."""
    script = Script(late_bound=64.0)
    script.handshake_read()
    script.now = 1.0
    first = _resync_with_a_barrier(script)
    used = {first}
    while len(used) < 239:  # every other barrier address, within the quiet time
        used.add(_resync_with_a_barrier(script))
    assert script.now < 64.0
    script.now = 65.0
    assert _resync_with_a_barrier(script) == first


def test_a_read_whose_second_resync_try_found_no_barrier_free_leaves_a_numbering_a_write_does_not_trust() -> None:
    """A barrier read lost, and no other address free: the read's resync goes on with read FRN
    at once.  An earlier reply may follow that answer, so the next write does not go in this
    numbering: it resyncs (here: waits for quiet, no barrier being free)."""
    script = Script(late_bound=100.0)
    script.handshake_read()
    for _ in range(238):  # every barrier address but one
        _resync_with_a_barrier(script)
    assert script.start(READ) == frame_command(READ, 2)
    _barrier(script.reply(encode_id_mismatch(0x55)))  # the last free address
    assert script.wait() == frame_command(cmds.read_frn(), 0)  # lost: no address left
    assert script.reply(FRN_REPLY) == frame_command(READ, 1)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1))
    assert script.verdict() is SlcVerdict.DONE
    assert script.start(WRITE) == b""
    assert script.session.state is SessionState.QUIET


def test_a_reads_answer_held_back_until_its_resync_is_taken_an_older_reply_is_not() -> None:
    """A read whose ``;Z`` met silence resyncs; its own answer, held back on the line, may still
    come: a value the controller held, taken at once (the next command resyncs: the ID 00 read
    is still on its way).  A reply with another ID answers an earlier message: ignored."""
    session = _started()
    assert session.data_to_send() == frame_command(READ, 5)
    session.handle_timeout(TIMEOUT)
    assert session.data_to_send() == encode_retransmit(5)
    session.handle_timeout(2 * TIMEOUT)
    _barrier(session.data_to_send())
    session.receive_data(encode_data_reply("000200400001", 4), 0.61)  # an older read's
    assert session.result is None and session.data_to_send() == b""
    session.receive_data(encode_data_reply("000200400002", 5), 0.62)
    result = session.take_result()
    assert result.verdict is SlcVerdict.DONE
    assert isinstance(result.answer, DataReply) and result.answer.body_hex == "000200400002"
    session.start(READ, 0.63)
    _barrier(session.data_to_send())


def test_a_reply_with_our_id_that_does_not_answer_the_command_is_not_its_answer() -> None:
    """A reply with the read's ID but another address's echo (or ``;R``) answers an earlier
    message with the same ID: the read waits for its own."""
    session = _started()
    session.data_to_send()
    session.receive_data(encode_data_reply("000200420001", 5), 0.01)
    session.receive_data(encode_ack(5), 0.02)
    assert session.result is None and session.data_to_send() == b""
    session.receive_data(encode_data_reply("000200400002", 5), 0.03)
    result = session.take_result()
    assert isinstance(result.answer, DataReply) and result.answer.body_hex == "000200400002"


def test_a_resync_that_heard_only_stale_replies_goes_on_empty_reads_are_not_heard() -> None:
    """A whole reply of an earlier message during a resync shows the controller is there: when
    the tries run out, a read resyncs again.  An empty read (no bytes) is silence: FAILED."""
    script = Script(retries=1)
    script.handshake_read()
    assert script.start(READ) == frame_command(READ, 2)
    _barrier(script.reply(encode_id_mismatch(0x55)))
    assert script.reply(encode_ack(1)) == b""  # an earlier message's reply
    _barrier(script.wait())
    _barrier(script.wait())  # the tries run out, the controller was heard: a new resync
    assert script.session.result is None
    assert script.reply(b"") == b""
    _barrier(script.wait())
    assert script.reply(b"") == b""
    assert script.wait() == b""
    assert script.verdict() is SlcVerdict.FAILED


# --- the defaults and the windows of the adaptive times ---------------------------------------


def _default_script() -> Script:
    """A session built with the documented defaults (no timeouts given)."""
    script = Script()
    script.session = SlcSession()
    return script


def test_the_defaults_wait_0_3_s_for_a_reply_adapt_no_lower_than_50_ms_and_wait_1_5_x_for_quiet() -> None:
    """"Normally the SLC will respond within 0.3 seconds": a session built with the defaults
    waits that long for a reply; a controller answering in 1/64 s brings the reply timeout down
    to 50 ms, no lower; the quiet wait before a read FRN resync is 1.5 x 0.3 s."""
    script = _default_script()
    assert script.start(READ) == frame_command(cmds.read_frn(), 0)
    assert script.session.next_deadline() == pytest.approx(script.now + 0.3)
    assert script.reply(FRN_REPLY, dt=1 / 64) == frame_command(READ, 1)
    assert script.session.next_deadline() == pytest.approx(script.now + 0.3)
    script.reply(encode_data_reply(READ_REPLY_BODY, 1), dt=1 / 64)
    assert script.verdict() is SlcVerdict.DONE
    for n in range(2, 8):
        script.read_answered(n, dt=1 / 64)
    script.start(READ)  # 8 reply times of 1/64 s: 2 x 1/64 s, raised to 50 ms
    assert script.session.next_deadline() == pytest.approx(script.now + 0.05)
    assert script.wait() == encode_retransmit(8)
    script.reply(encode_data_reply(READ_REPLY_BODY, 8), dt=1 / 64)  # two messages: a write resyncs
    assert script.verdict() is SlcVerdict.DONE
    _barrier(script.start(WRITE))
    sent = script.now
    assert script.reply(encode_refused(0)) == b""  # program mode: quiet, then read FRN
    assert script.session.next_deadline() == pytest.approx(sent + 1.5 * 0.3)


@pytest.mark.parametrize("fast", [30, 31])
def test_the_reply_timeout_follows_the_slowest_of_the_last_32_reply_times(fast: int) -> None:
    """A slow first reply (1/8 s: a 1/4 s timeout) counts while it is one of the last 32 reply
    times; once 32 newer fast ones (1/64 s) came, the timeout is 50 ms."""
    script = _default_script()
    assert script.start(READ) == frame_command(cmds.read_frn(), 0)
    assert script.reply(FRN_REPLY, dt=1 / 8) == frame_command(READ, 1)  # the slow one
    script.reply(encode_data_reply(READ_REPLY_BODY, 1), dt=1 / 64)
    assert script.verdict() is SlcVerdict.DONE
    for n in range(2, 2 + fast):
        script.read_answered(n, dt=1 / 64)
    script.start(READ)  # 1 + fast reply times of 1/64 s after the slow one
    assert script.session.next_deadline() == script.now + (1 / 4 if 1 + fast < 32 else 0.05)


@pytest.mark.parametrize("fast", [30, 31])
def test_the_quiet_wait_follows_the_latest_of_the_last_32_answers(fast: int) -> None:
    """An answer seen 0.55 s after its copy makes the quiet wait 1.5 x 0.55 s while it is one of
    the last 32 answers' lateness; once 32 newer answers came (all early), it is the 1.5 x 0.3 s
    of the defaults again."""
    script = _default_script()
    script.handshake_read()
    script.read_answered_after_retransmit(2, dt=0.25)  # 0.55 s after the copy
    for n in range(3, 3 + fast):
        script.read_answered(n, dt=1 / 64)
    script.read_answered_after_retransmit(3 + fast, dt=1 / 64)  # two messages: a write resyncs
    _barrier(script.start(WRITE))  # 1 + fast answers after the late one
    sent = script.now
    assert script.reply(encode_refused(0)) == b""
    quiet = 1.5 * (0.55 if 1 + fast < 32 else 0.3)
    assert script.session.next_deadline() == pytest.approx(sent + quiet)
