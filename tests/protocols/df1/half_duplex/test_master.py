"""DF1 half-duplex master core: byte scripts with a fake clock, then fault scripts against slaves.

The reading of the manuals (1770-6.5.16 ch. 3/5, 1775-KA ch. 11, 1770-KF2 ch. 4) is in
docs/develop/df1-half-duplex-notes.md; section numbers below refer to it.
"""

from __future__ import annotations

import itertools
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.kinds.df1.sim.df1_half_duplex_slave import VARIANTS, HalfDuplexSlave, SlaveVariant
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    EOT_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    Checksum,
    encode_frame,
    encode_master_message,
    encode_poll,
)
from gateway.protocols.df1.half_duplex.events import (
    FailReason,
    LineConfig,
    MasterEvent,
    ReplyReceived,
    RequestFailed,
    SlaveInitiated,
    StationConfig,
    StationDemoted,
    StationRestored,
    StrayReply,
)
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster, LineState
from gateway.protocols.df1.half_duplex.transmitter import HalfDuplexTransmitter
from gateway.protocols.df1.pccc import PcccHeader, reply_matches
from gateway.sim.variants import variant_matrix

GATEWAY = 0x00  # the master's own DF1 address (SRC of its commands)


def command(station: int, tns: int, payload: bytes = b"\x01\x02") -> bytes:
    """A PCCC command packet: DST SRC CMD STS TNS(lo hi) data."""
    return bytes((station, GATEWAY, 0x0F, 0x00)) + tns.to_bytes(2, "little") + payload


def reply_to(cmd: bytes, data: bytes) -> bytes:
    return bytes((cmd[1], cmd[0], cmd[2] | 0x40, 0x00)) + cmd[4:6] + data


def events(master: HalfDuplexMaster) -> list[MasterEvent]:
    found: list[MasterEvent] = []
    while (event := master.next_event()) is not NEED_DATA:
        assert not isinstance(event, type(NEED_DATA))
        found.append(event)
    return found


def make(
    *stations: int, checksum: Checksum = Checksum.BCC, line: Mapping[str, Any] | None = None, **station_kw: Any
) -> HalfDuplexMaster:
    config = replace(LineConfig(checksum), **(line or {}))
    station_kw.setdefault("reply_wait", 0.0)  # the scripts poll for a reply at once; tests of the wait give it
    master = HalfDuplexMaster(config, [replace(StationConfig(s), **station_kw) for s in stations])
    master.start(0.0)
    return master


def feed(master: HalfDuplexMaster, data: bytes, now: float, mode: str) -> None:
    """Feed ``data`` whole or byte by byte."""
    if mode == "whole":
        master.receive_data(data, now)
    else:
        for byte in data:
            master.receive_data(bytes((byte,)), now)


MODES = ["whole", "bytes"]


# ------------------------------------------------------------------------------- byte scripts


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("checksum", list(Checksum))
def test_command_ack_poll_reply_ack_poll_eot(mode: str, checksum: Checksum) -> None:
    """§3: master message, DLE ACK, poll, reply, DLE ACK, poll again until DLE EOT."""
    master = make(5, checksum=checksum, poll_interval=10.0)
    assert master.data_to_send() == encode_poll(5)  # the first background poll
    feed(master, EOT_SYMBOL, 0.0, mode)
    cmd = command(5, 0x1234)
    request = master.submit(5, cmd, 0.1)
    assert master.data_to_send() == encode_master_message(5, cmd, checksum)
    feed(master, ACK_SYMBOL, 0.1, mode)
    assert master.data_to_send() == encode_poll(5)
    answer = reply_to(cmd, b"\xaa\x10\x55")
    feed(master, encode_frame(answer, checksum), 0.2, mode)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(5)  # ACK, then poll the same station again
    assert events(master) == [ReplyReceived(request, 5, answer)]
    feed(master, EOT_SYMBOL + b"\x00\xff\x10", 0.3, mode)  # trailing garbage after the EOT is ignored
    assert master.data_to_send() == b""
    assert master.state is LineState.IDLE
    assert master.next_deadline() == pytest.approx(10.2)  # poll_interval after the last poll
    counters = master.counters(5)
    assert (counters.polls, counters.eots, counters.messages_sent, counters.messages_received) == (3, 2, 1, 1)


@pytest.mark.parametrize("mode", MODES)
def test_unacknowledged_message_is_resent_identically_then_fails(mode: str) -> None:
    """KF2 Fig. 4.18: no ACK -> the same frame again (same TNS); after the retries, NO_ACK."""
    master = make(1, line={"ack_timeout": 0.5, "message_resends": 2}, poll_interval=100.0, demote_after=10)
    master.data_to_send()
    feed(master, EOT_SYMBOL, 0.0, mode)
    cmd = command(1, 7)
    request = master.submit(1, cmd, 0.0)
    frame = encode_master_message(1, cmd, Checksum.BCC)
    assert master.data_to_send() == frame
    assert master.next_deadline() == pytest.approx(0.5)
    master.handle_timeout(0.5)
    assert master.data_to_send() == frame
    feed(master, NAK_SYMBOL, 0.6, mode)  # a NAKing slave (§5 row 1): resend at once
    assert master.data_to_send() == frame
    master.handle_timeout(1.1)
    assert events(master) == [RequestFailed(request, 1, FailReason.NO_ACK, may_have_executed=True)]
    assert master.counters(1).resends == 2


def test_dead_station_is_demoted_fails_fast_and_comes_back_on_slow_poll() -> None:
    """KA p. 11-9: remove a silent slave from the active list, poll it occasionally (§5 rows 10, 11)."""
    master = make(2, poll_timeout=0.2, demote_after=3, poll_interval=1.0, slow_poll_interval=30.0)
    now = 0.0
    for _ in range(3):
        assert master.data_to_send() == encode_poll(2)
        now = master.next_deadline() or 0.0
        master.handle_timeout(now)
    assert events(master) == [StationDemoted(2)]
    assert not master.is_active(2)
    request = master.submit(2, command(2, 1), now)
    assert events(master) == [RequestFailed(request, 2, FailReason.STATION_DEMOTED, may_have_executed=False)]
    assert master.data_to_send() == b""
    assert master.next_deadline() == pytest.approx(now + 30.0)
    master.handle_timeout(now + 30.0)
    assert master.data_to_send() == encode_poll(2)
    master.receive_data(EOT_SYMBOL, now + 30.1)
    assert events(master) == [StationRestored(2)]
    assert master.counters(2).demotions == 1


def test_demoted_station_is_slow_polled_even_while_the_others_always_have_commands() -> None:
    """A demoted station's slow poll takes its turn in the round robin: queued commands of busy
    stations (a gateway polling continuously) must not starve it, or it is never restored."""
    master = make(1, 2, line={"ack_timeout": 0.1}, poll_timeout=0.1, demote_after=3, poll_interval=100.0,
                  slow_poll_interval=2.0)
    slave = HalfDuplexSlave(1, Checksum.BCC, lambda cmd: reply_to(cmd, b"\x00\x00"))  # station 2 is absent
    tns = itertools.count(1)
    master.submit(1, command(1, next(tns)), 0.0)
    master.submit(2, command(2, next(tns)), 0.0)  # the absent station's unit reads too, until demoted
    now, replies, polls_of_2 = 0.0, 0, []
    while now < 12.0:
        for event in events(master):
            assert not isinstance(event, RequestFailed) or event.station == 2, event
            if isinstance(event, ReplyReceived):
                replies += 1
                master.submit(1, command(1, next(tns)), now)  # station 1 always has its next command
            if isinstance(event, RequestFailed) and master.is_active(2):
                master.submit(2, command(2, next(tns)), now)
        sent = master.data_to_send()
        polls_of_2 += [now] * sent.count(encode_poll(2))
        slave.receive_data(sent)
        answer = slave.data_to_send()
        if answer:
            now += 0.01
            master.receive_data(answer, now)
            continue
        deadline = master.next_deadline()
        assert deadline is not None
        now = max(now, deadline)
        master.handle_timeout(now)
    assert not master.is_active(2) and master.counters(2).demotions == 1 and replies > 100
    slow = [t for t in polls_of_2 if t > 2.0]  # demoted after 3 unacknowledged commands (1.2 s)
    assert len(slow) >= 4, polls_of_2  # every 2 s after the demotion, despite station 1's traffic
    assert all(b - a < 2.5 for a, b in itertools.pairwise(slow)), slow


