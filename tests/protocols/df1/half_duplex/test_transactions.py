"""PCCC transactions over the half-duplex master (``gateway.protocols.df1.half_duplex.transactions``).

Byte scripts with a fake clock: the stations are played by a function that decides, for each
command the master puts on the line, whether it is acknowledged and what the reply is; polls are
answered with the reply when one is owed, else DLE EOT.  The verdicts are those of full duplex:
a read is asked again with a new TNS, a write is sent once and read back when its answer is lost.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import pytest

from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import ACK_SYMBOL, EOT_SYMBOL, Checksum, NeedData, encode_frame, encode_poll
from gateway.protocols.df1.full_duplex.transaction import (
    OutcomeUnknown,
    TransactionDone,
    TransactionEvent,
    TransactionFailed,
    TransactionRefused,
)
from gateway.protocols.df1.half_duplex.events import (
    FailReason,
    LineConfig,
    MasterEvent,
    RequestFailed,
    SlaveInitiated,
    StationConfig,
    StationDemoted,
)
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster
from gateway.protocols.df1.half_duplex.transactions import HalfDuplexTransactions, PcccRequestLike, encode_packet
from gateway.protocols.df1.pccc import (
    PcccCommand,
    PcccHeader,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    decode_command,
    encode_command,
    encode_reply,
)

N = FileType.INTEGER
READ = ProtectedTypedLogicalRead(N, 7, 5, 0, 2)
WRITE = ProtectedTypedLogicalWrite(N, 7, 10, 0, b"\x34\x12")
READ_BACK = ProtectedTypedLogicalRead(N, 7, 10, 0, 2)

#: What a station does with a command: None (never heard: no DLE ACK), "ack" (DLE ACK, no reply
#: ever), or the reply packet it sends when next polled.
Answer = Callable[[PcccCommand], "bytes | str | None"]


def ok(command: PcccCommand, data: bytes = b"") -> bytes:
    return encode_reply(command.header, sts=0, data=data)


def refused(command: PcccCommand) -> bytes:
    return encode_reply(command.header, sts=0x10)


@dataclass
class Line:
    """HalfDuplexTransactions on a BCC line of ``stations``; ``answer`` plays every station."""

    answer: Answer
    stations: tuple[int, ...] = (1,)
    retries: int = 3
    source: int = 0
    first_tns: int = 0x100
    station_kw: dict[str, Any] = field(default_factory=dict)
    dead: set[int] = field(default_factory=set)  #: stations that answer nothing, polls included
    now: float = 0.0
    heard: list[tuple[int, PcccCommand]] = field(default_factory=list)  #: commands, as each station heard them
    events: list[TransactionEvent | MasterEvent] = field(default_factory=list)
    started: int = 0

    def __post_init__(self) -> None:
        self.txns = HalfDuplexTransactions(source=self.source, retries=self.retries, first_tns=self.first_tns)
        self.master = self.connect()
        self.owed: dict[int, list[bytes]] = {s: [] for s in self.stations}

    def connect(self, reason: str = "") -> HalfDuplexMaster:
        config = {"poll_interval": 100.0, "max_polls": 3, "demote_after": 5, **self.station_kw}
        master = HalfDuplexMaster(LineConfig(Checksum.BCC, message_resends=0),
                                  [StationConfig(s, **config) for s in self.stations])
        self.txns.attach(master, self.now, reason=reason)
        master.start(self.now)
        self.master = master
        self.collect()
        return master

    def start(self, request: PcccRequestLike, *, write: bool, station: int = 1) -> int:
        handle = self.txns.start(station, request, self.now, write=write)
        self.started += 1
        self.collect()
        return handle

    def collect(self) -> None:
        while not isinstance(event := self.txns.next_event(), NeedData):
            self.events.append(event)

    def verdicts(self) -> list[TransactionEvent]:
        kinds = TransactionDone | TransactionRefused | OutcomeUnknown | TransactionFailed
        return [e for e in self.events if isinstance(e, kinds)]

    def run(self, *, until: Callable[[], bool] | None = None, steps: int = 3000) -> None:
        """Carry bytes and move the clock until ``until`` holds (default: every transaction settled)."""
        done = until or (lambda: len(self.verdicts()) >= self.started)
        for _ in range(steps):
            if done():
                return
            out = self.master.data_to_send().removeprefix(ACK_SYMBOL)  # our ACK of a station's reply
            if out and out[2] in self.dead:
                pass
            elif out.startswith(b"\x10\x01"):  # DLE SOH STN DLE STX packet DLE ETX BCC
                station = out[2]
                packet = out[5 : out.index(b"\x10\x03")].replace(b"\x10\x10", b"\x10")
                if PcccHeader.decode(packet).is_reply:  # our reply to a station's own message: not acknowledged
                    continue
                command = decode_command(packet)
                self.heard.append((station, command))
                what = self.answer(command)
                if isinstance(what, bytes):
                    self.owed[station].append(what)
                if what is not None:
                    self.txns.receive_data(ACK_SYMBOL, self.now)
            elif out.startswith(b"\x10\x05"):  # DLE ENQ STN BCC
                owed = self.owed[out[2]]
                self.txns.receive_data(encode_frame(owed.pop(0), Checksum.BCC) if owed else EOT_SYMBOL, self.now)
            if not out or out[2] in self.dead:
                deadline = self.master.next_deadline()
                assert deadline is not None
                self.now = max(self.now, deadline)
                self.txns.handle_timeout(self.now)
            self.collect()
        raise AssertionError("no verdict")


# ------------------------------------------------------------------------------------------ reads


def test_a_read_is_sent_with_the_lines_tns_and_answered_by_its_reply() -> None:
    line = Line(lambda c: ok(c, b"\x07\x00"), stations=(4,), source=9, first_tns=0x10203)  # 16 bits: 0x0203
    handle = line.start(READ, write=False, station=4)
    line.run()
    [(station, command)] = line.heard
    assert station == 4 and command.request == READ
    assert (command.header.dst, command.header.src, command.header.tns) == (4, 9, 0x0203)
    [done] = line.verdicts()
    assert isinstance(done, TransactionDone) and done.handle == handle
    assert done.reply.data == b"\x07\x00" and not done.verified
    assert line.txns.counters(4).read_retries == 0


def test_a_refused_read_is_refused_at_once() -> None:
    line = Line(refused)
    handle = line.start(READ, write=False)
    line.run()
    assert [type(v) for v in line.verdicts()] == [TransactionRefused]
    assert line.verdicts()[0].handle == handle and len(line.heard) == 1


def test_a_read_without_a_reply_is_asked_again_with_a_new_tns_then_fails() -> None:
    line = Line(lambda c: "ack", retries=2)
    handle = line.start(READ, write=False)
    line.run()
    assert [c.request for _, c in line.heard] == [READ] * 3  # 1 + retries
    assert [c.header.tns for _, c in line.heard] == [0x100, 0x101, 0x102]
    [failed] = line.verdicts()
    assert failed == TransactionFailed(handle, f"{FailReason.NO_REPLY.value} (after 3 tries)")
    assert line.txns.counters(1).read_retries == 2


def test_a_read_answered_on_its_last_try_is_done() -> None:
    tries: list[int] = []

    def third_time(command: PcccCommand) -> bytes | str:
        tries.append(command.header.tns)
        return ok(command, b"\x01\x00") if len(tries) == 3 else "ack"

    line = Line(third_time, retries=2)
    line.start(READ, write=False)
    line.run()
    assert [type(v) for v in line.verdicts()] == [TransactionDone] and len(tries) == 3


def test_a_read_for_a_demoted_station_fails_at_once_without_retries() -> None:
    line = Line(ok, station_kw={"demote_after": 1}, dead={1})
    line.run(until=lambda: not line.master.is_active(1))
    handle = line.start(READ, write=False)
    [failed] = line.verdicts()
    assert failed == TransactionFailed(handle, f"{FailReason.STATION_DEMOTED.value} (after 1 tries)")
    assert line.heard == [] and line.txns.counters(1).read_retries == 0


def test_a_reply_that_does_not_decode_is_no_answer() -> None:
    """STS F0 without its EXT STS byte: the read is asked again, as for a reply that never came."""
    answers = iter([b"broken", b"good"])

    def answer(command: PcccCommand) -> bytes:
        if next(answers) == b"broken":
            return PcccHeader(0, 1, command.header.cmd | 0x40, 0xF0, command.header.tns).encode()
        return ok(command, b"\x02\x00")

    line = Line(answer)
    line.start(READ, write=False)
    line.run()
    [done] = line.verdicts()
    assert isinstance(done, TransactionDone) and done.reply.data == b"\x02\x00"
    assert len(line.heard) == 2 and line.txns.counters(1).read_retries == 1


# ----------------------------------------------------------------------------------------- writes


def test_a_write_answered_sts_0_is_done_and_sent_once() -> None:
    line = Line(ok)
    handle = line.start(WRITE, write=True)
    line.run()
    assert [c.request for _, c in line.heard] == [WRITE]
    [done] = line.verdicts()
    assert isinstance(done, TransactionDone) and done.handle == handle and not done.verified


def test_a_refused_write_is_refused_and_never_read_back() -> None:
    line = Line(refused)
    line.start(WRITE, write=True)
    line.run()
    assert [type(v) for v in line.verdicts()] == [TransactionRefused]
    assert [c.request for _, c in line.heard] == [WRITE] and line.txns.counters(1).read_backs == 0


def test_a_write_whose_reply_never_comes_is_read_back_and_done_when_it_holds() -> None:
    line = Line(lambda c: "ack" if c.request == WRITE else ok(c, b"\x34\x12"))
    handle = line.start(WRITE, write=True)
    line.run()
    assert [c.request for _, c in line.heard] == [WRITE, READ_BACK]  # the write is never sent again
    [done] = line.verdicts()
    assert isinstance(done, TransactionDone) and done.handle == handle and done.verified
    assert done.reply.data == b"\x34\x12"
    assert line.txns.counters(1).read_backs == 1


def test_a_write_never_acknowledged_may_have_run_and_is_read_back() -> None:
    """No DLE ACK after every copy: the slave may have it (its ACK was lost), so it is read back."""
    line = Line(lambda c: None if c.request == WRITE else ok(c, b"\x00\x00"))
    line.start(WRITE, write=True)
    line.run()
    assert [c.request for _, c in line.heard] == [WRITE, READ_BACK]
    [unknown] = line.verdicts()
    assert isinstance(unknown, OutcomeUnknown)
    assert "the read-back gave 00 00, not the value written" in unknown.reason


def test_a_write_whose_read_backs_are_never_answered_is_unknown_after_retries_plus_one() -> None:
    line = Line(lambda c: "ack", retries=1)
    line.start(WRITE, write=True)
    line.run()
    assert [c.request for _, c in line.heard] == [WRITE, READ_BACK, READ_BACK]
    assert [c.header.tns for _, c in line.heard] == [0x100, 0x101, 0x102]
    [unknown] = line.verdicts()
    assert isinstance(unknown, OutcomeUnknown) and "2 read-backs got no answer" in unknown.reason
    assert line.txns.counters(1).read_backs == 2 and line.txns.counters(1).read_retries == 0


def test_a_write_for_a_demoted_station_never_left_and_failed() -> None:
    line = Line(ok, station_kw={"demote_after": 1}, dead={1})
    line.run(until=lambda: not line.master.is_active(1))
    handle = line.start(WRITE, write=True)
    [failed] = line.verdicts()
    assert isinstance(failed, TransactionFailed) and failed.handle == handle
    assert failed.reason.startswith(f"{FailReason.STATION_DEMOTED.value}; the write was never sent")
    assert line.heard == []


def test_a_write_goes_before_another_stations_queued_read() -> None:
    """Writes and their read-backs are urgent: the master serves them first."""
    line = Line(lambda c: ok(c, b"\x00\x00"), stations=(1, 2))
    line.start(READ, write=False, station=2)  # queued while station 1 is polled at the start
    line.start(WRITE, write=True, station=1)
    line.run()
    assert [(s, c.request) for s, c in line.heard] == [(1, WRITE), (2, READ)]


# -------------------------------------------------------------------------------- a new connection


def test_a_new_master_settles_what_ran_on_the_old_one() -> None:
    line = Line(lambda c: "ack", stations=(1, 2))
    read = line.start(READ, write=False, station=2)
    write = line.start(WRITE, write=True, station=1)
    line.run(until=lambda: len(line.heard) == 2)
    line.now = 3.0
    line.connect(reason="port lost")
    assert line.verdicts()[0] == TransactionFailed(read, "port lost")
    unknown = line.verdicts()[1]
    assert isinstance(unknown, OutcomeUnknown) and unknown.handle == write
    assert unknown.reason.startswith("port lost") and "(after 3 s)" in unknown.reason
    # the old master's events no longer reach the transactions: a new one runs on its own
    line.answer = ok
    handle = line.start(READ, write=False, station=1)
    line.run(until=lambda: len(line.verdicts()) == 3)
    assert isinstance(line.verdicts()[2], TransactionDone) and line.verdicts()[2].handle == handle


def test_a_new_master_after_a_settled_transaction_reports_nothing_again() -> None:
    line = Line(ok)
    line.start(READ, write=False)
    line.run()
    line.connect(reason="port lost")
    assert len(line.verdicts()) == 1


# ------------------------------------------------------------------------------- the rest passes


def test_master_events_that_are_no_transactions_go_to_the_driver() -> None:
    initiated = encode_command(READ, dst=0, src=1, tns=0x77)
    line = Line(ok, stations=(1, 2), station_kw={"demote_after": 1}, dead={2})
    line.owed[1].append(initiated)  # station 1 sends its own command at the first poll
    line.run(until=lambda: any(isinstance(e, StationDemoted) for e in line.events))
    assert line.events == [SlaveInitiated(1, initiated), StationDemoted(2)]
    assert line.verdicts() == []


def test_encode_packet_is_the_pccc_command() -> None:
    assert encode_packet(READ, dst=3, src=4, tns=0x1234) == encode_command(READ, dst=3, src=4, tns=0x1234)


def test_by_default_commands_go_from_station_0_numbered_from_tns_1() -> None:
    """The defaults (those of the full-duplex core): the first command's SRC is 0 and its TNS 1."""
    txns = HalfDuplexTransactions()
    master = HalfDuplexMaster(LineConfig(Checksum.BCC), [StationConfig(1)])
    txns.attach(master, 0.0, reason="")
    master.start(0.0)
    txns.start(1, READ, 0.0, write=False)
    assert master.data_to_send() == encode_poll(1)  # the poll that was under way
    txns.receive_data(EOT_SYMBOL, 0.0)
    out = master.data_to_send()
    packet = out[5 : out.index(b"\x10\x03")].replace(b"\x10\x10", b"\x10")
    assert packet == encode_packet(READ, dst=1, src=0, tns=1)


