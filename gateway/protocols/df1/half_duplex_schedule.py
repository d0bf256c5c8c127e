"""Which exchange the DF1 half-duplex master runs next (sans-I/O).

The line state machine (``half_duplex.py``) asks :meth:`Scheduler.pick` whenever the line is idle
and carries out the answer: poll a station (:class:`PollNext`), send a queued master message
(:class:`SendNext`), or nothing until a wake time (:class:`Idle`).  The scheduler only reads the
stations' queues and timers; it keeps the round robin and the current station's turn.

Order, first match wins:

1. a write (``urgent``) that can move: its station's reply poll when due (also the poll for the
   read that holds its place under ``max_outstanding``), else the write itself - AG Figure 1.2 (the
   master sends its outgoing messages before it selects the next station to poll), KA p. 11-9.
   Not while other work has waited ``write_precedence``: writes never starve the polls;
2. the station of this turn again, while it has messages (up to ``max_messages_per_turn``);
3. a reply to a slave's own message (its MSG waits for it);
4. round robin: a due poll for a reply, a due slow poll of a demoted station, or a queued command
   (so a slow station's reply polls cannot starve the others, and busy stations cannot starve a
   demoted one's slow poll: under continuous polling it would never be restored);
5. background polls of active stations (an active station with traffic is polled for its replies
   anyway, and every poll restarts its ``poll_interval``).

This module does no I/O.
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass, field

from gateway.protocols.df1.half_duplex_events import LineConfig, StationConfig, StationCounters

__all__ = ["Idle", "PendingRequest", "Pick", "PollNext", "Scheduler", "SendNext", "StationState"]


@dataclass(slots=True)
class PendingRequest:
    """A master message of the line: queued, on the line, or delivered and awaiting its reply."""

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
    queued_at: float = 0.0  #: when it was submitted


@dataclass(slots=True)
class StationState:
    config: StationConfig
    active: bool = True
    failures: int = 0
    queue: deque[PendingRequest] = field(default_factory=deque)
    awaiting: list[PendingRequest] = field(default_factory=list)
    next_poll_at: float = 0.0
    last_head: bytes | None = None
    counters: StationCounters = field(default_factory=StationCounters)


@dataclass(frozen=True, slots=True)
class PollNext:
    station: int
    again: bool  #: one more poll in the station's turn


@dataclass(frozen=True, slots=True)
class SendNext:
    request: PendingRequest  #: already taken off its station's queue


@dataclass(frozen=True, slots=True)
class Idle:
    wake: float | None  #: when something falls due; None: only an input can start work


Pick = PollNext | SendNext | Idle


class Scheduler:
    """The master's choice of the next exchange (module docstring)."""

    def __init__(self, line: LineConfig, stations: dict[int, StationState], order: list[int]) -> None:
        self.line = line
        self.stations = stations
        self.order = order
        self.rr = 0
        self.turn_station: int | None = None
        self.turn_polls = 0
        self.poll_again = False  #: set by the line after an answer that may be followed by more

    def polled(self, number: int, *, again: bool) -> None:
        """The line sends a poll to ``number`` (``again``: within its turn)."""
        if not again or self.turn_station != number:
            self.turn_station = number
            self.turn_polls = 0
        self.turn_polls += 1

    def urgent_waiting(self, now: float, besides: int | None = None) -> StationState | None:
        """The first station (round robin) with a write that can move now: its reply poll is due,
        or it is queued and the station can take it (``max_outstanding``).  None while other work
        has been held back too long (:meth:`held_back`)."""
        if self.held_back(now):
            return None
        for station in self._rotation():
            if station.config.station == besides or not station.active:
                continue
            if not any(r.urgent for r in itertools.chain(station.queue, station.awaiting)):
                continue
            if any(r.poll_at <= now for r in station.awaiting) or (
                station.queue and len(station.awaiting) < station.config.max_outstanding
            ):
                return station
        return None

    def held_back(self, now: float) -> bool:
        """Other work has waited ``write_precedence`` for writes: it goes next."""
        since = now - self.line.write_precedence
        for station in self.stations.values():
            if not station.active:
                continue
            if any(not r.urgent and r.queued_at <= since for r in station.queue):
                return True
            if any(not r.urgent and r.poll_at <= since for r in station.awaiting):
                return True
        return False

    def pick(self, now: float) -> Pick:
        turn = self.turn_station
        again = self.poll_again
        self.poll_again = False
        station = self.urgent_waiting(now)
        if station is not None:
            self._serve(station)
            if any(r.poll_at <= now for r in station.awaiting):
                return PollNext(station.config.station, self.turn_station == station.config.station)
            return SendNext(station.queue.popleft())
        if again and turn is not None and self.turn_polls < self.line.max_messages_per_turn:
            return PollNext(turn, True)
        for station in self._rotation():
            if station.active and station.queue and not station.queue[0].expects_reply:
                self._serve(station)
                return SendNext(station.queue.popleft())
        wake: list[float] = []
        for station in self._rotation():
            due = [r.poll_at for r in station.awaiting]
            wake += due + [r.reply_deadline for r in station.awaiting if r.poll_at < r.reply_deadline]
            if (due and min(due) <= now) or (not station.active and station.next_poll_at <= now):
                self._serve(station)
                return PollNext(station.config.station, False)
            if station.active and station.queue and len(station.awaiting) < station.config.max_outstanding:
                self._serve(station)
                return SendNext(station.queue.popleft())
        for station in self._rotation():
            if station.next_poll_at <= now:
                self._serve(station)
                return PollNext(station.config.station, False)
            wake.append(station.next_poll_at)
        return Idle(min(wake) if wake else None)

    def _rotation(self) -> list[StationState]:
        order = self.order[self.rr :] + self.order[: self.rr]
        return [self.stations[number] for number in order]

    def _serve(self, station: StationState) -> None:
        self.rr = (self.order.index(station.config.station) + 1) % len(self.order)
