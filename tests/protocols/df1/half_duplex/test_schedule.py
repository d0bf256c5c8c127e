"""The stations of a half-duplex line and the choice of the next exchange (``half_duplex/schedule.py``).

The rules, from the manuals as ``docs/develop/df1-half-duplex-notes.md`` section 3 reads them:

* duplicate detection at the master: a slave whose DLE ACK was lost sends the same message again at
  the next poll; the master acknowledges it and discards it, keeping a record of "the first 6
  link-level data bytes of the last transmission from each station" (1775-KA p. 11-16/11-17); SRC,
  CMD and TNS identify a packet (1770-6.5.16 p. 6-3);
* a reply is the command's CMD with bit 6 set and the same TNS (1770-6.5.16 p. 6-4);
* "poll each slave repeatedly until that slave has transmitted all of its messages ... then the
  master can poll the next slave"; a slave that does not answer is removed from the active list and
  polled "occasionally" (KA p. 11-9);
* the master sends its outgoing messages before it selects the next station to poll (AG-UM008
  Figure 1.2), writes first, but not for ever (``write_precedence``).

Packets here are written out byte by byte: ``DST SRC CMD STS TNS_lo TNS_hi [data]``.
"""

from __future__ import annotations

from typing import Any

import pytest

from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex import events as hd
from gateway.protocols.df1.half_duplex.schedule import (
    ExchangeScheduler,
    LineStations,
    MasterRequest,
    PollStation,
    SendRequest,
)

MASTER = 0
#: a slave's own command (its MSG): station 3 to the master, CMD 0F, TNS 0x0110, FNC AA and data
SLAVE_MSG = bytes([MASTER, 3, 0x0F, 0x00, 0x10, 0x01, 0xAA, 0x02, 0x07, 0x89, 0x00, 0x00, 0x2A, 0x00])
#: the master's command to station 3: CMD 0F, TNS 0x1234, protected typed logical read (FNC A2)
READ = bytes([3, MASTER, 0x0F, 0x00, 0x34, 0x12, 0xA2, 0x02, 0x07, 0x89, 0x00, 0x00])
#: station 3's reply to it: DST / SRC swapped, CMD 0F + 40 hex, STS 0, the same TNS, one word
REPLY = bytes([MASTER, 3, 0x4F, 0x00, 0x34, 0x12, 0x2A, 0x00])


def request(request_id: int, station: int, tns: int, *, urgent: bool = False, write_mark: float = 0.0,
            expects_reply: bool = True) -> MasterRequest:
    message = bytes([station, MASTER, 0x0F, 0x00, tns & 0xFF, tns >> 8, 0xA2, 0x02, 0x07, 0x89, 0x00, 0x00])
    return MasterRequest(request_id, station, message, frame=b"", urgent=urgent, write_mark=write_mark,
                         expects_reply=expects_reply)


def line_of(*numbers: int, line: hd.LineConfig | None = None, **station: Any) -> tuple[LineStations, ExchangeScheduler]:
    stations = LineStations([hd.StationConfig(n, **station) for n in numbers])
    return stations, ExchangeScheduler(line or hd.LineConfig(Checksum.BCC), stations)


def take(stations: LineStations, scheduler: ExchangeScheduler, now: float) -> PollStation | SendRequest | None:
    """The next exchange, carried out as the master core does: a poll restarts the station's poll
    period and its turn; a sent command awaits its reply."""
    exchange = scheduler.next_exchange(now)
    if isinstance(exchange, PollStation):
        stations[exchange.station].polled(now)
        scheduler.polled(exchange.station, again=exchange.again)
    elif isinstance(exchange, SendRequest) and exchange.request.expects_reply:
        exchange.request.poll_at = now + 0.1
        exchange.request.reply_deadline = now + 5.0
        stations[exchange.request.station].awaiting.append(exchange.request)
    return exchange


# ------------------------------------------------------------------------ what a station sends


def test_a_message_sent_again_after_a_lost_ack_is_discarded() -> None:
    stations, _ = line_of(3)
    station = stations[3]
    assert station.received(SLAVE_MSG) == hd.SlaveInitiated(3, SLAVE_MSG)
    assert station.received(SLAVE_MSG) is None  # the same message at the next poll: ACKed, not delivered
    assert (station.counters.messages_received, station.counters.duplicates) == (1, 1)


def test_the_same_header_is_a_repeat_and_the_next_tns_is_a_new_message() -> None:
    stations, _ = line_of(3)
    station = stations[3]
    assert station.received(SLAVE_MSG) is not None
    same_head = SLAVE_MSG[:6] + bytes([0xAA, 0x02, 0x07, 0x89, 0x00, 0x00, 0x2B, 0x00])
    assert station.received(same_head) is None
    next_tns = SLAVE_MSG[:4] + bytes([0x11, 0x01]) + SLAVE_MSG[6:]
    assert station.received(next_tns) == hd.SlaveInitiated(3, next_tns)


