"""The simulators' scan: answers at the end of the scan in progress, within the manual's bound.

A controller services its channel at the end of each program scan, so an answer comes at most one
scan after its command; the SLC 100/150 manual bounds the wait: "Normally the SLC will respond
within 0.3 seconds to any transmission".  Fake clocks and seeded generators: every run is the same.
"""

from __future__ import annotations

import itertools
import random

import pytest

from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.kinds.df1.sim.plc_msg import PlcMsgSimulator
from gateway.kinds.df1.sim.slc500 import Slc500Options, Slc500Simulator
from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    EOT_SYMBOL,
    Checksum,
    Symbol,
    encode_frame,
    encode_master_message,
    encode_poll,
)
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, encode_command
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.framing import frame_command
from gateway.sim import create_simulator, parse_sim_url
from gateway.sim.scan import ScanClock, ScanTime

FIXED = 0.05  # a fixed scan of 50 ms
MANUAL_BOUND = 0.3  # "Normally the SLC will respond within 0.3 seconds to any transmission"


def on_grid(times: list[float], step: float, origin: float) -> bool:
    """Every time is ``origin`` plus a whole number of ``step``."""
    return all(abs((t - origin) / step - round((t - origin) / step)) < 1e-6 for t in times)


# --------------------------------------------------------------------------------- the clock


def test_a_fixed_scan_answers_at_its_ends_at_most_one_scan_later() -> None:
    clock = ScanClock(ScanTime(FIXED, FIXED), random.Random(7))
    arrivals = [0.0]
    rng = random.Random(3)
    for _ in range(300):
        arrivals.append(arrivals[-1] + rng.uniform(0.0, 0.2))
    answers = [clock.answer_at(t) for t in arrivals]
    assert all(0 < a - t <= FIXED for t, a in zip(arrivals, answers, strict=True))
    assert on_grid(answers, FIXED, answers[0])  # the scan ends: one grid of 50 ms
    delays = [a - t for t, a in zip(arrivals, answers, strict=True)]
    assert min(delays) < 0.1 * FIXED and max(delays) > 0.9 * FIXED  # spread over the scan, not fixed


def test_a_command_arriving_during_a_scan_is_answered_when_that_scan_ends() -> None:
    clock = ScanClock(ScanTime(FIXED, FIXED), random.Random(1))
    end = clock.answer_at(1.0)
    assert clock.answer_at(1.0 + (end - 1.0) / 2) == end  # same scan, same end
    assert clock.answer_at(end) == pytest.approx(end + FIXED)  # at the end: the next scan's end
    assert clock.answer_at(end + 0.001) == pytest.approx(end + FIXED)


def test_a_varying_scan_keeps_every_answer_within_its_longest_scan() -> None:
    scan = ScanTime(0.02, 0.06)
    clock = ScanClock(scan, random.Random(11))
    t, ends = 0.0, []
    for _ in range(2000):
        t += 0.004  # a command every 4 ms: every scan gets some
        end = clock.answer_at(t)
        assert t < end <= t + 0.06
        if not ends or end != ends[-1]:
            ends.append(end)
    gaps = [b - a for a, b in itertools.pairwise(ends)]
    assert min(gaps) >= 0.02 - 1e-9 and max(gaps) <= 0.06 + 1e-9  # each scan 20-60 ms
    assert max(gaps) - min(gaps) > 0.03  # they vary


def test_the_same_seed_gives_the_same_answers() -> None:
    times = [0.013 * n for n in range(50)]
    first = [ScanClock(ScanTime(0.02, 0.06), random.Random(5)).answer_at(t) for t in times]
    again = [ScanClock(ScanTime(0.02, 0.06), random.Random(5)).answer_at(t) for t in times]
    assert first == again


def test_a_long_silence_finds_a_scan_at_a_random_point() -> None:
    clock = ScanClock(ScanTime(FIXED, FIXED), random.Random(2))
    clock.answer_at(0.0)
    later = 3600.0
    assert later < clock.answer_at(later) <= later + FIXED


