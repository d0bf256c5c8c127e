"""The stations of a DF1 half-duplex line and the choice of its next exchange (sans-I/O).

The master core (``master.py``) owns the line: bytes, timers, its transition table.  This
module owns what it knows of each station - its queued and awaiting requests, whether it answers
(demotion), what a message it sends means (:meth:`StationRecord.received`) - and decides, each time
the line is free, which exchange comes next (:meth:`ExchangeScheduler.next_exchange`).  Manuals:
1770-6.5.16 chapter 3; 1775-KA p. 11-9; AG-UM008 Figure 1.2; the reading is in
``docs/develop/df1-half-duplex-notes.md``.

* Between commands every station is polled every ``poll_interval`` for the messages it initiates.
  An answerless poll, or a master message without its DLE ACK (each copy sent), is one failure;
  ``demote_after`` failures in a row (no answer of any kind between them) demote a station: its
  requests fail at once and it is polled every ``slow_poll_interval`` until it answers (Kepware's
  auto-demotion; KA p. 11-9 "poll the inactive slaves occasionally").
* Writes first: a command submitted ``urgent`` (a write, or its read-back) is queued ahead of its
  station's other commands and goes before other stations' work - its station's reply poll when
  due (also for the read that holds its place under ``max_outstanding``), else the write itself;
  an unacknowledged copy of another station's message waits for it; while its reply poll is not
  due yet (``reply_wait``) the line stays free for it, where another exchange could hold it for an
  answer timeout.  AG Figure 1.2 (the master checks for and sends its outgoing messages before it
  selects the next station to poll); KA p. 11-9.
* Not for ever: work that writes have kept waiting ``write_precedence`` goes before the next write,
  the longest held first, so writes never starve the polls that keep every station's data fresh.
  What counts is the line time the writes' exchanges took while that work waited
  (:meth:`ExchangeScheduler.write_time`), not the time it waited: on a noisy line every read waits
  seconds for the answer timeouts of other reads, which is no wait for writes.

This module does no I/O.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.half_duplex import events as hd
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, PcccHeader, duplicate_key, reply_matches
from gateway.protocols.df1.pccc.codes import REPLY_BIT

__all__ = [
    "Exchange",
    "ExchangeScheduler",
    "LineStations",
    "MasterRequest",
    "PollStation",
    "SendRequest",
    "StationRecord",
]

@dataclass(slots=True)
class MasterRequest:
    """A master message to deliver to a station: a command, or the reply to a slave's own command."""

    request_id: int
    station: int
    message: bytes
    frame: bytes
    sends: int = 0
    polls: int = 0
    poll_at: float = 0.0
    reply_deadline: float = 0.0
    expects_reply: bool = True  #: False: the reply to a slave's own command; done at its DLE ACK
    urgent: bool = False  #: a write (or its read-back): served before other stations' work
    #: the line's write time (:meth:`ExchangeScheduler.write_time`) when it was submitted, and again
    #: when it was acknowledged (then it waits for its reply poll)
    write_mark: float = 0.0

    def failed(self, reason: hd.FailReason, may_have_executed: bool) -> hd.RequestFailed:
        """The event that reports this request failed."""
        return hd.RequestFailed(self.request_id, self.station, reason, may_have_executed)


