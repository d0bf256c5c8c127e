"""The SLC 100/150 transaction core: the rules that keep a write from running twice or a reply lying.

Each test names a rule of :mod:`gateway.protocols.slc_ascii.transaction` and plays one line
history through the core's public surface: frames out (``data_to_send``), bytes in
(``receive_data``), a fake clock (``handle_timeout`` at ``next_deadline``), the verdict.  The
controller is the simulator (:class:`SlcAsciiSimulator`): every reply is the one it gives to the
frame the core sent; the test only decides each reply's fate on the line (delivered now, later,
twice, or lost) and when the controller power-cycles.  Each of these rules was once broken by a
one-line change with the rest of the suite passing.
"""

from __future__ import annotations

import pytest

from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.framing import NEED_DATA, CommandDecoder, CommandFrame
from gateway.protocols.slc_ascii.transaction import SlcSession, SlcVerdict

TIMEOUT = 0.3
READ = cmds.read_bytes(0x40, 2)


class Wire:
    """The core and the simulator, with the line's fate of every frame decided by the test."""

    def __init__(self, **variants: str) -> None:
        self.sim = SlcAsciiSimulator(ladder=False, variants=variants)
        self.session = SlcSession(timeout=TIMEOUT, retries=3)
        self.now = 0.0
        #: every frame the core sent: (time, ID, the command's code, or None for ;Z)
        self.sent: list[tuple[float, int, int | None]] = []
        #: the parameters of each frame in ``sent`` (empty for ;Z)
        self.params: list[bytes] = []
        #: every reply delivered to the core
        self.delivered: list[bytes] = []
        self._decoder = CommandDecoder()

    def out(self) -> list[bytes]:
        """The frames the core sends now (recorded)."""
        data = self.session.data_to_send()
        self._decoder.receive_data(data)
        while (event := self._decoder.next_event()) is not NEED_DATA:
            code = event.code if isinstance(event, CommandFrame) else None
            self.sent.append((self.now, event.msg_id, code))  # type: ignore[union-attr]
            self.params.append(event.params if isinstance(event, CommandFrame) else b"")
        return [f + b"\r" for f in data.split(b"\r") if f]

    def controller(self, frames: list[bytes]) -> list[bytes]:
        """The frames reach the controller: its replies, in order."""
        return [out.data for frame in frames for out in self.sim.receive(frame, self.now)]

    def deliver(self, replies: list[bytes], dt: float = 0.005) -> None:
        for reply in replies:
            self.now += dt
            self.delivered.append(reply)
            self.session.receive_data(reply, self.now)

    def wait(self) -> None:
        """Nothing arrives until the core's next deadline."""
        deadline = self.session.next_deadline()
        assert deadline is not None
        self.now = max(self.now, deadline)
        self.session.handle_timeout(self.now)

    def exchange(self) -> None:
        """A perfect line until the transaction ends (time passes only while the core waits)."""
        while self.session.result is None:
            frames = self.out()
            if frames:
                self.deliver(self.controller(frames))
            else:
                self.wait()
        self.out()

    def run(self, command: cmds.Command) -> SlcVerdict:
        self.session.start(command, self.now)
        self.exchange()
        return self.session.take_result().verdict

    def applied(self, value: int) -> int:
        return sum(1 for kind, _, v in self.sim.applied_writes if kind == "word" and v == value)


def in_step(**variants: str) -> Wire:
    """A session in step with its controller after two reads on a perfect line."""
    wire = Wire(**variants)
    assert wire.run(READ) is SlcVerdict.DONE
    assert wire.run(READ) is SlcVerdict.DONE
    return wire


def began_with_a_barrier(wire: Wire, before: int) -> bool:
    """Whether the numbering in force at ``wire.sent[before]`` began with a sound barrier: the
    last run of ID 00 frames before it began ``late_bound`` after the frame before it (quiet), or
    each of them is a read of an address no ID 00 frame asked for in the ``late_bound`` before
    it (its answer echoes the address: no earlier message's answer looks like it)."""
    last = max(i for i in range(before) if wire.sent[i][1] == 0 and wire.sent[i][2] is not None)
    first = last
    while first > 0 and wire.sent[first - 1][1] == 0 and wire.sent[first - 1][2] is not None:
        first -= 1
    if first == 0 or wire.sent[first][0] - wire.sent[first - 1][0] >= wire.session.late_bound - 1e-9:
        return True
    bound = wire.session.late_bound

    def unique(i: int) -> bool:
        t, _, code = wire.sent[i]
        return code == cmds.CommandCode.READ and not any(
            wire.sent[j][1] == 0 and wire.params[j] == wire.params[i] and t - wire.sent[j][0] < bound
            for j in range(i))

    return all(unique(i) for i in range(first, last + 1))