@pytest.mark.parametrize(("text", "scan"), [("0.05", ScanTime(0.05, 0.05)), ("0.02-0.06", ScanTime(0.02, 0.06)),
                                            (" 0.3 ", ScanTime(0.3, 0.3))])
def test_the_scan_option_reads_a_fixed_scan_or_a_range(text: str, scan: ScanTime) -> None:
    assert ScanTime.parse(text) == scan
    assert ScanTime.parse(scan.text()) == scan


@pytest.mark.parametrize(("text", "words"), [
    ("0.5", "0.3"),  # the manual's bound
    ("0.02-0.31", "0.3"),
    ("0", "0 < shortest"),
    ("0.06-0.02", "shortest <= longest"),
    ("fast", "S or MIN-MAX"),
])
def test_a_bad_scan_is_refused_with_the_reason(text: str, words: str) -> None:
    with pytest.raises(ValueError, match=words.replace(".", r"\.")):
        ScanTime.parse(text)
    assert MANUAL_BOUND == 0.3


# ------------------------------------------------------------------------- SLC 100/150 (ASCII)


def slc_answers(sim: SlcAsciiSimulator, arrivals: list[float]) -> list[float]:
    """When each read sent at ``arrivals`` is answered (one command at a time, IDs in sequence)."""
    answers = []
    for n, t in enumerate(arrivals):
        out = sim.receive(frame_command(cmds.read_bytes(0x40, 2), n % 0x7F), t)
        assert len(out) == 1 and out[0].data.startswith(b":")
        answers.append(t + out[0].delay)
    return answers


def test_slc150_with_a_scan_answers_at_the_end_of_the_scan() -> None:
    sim = SlcAsciiSimulator(faults=FaultPlan(scan=ScanTime(FIXED, FIXED), seed=4), ladder=False)
    arrivals = [0.137 * n for n in range(40)]
    answers = slc_answers(sim, arrivals)
    assert all(0 < a - t <= FIXED for t, a in zip(arrivals, answers, strict=True))
    assert on_grid(answers, FIXED, answers[0])


def test_slc150_scan_and_a_slow_reading_keep_the_manuals_bound() -> None:
    # reply_time=spread: every reply anywhere within the reply time (0.3 s); the scan does not add to it
    sim = SlcAsciiSimulator(faults=FaultPlan(scan=ScanTime(FIXED, FIXED), seed=4), ladder=False,
                            variants={"reply_time": "spread"})
    arrivals = [1.0 * n for n in range(200)]  # one at a time: no reply holds back the next
    answers = slc_answers(sim, arrivals)
    delays = [a - t for t, a in zip(arrivals, answers, strict=True)]
    assert all(0 < d <= MANUAL_BOUND for d in delays)
    assert max(delays) > 0.25  # the reading's slow replies are kept


def test_slc150_without_a_scan_answers_at_once() -> None:
    sim = SlcAsciiSimulator(ladder=False)
    arrivals = [0.137 * n for n in range(5)]
    assert slc_answers(sim, arrivals) == arrivals


def test_slc150_scan_from_a_sim_url_and_its_errors() -> None:
    sim = create_simulator("slc150", {"scan": "0.02-0.06", "seed": "3", "ladder": "0"})
    assert isinstance(sim, SlcAsciiSimulator) and sim.faults.scan == ScanTime(0.02, 0.06)
    answers = slc_answers(sim, [0.5 * n for n in range(20)])
    assert all(0 < a - 0.5 * n <= 0.06 for n, a in enumerate(answers))
    with pytest.raises(ValueError, match=r"0\.3"):
        create_simulator("slc150", {"scan": "0.4"})
    assert parse_sim_url("sim://slc150?scan=0.05&paced=1")[1]["scan"] == "0.05"


# ------------------------------------------------------------------------- DF1 full duplex


def df1_read(tns: int) -> bytes:
    request = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2)
    return encode_frame(encode_command(request, dst=1, src=0, tns=tns), Checksum.CRC)