@dataclass(slots=True)
class StationRecord:
    """What the master knows of one station."""

    config: hd.StationConfig
    active: bool = True
    failures: int = 0
    queue: deque[MasterRequest] = field(default_factory=deque)
    awaiting: list[MasterRequest] = field(default_factory=list)
    next_poll_at: float = 0.0
    last_head: tuple[int, int, int] | None = None  #: SRC CMD TNS of the last message (duplicate_key)
    counters: hd.StationCounters = field(default_factory=hd.StationCounters)

    @property
    def number(self) -> int:
        return self.config.station

    def answered(self) -> hd.StationRestored | None:
        """The station answered: the failures in a row end; a demoted station is restored."""
        self.failures = 0
        if self.active:
            return None
        self.active = True
        self.next_poll_at = 0.0
        return hd.StationRestored(self.number)

    def failed(self, now: float) -> list[hd.MasterEvent]:
        """One more failure in a row; at ``demote_after`` the station is demoted and its requests
        fail.  Returns the events (none while the station stays active)."""
        self.failures += 1
        if not self.active or self.failures < self.config.demote_after:
            return []
        self.active = False
        self.next_poll_at = now + self.config.slow_poll_interval
        self.counters.demotions += 1
        events: list[hd.MasterEvent] = [hd.StationDemoted(self.number)]
        while self.queue:
            request = self.queue.popleft()
            events.append(request.failed(hd.FailReason.STATION_DEMOTED, False))
        events += [self.fail_awaiting(request, hd.FailReason.STATION_DEMOTED) for request in list(self.awaiting)]
        return events

    def fail_awaiting(self, request: MasterRequest, reason: hd.FailReason) -> hd.RequestFailed:
        self.awaiting.remove(request)
        return request.failed(reason, True)

    def enqueue(self, request: MasterRequest) -> None:
        """The reply to a slave's own command first, then urgent requests (writes), then the rest."""
        if not request.expects_reply:
            self.queue.appendleft(request)
        elif request.urgent:
            # behind the replies to the slave's own messages and the urgent requests already queued
            at = next((i for i, r in enumerate(self.queue) if r.expects_reply and not r.urgent), len(self.queue))
            self.queue.insert(at, request)
        else:
            self.queue.append(request)

    def received(self, message: bytes) -> hd.MasterEvent | None:
        """A good message of this station (already acknowledged): its reply to one of our requests,
        a stray reply, or a command of its own; None for a repeat (it resends when our DLE ACK was
        lost: its SRC, CMD and TNS are the last message's, with no EOT between, KA p. 11-17; 1770-6.5.16
        p. 6-3).  A message too short for a PCCC header is never a repeat."""
        head = duplicate_key(message) if len(message) >= HEADER_SIZE else None
        if head is not None and head == self.last_head:
            self.counters.duplicates += 1
            return None
        self.last_head = head
        self.counters.messages_received += 1
        if len(message) >= HEADER_SIZE and message[2] & REPLY_BIT:
            reply = PcccHeader.decode(message)
            for request in self.awaiting:
                if reply_matches(request.message, reply):
                    self.awaiting.remove(request)
                    return hd.ReplyReceived(request.request_id, self.number, message)
            return hd.StrayReply(self.number, message)
        return hd.SlaveInitiated(self.number, message)

    def polled(self, now: float) -> None:
        self.counters.polls += 1
        interval = self.config.poll_interval if self.active else self.config.slow_poll_interval
        self.next_poll_at = now + interval


class LineStations:
    """The stations of one line by number, in their configured order (the round robin's)."""

    def __init__(self, configs: list[hd.StationConfig]) -> None:
        numbers = [s.station for s in configs]
        if len(set(numbers)) != len(numbers):
            raise ValueError(f"station numbers must be unique on a line, got {sorted(numbers)}")
        if not configs:
            raise ValueError("a half-duplex line needs at least one station")
        self.order: Final = numbers
        self._by_number: Final = {s.station: StationRecord(s) for s in configs}

    def __getitem__(self, number: int) -> StationRecord:
        return self._by_number[number]

    def __iter__(self) -> Iterator[StationRecord]:
        return iter(self._by_number.values())

    def target(self, station: int, message: bytes, what: str) -> StationRecord:
        """The station a packet (``what``) is for; ValueError for a station not on the line or a
        packet without a PCCC header."""
        target = self._by_number.get(station)
        if target is None:
            raise ValueError(f"station {station} is not on this line (stations: {self.order})")
        if len(message) < HEADER_SIZE:
            raise ValueError(f"{what} has at least DST SRC CMD STS TNS (6 bytes)")
        return target

    def tns_in_use(self, tns: int, in_flight: MasterRequest | None) -> bool:
        """A request queued, awaiting its reply or ``in_flight`` has this TNS."""
        if any(
            r.expects_reply and duplicate_key(r.message)[2] == tns
            for station in self
            for r in itertools.chain(station.queue, station.awaiting)
        ):
            return True
        return in_flight is not None and in_flight.expects_reply and duplicate_key(in_flight.message)[2] == tns