def test_negative_retries_are_refused() -> None:
    with pytest.raises(ValueError, match="negative"):
        HalfDuplexTransactions(retries=-1)
    assert HalfDuplexTransactions(retries=0).retries == 0


def test_a_write_whose_reply_does_not_decode_may_have_run_and_is_read_back() -> None:
    """The reply came (garbled in its PCCC content): the write reached the controller, so it is
    never reported as never sent."""
    def answer(command: PcccCommand) -> bytes:
        if command.request == WRITE:
            return PcccHeader(0, 1, command.header.cmd | 0x40, 0xF0, command.header.tns).encode()
        return ok(command, b"\x34\x12")

    line = Line(answer)
    line.start(WRITE, write=True)
    line.run()
    assert [c.request for _, c in line.heard] == [WRITE, READ_BACK]
    [done] = line.verdicts()
    assert isinstance(done, TransactionDone) and done.verified


def test_every_transaction_a_demotion_fails_is_reported_with_it_at_once() -> None:
    """A dead station: the one demotion fails a read awaiting its reply and a queued one; both
    verdicts come out of the same call as StationDemoted, none is held back for a later one."""
    line = Line(lambda c: "ack", station_kw={"demote_after": 2, "reply_wait": 50.0, "max_outstanding": 1},
                retries=0)
    awaiting = line.start(READ, write=False)
    queued = line.start(ProtectedTypedLogicalRead(N, 7, 6, 0, 2), write=False)
    line.run(until=lambda: len(line.heard) == 1)
    line.dead.add(1)  # the station dies: its polls go unanswered
    line.run(until=lambda: any(isinstance(e, StationDemoted) for e in line.events))
    assert line.events[0] == StationDemoted(1)
    failed = {(v.handle, type(v)) for v in line.verdicts()}
    assert failed == {(awaiting, TransactionFailed), (queued, TransactionFailed)}


def test_the_fate_of_a_reply_to_a_slaves_message_goes_to_the_driver() -> None:
    line = Line(lambda c: None)
    request = line.master.send_reply(1, bytes.fromhex("01 00 4F 00 44 00"), 0.0)
    line.run(until=lambda: bool(line.events))
    assert line.events == [RequestFailed(request, 1, FailReason.NO_ACK, may_have_executed=True)]
