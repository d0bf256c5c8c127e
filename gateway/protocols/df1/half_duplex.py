"""DF1 half-duplex master: one master owns one line and polls several slave stations (sans-I/O).

Manual: A-B 1770-6.5.16 chapter 3 and p. 5-2; 1775-KA p. 11-9 .. 11-17 and 1770-KF2 p. 4-26 .. 4-33
(the same chapter); SLC 500 1747-RM001 p. 13-56 .. 13-68 (master parameters).  The reading, and
every point the manuals leave open, is in ``docs/df1-half-duplex-notes.md``.

What the core does
------------------
* A command (a PCCC packet ``DST SRC CMD STS TNS ...``) submitted for a station is sent as a master
  message ``DLE SOH STN DLE STX ... DLE ETX check``; without a ``DLE ACK`` within the ACK timeout the
  *identical* bytes are sent again (same TNS, so a slave with duplicate detection executes it once),
  at most ``message_resends`` times.
* After the ACK the master waits ``reply_wait`` and polls the station (``DLE ENQ STN BCC``) until
  the reply comes: a slave message of the polled station that ``pccc.reply_matches`` the command
  (same TNS, CMD + 40 hex; DST / SRC are not compared, see there).  Each ``DLE EOT`` counts one
  poll; after ``max_polls`` of them the request fails, and so it does at the first EOT after
  ``reply_timeout`` from the ACK.  The deadline itself only makes the reply's poll due: while the
  line was busy with other stations the reply may be waiting in the slave, and only its EOT says
  it is not.  A reply
  is only ever matched against the requests of the station that was polled, so it cannot be
  attributed to another station.
* Every good slave message is acknowledged with ``DLE ACK`` and the station is polled again (up to
  ``max_messages_per_turn``), until it answers ``DLE EOT``.  A repeat of the last message's first six
  bytes before an EOT is the slave resending because our ACK was lost: ACKed and discarded
  (KA p. 11-17).  A bad slave frame is not acknowledged (never NAKed: on half duplex DLE NAK is the
  master's global link reset, Table 2.C) and the station is polled again (KA Figure 11.8).
* Between commands every station is polled every ``poll_interval`` for the messages it initiates.
  An answerless poll, or a master message without its DLE ACK (each copy sent), is one failure;
  ``demote_after`` failures in a row (no answer of any kind between them) demote a station: its
  requests fail at once and it is polled every ``slow_poll_interval`` until it answers (Kepware's
  auto-demotion; KA p. 11-9 "poll the inactive slaves occasionally").
* Writes first: a command submitted ``urgent`` (a write, or its read-back) is queued ahead of its
  station's other commands and goes before other stations' work - its station's reply poll when
  due (also for the read that holds its place under ``max_outstanding``), else the write itself;
  an unacknowledged copy of another station's message waits for it.  AG Figure 1.2 (the master
  checks for and sends its outgoing messages before it selects the next station to poll); KA
  p. 11-9.  Work that has waited ``write_precedence`` goes before the next write, so writes never
  starve the polls that keep every station's data fresh.
* Timing: the line is quiet ``pre_transmit_delay`` after the last byte heard before the master
  transmits; ``rts`` goes true ``rts_send_delay`` before the first byte and false ``rts_off_delay``
  after the last one (transmission time = bytes x ``char_time``); answer timers start when the last
  byte has left.  These are deadlines, never sleeps.
* Echo suppression (2-wire RS-485): with ``echo`` the master expects to hear its own bytes first and
  strips them; a byte that differs is a collision, counted, and the exchange runs into its timeout.

The driver loop: ``start(now)`` once; then ``receive_data(data, now)``; ``data_to_send()``; set RTS
from ``rts``; sleep until ``next_deadline()``; ``handle_timeout(now)``; ``next_event()`` until
``NEED_DATA``.

This module does no I/O.
"""

from __future__ import annotations

import enum
import itertools
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    EotReceived,
    Frame,
    MasterMessage,
    NakReceived,
    NeedData,
    Poll,
    encode_master_message,
    encode_poll,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.half_duplex_events import (
    FailReason,
    LineConfig,
    MasterEvent,
    MessageDelivered,
    ReplyReceived,
    RequestFailed,
    SlaveInitiated,
    StationConfig,
    StationCounters,
    StationDemoted,
    StationRestored,
    StrayReply,
)
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, PcccHeader, reply_matches
from gateway.protocols.df1.pccc.codes import REPLY_BIT