@frozen
class PollStation:
    """Poll ``station``; ``again``: one more poll of the station whose turn it is."""

    station: int
    again: bool = False


@frozen
class SendRequest:
    """Send ``request`` (already taken off its station's queue)."""

    request: MasterRequest


Exchange = PollStation | SendRequest


class ExchangeScheduler:
    """Which exchange the free line carries next (module docstring); the round robin and the turn
    of the station that has messages are its state."""

    def __init__(self, line: hd.LineConfig, stations: LineStations) -> None:
        self.line: Final = line
        self._stations: Final = stations
        self._order: Final = stations.order
        self._rr = 0  #: where the round robin of the other work goes on
        self._rr_writes = 0  #: where the round robin of the stations with writes goes on
        self.turn_station: int | None = None  #: the station polled last, while it has messages
        self.turn_polls = 0
        self.poll_again = False  #: poll the turn's station again (it sent a message, or a bad frame)
        self.wake: float | None = None  #: after :meth:`next_exchange` found nothing: when to ask again
        self._write_time = 0.0  #: line time of the ended exchanges chosen for a write
        self._write_since: float | None = None  #: the exchange on the line was chosen for a write, at that time

    def polled(self, number: int, *, again: bool) -> None:
        """``number`` is being polled (``again``: within its turn)."""
        if not again or self.turn_station != number:
            self.turn_station = number
            self.turn_polls = 0
        self.turn_polls += 1

    def rotation(self, writes: bool = False) -> list[StationRecord]:
        """The stations in round-robin order, from where the round robin of writes (``writes``) or
        of the other work goes on."""
        at = self._rr_writes if writes else self._rr
        order = self._order[at:] + self._order[:at]
        return [self._stations[number] for number in order]

    def serve(self, station: StationRecord, *, write: bool = False) -> None:
        """``station`` had its turn: its round robin goes on after it.  A write's turn does not move
        the round robin of the other work: writes go to the stations in their own order (an HMI
        writing to stations 1, 2, 3 in turn), which would make that round robin skip the same
        station again and again, its reads waiting out ``write_precedence``."""
        after = (self._order.index(station.number) + 1) % len(self._order)
        if write:
            self._rr_writes = after
        else:
            self._rr = after

    def write_time(self, now: float) -> float:
        """Seconds of line time the exchanges chosen for writes took since the line started (the one
        on the line up to ``now``): from the choice of a write's exchange (the write, its station's
        reply poll, and the copies of the write sent again) to the next choice of the free line."""
        running = now - self._write_since if self._write_since is not None else 0.0
        return self._write_time + running

    def held_back(self, now: float) -> tuple[StationRecord, MasterRequest | None] | None:
        """The work that writes have kept waiting longest, once writes had the line for
        ``write_precedence`` while it waited: it goes next, before the next write (writes cannot
        starve the polls that keep every station's data fresh).  ``(station, command)``: send the
        command, its station's next, which the station can take (``max_outstanding``), waiting since
        its submission; ``(station, None)``: poll the station for the reply to a command, due, waiting
        since its DLE ACK.  None: no such work can move now."""
        since = self.write_time(now) - self.line.write_precedence
        found: tuple[float, StationRecord, MasterRequest | None] | None = None
        for station in self.rotation():
            if not station.active:
                continue
            for r in station.awaiting:
                if not r.urgent and r.poll_at <= now and r.write_mark <= since and (
                    found is None or r.write_mark < found[0]
                ):
                    found = (r.write_mark, station, None)
            if station.queue and len(station.awaiting) < station.config.max_outstanding:
                head = station.queue[0]
                if not head.urgent and head.write_mark <= since and (found is None or head.write_mark < found[0]):
                    found = (head.write_mark, station, head)
        return None if found is None else (found[1], found[2])

    def urgent_waiting(self, now: float, besides: int | None = None) -> StationRecord | None:
        """The first station (round robin) with a write that can move now: its reply poll is due,
        or it is queued and the station can take it (``max_outstanding``).  None while other work
        has been held back too long (:meth:`held_back`)."""
        if self.held_back(now) is not None:
            return None
        for station in self.rotation(writes=True):
            if station.number == besides or not station.active:
                continue
            if not any(r.urgent for r in itertools.chain(station.queue, station.awaiting)):
                continue
            if any(r.poll_at <= now for r in station.awaiting) or (
                station.queue and len(station.awaiting) < station.config.max_outstanding
            ):
                return station
        return None

    def mark_overdue(self, now: float) -> None:
        """A request past its reply deadline is polled for once more: its EOT decides."""
        for station in self._stations:
            for request in station.awaiting:
                if now >= request.reply_deadline:
                    request.poll_at = min(request.poll_at, now)

    def next_exchange(self, now: float) -> Exchange | None:
        """The next exchange, or None (then :attr:`wake` says when something falls due).

        Priority: work that writes have kept waiting too long (:meth:`held_back`); a write
        (:meth:`urgent_waiting`): its station's reply poll when due (its reply, or
        the reply of the read that holds its place), else the write; the station of this turn again
        while it has messages; a reply to a slave's own message; then, round robin over the
        stations, a due poll for a reply, a due slow poll of a demoted station or a queued command
        (so a slow station's reply polls cannot starve the others, and busy stations cannot starve
        a demoted one's slow poll: under continuous polling it would never be restored); then
        background polls of active stations (an active station with traffic is polled for its
        replies anyway, and every poll restarts its ``poll_interval``).
        """
        if self._write_since is not None:  # the write's exchange has ended: the line is free
            self._write_time += now - self._write_since
            self._write_since = None
        turn = self.turn_station
        again = self.poll_again
        self.poll_again = False
        held = self.held_back(now)
        if held is not None:
            owner, command = held
            self.serve(owner)
            if command is None:
                return PollStation(owner.number, again=turn == owner.number)
            return SendRequest(owner.queue.popleft())
        station = self.urgent_waiting(now)
        if station is not None:
            self.serve(station, write=True)
            self._write_since = now
            if any(r.poll_at <= now for r in station.awaiting):
                return PollStation(station.number, again=self.turn_station == station.number)
            return SendRequest(station.queue.popleft())
        writing = [s for s in self._stations
                   if s.active and any(r.urgent for r in itertools.chain(s.queue, s.awaiting))]
        if replies := [r.poll_at for s in writing for r in s.awaiting]:
            # A write waits for a reply not due yet (reply_wait): the line stays free for its poll,
            # where other work could take it for an answer timeout.
            self.wake = min(replies)
            return None
        if again and turn is not None and self.turn_polls < self.line.max_messages_per_turn:
            return PollStation(turn, again=True)
        for station in self.rotation():
            if station.active and station.queue and not station.queue[0].expects_reply:
                self.serve(station)  # a slave's MSG waits for this reply: before other work
                return SendRequest(station.queue.popleft())
        wake: list[float] = []
        for station in self.rotation():
            due = [r.poll_at for r in station.awaiting]
            wake += due
            if (due and min(due) <= now) or (not station.active and station.next_poll_at <= now):
                self.serve(station)
                return PollStation(station.number)
            if station.active and station.queue and len(station.awaiting) < station.config.max_outstanding:
                self.serve(station)
                return SendRequest(station.queue.popleft())
        for station in self.rotation():
            if station.next_poll_at <= now:
                self.serve(station)
                return PollStation(station.number)
            wake.append(station.next_poll_at)
        self.wake = min(wake)  # every station that is not due has added its next poll
        return None