def test_a_write_never_goes_out_in_a_numbering_begun_without_a_barrier() -> None:
    """A read that meets ``;I`` resyncs at once.  A write may go out in that numbering only if the
    resync was a sound barrier (a read whose answer no earlier message's answer looks like, or
    after quiet): its ``;I`` proof rests on no reply of an earlier message following it."""
    wire = in_step()
    wire.sim.power_cycle()  # the next read meets ;I00, and resyncs at once
    assert wire.run(READ) is SlcVerdict.DONE
    ids = [msg_id for _, msg_id, code in wire.sent[-3:] if code is not None]
    assert ids == [3, 0, 1], f"expected the read, an immediate resync and the read again, not {ids}"
    assert wire.run(cmds.write_word(0x40, 77)) is SlcVerdict.DONE
    write = next(i for i, (_, _, code) in enumerate(wire.sent) if code == cmds.CommandCode.WRITE)
    assert began_with_a_barrier(wire, write), f"write sent in an untrusted numbering: {wire.sent}"
    assert wire.applied(77) == 1


@pytest.mark.parametrize("kind", ["write", "read"])
def test_after_an_unknown_or_failed_outcome_the_next_command_begins_with_a_resync(kind: str) -> None:
    """When a transaction ends without an answer the controller's ID state is unknown (it may
    have taken our ID, or power-cycled): the next command begins with an ID 00 resync."""
    wire = in_step()
    command = cmds.write_word(0x42, 55) if kind == "write" else READ
    wire.session.start(command, wire.now)
    while wire.session.result is None:  # the controller hears everything, every reply is lost
        frames = wire.out()
        if frames:
            wire.controller(frames)
        else:
            wire.wait()
    assert wire.session.take_result().verdict is (SlcVerdict.UNKNOWN if kind == "write" else SlcVerdict.FAILED)
    before = len(wire.sent)
    assert wire.run(READ) is SlcVerdict.DONE
    first_id = wire.sent[before][1]
    assert first_id == 0, f"the command after an unknown outcome went with ID {first_id:02X}, not a resync"


def test_after_a_transaction_of_several_messages_a_write_goes_out_after_a_barrier() -> None:
    """A transaction that sent more than one message may still have replies on the way when it
    ends, and they would meet the next write's copies (a stray ``;I`` proves nothing, but costs
    the write a copy or a ``;Z``).  So the next write's first copy goes out only after a barrier
    (a resync whose answer no earlier reply can follow) or quiet (``late_bound``)."""
    wire = in_step()
    wire.session.start(READ, wire.now)
    wire.controller(wire.out())  # the reply is lost
    wire.wait()  # ;Z
    wire.deliver(wire.controller(wire.out()))  # the ;Z fetches the answer: DONE, after two messages
    assert wire.session.take_result().verdict is SlcVerdict.DONE
    last = len(wire.sent) - 1
    assert wire.run(cmds.write_word(0x44, 88)) is SlcVerdict.DONE
    write = next(i for i in range(last + 1, len(wire.sent)) if wire.sent[i][2] == cmds.CommandCode.WRITE)
    quiet = wire.sent[write][0] - wire.sent[last][0] >= wire.session.late_bound - 1e-9
    resynced = any(wire.sent[i][1] == 0 for i in range(last + 1, write))
    assert quiet or (resynced and began_with_a_barrier(wire, write)), (
        f"the write's first copy went {wire.sent[write][0] - wire.sent[last][0]:.3f} s after the last message, "
        f"with no barrier before it: {wire.sent[last:]}")