def test_only_the_last_message_of_a_station_is_remembered() -> None:
    stations, _ = line_of(3)
    station = stations[3]
    other = SLAVE_MSG[:4] + bytes([0x11, 0x01]) + SLAVE_MSG[6:]
    station.received(SLAVE_MSG)
    station.received(other)
    assert station.received(SLAVE_MSG) == hd.SlaveInitiated(3, SLAVE_MSG)  # not the last one: new


def test_each_station_has_its_own_record() -> None:
    stations, _ = line_of(3, 4)
    from_4 = bytes([MASTER, 4]) + SLAVE_MSG[2:]
    assert stations[3].received(SLAVE_MSG) is not None
    assert stations[4].received(from_4) == hd.SlaveInitiated(4, from_4)


def test_a_message_shorter_than_a_header_is_never_a_repeat() -> None:
    stations, _ = line_of(3)
    assert stations[3].received(b"\x00\x03\x0f") == hd.SlaveInitiated(3, b"\x00\x03\x0f")
    assert stations[3].received(b"\x00\x03\x0f") == hd.SlaveInitiated(3, b"\x00\x03\x0f")


def test_a_reply_goes_to_the_request_with_its_tns_and_a_reply_to_none_is_stray() -> None:
    stations, _ = line_of(3)
    station = stations[3]
    read = MasterRequest(7, 3, READ, frame=b"")
    station.awaiting.append(read)
    other_tns = REPLY[:4] + bytes([0x35, 0x12]) + REPLY[6:]
    assert station.received(other_tns) == hd.StrayReply(3, other_tns)
    assert station.awaiting == [read]
    assert station.received(REPLY) == hd.ReplyReceived(7, 3, REPLY)
    assert station.awaiting == []


# ----------------------------------------------------------------------------------- demotion


def test_failures_in_a_row_demote_a_station_and_fail_its_requests() -> None:
    stations, _ = line_of(3, demote_after=3, slow_poll_interval=10.0)
    station = stations[3]
    queued, sent = request(1, 3, 0x0001), request(2, 3, 0x0002)
    station.queue.append(queued)
    station.awaiting.append(sent)
    assert station.failed(0.0) == []
    assert station.failed(0.5) == []
    assert station.failed(1.0) == [
        hd.StationDemoted(3),
        hd.RequestFailed(1, 3, hd.FailReason.STATION_DEMOTED, may_have_executed=False),  # never sent
        hd.RequestFailed(2, 3, hd.FailReason.STATION_DEMOTED, may_have_executed=True),  # ACKed: may have run
    ]
    assert not station.active and not station.queue and not station.awaiting
    assert station.next_poll_at == 11.0  # polled "occasionally": after slow_poll_interval
    assert station.counters.demotions == 1


def test_an_answer_between_failures_starts_the_count_again() -> None:
    stations, _ = line_of(3, demote_after=3)
    station = stations[3]
    station.failed(0.0)
    station.failed(0.5)
    assert station.answered() is None
    assert station.failed(1.0) == [] and station.failed(1.5) == []
    assert station.active


def test_a_demoted_station_that_answers_is_restored() -> None:
    stations, _ = line_of(3, demote_after=1)
    station = stations[3]
    station.failed(0.0)
    assert station.answered() == hd.StationRestored(3)
    assert station.active and station.failures == 0


# --------------------------------------------------------------------------- the next exchange


def test_between_commands_every_station_is_polled_in_turn_every_poll_interval() -> None:
    stations, scheduler = line_of(1, 2, 3, poll_interval=1.0)
    assert [take(stations, scheduler, 0.0) for _ in range(3)] == [PollStation(1), PollStation(2), PollStation(3)]
    assert take(stations, scheduler, 0.2) is None
    assert scheduler.wake == 1.0
    assert take(stations, scheduler, 1.0) == PollStation(1)


def test_a_station_with_messages_is_polled_again_up_to_the_turn_limit() -> None:
    line = hd.LineConfig(Checksum.BCC, max_messages_per_turn=3)
    stations, scheduler = line_of(1, 2, line=line)
    assert take(stations, scheduler, 0.0) == PollStation(1)
    for _ in range(2):  # station 1 answered each poll with a message: poll it again
        scheduler.poll_again = True
        assert take(stations, scheduler, 0.0) == PollStation(1, again=True)
    scheduler.poll_again = True  # a third message: its turn is over, the next station's comes
    assert take(stations, scheduler, 0.0) == PollStation(2)