__all__ = [
    "NEED_DATA",
    "FailReason",
    "HalfDuplexMaster",
    "LineConfig",
    "LineState",
    "MasterEvent",
    "MessageDelivered",
    "ReplyReceived",
    "RequestFailed",
    "SlaveInitiated",
    "StationConfig",
    "StationCounters",
    "StationDemoted",
    "StationRestored",
    "StrayReply",
]

#: The first six bytes of a message (DST SRC CMD STS TNS) identify it for duplicate detection.
_HEAD: Final = 6


# ------------------------------------------------------------------------------- state machine


class LineState(enum.Enum):
    IDLE = "idle"  #: nothing on the line; the scheduler picks the next exchange
    TRANSMIT = "transmit"  #: bytes waiting for the line to be quiet and RTS key-up
    WAIT_ACK = "wait-ack"  #: master message sent, waiting for DLE ACK
    WAIT_POLL = "wait-poll"  #: poll sent, waiting for a message or DLE EOT


class Input(enum.Enum):
    TX_READY = "tx-ready"
    TIMEOUT = "timeout"
    ACK = "ack"
    NAK = "nak"
    EOT = "eot"
    MESSAGE = "message"
    BAD = "bad"


@dataclass(slots=True)
class _Request:
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
class _Station:
    config: StationConfig
    active: bool = True
    failures: int = 0
    queue: deque[_Request] = field(default_factory=deque)
    awaiting: list[_Request] = field(default_factory=list)
    next_poll_at: float = 0.0
    last_head: bytes | None = None
    counters: StationCounters = field(default_factory=StationCounters)