def test_stray_i_from_a_transaction_of_several_messages_never_makes_the_next_write_run_twice() -> None:
    """The write before ours needed a second copy: its first copy ran but its ack was held back on
    the line, the ``;Z`` met an older reply (which the line repeated late) and the core resent the
    command with the same ID; the controller refused that copy with ``;I`` and the ID, and the line
    repeats that frame too.  Both ``;I`` arrive after our write's first copy went out and ran.
    Taken as answers to our write's copies they look like proof that it did not run, and it would
    be sent again under a new ID: applied twice."""
    wire = in_step()
    session = wire.session
    older = wire.delivered[-1]  # the reply to the read before
    session.start(cmds.write_word(0x44, 11), wire.now)
    first = wire.out()
    late_ack = wire.controller(first)  # the write runs; its ack is held back
    wire.wait()  # the reply timeout: ;Z
    z_answer = wire.controller(wire.out())  # the controller repeats the ack, also held back
    wire.deliver([older])  # the older reply, repeated by the line: the core resends (same ID)
    second = wire.out()
    assert second == first, "a resend keeps the ID"
    stray = wire.controller(second)  # ;I with this write's ID: it already ran
    assert len(stray) == 1 and stray[0].startswith(b";I")
    wire.deliver(late_ack)
    assert session.take_result().verdict is SlcVerdict.DONE  # three messages: copy, ;Z, copy
    session.start(cmds.write_word(0x44, 12), wire.now)
    ours = wire.controller(wire.out())  # our first copy, if the core sends it now, runs
    wire.deliver(z_answer + stray + stray + ours)  # what the line held back, then our replies
    wire.exchange()
    assert wire.applied(11) == 1
    assert wire.applied(12) == 1, f"write applied {wire.applied(12)} times"
    assert session.take_result().verdict is SlcVerdict.DONE


@pytest.mark.parametrize("kind", ["read", "write"])
def test_e_after_a_z_is_never_taken_for_a_refusal_even_after_a_resend(kind: str) -> None:
    """``z_after_power_up=error``: a controller power-cycled since its last reply answers ``;Z``
    with ``;E`` and the ``;Z``'s ID (ours).  That ``;E`` says nothing of our command, also when
    the core has resent the command since the ``;Z`` (an older reply, repeated late by the line,
    came first and looked like the ``;Z``'s answer): a read asks again, and a write whose first
    copy may have run ends UNKNOWN.  REFUSED would tell SCADA the controller refused a legal read,
    or a write it ran."""
    wire = in_step(z_after_power_up="error")
    session = wire.session
    older = wire.delivered[-1]
    command = cmds.write_word(0x40, 66) if kind == "write" else READ
    session.start(command, wire.now)
    wire.controller(wire.out())  # the command runs (a write is applied); its reply is lost
    wire.sim.power_cycle()  # and the controller power-cycles: no last reply to repeat
    wire.wait()  # the reply timeout: ;Z
    e_to_z = wire.controller(wire.out())
    assert len(e_to_z) == 1 and e_to_z[0].startswith(b";E"), e_to_z
    wire.deliver([older])  # before the ;E: the older reply, repeated by the line: a resend
    resent = wire.out()
    assert len(resent) == 1 and resent[0].startswith(b"#"), resent
    wire.deliver(e_to_z)
    if kind == "write":
        result = session.take_result()
        assert result.verdict is SlcVerdict.UNKNOWN, f"{result}: the write ran"
        assert wire.applied(66) == 1
    else:
        assert session.result is None or session.result.verdict is not SlcVerdict.REFUSED, session.result
        wire.deliver(wire.controller(resent))  # ;I00: the power-cycled controller expects 00
        wire.exchange()
        assert session.take_result().verdict is SlcVerdict.DONE


def test_a_line_that_repeats_frames_both_ways_never_makes_a_write_run_twice() -> None:
    """The line repeats our previous write's frame: the controller runs it and refuses the copy with
    ``;I`` and its ID, and the line repeats that ``;I`` too.  Both arrive after our write's first
    copy went out and ran.  The first is not proof (``test_stray_i_of_a_repeated_previous_message_
    never_makes_a_write_run_twice``): the core sends a second copy with our ID.  The repeated ``;I``
    is no answer to that copy either; taken for one, it looks like proof that our write did not
    run, and the write is sent again under a new ID: applied twice."""
    wire = in_step()
    session = wire.session
    session.start(cmds.write_word(0x42, 21), wire.now)
    replies = wire.controller(wire.out() * 2)  # the line repeats the frame: ;R and ;I
    assert [r[:2] for r in replies] == [b";R", b";I"], replies
    ack, stray = replies
    wire.deliver([ack])
    assert session.take_result().verdict is SlcVerdict.DONE
    session.start(cmds.write_word(0x42, 22), wire.now)
    ours = wire.controller(wire.out())  # our write runs
    wire.deliver([stray, stray, *ours])  # the ;I, the line's repeat of it, then our ack
    wire.exchange()
    assert wire.applied(21) == 1
    assert wire.applied(22) == 1, f"write applied {wire.applied(22)} times"