def test_bad_slave_frame_is_not_acknowledged_and_the_station_is_polled_again() -> None:
    """KA Fig. 11.8: a block check error -> no ACK (never NAK, §1), poll again, same message."""
    master = make(3, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(3)
    initiated = bytes((GATEWAY, 3, 0x0F, 0x00, 0x01, 0x00, 0xAB))
    frame = bytearray(encode_frame(initiated, Checksum.BCC))
    frame[-1] ^= 0x55
    master.receive_data(bytes(frame), 0.01)
    assert master.data_to_send() == encode_poll(3)
    assert events(master) == []
    master.receive_data(encode_frame(initiated, Checksum.BCC), 0.02)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(3)
    assert events(master) == [SlaveInitiated(3, initiated)]


def test_resent_message_after_lost_ack_is_acknowledged_and_discarded() -> None:
    """KA Fig. 11.9 / p. 11-17: same first six bytes before an EOT = a resend: ACK, discard."""
    master = make(4, poll_interval=100.0)
    master.data_to_send()
    initiated = bytes((GATEWAY, 4, 0x0F, 0x00, 0x09, 0x00, 0x01))
    master.receive_data(encode_frame(initiated, Checksum.BCC), 0.0)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(4)
    master.receive_data(encode_frame(initiated, Checksum.BCC), 0.1)  # our ACK was lost
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(4)
    assert events(master) == [SlaveInitiated(4, initiated)]
    assert master.counters(4).duplicates == 1
    master.receive_data(EOT_SYMBOL, 0.2)
    # After an EOT the same head is a new message (the slave reused its TNS, e.g. after a restart).
    later = master.next_deadline()
    assert later is not None
    assert later == pytest.approx(100.1)
    master.handle_timeout(later)
    assert master.data_to_send() == encode_poll(4)
    master.receive_data(encode_frame(initiated, Checksum.BCC), later)
    assert events(master) == [SlaveInitiated(4, initiated)]


def test_reply_polls_stop_after_max_polls() -> None:
    master = make(6, max_polls=3, poll_interval=100.0, reply_timeout=100.0)
    master.data_to_send()
    master.receive_data(EOT_SYMBOL, 0.0)
    request = master.submit(6, command(6, 2), 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)
    for _ in range(3):
        assert master.data_to_send() == encode_poll(6)
        master.receive_data(EOT_SYMBOL, 0.0)
    assert events(master) == [RequestFailed(request, 6, FailReason.NO_REPLY, may_have_executed=True)]


def test_reply_timeout_and_late_reply_is_stray() -> None:
    master = make(6, reply_timeout=1.0, reply_wait=0.4, poll_interval=100.0)
    master.data_to_send()
    master.receive_data(EOT_SYMBOL, 0.0)
    cmd = command(6, 3)
    request = master.submit(6, cmd, 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == b""  # Reply Message Wait Time (RM p. 13-67)
    assert master.next_deadline() == pytest.approx(0.4)
    master.handle_timeout(0.4)
    now = 0.4
    found: list[MasterEvent] = []
    while not found:  # polled again reply_wait after every EOT until the reply timeout (1.0 after the ACK)
        assert master.data_to_send() == encode_poll(6)
        now += 0.15
        master.receive_data(EOT_SYMBOL, now)
        found = events(master)
        if not found:
            assert master.data_to_send() == b""
            assert master.next_deadline() == pytest.approx(now + 0.4)
            now += 0.4
            master.handle_timeout(now)
    assert found == [RequestFailed(request, 6, FailReason.NO_REPLY, may_have_executed=True)]
    assert now == pytest.approx(1.1)  # the first EOT after the reply timeout (polls at 0.4 and 0.95)
    later = master.next_deadline()
    assert later is not None
    master.handle_timeout(later)
    assert master.data_to_send() == encode_poll(6)
    late = reply_to(cmd, b"\x01")
    master.receive_data(encode_frame(late, Checksum.BCC), later)
    assert events(master) == [StrayReply(6, late)]


def test_reply_from_the_polled_station_never_matches_another_stations_request() -> None:
    """A reply is matched only within the polled station, by CMD and TNS (``pccc.reply_matches``)."""
    master = make(1, 2, poll_interval=100.0)
    for _ in range(2):
        master.data_to_send()
        master.receive_data(EOT_SYMBOL, 0.0)
    cmd1 = command(1, 10)
    master.submit(1, cmd1, 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == encode_poll(1)
    # Station 1 answers with a frame that is station 2's reply (a late frame on the line).
    foreign = reply_to(command(2, 11), b"\x02")
    master.receive_data(encode_frame(foreign, Checksum.BCC), 0.1)
    assert events(master) == [StrayReply(1, foreign)]
    assert not reply_matches(cmd1, PcccHeader.decode(foreign))


@pytest.mark.parametrize("reading", ["swapped", "unswapped", "own_station", "zero"])
def test_reply_is_matched_whatever_its_dst_and_src(reading: str) -> None:
    """1770-6.5.16 p. 6-4 swaps DST / SRC in a reply, but a module may put its own node number in
    SRC 0 and some devices do not swap: the one matcher (TNS, CMD | 40) takes every reading."""
    master = make(1, poll_interval=100.0)
    master.data_to_send()
    master.receive_data(EOT_SYMBOL, 0.0)
    cmd = command(1, 10)
    request_id = master.submit(1, cmd, 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == encode_poll(1)
    answer = reply_to(cmd, b"\x07")
    dst_src = {"swapped": answer[:2], "unswapped": cmd[:2], "own_station": bytes((GATEWAY, 1)), "zero": b"\x00\x00"}
    answer = dst_src[reading] + answer[2:]
    master.receive_data(encode_frame(answer, Checksum.BCC), 0.1)
    assert events(master) == [ReplyReceived(request_id, 1, answer)]


def test_timing_quiet_line_rts_key_up_and_off_delays() -> None:
    """RM p. 13-59: RTS send delay, RTS off delay; pre-transmit delay after the last byte heard."""
    line = {"char_time": 0.01, "pre_transmit_delay": 0.05, "rts_send_delay": 0.02, "rts_off_delay": 0.03}
    master = make(7, line=line, poll_timeout=1.0, poll_interval=100.0)
    assert master.rts
    assert master.data_to_send() == b""  # RTS is up, the modem keys up first
    assert master.next_deadline() == pytest.approx(0.02)
    master.handle_timeout(0.02)
    poll = encode_poll(7)
    assert master.data_to_send() == poll
    end = 0.02 + len(poll) * 0.01
    assert master.next_deadline() == pytest.approx(end + 0.03)  # RTS off
    master.handle_timeout(end + 0.03)
    assert not master.rts
    assert master.next_deadline() == pytest.approx(end + 1.0)  # the poll timer runs from the last byte
    initiated = bytes((GATEWAY, 7, 0x0F, 0x00, 0x01, 0x00))
    master.receive_data(encode_frame(initiated, Checksum.BCC), 0.2)
    assert master.data_to_send() == b""  # the ACK waits for the quiet time, RTS not yet up
    assert not master.rts
    assert master.next_deadline() == pytest.approx(0.25)
    master.handle_timeout(0.25)
    assert master.rts
    assert master.next_deadline() == pytest.approx(0.27)
    master.handle_timeout(0.27)
    assert master.data_to_send() == ACK_SYMBOL


@pytest.mark.parametrize("mode", MODES)
def test_echo_suppression_strips_own_bytes(mode: str) -> None:
    """2-wire RS-485 (§5 row 12): the master hears its own poll before the slave's answer."""
    master = make(8, line={"echo": True}, poll_interval=100.0)
    poll = master.data_to_send()
    assert poll == encode_poll(8)
    feed(master, poll + EOT_SYMBOL, 0.0, mode)
    assert master.counters(8).eots == 1
    assert master.collisions == 0
    master.handle_timeout(100.0)
    poll = master.data_to_send()
    feed(master, b"\x10\x05\x99" + EOT_SYMBOL, 100.0, mode)  # our poll came back garbled: a collision
    assert master.collisions == 1


def test_link_reset_sends_dle_nak_and_fails_awaiting_requests() -> None:
    """Table 2.C: DLE NAK makes the slaves drop queued messages; awaited replies will not come."""
    master = make(9, poll_interval=100.0)
    master.data_to_send()
    master.receive_data(EOT_SYMBOL, 0.0)
    request = master.submit(9, command(9, 4), 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == encode_poll(9)
    master.receive_data(EOT_SYMBOL, 0.0)
    assert master.data_to_send() == encode_poll(9)  # still waiting for the reply: polled again
    master.reset_link(0.0)
    assert master.data_to_send() == b""  # the reset waits for the exchange in progress
    master.receive_data(EOT_SYMBOL, 0.1)
    assert master.data_to_send().startswith(NAK_SYMBOL)
    assert RequestFailed(request, 9, FailReason.LINK_RESET, may_have_executed=True) in events(master)


def test_configuration_and_submit_errors() -> None:
    with pytest.raises(ValueError, match="unique"):
        make(1, 1)
    with pytest.raises(ValueError, match=r"0\.\.254"):
        StationConfig(255)
    with pytest.raises(ValueError, match="poll_timeout"):
        StationConfig(1, poll_timeout=0)
    with pytest.raises(ValueError, match="ack_timeout"):
        LineConfig(Checksum.BCC, ack_timeout=0)
    master = make(1, 2)
    with pytest.raises(ValueError, match="not on this line"):
        master.submit(3, command(3, 1), 0.0)
    with pytest.raises(ValueError, match=r"a command packet has at least DST SRC CMD STS TNS \(6 bytes\)"):
        master.submit(1, b"\x01", 0.0)
    master.submit(1, command(1, 5), 0.0)
    with pytest.raises(ValueError, match="TNS 0500"):
        master.submit(2, command(2, 5), 0.0)


# ---------------------------------------------------------------------- against slave models


@dataclass
class Plc:
    """A controller behind a slave: executes commands, answers with its station in the data."""

    station: int
    executed: list[bytes] = field(default_factory=list)

    def __call__(self, cmd: bytes) -> bytes:
        self.executed.append(cmd)
        return reply_to(cmd, bytes((self.station,)) + cmd[6:])


@dataclass
class Faults:
    """Lose or corrupt whole transmissions, from a seeded random source."""

    rng: random.Random
    master_lost: float = 0.0
    slave_corrupt: float = 0.0
    slave_lost: float = 0.0

    def master(self, data: bytes) -> bytes:
        return b"" if self.rng.random() < self.master_lost else data

    def slave(self, data: bytes) -> bytes:
        if data and self.rng.random() < self.slave_lost:
            return b""
        if data and self.rng.random() < self.slave_corrupt:
            spoiled = bytearray(data)
            spoiled[self.rng.randrange(len(spoiled))] ^= 1 << self.rng.randrange(8)
            return bytes(spoiled)
        return data


def slow(slave: HalfDuplexSlave, plc: Plc, polls: int) -> Callable[[bytes], bytes]:
    def handler(cmd: bytes) -> bytes:
        slave.busy = polls
        return plc(cmd)

    return handler


def run(master: HalfDuplexMaster, slaves: list[HalfDuplexSlave], faults: Faults, until: float) -> float:
    """Move bytes between the master and the slaves on a fake clock until ``until``."""
    now = 0.0
    while now < until:
        out = master.data_to_send()
        if out:
            heard = faults.master(out)
            answer = b""
            for slave in slaves:
                slave.receive_data(heard)
                answer += slave.data_to_send()
            answer = faults.slave(answer)
            if answer:
                master.receive_data(answer, now + 0.001)
            continue
        deadline = master.next_deadline()
        if deadline is None:
            break
        now = max(now, deadline)
        master.handle_timeout(now)
    return now


def test_three_live_one_absent_all_readings_clean_line() -> None:
    """Every combination of slave readings: replies from the right station, writes executed once."""
    for choice in variant_matrix(VARIANTS):
        variant = SlaveVariant.from_choices(choice)
        plcs = {n: Plc(n) for n in (1, 2, 3)}
        slaves = [HalfDuplexSlave(n, Checksum.CRC, plcs[n], variant) for n in (1, 2, 3)]
        master = make(1, 2, 3, 4, checksum=Checksum.CRC, poll_timeout=0.05, poll_interval=0.5)
        requests = {master.submit(n, command(n, 100 + n), 0.0): n for n in (1, 2, 3, 4)}
        run(master, slaves, Faults(random.Random(0)), 5.0)
        found = events(master)
        replies = [e for e in found if isinstance(e, ReplyReceived)]
        assert sorted(e.station for e in replies) == [1, 2, 3], choice
        for e in replies:
            assert requests[e.request_id] == e.station and e.message[6] == e.station
        assert StationDemoted(4) in found
        failed = [e for e in found if isinstance(e, RequestFailed)]
        assert [(requests[e.request_id], e.reason) for e in failed] == [(4, FailReason.NO_ACK)]
        assert all(len(p.executed) == 1 for p in plcs.values())


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    checksum=st.sampled_from(list(Checksum)),
    choice=st.sampled_from(list(variant_matrix(VARIANTS))),
    busy_polls=st.integers(0, 2),
)
def test_noisy_line_exactly_once_and_right_station(
    seed: int, checksum: Checksum, choice: dict[str, str], busy_polls: int
) -> None:
    """1 in 6 slave transmissions corrupted, 1 in 10 master transmissions unheard (issue #12).

    With duplicate detection on, no command is executed twice; under every reading, no reply is
    reported for the wrong station or request, and every request ends in a reply or a failure.
    """
    variant = SlaveVariant.from_choices(choice)
    plcs = {n: Plc(n) for n in (1, 2, 3)}
    slaves = [HalfDuplexSlave(n, checksum, plcs[n], variant) for n in (1, 2, 3)]
    for slave in slaves:  # a slow CPU: the reply is ready only after ``busy_polls`` more polls (§5 row 5)
        slave.handler = slow(slave, plcs[slave.station], busy_polls)
    master = make(1, 2, 3, 4, checksum=checksum, poll_timeout=0.05, poll_interval=0.5, demote_after=4)
    rng = random.Random(seed)
    requests: dict[int, tuple[int, bytes]] = {}
    for index in range(12):
        station = rng.choice([1, 2, 3, 4])
        cmd = command(station, 1000 + index, bytes((index,)))
        requests[master.submit(station, cmd, 0.0)] = (station, cmd)
    run(master, slaves, Faults(rng, master_lost=0.1, slave_corrupt=1 / 6), 60.0)
    found = events(master)
    concluded: set[int] = set()
    for event in found:
        if isinstance(event, ReplyReceived):
            station, cmd = requests[event.request_id]
            assert event.station == station
            assert reply_matches(cmd, PcccHeader.decode(event.message))
            assert event.message[6] == station and event.message[7:] == cmd[6:]
            concluded.add(event.request_id)
        elif isinstance(event, RequestFailed):
            assert event.station == requests[event.request_id][0]
            concluded.add(event.request_id)
    assert concluded == set(requests)
    if variant.duplicate_detect:
        for plc in plcs.values():
            assert len(plc.executed) == len(set(plc.executed)), choice
    # The absent station never got a command executed anywhere.
    assert all(cmd[0] == plc.station for plc in plcs.values() for cmd in plc.executed)


def test_answer_in_progress_at_the_deadline_is_allowed_to_finish_once() -> None:
    """A slow answer straddling the poll timeout is not met by the next exchange (wrong station)."""
    master = make(1, 2, poll_timeout=0.1, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(1)
    initiated = bytes((GATEWAY, 1, 0x0F, 0x00, 0x05, 0x00, 0x42))
    frame = encode_frame(initiated, Checksum.BCC)
    master.receive_data(frame[:5], 0.09)
    master.handle_timeout(0.1)  # the deadline, mid-frame: extended once
    assert master.data_to_send() == b""
    master.receive_data(frame[5:], 0.15)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(1)
    assert events(master) == [SlaveInitiated(1, initiated)]
    master.receive_data(EOT_SYMBOL, 0.16)
    assert master.data_to_send() == encode_poll(2)
    master.receive_data(frame[:5], 0.2)  # a frame that never ends: the grace is used once only
    master.handle_timeout(0.26)
    master.handle_timeout(0.36)
    assert master.counters(2).timeouts == 1
    assert master.data_to_send() == encode_poll(2)  # retried; the stale half frame was dropped


def test_a_silent_station_does_not_fail_the_replies_of_the_others() -> None:
    """Station 2 never answers; station 1 does at once.  While station 2's unacknowledged copies
    take the line, station 1's reply deadline passes: its reply is still collected by a poll (the
    deadline only makes that poll due), the copies to station 2 are interleaved with other
    stations' polls, and every copy without its ACK counts towards demoting station 2."""
    master = make(1, 2, poll_interval=100.0, reply_timeout=0.6, poll_timeout=0.5, demote_after=5)
    now = 0.0
    cmd1, cmd2 = command(1, 10), command(2, 11)
    first = master.submit(1, cmd1, now)
    owed: bytes | None = None  # station 1's reply, queued in the slave
    found: list[MasterEvent] = []
    for _ in range(200):
        out = master.data_to_send()
        if out.startswith(b"\x10\x01\x01"):
            master.receive_data(ACK_SYMBOL, now)
            owed = reply_to(cmd1, b"\x05")
            master.submit(2, cmd2, now)  # station 2's command comes while station 1's reply waits
        elif out.startswith(b"\x10\x05\x01"):
            master.receive_data(EOT_SYMBOL if owed is None else encode_frame(owed, Checksum.BCC), now)
            owed = None
        found += events(master)
        if any(isinstance(e, ReplyReceived) for e in found) and not master.is_active(2):
            break
        if out and out != ACK_SYMBOL:
            continue
        deadline = master.next_deadline()
        assert deadline is not None
        now = max(now, deadline)
        master.handle_timeout(now)
        found += events(master)
    assert ReplyReceived(first, 1, reply_to(cmd1, b"\x05")) in found
    assert not any(isinstance(e, RequestFailed) and e.station == 1 for e in found)
    assert not master.is_active(2) and master.is_active(1)


# ------------------------------------------------------------------------------- write precedence


def after_start_polls(master: HalfDuplexMaster, now: float = 0.0) -> None:
    """Answer the first background poll of every station with DLE EOT."""
    while (sent := master.data_to_send()).startswith(b"\x10\x05"):
        feed(master, EOT_SYMBOL, now, "whole")
    assert sent == b""


def test_a_write_goes_before_other_stations_queued_reads_and_its_reply_poll_next() -> None:
    """AG Figure 1.2: the master sends its outgoing messages before it selects the next station to
    poll.  A write (``urgent``) queued after reads of other stations is sent first, and its station
    is polled for the reply before the others' commands go out."""
    master = make(1, 2, 3, poll_interval=10.0)
    after_start_polls(master)
    read2, read3, write1 = command(2, 0x10), command(3, 0x11), command(1, 0x12, b"\xaa\x01")
    master.submit(2, read2, 0.1)
    sent = master.data_to_send()
    assert sent == encode_master_message(2, read2, Checksum.BCC)
    master.submit(3, read3, 0.1)
    write_id = master.submit(1, write1, 0.1, urgent=True)
    feed(master, ACK_SYMBOL, 0.11, "whole")  # station 2 has the read: the write goes next, not station 3's read
    assert master.data_to_send() == encode_master_message(1, write1, Checksum.BCC)
    feed(master, ACK_SYMBOL, 0.12, "whole")
    assert master.data_to_send() == encode_poll(1)  # the write's reply poll, before anything else
    answer = reply_to(write1, b"")
    feed(master, encode_frame(answer, Checksum.BCC), 0.13, "whole")
    assert events(master) == [ReplyReceived(write_id, 1, answer)]


def test_a_read_holding_a_writes_place_is_polled_first() -> None:
    """``max_outstanding`` 1: the station's read awaiting its reply is polled for it before the
    write can go; the write follows at once."""
    master = make(1, 2, poll_interval=10.0)
    after_start_polls(master)
    read1 = command(1, 0x20)
    master.submit(1, read1, 0.1)
    assert master.data_to_send() == encode_master_message(1, read1, Checksum.BCC)
    master.submit(2, command(2, 0x21), 0.1)
    write1 = command(1, 0x22, b"\xaa\x01")
    master.submit(1, write1, 0.1, urgent=True)
    feed(master, ACK_SYMBOL, 0.11, "whole")
    assert master.data_to_send() == encode_poll(1)  # not station 2's read
    feed(master, encode_frame(reply_to(read1, b"\x01\x00"), Checksum.BCC), 0.12, "whole")
    assert master.data_to_send() == ACK_SYMBOL + encode_master_message(1, write1, Checksum.BCC)


def test_writes_hold_other_work_back_at_most_write_precedence() -> None:
    """A read that has waited ``write_precedence`` goes before the next write: writes cannot
    starve the polls that keep data fresh."""
    master = make(1, 2, poll_interval=10.0, line={"write_precedence": 0.5})
    after_start_polls(master)
    read2 = command(2, 0x30)
    write1 = command(1, 0x31, b"\xaa\x01")
    master.submit(1, write1, 0.0, urgent=True)
    assert master.data_to_send() == encode_master_message(1, write1, Checksum.BCC)
    master.submit(2, read2, 0.0)
    feed(master, ACK_SYMBOL, 0.6, "whole")  # the read has waited 0.6 s > 0.5 s
    assert master.data_to_send() == encode_master_message(2, read2, Checksum.BCC)


def test_an_unacknowledged_copy_waits_for_a_write_at_another_station() -> None:
    """A read's master message without its ACK: while a write waits at another station, the write
    goes first and the identical copy follows (the other station's frames do not reach this slave)."""
    master = make(1, 2, poll_interval=10.0, demote_after=5)
    after_start_polls(master)
    read2 = command(2, 0x40)
    master.submit(2, read2, 0.0)
    copy = master.data_to_send()
    assert copy == encode_master_message(2, read2, Checksum.BCC)
    write1 = command(1, 0x41, b"\xaa\x01")
    master.submit(1, write1, 0.1, urgent=True)
    master.handle_timeout(0.6)  # no ACK from station 2
    assert master.data_to_send() == encode_master_message(1, write1, Checksum.BCC)
    feed(master, ACK_SYMBOL, 0.61, "whole")
    assert master.data_to_send() == encode_poll(1)
    feed(master, encode_frame(reply_to(write1, b""), Checksum.BCC), 0.62, "whole")
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(1)  # its turn ends with DLE EOT
    feed(master, EOT_SYMBOL, 0.63, "whole")
    assert master.data_to_send() == copy  # the write is done: the same copy, same TNS


# ------------------------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    ("key", "lowest"),
    [("poll_timeout", None), ("reply_timeout", None), ("reply_wait", 0.0), ("poll_interval", None),
     ("slow_poll_interval", None), ("max_polls", 1), ("demote_after", 1), ("max_outstanding", 1)],
)
def test_station_tunables_take_their_lowest_value_and_refuse_below(key: str, lowest: float | None) -> None:
    """Times must be positive (a wait of 0 where one is needed would spin), ``reply_wait`` may be
    0; counts at least 1."""
    def config(value: float) -> StationConfig:
        change: dict[str, Any] = {key: value}
        return replace(StationConfig(1), **change)

    if lowest is None:  # a time that must be > 0: any positive value, not 0
        assert getattr(config(0.001), key) == 0.001
        for bad in (0, -0.5):
            with pytest.raises(ValueError, match=f"{key} must be > 0, got {bad}"):
                config(bad)
        return
    assert getattr(config(lowest), key) == lowest
    if isinstance(lowest, int):
        with pytest.raises(ValueError, match=key):
            config(lowest - 1)
        return
    with pytest.raises(ValueError, match=f"{key} must be >= 0, got -0.001"):  # names the key
        config(-0.001)


def test_station_numbers_are_0_to_254() -> None:
    assert StationConfig(0).station == 0 and StationConfig(254).station == 254
    for bad in (-1, 255):
        with pytest.raises(ValueError, match=f"0..254 .255 is broadcast., got {bad}"):
            StationConfig(bad)


@pytest.mark.parametrize("key", ["char_time", "pre_transmit_delay", "rts_send_delay", "rts_off_delay",
                                 "write_precedence"])
def test_line_delays_may_be_0_never_negative(key: str) -> None:
    zero: dict[str, Any] = {key: 0.0}
    negative: dict[str, Any] = {key: -0.001}
    assert getattr(replace(LineConfig(Checksum.BCC), **zero), key) == 0.0
    with pytest.raises(ValueError, match=f"{key} must be >= 0, got -0.001"):
        replace(LineConfig(Checksum.BCC), **negative)


def test_line_counts_and_ack_timeout_limits() -> None:
    assert LineConfig(Checksum.BCC, message_resends=0).message_resends == 0
    assert LineConfig(Checksum.BCC, max_messages_per_turn=1).max_messages_per_turn == 1
    assert LineConfig(Checksum.BCC, ack_timeout=0.001).ack_timeout == 0.001
    bad: list[dict[str, Any]] = [{"message_resends": -1}, {"max_messages_per_turn": 0}, {"ack_timeout": 0},
                                   {"ack_timeout": -1.0}]
    for kwargs in bad:
        with pytest.raises(ValueError):
            replace(LineConfig(Checksum.BCC), **kwargs)
    for value in (0, -1.0):  # the error names the key
        with pytest.raises(ValueError, match=f"ack_timeout must be > 0, got {value}"):
            LineConfig(Checksum.BCC, ack_timeout=value)


def test_the_cores_defaults_are_the_config_keys_defaults() -> None:
    """A master built without a config (``gateway.kinds.df1.tool``, the e2e benches) polls as a
    configured line whose keys are left out.  The reply timeout is not compared: the config's
    ``timeout`` key is the full-duplex one too, and every caller passes it."""
    from gateway.kinds.df1.config import Df1LinkConfig

    fields = Df1LinkConfig.model_fields
    station = StationConfig(1)
    for key in ("poll_timeout", "reply_wait", "max_polls", "poll_interval", "demote_after", "slow_poll_interval"):
        assert getattr(station, key) == fields[key].default, key
    line = LineConfig(Checksum.BCC)
    assert (line.ack_timeout, line.message_resends) == (fields["ack_timeout"].default,
                                                        fields["message_retries"].default)
    assert (line.char_time, line.pre_transmit_delay, line.rts_send_delay, line.rts_off_delay, line.echo) == (
        0.0, fields["pre_transmit_delay"].default, fields["rts_send_delay"].default,
        fields["rts_off_delay"].default, fields["echo"].default,
    )


# ------------------------------------------------------------------------- the line, exchange by exchange


def test_start_with_a_link_reset_sends_dle_nak_before_the_first_poll() -> None:
    master = HalfDuplexMaster(LineConfig(Checksum.BCC), [StationConfig(1, poll_interval=100.0)])
    master.start(0.0, link_reset=True)
    assert master.data_to_send() == NAK_SYMBOL + encode_poll(1)
    plain = HalfDuplexMaster(LineConfig(Checksum.BCC), [StationConfig(1, poll_interval=100.0)])
    plain.start(0.0)
    assert plain.data_to_send() == encode_poll(1)


def test_what_answers_nothing_of_ours_is_counted_ignored_and_changes_nothing() -> None:
    master = make(1, 2, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(ACK_SYMBOL, 0.01)  # a poll is not acknowledged
    master.receive_data(encode_poll(2), 0.01)  # another master's poll (or our own echo)
    assert master.ignored == 2 and master.state is LineState.WAIT_POLL
    assert master.data_to_send() == b""
    master.receive_data(EOT_SYMBOL, 0.02)
    assert master.data_to_send() == encode_poll(2)
    master.receive_data(EOT_SYMBOL, 0.03)
    assert master.next_deadline() == pytest.approx(100.0) and master.ignored == 2  # idle till the next poll
    master.receive_data(EOT_SYMBOL + ACK_SYMBOL, 0.04)  # nothing is asked: stray symbols
    assert master.ignored == 4 and master.data_to_send() == b"" and events(master) == []
    assert (master.counters(1).eots, master.counters(2).eots) == (1, 1)


@pytest.mark.parametrize("answer", ["bad frame", "DLE NAK"])
def test_a_damaged_answer_to_a_poll_is_counted_and_the_station_polled_again(answer: str) -> None:
    master = make(3, 4, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(3)
    frame = bytearray(encode_frame(bytes((GATEWAY, 3, 0x0F, 0x00, 0x01, 0x00)), Checksum.BCC))
    frame[-1] ^= 0xFF
    master.receive_data(bytes(frame) if answer == "bad frame" else NAK_SYMBOL, 0.01)
    assert master.data_to_send() == encode_poll(3)  # the same station, not station 4
    assert master.counters(3).bad_frames == 1 and master.counters(3).polls == 2
    assert master.counters(3).timeouts == 0 and master.is_active(3)


def test_unacknowledged_copies_demote_the_station_and_fail_its_requests() -> None:
    """Each copy without its DLE ACK is one failure; at ``demote_after`` the one being sent fails
    NO_ACK (it may have arrived), queued ones fail as never sent, awaited ones as maybe run."""
    master = make(1, line={"ack_timeout": 0.2, "message_resends": 5}, poll_interval=100.0, demote_after=3,
                  reply_timeout=100.0, reply_wait=50.0, max_outstanding=2)
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(EOT_SYMBOL, 0.0)
    awaited = master.submit(1, command(1, 1), 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)  # awaits its reply; its first poll is 50 s away
    sent = master.submit(1, command(1, 2), 0.0)
    queued = master.submit(1, command(1, 3), 0.0)
    copies = [master.data_to_send()]
    now = 0.0
    while master.is_active(1):
        now = master.next_deadline() or now
        master.handle_timeout(now)
        copies.append(master.data_to_send())
    assert copies == [encode_master_message(1, command(1, 2), Checksum.BCC)] * 3 + [b""]
    assert now == pytest.approx(0.6)
    assert master.counters(1).timeouts == 3 and master.counters(1).resends == 2
    assert master.counters(1).demotions == 1 and master.counters(1).messages_sent == 4  # awaited + 3 copies
    assert events(master) == [
        StationDemoted(1),
        RequestFailed(queued, 1, FailReason.STATION_DEMOTED, may_have_executed=False),
        RequestFailed(awaited, 1, FailReason.STATION_DEMOTED, may_have_executed=True),
        RequestFailed(sent, 1, FailReason.NO_ACK, may_have_executed=True),
    ]


def test_a_tns_is_free_again_once_its_request_is_settled() -> None:
    master = make(1, 2, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(1)
    cmd = command(1, 0x0501)
    request = master.submit(1, cmd, 0.0)
    with pytest.raises(ValueError, match="TNS 0105 is already in use"):
        master.submit(2, command(2, 0x0501), 0.0)  # queued at station 1
    master.receive_data(EOT_SYMBOL, 0.0)
    assert master.data_to_send() == encode_master_message(1, cmd, Checksum.BCC)
    with pytest.raises(ValueError, match="already in use"):
        master.submit(2, command(2, 0x0501), 0.0)  # on the line
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == encode_poll(1)
    with pytest.raises(ValueError, match="already in use"):
        master.submit(2, command(2, 0x0501), 0.0)  # awaiting its reply
    master.receive_data(encode_frame(reply_to(cmd, b""), Checksum.BCC), 0.0)
    assert events(master) == [ReplyReceived(request, 1, reply_to(cmd, b""))]
    master.submit(2, command(2, 0x0501), 0.0)  # settled: free
    master.send_reply(2, bytes.fromhex("02 00 4F 00 01 05"), 0.0)  # a reply carries the slave's TNS: not checked
    with pytest.raises(ValueError, match=r"a reply packet has at least DST SRC CMD STS TNS \(6 bytes\)"):
        master.send_reply(2, b"\x02\x00\x4f", 0.0)
    with pytest.raises(ValueError, match="not on this line"):
        master.send_reply(3, bytes.fromhex("03 00 4F 00 01 05"), 0.0)


def test_a_line_needs_a_station() -> None:
    with pytest.raises(ValueError, match="at least one station"):
        HalfDuplexMaster(LineConfig(Checksum.BCC), [])


def test_a_station_with_messages_keeps_the_line_for_max_messages_per_turn_polls() -> None:
    master = make(1, 2, line={"max_messages_per_turn": 3}, poll_interval=100.0)
    heard = []
    for n in range(4):
        out = master.data_to_send().removeprefix(ACK_SYMBOL)
        heard.append(out)
        if out == encode_poll(1):  # station 1 always has another message
            master.receive_data(encode_frame(bytes((GATEWAY, 1, 0x0F, 0x00, n, 0x00)), Checksum.BCC), 0.0)
        else:
            master.receive_data(EOT_SYMBOL, 0.0)
    assert heard == [encode_poll(1)] * 3 + [encode_poll(2)]  # then the turn ends, though 1 has more
    assert master.counters(1).messages_received == 3 and master.data_to_send() == b""


# ------------------------------------------------------------------------------- which exchange next


def test_queued_commands_go_round_robin_over_the_stations() -> None:
    master = make(1, 2, 3, poll_interval=100.0, reply_wait=50.0, max_outstanding=5)
    after_start_polls(master)
    cmds = {(s, n): command(s, 0x10 * s + n) for s in (1, 2, 3) for n in (1, 2)}
    for (s, _), cmd in cmds.items():
        master.submit(s, cmd, 0.1)
    sent = []
    for _ in range(6):
        out = master.data_to_send()
        sent.append(next(key for key, cmd in cmds.items() if out == encode_master_message(key[0], cmd, Checksum.BCC)))
        feed(master, ACK_SYMBOL, 0.1, "whole")
    assert sent == [(1, 1), (2, 1), (3, 1), (1, 2), (2, 2), (3, 2)]


def test_urgent_requests_queue_behind_replies_and_earlier_writes_ahead_of_reads() -> None:
    master = make(1, poll_interval=100.0, reply_wait=50.0, max_outstanding=9)
    assert master.data_to_send() == encode_poll(1)  # the line is busy: everything below queues
    read_a, write_a, read_b, write_b = command(1, 1), command(1, 2, b"\xaa"), command(1, 3), command(1, 4, b"\xbb")
    reply = bytes.fromhex("01 00 4F 00 44 00")
    master.submit(1, read_a, 0.0)
    master.submit(1, write_a, 0.0, urgent=True)
    master.submit(1, read_b, 0.0)
    master.submit(1, write_b, 0.0, urgent=True)
    master.send_reply(1, reply, 0.0)
    master.receive_data(EOT_SYMBOL, 0.0)
    order = []
    for _ in range(5):
        order.append(master.data_to_send())
        master.receive_data(ACK_SYMBOL, 0.0)
    assert order == [encode_master_message(1, m, Checksum.BCC) for m in (reply, write_a, write_b, read_a, read_b)]


def test_a_reply_past_its_deadline_is_polled_at_the_next_free_line_and_its_eot_fails_it() -> None:
    """A reply wait longer than the reply timeout: once the deadline has passed, the reply's poll
    is due at the next scheduling (here after station 2's command), not only after the wait; its
    DLE EOT fails the request.  Left alone, the poll comes after the reply wait."""
    master = make(1, 2, poll_interval=100.0, reply_wait=2.0, reply_timeout=1.0)
    after_start_polls(master)
    request = master.submit(1, command(1, 5), 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == b"" and master.next_deadline() == pytest.approx(2.0)
    master.submit(2, command(2, 6), 1.5)
    assert master.data_to_send() == encode_master_message(2, command(2, 6), Checksum.BCC)
    master.receive_data(ACK_SYMBOL, 1.5)
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(EOT_SYMBOL, 1.5)
    assert events(master) == [RequestFailed(request, 1, FailReason.NO_REPLY, may_have_executed=True)]


# ------------------------------------------------------------------------------------ the wire


def test_a_byte_heard_while_bytes_wait_to_go_pushes_them_back_by_the_quiet_time() -> None:
    line = {"pre_transmit_delay": 0.05}
    master = make(7, line=line, poll_timeout=1.0, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(7)
    initiated = bytes((GATEWAY, 7, 0x0F, 0x00, 0x01, 0x00))
    master.receive_data(encode_frame(initiated, Checksum.BCC), 0.2)
    assert master.data_to_send() == b"" and master.state is LineState.TRANSMIT  # our ACK waits
    assert master.next_deadline() == pytest.approx(0.25)
    master.receive_data(b"\x00", 0.22)  # line noise: the line is busy again
    master.handle_timeout(0.25)  # (RTS keys up as planned)
    assert master.data_to_send() == b""
    assert master.next_deadline() == pytest.approx(0.27)
    master.handle_timeout(0.27)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(7)


def test_rts_keys_up_after_the_quiet_time_and_drops_after_the_last_byte() -> None:
    line = {"char_time": 0.001, "pre_transmit_delay": 0.05, "rts_send_delay": 0.02, "rts_off_delay": 0.03}
    master = make(7, line=line, poll_timeout=1.0, poll_interval=100.0)
    master.handle_timeout(0.02)
    assert master.data_to_send() == encode_poll(7) and master.rts
    assert master.next_deadline() == pytest.approx(0.054)  # 4 bytes, then the RTS off delay
    master.handle_timeout(0.054)
    assert not master.rts
    master.receive_data(EOT_SYMBOL, 0.5)  # the line is quiet again at 0.55
    assert master.next_deadline() == pytest.approx(100.0)  # the background poll
    cmd = command(7, 1)
    master.submit(7, cmd, 0.51)
    assert master.data_to_send() == b"" and not master.rts
    assert master.next_deadline() == pytest.approx(0.55)  # RTS on after the quiet time
    master.handle_timeout(0.55)
    assert master.rts and master.data_to_send() == b""
    first_byte = master.next_deadline()
    assert first_byte == pytest.approx(0.57)  # the first byte after the RTS send delay
    master.handle_timeout(first_byte)
    frame = encode_master_message(7, cmd, Checksum.BCC)
    assert master.data_to_send() == frame and master.rts
    assert first_byte is not None
    end = first_byte + len(frame) * 0.001
    rts_off = master.next_deadline()
    assert rts_off is not None and rts_off == pytest.approx(end + 0.03)
    master.handle_timeout(rts_off)
    assert not master.rts
    assert master.next_deadline() == pytest.approx(end + 0.5)  # the ACK timer runs from the last byte


@pytest.mark.parametrize("mode", MODES)
def test_echo_of_our_own_bytes_is_stripped_across_chunks_and_a_collision_keeps_what_follows(mode: str) -> None:
    master = make(8, 9, line={"echo": True}, poll_interval=100.0)
    poll = master.data_to_send()
    assert poll == encode_poll(8)
    feed(master, poll[:2], 0.0, mode)  # the echo arrives in two pieces
    feed(master, poll[2:] + EOT_SYMBOL, 0.0, mode)
    assert master.counters(8).eots == 1 and master.collisions == 0
    assert master.data_to_send() == encode_poll(9)
    feed(master, b"\x10\x05\x07" + EOT_SYMBOL, 0.0, mode)  # our poll of 9 came back as a poll of 7: collision
    assert master.collisions == 1
    assert master.counters(9).eots == 1  # what followed the garbled echo is still heard


@pytest.mark.parametrize(("demote_after", "polls_of_1"), [(10, 3), (2, 2)])
def test_an_answerless_poll_is_repeated_within_the_turn_until_the_turn_ends_or_the_station_is_demoted(
    demote_after: int, polls_of_1: int
) -> None:
    master = make(1, 2, line={"max_messages_per_turn": 3}, poll_timeout=0.2, demote_after=demote_after,
                  poll_interval=100.0)
    heard = [master.data_to_send()]
    now = 0.0
    while heard[-1] == encode_poll(1):
        now += 0.2
        master.handle_timeout(now)
        heard.append(master.data_to_send())
    assert heard == [encode_poll(1)] * polls_of_1 + [encode_poll(2)]
    assert master.counters(1).timeouts == polls_of_1
    assert master.is_active(1) is (polls_of_1 < demote_after)


def test_a_station_demoted_again_after_its_restoration_counts_two_demotions() -> None:
    master = make(2, poll_timeout=0.2, demote_after=2, poll_interval=1.0, slow_poll_interval=5.0)
    now = 0.0
    for _ in range(2):
        while master.is_active(2):
            assert master.data_to_send() == encode_poll(2)
            now = master.next_deadline() or now
            master.handle_timeout(now)
        now = master.next_deadline() or now  # the slow poll
        master.handle_timeout(now)
        assert master.data_to_send() == encode_poll(2)
        master.receive_data(EOT_SYMBOL, now)  # restored
    assert events(master) == [StationDemoted(2), StationRestored(2)] * 2
    assert master.counters(2).demotions == 2


def test_every_resent_message_is_counted_a_duplicate() -> None:
    master = make(4, poll_interval=100.0)
    master.data_to_send()
    initiated = bytes((GATEWAY, 4, 0x0F, 0x00, 0x09, 0x00, 0x01))
    for _ in range(3):  # the first, then two resends (our ACK lost twice)
        master.receive_data(encode_frame(initiated, Checksum.BCC), 0.0)
        assert master.data_to_send() == ACK_SYMBOL + encode_poll(4)
    assert events(master) == [SlaveInitiated(4, initiated)]
    assert (master.counters(4).messages_received, master.counters(4).duplicates) == (1, 2)


def test_a_master_not_started_has_no_deadline() -> None:
    master = HalfDuplexMaster(LineConfig(Checksum.BCC), [StationConfig(1)])
    assert master.next_deadline() is None and master.data_to_send() == b""
    master.start(0.0)
    assert master.data_to_send() == encode_poll(1) and master.next_deadline() == pytest.approx(0.5)


def test_the_grace_for_an_answer_in_progress_is_one_more_answer_timeout() -> None:
    master = make(1, poll_timeout=0.1, poll_interval=100.0)
    assert master.data_to_send() == encode_poll(1)
    frame = encode_frame(bytes((GATEWAY, 1, 0x0F, 0x00, 0x05, 0x00, 0x42)), Checksum.BCC)
    master.receive_data(frame[:5], 0.09)
    master.handle_timeout(0.1)
    assert master.next_deadline() == pytest.approx(0.2)
    master.handle_timeout(0.19)
    assert master.counters(1).timeouts == 0
    master.handle_timeout(0.2)
    assert master.counters(1).timeouts == 1


def test_a_copy_without_its_ack_waits_for_a_write_though_reads_waited_long_for_answer_timeouts() -> None:
    """An absent station's command without its ACK holds the line an ACK timeout per copy: the other
    stations' reads wait longer than ``write_precedence`` for it, but not for writes, so a write
    that comes meanwhile still goes before the next copy (it used to lose its precedence to them)."""
    master = make(1, 2, 3, poll_interval=10.0, demote_after=10, line={"ack_timeout": 0.5, "write_precedence": 0.5})
    after_start_polls(master)
    read2, read3, write1 = command(2, 0x90), command(3, 0x91), command(1, 0x92, b"\xaa\x01")
    master.submit(2, read2, 0.0)
    copy = master.data_to_send()
    assert copy == encode_master_message(2, read2, Checksum.BCC)
    master.submit(3, read3, 0.0)
    master.handle_timeout(0.5)  # no ACK from station 2; no write waits: the copy again
    assert master.data_to_send() == copy
    master.submit(1, write1, 0.6, urgent=True)
    master.handle_timeout(1.0)  # no ACK again; station 3's read has waited 1.0 s > write_precedence
    assert master.data_to_send() == encode_master_message(1, write1, Checksum.BCC)


def test_a_write_goes_first_whenever_it_comes_while_other_work_is_fresh() -> None:
    """``write_precedence`` counts from when the other work was queued, not from the line's start."""
    master = make(1, 2, poll_interval=100.0)
    after_start_polls(master)
    read2, write1 = command(2, 0x50), command(1, 0x51, b"\xaa\x01")
    busy = command(1, 0x52)
    master.submit(1, busy, 50.0)  # the line is busy with station 1
    assert master.data_to_send() == encode_master_message(1, busy, Checksum.BCC)
    master.submit(2, read2, 50.0)
    master.submit(1, write1, 50.1, urgent=True)
    master.receive_data(ACK_SYMBOL, 50.2)
    assert master.data_to_send() == encode_poll(1)  # the write's station: the reply poll first
    master.receive_data(encode_frame(reply_to(busy, b""), Checksum.BCC), 50.2)
    assert master.data_to_send() == ACK_SYMBOL + encode_master_message(1, write1, Checksum.BCC)


def test_a_copy_without_its_ack_goes_again_at_once_when_the_waiting_write_is_at_its_own_station() -> None:
    """Only a write at another station makes an unacknowledged copy wait; at its own station the
    copy goes first (before that station's due reply poll), so the slave sees it next."""
    master = make(2, line={"ack_timeout": 0.5}, poll_interval=100.0, reply_wait=0.4, max_outstanding=2,
                  demote_after=10)
    after_start_polls(master)
    read_a, read_b, write = command(2, 0x60), command(2, 0x61), command(2, 0x62, b"\xaa\x01")
    master.submit(2, read_a, 0.0)
    master.data_to_send()
    master.receive_data(ACK_SYMBOL, 0.0)  # read A awaits its reply; its poll is due at 0.4
    master.submit(2, read_b, 0.0)
    copy = master.data_to_send()
    assert copy == encode_master_message(2, read_b, Checksum.BCC)
    master.submit(2, write, 0.1, urgent=True)
    master.handle_timeout(0.5)  # no ACK of read B
    assert master.data_to_send() == copy


def test_any_answer_restarts_the_count_of_failures_in_a_row() -> None:
    master = make(2, poll_timeout=0.2, demote_after=3, poll_interval=100.0)
    for answered in (False, False, True, False, False):
        assert master.data_to_send() == encode_poll(2)
        now = master.next_deadline()
        assert now is not None
        if answered:
            master.receive_data(EOT_SYMBOL, now - 0.1)
            now = master.next_deadline()  # the next background poll
            assert now is not None
        master.handle_timeout(now)
    assert master.is_active(2) and master.counters(2).timeouts == 4
    assert master.data_to_send() == encode_poll(2)
    master.handle_timeout(master.next_deadline() or 0.0)  # the third in a row
    assert not master.is_active(2) and events(master) == [StationDemoted(2)]


def test_a_restored_station_is_polled_again_at_once_for_its_messages() -> None:
    master = make(2, poll_timeout=0.1, demote_after=1, poll_interval=100.0, slow_poll_interval=0.3)
    assert master.data_to_send() == encode_poll(2)
    master.handle_timeout(0.1)
    assert not master.is_active(2) and master.next_deadline() == pytest.approx(0.4)
    master.handle_timeout(0.4)
    assert master.data_to_send() == encode_poll(2)
    master.receive_data(EOT_SYMBOL, 0.45)
    assert master.is_active(2)
    assert master.data_to_send() == encode_poll(2)  # not only after its poll interval


def test_each_turn_of_a_station_gets_its_own_max_messages_per_turn() -> None:
    master = make(1, line={"max_messages_per_turn": 2}, poll_interval=10.0)
    message = encode_frame(bytes((GATEWAY, 1, 0x0F, 0x00, 0x01, 0x00)), Checksum.BCC)
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(message, 0.0)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(1)  # the turn's second poll
    master.receive_data(EOT_SYMBOL, 0.0)
    master.handle_timeout(10.0)  # the next background poll: a new turn
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(encode_frame(bytes((GATEWAY, 1, 0x0F, 0x00, 0x02, 0x00)), Checksum.BCC), 10.0)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(1)


@pytest.mark.parametrize(("waited", "first"), [(0.5, "read"), (0.49, "write")])
def test_work_that_has_waited_write_precedence_goes_before_the_next_write(waited: float, first: str) -> None:
    """A queued read that writes have kept waiting exactly ``write_precedence`` goes before the next
    write (the first write waits for its ACK until then)."""
    master = make(1, 2, line={"write_precedence": 0.5}, poll_interval=100.0, reply_wait=0.0)
    after_start_polls(master)
    read2, write1 = command(2, 0x70), command(1, 0x71, b"\xaa\x01")
    busy = command(1, 0x72, b"\xaa\x01")
    master.submit(1, busy, 1.0, urgent=True)
    master.data_to_send()
    master.submit(2, read2, 1.0)
    master.submit(1, write1, 1.0, urgent=True)
    master.receive_data(ACK_SYMBOL, 1.0 + waited)  # else station 1's reply poll, then its write
    assert master.data_to_send() == (encode_master_message(2, read2, Checksum.BCC) if first == "read"
                                     else encode_poll(1))


@pytest.mark.parametrize(("waited", "first"), [(0.6, "read"), (0.1, "write's station")])
def test_a_demoted_station_is_passed_over_when_writes_and_waiting_work_are_weighed(waited: float, first: str) -> None:
    """Station 1 is demoted and first in the round robin: it is skipped, not the end of the search,
    both when looking for waiting work (station 2's read) and for a write (station 3's)."""
    master = make(1, 2, 3, line={"write_precedence": 0.5}, poll_timeout=0.1, demote_after=1, poll_interval=100.0,
                  slow_poll_interval=100.0)
    assert master.data_to_send() == encode_poll(1)
    master.handle_timeout(0.1)  # no answer: demoted
    assert not master.is_active(1)
    after_start_polls(master, 0.1)
    busy, read2, write3 = command(3, 0x80, b"\xaa\x01"), command(2, 0x81), command(3, 0x82, b"\xaa\x01")
    master.submit(3, busy, 1.0, urgent=True)  # a write: the read waits for writes
    assert master.data_to_send() == encode_master_message(3, busy, Checksum.BCC)
    master.submit(2, read2, 1.0)
    master.submit(3, write3, 1.0, urgent=True)
    master.receive_data(ACK_SYMBOL, 1.0 + waited)
    assert master.data_to_send() == (encode_master_message(2, read2, Checksum.BCC) if first == "read"
                                     else encode_poll(3))


# ------------------------------------------------------------------- edges of the line's timing and counts


def test_a_stray_answer_on_an_idle_line_is_only_counted_even_when_a_poll_is_due() -> None:
    """An answer nothing asked for is ignored: it does not start the exchange that is due; the
    driver's ``handle_timeout`` at ``next_deadline`` does."""
    master = make(1, poll_interval=1.0)
    after_start_polls(master)
    assert master.next_deadline() == 1.0
    master.receive_data(EOT_SYMBOL, 1.5)  # the driver is late: the background poll is overdue
    assert master.ignored == 1 and master.data_to_send() == b"" and master.state is LineState.IDLE
    master.handle_timeout(1.5)
    assert master.data_to_send() == encode_poll(1) and master.ignored == 1


def test_each_damaged_answer_is_counted() -> None:
    master = make(3, poll_interval=100.0)
    frame = bytearray(encode_frame(bytes((GATEWAY, 3, 0x0F, 0x00, 0x01, 0x00)), Checksum.BCC))
    frame[-1] ^= 0xFF
    for n in (1, 2):
        assert master.data_to_send() == encode_poll(3)
        master.receive_data(bytes(frame), 0.01 * n)
        assert master.counters(3).bad_frames == n


def test_each_collision_is_counted() -> None:
    """2-wire RS-485: every poll that comes back garbled is one more collision."""
    master = make(8, line={"echo": True}, poll_interval=100.0)
    for n, now in ((1, 0.0), (2, 0.5)):
        assert master.data_to_send() == encode_poll(8)
        master.receive_data(b"\x10\x05\x99", now)
        assert master.collisions == n
        master.handle_timeout(now + 0.5)  # no answer: the station is polled again


def test_bytes_heard_while_keying_up_push_the_transmission_past_quiet_time_and_rts_send_delay() -> None:
    """RTS is up and the poll waits ``rts_send_delay``; a byte heard meanwhile (another master)
    makes the line busy: the poll goes ``pre_transmit_delay`` after it plus the key-up time."""
    master = make(1, line={"pre_transmit_delay": 0.5, "rts_send_delay": 0.25}, poll_interval=100.0)
    assert master.state is LineState.TRANSMIT and master.next_deadline() == 0.25
    master.receive_data(b"\x00", 0.125)
    assert master.next_deadline() == 0.125 + 0.5 + 0.25
    master.handle_timeout(0.75)
    assert master.data_to_send() == b""
    master.handle_timeout(0.875)
    assert master.data_to_send() == encode_poll(1)


@pytest.mark.parametrize(("acked", "polled"), [(1.0, 1), (0.75, 2)])
def test_a_reply_poll_that_has_waited_write_precedence_goes_before_a_writes_reply_poll(
    acked: float, polled: int
) -> None:
    """Station 1's read is due to be polled for its reply from 0.0 while station 2's write goes
    out; when the write is acknowledged the read has waited ``write_precedence`` (or not yet)."""
    master = make(1, 2, line={"write_precedence": 1.0, "ack_timeout": 2.0}, poll_interval=100.0)
    after_start_polls(master)
    read1, write2 = command(1, 0x90), command(2, 0x91, b"\xaa\x01")
    master.submit(1, read1, 0.0)
    assert master.data_to_send() == encode_master_message(1, read1, Checksum.BCC)
    master.submit(2, write2, 0.0, urgent=True)
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == encode_master_message(2, write2, Checksum.BCC)
    master.receive_data(ACK_SYMBOL, acked)
    assert master.data_to_send() == encode_poll(polled)


def test_a_writes_reply_poll_within_a_turn_counts_towards_max_messages_per_turn() -> None:
    """Station 1 sends a message of its own when polled for its write's reply: the next poll for
    the reply is the turn's second, so after the reply the turn (2 polls) is over."""
    master = make(1, 2, line={"max_messages_per_turn": 2}, poll_interval=100.0)
    after_start_polls(master)
    write1 = command(1, 0xA0, b"\xaa\x01")
    master.submit(1, write1, 0.0, urgent=True)
    assert master.data_to_send() == encode_master_message(1, write1, Checksum.BCC)
    master.receive_data(ACK_SYMBOL, 0.0)
    assert master.data_to_send() == encode_poll(1)
    own = bytes((GATEWAY, 1, 0x0F, 0x00, 0x01, 0x00))
    master.receive_data(encode_frame(own, Checksum.BCC), 0.0)
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(1)
    master.receive_data(encode_frame(reply_to(write1, b""), Checksum.BCC), 0.0)
    assert master.data_to_send() == ACK_SYMBOL  # the turn is over; nothing else is due
    assert [type(e) for e in events(master)] == [SlaveInitiated, ReplyReceived]


def test_the_line_wakes_for_the_earliest_reply_poll_of_any_station() -> None:
    master = make(1, 2, poll_interval=100.0, reply_wait=1.0)
    after_start_polls(master)
    read1, read2 = command(1, 0xB0), command(2, 0xB1)
    master.submit(1, read1, 0.0)
    master.receive_data(ACK_SYMBOL, 0.0)  # station 1's reply poll at 1.0
    master.submit(2, read2, 0.5)
    assert master.data_to_send() == encode_master_message(1, read1, Checksum.BCC) + encode_master_message(
        2, read2, Checksum.BCC
    )
    master.receive_data(ACK_SYMBOL, 0.5)  # station 2's at 1.5
    assert master.next_deadline() == 1.0
    master.handle_timeout(1.0)
    assert master.data_to_send() == encode_poll(1)


def test_a_demoted_stations_slow_poll_is_due_at_exactly_its_time() -> None:
    """At the slow poll's time the demoted station, first in the round robin, is polled before
    another station's queued command."""
    master = make(1, 2, poll_timeout=0.5, demote_after=1, poll_interval=100.0, slow_poll_interval=2.0)
    assert master.data_to_send() == encode_poll(1)
    master.handle_timeout(0.5)  # no answer: demoted, slow poll at 2.5
    assert not master.is_active(1)
    after_start_polls(master, 0.5)
    assert master.next_deadline() == 2.5
    read2 = command(2, 0xC0)
    master.submit(2, read2, 2.5)
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(EOT_SYMBOL, 2.5)
    assert master.is_active(1)
    assert master.data_to_send() == encode_master_message(2, read2, Checksum.BCC)


def test_a_request_is_polled_for_at_exactly_its_reply_deadline() -> None:
    """``reply_timeout`` before ``reply_wait`` is over: the deadline makes the reply's poll due, so
    at that time it goes before another station's queued command, as any due reply poll does."""
    master = make(1, 2, poll_interval=100.0, reply_wait=2.0, reply_timeout=1.0, max_outstanding=2)
    after_start_polls(master)
    read1, read2, again2 = command(1, 0xD0), command(2, 0xD1), command(2, 0xD2)
    master.submit(1, read1, 0.0)
    master.receive_data(ACK_SYMBOL, 0.0)  # station 1: reply deadline 1.0, reply poll 2.0
    master.submit(2, read2, 0.5)
    master.receive_data(ACK_SYMBOL, 0.5)  # station 2 was served last: station 1 is first in the round
    master.data_to_send()
    master.submit(2, again2, 1.0)
    assert master.data_to_send() == encode_poll(1)


def test_a_write_waits_while_its_stations_read_holds_the_only_place() -> None:
    """``max_outstanding`` 1: a read awaits its reply (polled for at 1.0); the write submitted
    meanwhile waits for that reply, and goes right after it."""
    master = make(1, poll_interval=100.0, reply_wait=1.0)
    after_start_polls(master)
    read1, write1 = command(1, 0xE0), command(1, 0xE1, b"\xaa\x01")
    master.submit(1, read1, 0.0)
    master.receive_data(ACK_SYMBOL, 0.0)
    master.data_to_send()
    master.submit(1, write1, 0.25, urgent=True)
    assert master.data_to_send() == b"" and master.next_deadline() == 1.0
    master.handle_timeout(1.0)
    assert master.data_to_send() == encode_poll(1)
    master.receive_data(encode_frame(reply_to(read1, b"\x01\x00"), Checksum.BCC), 1.0)
    assert master.data_to_send() == ACK_SYMBOL + encode_master_message(1, write1, Checksum.BCC)


def test_the_transmitter_sends_what_it_was_given_once() -> None:
    """``send`` puts the bytes of the last ``prepare`` on the line, and only once: a second ``send``
    without a new ``prepare`` sends nothing (a frame is never repeated by the transmitter)."""
    tx = HalfDuplexTransmitter(LineConfig(Checksum.BCC))
    assert tx.prepare(b"\x10\x05\x01\xff", 0.0)
    tx.send(0.0)
    assert tx.data_to_send() == b"\x10\x05\x01\xff"
    tx.send(1.0)
    assert tx.data_to_send() == b""


def test_the_transmitter_sends_nothing_before_it_is_given_bytes() -> None:
    """``send`` without any ``prepare`` puts nothing on the line."""
    tx = HalfDuplexTransmitter(LineConfig(Checksum.BCC))
    tx.send(0.0)
    assert tx.data_to_send() == b""


def test_rts_is_off_until_there_is_something_to_send() -> None:
    """A new transmitter, and a master not started yet, do not key the modem; RTS goes up for
    the first bytes prepared."""
    line = replace(LineConfig(Checksum.BCC), rts_send_delay=0.02)
    tx = HalfDuplexTransmitter(line)
    assert not tx.rts
    assert not HalfDuplexMaster(line, [StationConfig(1)]).rts
    assert not tx.prepare(encode_poll(1), 0.0) and tx.rts