class HalfDuplexMaster:
    """The master side of a DF1 half-duplex line (see the module docstring)."""

    def __init__(self, line: LineConfig, stations: list[StationConfig]) -> None:
        numbers = [s.station for s in stations]
        if len(set(numbers)) != len(numbers):
            raise ValueError(f"station numbers must be unique on a line, got {sorted(numbers)}")
        if not stations:
            raise ValueError("a half-duplex line needs at least one station")
        self.line: Final = line
        self._stations: dict[int, _Station] = {s.station: _Station(s) for s in stations}
        self._order: Final = numbers
        self._decoder = FrameDecoder(line.checksum, half_duplex=True)
        self._state = LineState.IDLE
        self._out = bytearray()
        self._events: deque[MasterEvent] = deque()
        self._ids = itertools.count(1)
        self._echo = bytearray()
        self._quiet_until = float("-inf")
        self._pending: bytes = b""  #: bytes of the exchange in TRANSMIT
        self._after: LineState = LineState.IDLE  #: state once _pending is on the wire
        self._tx_at = 0.0
        self._deadline: float | None = None
        self._wake: float | None = None  #: IDLE: when the scheduler has something due
        self._rts_on_at: float | None = None
        self._rts_off_at: float | None = None
        self.rts = False
        self._current: int | None = None  #: station of the exchange in progress
        self._request: _Request | None = None  #: master message in progress
        self._turn_station: int | None = None
        self._turn_polls = 0
        self._poll_again = False
        self._reset_pending = False
        self._rr = 0
        self._message = b""  #: the slave message being handled
        self._grace_used = False  #: the answer deadline was extended once for a frame in progress
        self.collisions = 0
        self.ignored = 0

    # ----------------------------------------------------------------------------- public API

    @property
    def state(self) -> LineState:
        return self._state

    def counters(self, station: int) -> StationCounters:
        return self._stations[station].counters

    def is_active(self, station: int) -> bool:
        return self._stations[station].active

    def start(self, now: float, *, link_reset: bool = False) -> None:
        """Begin polling.  ``link_reset``: first send DLE NAK, as a master does at power-up (Table 2.C)."""
        if link_reset:
            self._reset_pending = True
        self._kick(now)

    def submit(self, station: int, message: bytes, now: float, *, urgent: bool = False) -> int:
        """Queue a command packet for ``station``; returns the request id used in its events.

        ``urgent`` (a write, or the read-back of one): queued ahead of the station's other commands
        and served before other stations' work (see :meth:`_schedule`)."""
        target = self._stations.get(station)
        if target is None:
            raise ValueError(f"station {station} is not on this line (stations: {self._order})")
        if len(message) < _HEAD:
            raise ValueError("a command packet has at least DST SRC CMD STS TNS (6 bytes)")
        tns = message[4:6]
        for other in self._stations.values():
            if any(r.expects_reply and r.message[4:6] == tns for r in itertools.chain(other.queue, other.awaiting)):
                raise ValueError(f"TNS {tns.hex()} is already in use on this line; allocate TNS per line")
        current = self._request
        if current is not None and current.expects_reply and current.message[4:6] == tns:
            raise ValueError(f"TNS {tns.hex()} is already in use on this line; allocate TNS per line")
        request_id = next(self._ids)
        if not target.active:
            self._events.append(RequestFailed(request_id, station, FailReason.STATION_DEMOTED, False))
            return request_id
        frame = encode_master_message(station, message, self.line.checksum)
        request = _Request(request_id, station, message, frame, urgent=urgent, queued_at=now)
        if urgent:
            # behind the replies to the slave's own messages and the urgent requests already queued
            at = next((i for i, r in enumerate(target.queue) if r.expects_reply and not r.urgent), len(target.queue))
            target.queue.insert(at, request)
        else:
            target.queue.append(request)
        self._kick(now)
        return request_id

    def send_reply(self, station: int, message: bytes, now: float) -> int:
        """Queue the PCCC reply to a command ``station`` initiated (:class:`SlaveInitiated`).

        Sent as a master message (``DLE SOH STN ...``; 1770-6.5.16 p. 5-2) ahead of the station's
        queued commands, resent identically while its DLE ACK is missing, as a command is; nothing is
        polled for.  Events: :class:`MessageDelivered` at the ACK, else ``RequestFailed(NO_ACK)``.
        The TNS is the slave's own (its MSG's), so it is not checked against the line's TNS.
        """
        target = self._stations.get(station)
        if target is None:
            raise ValueError(f"station {station} is not on this line (stations: {self._order})")
        if len(message) < _HEAD:
            raise ValueError("a reply packet has at least DST SRC CMD STS TNS (6 bytes)")
        request_id = next(self._ids)
        frame = encode_master_message(station, message, self.line.checksum)
        target.queue.appendleft(_Request(request_id, station, message, frame, expects_reply=False))
        self._kick(now)
        return request_id

    def reset_link(self, now: float) -> None:
        """Send DLE NAK, the global link reset (Table 2.C): slaves drop their queued messages."""
        self._reset_pending = True
        self._kick(now)

    def data_to_send(self) -> bytes:
        data = bytes(self._out)
        self._out.clear()
        return data

    def next_event(self) -> MasterEvent | NeedData:
        return self._events.popleft() if self._events else NEED_DATA

    def next_deadline(self) -> float | None:
        times = [t for t in (self._rts_on_at, self._rts_off_at) if t is not None]
        if self._state is LineState.TRANSMIT:
            times.append(self._tx_at)
        elif self._state is LineState.IDLE:
            if self._wake is not None:
                times.append(self._wake)
        elif self._deadline is not None:
            times.append(self._deadline)
        return min(times) if times else None

    def handle_timeout(self, now: float) -> None:
        self._update_rts(now)
        if self._state is LineState.TRANSMIT and now >= self._tx_at:
            self._step(Input.TX_READY, now)
        elif self._state in (LineState.WAIT_ACK, LineState.WAIT_POLL):
            if self._deadline is not None and now >= self._deadline:
                if self._decoder.in_frame and not self._grace_used:
                    # An answer is arriving: let it finish rather than meet it in the next exchange.
                    self._grace_used = True
                    self._deadline = now + self._answer_timeout()
                    return
                self._decoder.reset()
                self._step(Input.TIMEOUT, now)
        elif self._state is LineState.IDLE:
            self._schedule(now)

    def receive_data(self, data: bytes, now: float) -> None:
        if self._echo:
            same = 0
            limit = min(len(data), len(self._echo))
            while same < limit and data[same] == self._echo[same]:
                same += 1
            if same < limit:  # our own bytes came back different: a collision
                self.collisions += 1
                self._echo.clear()
            else:
                del self._echo[:same]
            data = data[same:]
        if not data:
            return
        self._quiet_until = max(self._quiet_until, now + self.line.pre_transmit_delay)
        if self._state is LineState.TRANSMIT:
            self._tx_at = max(self._tx_at, self._quiet_until + self.line.rts_send_delay)
        self._decoder.feed(data)
        while (event := self._decoder.next_event()) is not NEED_DATA:
            if isinstance(event, Frame):
                self._message = event.message
                self._step(Input.MESSAGE, now)
            elif isinstance(event, EotReceived):
                self._step(Input.EOT, now)
            elif isinstance(event, AckReceived):
                self._step(Input.ACK, now)
            elif isinstance(event, NakReceived):
                self._step(Input.NAK, now)
            elif isinstance(event, BadFrame) and not event.master:
                self._step(Input.BAD, now)
            elif isinstance(event, Poll | MasterMessage | BadFrame):
                self.ignored += 1  # another master's frame, or our own echo without echo mode

    # --------------------------------------------------------------------------- the table

    def _step(self, what: Input, now: float) -> None:
        handler = _TRANSITIONS.get((self._state, what))
        if handler is None:
            self.ignored += 1
            return
        handler(self, now)
        if self._state is LineState.IDLE:
            self._schedule(now)

    def _on_tx_ready(self, now: float) -> None:
        data = self._pending
        self._pending = b""
        self._out += data
        if self.line.echo:
            self._echo += data
        end = now + len(data) * self.line.char_time
        self._rts_off_at = end + self.line.rts_off_delay
        self._quiet_until = max(self._quiet_until, self._rts_off_at)
        self._update_rts(now)
        self._state = self._after
        self._grace_used = False
        self._deadline = None if self._state is LineState.IDLE else end + self._answer_timeout()

    def _answer_timeout(self) -> float:
        if self._state is LineState.WAIT_ACK:
            return self.line.ack_timeout
        assert self._current is not None
        return self._stations[self._current].config.poll_timeout

    def _on_acked(self, now: float) -> None:
        request = self._take_request()
        station = self._stations[request.station]
        self._answered(station)
        if not request.expects_reply:
            self._events.append(MessageDelivered(request.request_id, request.station))
            self._state = LineState.IDLE
            return
        request.poll_at = now + station.config.reply_wait
        request.reply_deadline = now + station.config.reply_timeout
        station.awaiting.append(request)
        self._state = LineState.IDLE

    def _on_naked(self, now: float) -> None:
        """DLE NAK from a slave (not the manual's: see the module docstring): it heard us; resend."""
        request = self._request
        assert request is not None
        self._answered(self._stations[request.station])
        self._resend_or_fail(request, now)

    def _on_ack_timeout(self, now: float) -> None:
        """No DLE ACK: an answerless exchange, counted towards demotion like a silent poll."""
        request = self._request
        assert request is not None
        station = self._stations[request.station]
        station.counters.timeouts += 1
        self._failed(station, now)
        if not station.active:
            self._take_request()
            self._events.append(RequestFailed(request.request_id, request.station, FailReason.NO_ACK, True))
            self._state = LineState.IDLE
            return
        self._resend_or_fail(request, now)

    def _resend_or_fail(self, request: _Request, now: float) -> None:
        station = self._stations[request.station]
        if request.sends <= self.line.message_resends:
            station.counters.resends += 1
            if not request.urgent and self._urgent_waiting(now, besides=request.station):
                # A write waits at another station: it goes first, this copy at the station's next
                # turn.  Other stations' frames do not reach this slave, so its duplicate detection
                # still sees the identical copy next.
                self._take_request()
                station.queue.appendleft(request)
                self._state = LineState.IDLE
                return
            self._send_message(request, now)  # the identical bytes: same TNS
            return
        self._take_request()
        self._events.append(RequestFailed(request.request_id, request.station, FailReason.NO_ACK, True))
        self._state = LineState.IDLE

    def _on_eot(self, now: float) -> None:
        station = self._polled()
        station.counters.eots += 1
        self._answered(station)
        station.last_head = None  # no resend can follow an EOT (KA p. 11-17)
        for request in list(station.awaiting):
            request.polls += 1
            if request.polls >= station.config.max_polls or now >= request.reply_deadline:
                self._fail_awaiting(station, request, FailReason.NO_REPLY)
        self._poll_again = False
        self._state = LineState.IDLE

    def _on_message(self, now: float) -> None:
        station = self._polled()
        message = self._message
        self._answered(station)
        self._poll_again = True
        self._transmit(ACK_SYMBOL, LineState.IDLE, now)
        head = message[:_HEAD]
        if head == station.last_head:
            station.counters.duplicates += 1
            return
        station.last_head = head
        station.counters.messages_received += 1
        number = station.config.station
        if len(message) >= HEADER_SIZE and message[2] & REPLY_BIT:
            reply = PcccHeader.decode(message)
            for request in station.awaiting:
                if reply_matches(request.message, reply):
                    station.awaiting.remove(request)
                    self._events.append(ReplyReceived(request.request_id, number, message))
                    return
            self._events.append(StrayReply(number, message))
        else:
            self._events.append(SlaveInitiated(number, message))

    def _on_bad_answer(self, now: float) -> None:
        station = self._polled()
        station.counters.bad_frames += 1
        self._poll_again = True  # not acknowledged: the slave resends at the next poll
        self._state = LineState.IDLE

    def _on_poll_timeout(self, now: float) -> None:
        station = self._polled()
        station.counters.timeouts += 1
        self._poll_again = station.active
        self._failed(station, now)
        self._state = LineState.IDLE

    # ------------------------------------------------------------------------------ helpers

    def _polled(self) -> _Station:
        assert self._current is not None
        return self._stations[self._current]

    def _take_request(self) -> _Request:
        request = self._request
        assert request is not None
        self._request = None
        return request

    def _answered(self, station: _Station) -> None:
        station.failures = 0
        if not station.active:
            station.active = True
            station.next_poll_at = 0.0
            self._events.append(StationRestored(station.config.station))

    def _failed(self, station: _Station, now: float) -> None:
        station.failures += 1
        if station.active and station.failures >= station.config.demote_after:
            station.active = False
            station.next_poll_at = now + station.config.slow_poll_interval
            station.counters.demotions += 1
            self._poll_again = False
            self._events.append(StationDemoted(station.config.station))
            while station.queue:
                request = station.queue.popleft()
                self._events.append(
                    RequestFailed(request.request_id, request.station, FailReason.STATION_DEMOTED, False)
                )
            for request in list(station.awaiting):
                self._fail_awaiting(station, request, FailReason.STATION_DEMOTED)

    def _fail_awaiting(self, station: _Station, request: _Request, reason: FailReason) -> None:
        station.awaiting.remove(request)
        self._events.append(RequestFailed(request.request_id, request.station, reason, True))

    def _update_rts(self, now: float) -> None:
        if self._rts_off_at is not None and now >= self._rts_off_at:
            self.rts = False
            self._rts_off_at = None
        if self._rts_on_at is not None and now >= self._rts_on_at:
            self.rts = True
            self._rts_on_at = None

    def _transmit(self, data: bytes, after: LineState, now: float) -> None:
        start = max(now, self._quiet_until)
        self._pending = data
        self._after = after
        self._state = LineState.TRANSMIT
        self._deadline = None
        self._tx_at = start + self.line.rts_send_delay
        if start <= now:
            self.rts = True
            self._rts_off_at = None
        else:
            self._rts_on_at = start  # after the previous RTS off (start >= quiet_until >= it)
        if self._tx_at <= now:
            self._on_tx_ready(now)

    def _send_poll(self, number: int, now: float, *, again: bool = False) -> None:
        station = self._stations[number]
        station.counters.polls += 1
        interval = station.config.poll_interval if station.active else station.config.slow_poll_interval
        station.next_poll_at = now + interval
        if not again or self._turn_station != number:
            self._turn_station = number
            self._turn_polls = 0
        self._turn_polls += 1
        self._current = number
        self._transmit(encode_poll(number), LineState.WAIT_POLL, now)

    def _send_message(self, request: _Request, now: float) -> None:
        request.sends += 1
        self._stations[request.station].counters.messages_sent += 1
        self._request = request
        self._current = request.station
        self._transmit(request.frame, LineState.WAIT_ACK, now)

    def _kick(self, now: float) -> None:
        if self._state is LineState.IDLE:
            self._schedule(now)

    def _rotation(self) -> list[_Station]:
        order = self._order[self._rr :] + self._order[: self._rr]
        return [self._stations[number] for number in order]

    def _serve(self, station: _Station) -> None:
        self._rr = (self._order.index(station.config.station) + 1) % len(self._order)

    def _schedule(self, now: float) -> None:
        """IDLE: pick the next exchange.

        Priority: a pending link reset; the station of this turn again while it has messages; then,
        round robin over the stations, a due poll for a reply, a due slow poll of a demoted
        station or a queued command (so a slow station's reply polls cannot starve the others, and
        busy stations cannot starve a demoted one's slow poll: under continuous polling it would
        never be restored); then background polls of active stations (an active station with
        traffic is polled for its replies anyway, and every poll restarts its ``poll_interval``).
        """
        while self._state is LineState.IDLE:
            self._wake = None
            self._current = None
            for station in self._stations.values():
                for request in station.awaiting:
                    if now >= request.reply_deadline:
                        request.poll_at = min(request.poll_at, now)  # ask once more: the EOT decides
            if self._reset_pending:
                self._reset_pending = False
                self._reset_all()
                self._transmit(NAK_SYMBOL, LineState.IDLE, now)
                continue
            if not self._pick(now):
                return

    def _held_back(self, now: float) -> bool:
        """Other work has waited ``write_precedence`` for writes: it goes next (writes cannot starve
        the polls that keep every station's data fresh)."""
        since = now - self.line.write_precedence
        for station in self._stations.values():
            if not station.active:
                continue
            if any(not r.urgent and r.queued_at <= since for r in station.queue):
                return True
            if any(not r.urgent and r.poll_at <= since for r in station.awaiting):
                return True
        return False

    def _urgent_waiting(self, now: float, besides: int | None = None) -> _Station | None:
        """The first station (round robin) with a write that can move now: its reply poll is due,
        or it is queued and the station can take it (``max_outstanding``).  None while other work
        has been held back too long (:meth:`_held_back`)."""
        if self._held_back(now):
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

    def _pick_urgent(self, now: float) -> bool:
        """A write (or its read-back) goes before other stations' work: the station's reply poll
        when due (its reply, or the reply of the read that holds its place), else the queued write."""
        station = self._urgent_waiting(now)
        if station is None:
            return False
        self._serve(station)
        if any(r.poll_at <= now for r in station.awaiting):
            self._send_poll(station.config.station, now, again=self._turn_station == station.config.station)
        else:
            self._send_message(station.queue.popleft(), now)
        return True

    def _pick(self, now: float) -> bool:
        turn = self._turn_station
        again = self._poll_again
        self._poll_again = False
        if self._pick_urgent(now):
            return True
        if again and turn is not None and self._turn_polls < self.line.max_messages_per_turn:
            self._send_poll(turn, now, again=True)
            return True
        for station in self._rotation():
            if station.active and station.queue and not station.queue[0].expects_reply:
                self._serve(station)  # a slave's MSG waits for this reply: before other work
                self._send_message(station.queue.popleft(), now)
                return True
        wake: list[float] = []
        for station in self._rotation():
            due = [r.poll_at for r in station.awaiting]
            wake += due + [r.reply_deadline for r in station.awaiting if r.poll_at < r.reply_deadline]
            if (due and min(due) <= now) or (not station.active and station.next_poll_at <= now):
                self._serve(station)
                self._send_poll(station.config.station, now)
                return True
            if station.active and station.queue and len(station.awaiting) < station.config.max_outstanding:
                self._serve(station)
                self._send_message(station.queue.popleft(), now)
                return True
        for station in self._rotation():
            if station.next_poll_at <= now:
                self._serve(station)
                self._send_poll(station.config.station, now)
                return True
            wake.append(station.next_poll_at)
        self._wake = min(wake) if wake else None
        return False

    def _reset_all(self) -> None:
        """After DLE NAK the slaves' queues are empty: requests awaiting a reply will get none."""
        for station in self._stations.values():
            station.last_head = None
            for request in list(station.awaiting):
                self._fail_awaiting(station, request, FailReason.LINK_RESET)