def _write_meets_the_stray_i_of_a_repeated_read(wire: Wire, value: int) -> tuple[list[bytes], bytes]:
    """The line repeats a read: the controller answers it and refuses the copy with ``;I`` and the
    read's ID.  A write follows; its first copy runs and its ``;R`` is lost, and the read's stray
    ``;I`` arrives.  Returns the write's frames (the core sends them again at once: a second copy
    with the same ID) and the stray ``;I``."""
    session = wire.session
    session.start(READ, wire.now)
    answer, stray = wire.controller(wire.out() * 2)
    assert stray.startswith(b";I"), stray
    wire.deliver([answer])
    assert session.take_result().verdict is SlcVerdict.DONE
    session.start(cmds.write_word(0x40, value), wire.now)
    first = wire.out()
    assert len(first) == 1 and first[0].startswith(b"#0503"), first
    assert [r[:2] for r in wire.controller(first)] == [b";R"]  # the write runs; its ack is lost
    assert wire.applied(value) == 1
    wire.deliver([stray])
    second = wire.out()
    assert second == first, "a copy with another ID than the first"
    return second, stray


@pytest.mark.parametrize("before_second_copy", ["lost", "power cycle"])
def test_a_repeated_stray_i_is_no_proof_that_a_write_did_not_run(before_second_copy: str) -> None:
    """The hypothesis state machine's counterexample, step by step: every reply is at risk and the
    line repeats frames both ways.  The write's first copy runs, its ``;R`` is lost; the stray
    ``;I`` of a repeated read makes the core send a second copy with the write's ID, which the line
    loses (after a power cycle, or alone); then the line's repeat of the stray ``;I`` comes.  No
    answer with the write's ID follows (the ``;R`` is gone), so waiting for one proves nothing: a
    ``;I`` with another ID can always be a stale or repeated reply.  Taken for proof, the write
    goes again under a new ID and runs twice."""
    wire = in_step()
    _, stray = _write_meets_the_stray_i_of_a_repeated_read(wire, 31)
    if before_second_copy == "power cycle":
        wire.sim.power_cycle()
    wire.deliver([stray])  # the line's repeat of the stray ;I
    wire.exchange()  # a perfect line from here on
    assert wire.applied(31) == 1, f"write applied {wire.applied(31)} times"
    result = wire.session.take_result()
    if before_second_copy == "power cycle":
        # the controller no longer has the ack to repeat: nothing can prove either way
        assert result.verdict is SlcVerdict.UNKNOWN, result
    else:
        assert result.verdict is SlcVerdict.DONE, result  # ;Z fetches the ack
    writes = [i for i, (_, _, code) in enumerate(wire.sent) if code == cmds.CommandCode.WRITE]
    assert len({wire.sent[i][1] for i in writes}) == 1, f"the write went under two IDs: {wire.sent}"


def test_a_write_that_ran_is_never_answered_failed() -> None:
    """The second counterexample: as above, and the second copy reaches the power-cycled controller
    (refused, ``;I00``, lost); from the repeat of the stray ``;I`` on, every reply is lost.  The
    write ran: FAILED (or REFUSED) would tell SCADA it did not.  UNKNOWN is the only true verdict."""
    wire = in_step()
    second, stray = _write_meets_the_stray_i_of_a_repeated_read(wire, 32)
    wire.sim.power_cycle()
    assert [r[:4] for r in wire.controller(second)] == [b";I00"]  # lost
    wire.deliver([stray])
    session = wire.session
    while session.result is None:  # the controller hears everything, every reply is lost
        frames = wire.out()
        if frames:
            wire.controller(frames)
        else:
            wire.wait()
    result = session.take_result()
    assert wire.applied(32) == 1
    assert result.verdict is SlcVerdict.UNKNOWN, result


@pytest.mark.parametrize("power_up_id", ["zero", "retained"])
def test_i_to_the_lines_repeat_of_a_write_that_ran_is_no_proof(power_up_id: str) -> None:
    """The line repeats the write's only copy, and the controller power-cycles between the two: the
    first runs (its ``;R`` is lost), the repeat is refused with ``;I00`` (zero reading) or ``;I``
    with the write's own ID (retained).  One copy sent, one ``;I`` with another ID back: the same
    bytes as a controller power-cycled before the write, which never ran.  Not proof either."""
    wire = in_step(power_up_id=power_up_id)
    session = wire.session
    session.start(cmds.write_word(0x42, 41), wire.now)
    frames = wire.out()
    assert [r[:2] for r in wire.controller(frames)] == [b";R"]  # runs; the ack is lost
    wire.sim.power_cycle()
    wire.deliver(wire.controller(frames))  # the line's repeat of the copy: refused
    wire.exchange()
    assert wire.applied(41) == 1, f"write applied {wire.applied(41)} times"
    assert session.take_result().verdict is SlcVerdict.UNKNOWN