def test_commands_go_before_background_polls() -> None:
    stations, scheduler = line_of(1, 2)
    read = request(1, 2, 0x0001)
    stations[2].enqueue(read)
    assert take(stations, scheduler, 0.0) == SendRequest(read)


def test_a_station_takes_at_most_max_outstanding_commands_at_once() -> None:
    stations, scheduler = line_of(2, max_outstanding=1)
    first, second = request(1, 2, 0x0001), request(2, 2, 0x0002)
    stations[2].enqueue(first)
    stations[2].enqueue(second)
    assert take(stations, scheduler, 0.0) == SendRequest(first)
    assert take(stations, scheduler, 0.0) == PollStation(2)  # a background poll, not the second command
    assert take(stations, scheduler, 0.1) == PollStation(2)  # the poll for the first one's reply
    stations[2].awaiting.clear()  # its reply came
    assert take(stations, scheduler, 0.2) == SendRequest(second)


def test_the_reply_to_a_slaves_own_message_goes_first() -> None:
    """The slave's MSG waits for the master's reply: it goes before queued commands, of its station
    and of the others."""
    stations, scheduler = line_of(1, 3)
    read = request(1, 1, 0x0001)
    own = request(2, 3, 0x0002)
    stations[3].enqueue(own)
    stations[1].enqueue(read)
    reply = MasterRequest(3, 3, REPLY, frame=b"", expects_reply=False)
    stations[3].enqueue(reply)
    assert list(stations[3].queue) == [reply, own]
    assert take(stations, scheduler, 0.0) == SendRequest(reply)


def test_a_write_goes_before_other_stations_work() -> None:
    stations, scheduler = line_of(1, 2)
    read = request(1, 1, 0x0001)
    write = request(2, 2, 0x0002, urgent=True)
    stations[1].enqueue(read)
    stations[2].enqueue(write)
    assert take(stations, scheduler, 0.0) == SendRequest(write)
    # its reply poll is due at 0.1: the line stays free for it (another exchange could hold it for
    # an answer timeout), and the read goes when the write's reply has come
    assert take(stations, scheduler, 0.0) is None
    assert scheduler.wake == pytest.approx(0.1)
    stations[2].awaiting.clear()
    assert take(stations, scheduler, 0.1) == SendRequest(read)


def test_a_write_does_not_move_the_round_robin_of_the_other_work() -> None:
    """An HMI writing to stations 1, 2, 3 in turn must not make the reads' round robin skip a station
    (station 1's read waited out write_precedence behind writes to the other stations)."""
    stations, scheduler = line_of(1, 2, 3)
    reads = {n: request(n, n, n) for n in (1, 2, 3)}
    for n, read in reads.items():
        stations[n].enqueue(read)
    write = request(4, 1, 0x0004, urgent=True)
    stations[1].enqueue(write)
    assert take(stations, scheduler, 0.0) == SendRequest(write)
    stations[1].awaiting.clear()  # its reply came
    assert [take(stations, scheduler, 0.0) for _ in range(3)] == [SendRequest(reads[n]) for n in (1, 2, 3)]


def test_writes_at_two_stations_take_turns() -> None:
    stations, scheduler = line_of(1, 2)
    first, second, other = request(1, 1, 1, urgent=True), request(2, 1, 2, urgent=True), request(3, 2, 3, urgent=True)
    stations[1].enqueue(first)
    stations[1].enqueue(second)
    stations[2].enqueue(other)
    assert take(stations, scheduler, 0.0) == SendRequest(first)
    stations[1].awaiting.clear()
    assert take(stations, scheduler, 0.0) == SendRequest(other)
    stations[2].awaiting.clear()
    assert take(stations, scheduler, 0.0) == SendRequest(second)


def test_a_write_goes_before_its_stations_queued_reads() -> None:
    stations, _ = line_of(2)
    read = request(1, 2, 0x0001)
    write = request(2, 2, 0x0002, urgent=True)
    stations[2].enqueue(read)
    stations[2].enqueue(write)
    assert list(stations[2].queue) == [write, read]


def test_work_that_writes_kept_waiting_write_precedence_goes_before_the_next_write() -> None:
    line = hd.LineConfig(Checksum.BCC, write_precedence=1.0)
    stations, scheduler = line_of(1, 2, line=line)
    read = request(1, 1, 0x0001, write_mark=scheduler.write_time(0.0))
    stations[1].enqueue(read)
    first = request(2, 2, 0x0002, urgent=True)
    stations[2].enqueue(first)
    assert take(stations, scheduler, 0.0) == SendRequest(first)
    stations[2].awaiting.clear()  # its reply came
    second = request(3, 2, 0x0003, urgent=True)
    stations[2].enqueue(second)
    assert take(stations, scheduler, 0.99) == SendRequest(second)  # the first write had the line 0.99 s
    stations[2].awaiting.clear()
    third = request(4, 2, 0x0004, urgent=True)
    stations[2].enqueue(third)
    assert scheduler.write_time(1.0) == pytest.approx(1.0)
    assert take(stations, scheduler, 1.0) == SendRequest(read)  # writes had the line 1.0 s = write_precedence