def is_frame(data: bytes) -> bool:
    return len(data) > 2 and data[1] == Symbol.STX


@pytest.mark.parametrize("model", ["slc504", "plc5"])
def test_df1_controller_acks_at_once_and_replies_at_the_end_of_the_scan(model: str) -> None:
    sim = create_simulator(model, {"scan": str(FIXED), "seed": "9", "ladder": "0"})
    assert isinstance(sim, Slc500Simulator)
    answers, t = [], 0.0
    for tns in range(1, 30):
        t += 0.0731 * (1 + tns % 3)
        out = sim.receive(df1_read(tns), t)
        assert [o.data for o in out] == [ACK_SYMBOL]  # the channel ACKs at once; the reply waits
        due = sim.next_deadline()
        assert due is not None and t < due <= t + FIXED
        replies = [o for o in sim.poll(due) if is_frame(o.data)]
        assert len(replies) == 1
        sim.receive(ACK_SYMBOL, due)  # the host ACKs the reply
        answers.append(due)
    assert on_grid(answers, FIXED, answers[0])


def test_df1_controller_without_a_scan_replies_with_its_ack() -> None:
    sim = Slc500Simulator(Slc500Options(), ladder=False)
    out = sim.receive(df1_read(1), 1.0)
    assert out[0].data == ACK_SYMBOL and any(is_frame(o.data) for o in out[1:])


# ------------------------------------------------------------------------ DF1 half duplex


def test_a_line_station_acks_at_once_and_its_reply_is_ready_at_the_end_of_its_scan() -> None:
    line = MultidropLine(LineOptions(stations=(1, 2), scan=ScanTime(FIXED, FIXED), seed=6))
    t, ready_times, eots = 0.0, [], 0
    for tns in range(1, 20):
        t += 0.191
        station = 1 + tns % 2
        command = encode_command(ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2),
                                 dst=station, src=0, tns=tns)
        out = line.receive(encode_master_message(station, command, Checksum.CRC), t)
        assert [o.data for o in out] == [ACK_SYMBOL]
        poll_at = t
        while True:  # poll every millisecond until the reply comes
            poll_at += 0.001
            answer = b"".join(o.data for o in line.receive(encode_poll(station), poll_at))
            if answer == EOT_SYMBOL:
                eots += 1
                continue
            assert is_frame(answer)
            line.receive(ACK_SYMBOL, poll_at)
            break
        assert t < poll_at <= t + FIXED + 0.001
        ready_times.append(poll_at)
    assert eots > 100  # the replies waited for their scans (about 25 polls each on average)


def test_line_scan_option_and_each_station_its_own_clock() -> None:
    line = MultidropLine.from_options({"stations": "1,2", "scan": "0.02-0.06", "seed": "1"})
    assert line.options.scan == ScanTime(0.02, 0.06)
    with pytest.raises(ValueError, match=r"0\.3"):
        MultidropLine.from_options({"scan": "1"})
    clocks = [slave.answer_at for slave in line.slaves.values()]
    assert all(clock is not None for clock in clocks)
    firsts = [clock(0.0) for clock in clocks if clock is not None]
    assert firsts[0] != firsts[1]  # independent phases


# -------------------------------------------------------------------- the PLC sending MSGs


def test_a_plc_sends_each_msg_at_the_end_of_a_scan() -> None:
    plc = PlcMsgSimulator(every=0.1, cycle=1.0, scan=ScanTime(FIXED, FIXED), seed=2)
    starts, now = [], 0.0
    for n in range(20):
        now = (starts[-1] if starts else 0.0) + 0.0137 * n  # the last MSG's reply came
        plc._advance(now)
        wait = 1.0 if plc._step == 0 else 0.1  # the script's cycle (1 s) begins again, else the next MSG
        due = plc._next
        assert due is not None and now + wait < due <= now + wait + FIXED
        starts.append(due)
    assert on_grid(starts, FIXED, starts[0])