_Handler = Callable[[HalfDuplexMaster, float], None]

#: (state, input) -> handler.  Pairs not listed are ignored (counted in ``ignored``): an ACK while
#: polling, a slave message while waiting for an ACK (a slave must not send unpolled), and so on.
_TRANSITIONS: Final[dict[tuple[LineState, Input], _Handler]] = {
    (LineState.TRANSMIT, Input.TX_READY): HalfDuplexMaster._on_tx_ready,
    (LineState.WAIT_ACK, Input.ACK): HalfDuplexMaster._on_acked,
    (LineState.WAIT_ACK, Input.NAK): HalfDuplexMaster._on_naked,
    (LineState.WAIT_ACK, Input.TIMEOUT): HalfDuplexMaster._on_ack_timeout,
    (LineState.WAIT_POLL, Input.EOT): HalfDuplexMaster._on_eot,
    (LineState.WAIT_POLL, Input.MESSAGE): HalfDuplexMaster._on_message,
    (LineState.WAIT_POLL, Input.BAD): HalfDuplexMaster._on_bad_answer,
    (LineState.WAIT_POLL, Input.NAK): HalfDuplexMaster._on_bad_answer,
    (LineState.WAIT_POLL, Input.TIMEOUT): HalfDuplexMaster._on_poll_timeout,
}