def test_the_work_writes_held_back_goes_first_then_the_writes_again() -> None:
    """Not the round robin's next: station 3's read, queued when the writes had had the line for
    1 s, has not waited for them and goes after the next write."""
    line = hd.LineConfig(Checksum.BCC, write_precedence=1.0)
    stations, scheduler = line_of(1, 2, 3, line=line)
    write = request(1, 2, 0x0001, urgent=True)
    stations[2].enqueue(write)
    assert take(stations, scheduler, 0.0) == SendRequest(write)  # the round robin goes on at station 3
    stations[2].awaiting.clear()
    held = request(2, 1, 0x0002, write_mark=scheduler.write_time(0.0))
    stations[1].enqueue(held)
    fresh = request(3, 3, 0x0003, write_mark=scheduler.write_time(1.0))
    stations[3].enqueue(fresh)
    second = request(4, 2, 0x0004, urgent=True)
    stations[2].enqueue(second)
    assert take(stations, scheduler, 1.0) == SendRequest(held)
    assert take(stations, scheduler, 1.0) == SendRequest(second)
    stations[2].awaiting.clear()  # its reply came
    assert take(stations, scheduler, 1.0) == SendRequest(fresh)


def test_work_kept_waiting_by_other_work_leaves_a_write_its_precedence() -> None:
    """On a noisy line a read waits seconds for the answer timeouts of other reads: that is no wait
    for writes, and the next write still goes first."""
    line = hd.LineConfig(Checksum.BCC, write_precedence=1.0)
    stations, scheduler = line_of(1, 2, 3, line=line)
    busy = request(1, 3, 0x0001)
    stations[3].enqueue(busy)
    assert take(stations, scheduler, 0.0) == SendRequest(busy)
    read = request(2, 1, 0x0002, write_mark=scheduler.write_time(0.0))
    stations[1].enqueue(read)
    write = request(3, 2, 0x0003, urgent=True, write_mark=scheduler.write_time(1.4))
    stations[2].enqueue(write)
    assert take(stations, scheduler, 1.5) == SendRequest(write)  # the read waited 1.5 s, not for writes
    assert scheduler.write_time(1.5) == 0.0
    assert scheduler.write_time(1.6) == pytest.approx(0.1)  # the write's exchange is on the line


def test_a_demoted_stations_slow_poll_is_not_starved_by_busy_stations() -> None:
    stations, scheduler = line_of(1, 2, demote_after=1, slow_poll_interval=10.0)
    stations[1].failed(0.0)
    exchanges = []
    for i in range(4):
        stations[2].enqueue(request(10 + i, 2, 0x0100 + i))
        exchange = take(stations, scheduler, 10.0)
        exchanges.append(exchange)
        stations[2].awaiting.clear()
    assert PollStation(1) in exchanges[:2]


# ------------------------------------------------------------------------------- the stations


def test_a_line_needs_stations_with_distinct_numbers() -> None:
    with pytest.raises(ValueError, match="unique"):
        LineStations([hd.StationConfig(1), hd.StationConfig(1)])
    with pytest.raises(ValueError, match="at least one station"):
        LineStations([])


def test_a_packet_for_a_station_not_on_the_line_or_without_a_header_is_refused() -> None:
    stations, _ = line_of(1, 2)
    with pytest.raises(ValueError, match=r"station 9 is not on this line \(stations: \[1, 2\]\)"):
        stations.target(9, READ, "command")
    with pytest.raises(ValueError, match="6 bytes"):
        stations.target(1, READ[:5], "command")
    assert stations.target(2, READ, "command") is stations[2]


def test_a_tns_is_in_use_while_its_command_is_queued_awaited_or_on_the_line() -> None:
    stations, _ = line_of(1, 2)
    stations[1].queue.append(request(1, 1, 0x0005))
    stations[2].awaiting.append(request(2, 2, 0x0006))
    on_line = request(3, 2, 0x0007)
    assert stations.tns_in_use(0x0005, None)
    assert stations.tns_in_use(0x0006, None)
    assert stations.tns_in_use(0x0007, on_line)
    assert not stations.tns_in_use(0x0008, on_line)
    # the reply to a slave's own message carries the slave's TNS, not one of the master's
    stations[1].queue.append(MasterRequest(4, 1, REPLY, frame=b"", expects_reply=False))
    assert not stations.tns_in_use(0x1234, None)
