"""DF1 half-duplex master: one master owns one line and polls several slave stations (sans-I/O).

Manual: A-B 1770-6.5.16 chapter 3 and p. 5-2; 1775-KA p. 11-9 .. 11-17 and 1770-KF2 p. 4-26 .. 4-33
(the same chapter); SLC 500 1747-RM001 p. 13-56 .. 13-68 (master parameters).  The reading, and
every point the manuals leave open, is in ``docs/develop/df1-half-duplex-notes.md``.

What the core does
------------------
* A command (a PCCC packet ``DST SRC CMD STS TNS ...``) submitted for a station is sent as a master
  message ``DLE SOH STN DLE STX ... DLE ETX check``; without a ``DLE ACK`` within the ACK timeout the
  *identical* bytes are sent again (same TNS, so a slave with duplicate detection executes it once),
  at most ``message_resends`` times.
* After the ACK the master waits ``reply_wait`` and polls the station (``DLE ENQ STN BCC``) until
  the reply comes: a slave message of the polled station that ``pccc.reply_matches`` the command
  (same TNS, CMD + 40 hex; DST / SRC are not compared, see there).  Each ``DLE EOT`` counts one
  poll and makes the next poll for the reply wait ``reply_wait`` again (a controller answers at the
  end of its scan: polled at once, it would answer EOT after EOT, each poll one more chance of a
  lost frame and a poll timeout); after ``max_polls`` of them the request fails, and so it does at the first EOT after
  ``reply_timeout`` from the ACK.  The deadline itself only makes the reply's poll due: while the
  line was busy with other stations the reply may be waiting in the slave, and only its EOT says
  it is not.  A reply is only ever matched against the requests of the station that was polled,
  so it cannot be attributed to another station.
* Every good slave message is acknowledged with ``DLE ACK`` and the station is polled again (up to
  ``max_messages_per_turn``), until it answers ``DLE EOT``.  A repeat of the last message's first six
  bytes before an EOT is the slave resending because our ACK was lost: ACKed and discarded
  (KA p. 11-17).  A bad slave frame is not acknowledged (never NAKed: on half duplex DLE NAK is the
  master's global link reset, Table 2.C) and the station is polled again (KA Figure 11.8).
* Which exchange comes next - writes first, round robin, background and slow polls, demotion
  after ``demote_after`` failures in a row - is ``schedule.py``'s.
* When bytes may go (quiet time, RTS keying) and echo suppression are ``transmitter.py``'s;
  answer timers start when the last byte has left, and a collision runs the exchange into its timeout.

Every change of :class:`LineState` is an entry of :data:`TRANSITIONS`: (state, input) -> (action,
next state); the scheduler picking the next exchange of a free line is the input ``SCHEDULE``.
The driver loop: ``start(now)`` once; then ``receive_data(data, now)``; ``data_to_send()``; set RTS
from ``rts``; sleep until ``next_deadline()``; ``handle_timeout(now)``; ``next_event()`` until ``NEED_DATA``.

This module does no I/O.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable
from typing import Final

from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    BadFrame,
    EotReceived,
    Frame,
    NakReceived,
    NeedData,
    encode_master_message,
    encode_poll,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.half_duplex.events import (
    FailReason,
    LineConfig,
    MasterEvent,
    MessageDelivered,
    RequestFailed,
    StationConfig,
    StationCounters,
)
from gateway.protocols.df1.half_duplex.schedule import (
    ExchangeScheduler,
    LineStations,
    MasterRequest,
    PollStation,
    StationRecord,
)
from gateway.protocols.df1.half_duplex.transmitter import HalfDuplexTransmitter
from gateway.protocols.df1.pccc.codec import duplicate_key
from gateway.protocols.transitions import Table, TableEnum, Transition, require_complete, stay

__all__ = ["TRANSITIONS", "HalfDuplexMaster", "LineState", "MasterAction", "MasterInput"]


class LineState(TableEnum):
    IDLE = "idle"  #: nothing on the line; the scheduler picks the next exchange
    TRANSMIT = "transmit"  #: bytes waiting for the line to be quiet and RTS key-up
    WAIT_ACK = "wait-ack"  #: master message sent, waiting for DLE ACK
    WAIT_POLL = "wait-poll"  #: poll sent, waiting for a message or DLE EOT


class MasterInput(TableEnum):
    SCHEDULE = "the line is free: the scheduler may start an exchange"
    SEND_MESSAGE = "the line is ready for the pending master message"
    SEND_POLL = "the line is ready for the pending poll"
    SEND_SYMBOL = "the line is ready for the pending DLE ACK / DLE NAK"
    TIMEOUT = "no answer in time"
    ACK = "DLE ACK"
    NAK = "DLE NAK"
    EOT = "DLE EOT"
    MESSAGE = "a slave message with a good check"
    BAD = "a damaged slave frame"


class MasterAction(TableEnum):
    SCHEDULE = "start the next exchange, if one is due"
    SEND = "put the pending bytes on the line; start the answer timer"
    ACKED = "the master message arrived: wait for its reply (or report it delivered)"
    NAKED = "the slave heard the master message: send it again, or fail it"
    ACK_TIMEOUT = "no DLE ACK: one failure of the station; send the message again, or fail it"
    EOT = "the slave has nothing to send: count a poll of its awaited replies"
    MESSAGE = "acknowledge the slave message and deliver it (a reply, or the slave's own command)"
    BAD_ANSWER = "a damaged answer: poll the station again"
    POLL_TIMEOUT = "no answer to the poll: one failure of the station"
    IGNORE = "nothing (counted in ``ignored``)"


def _master_table() -> Table[LineState, MasterInput, MasterAction]:
    T, L, In, A = Transition, LineState, MasterInput, MasterAction
    # an action that sends (again) moves on to TRANSMIT, or at once past it when the line is ready
    sent = frozenset({L.TRANSMIT, L.WAIT_ACK, L.WAIT_POLL})
    sending = (In.SEND_MESSAGE, In.SEND_POLL, In.SEND_SYMBOL)
    answers = (In.ACK, In.NAK, In.EOT, In.MESSAGE, In.BAD)

    return {
        (L.IDLE, In.SCHEDULE): T(A.SCHEDULE, L.IDLE, sent),
        # nothing asked, nothing held, no timer: a stray symbol or frame, or another master's
        **stay(A.IGNORE, L.IDLE, *sending, In.TIMEOUT, *answers),
        (L.TRANSMIT, In.SEND_MESSAGE): T(A.SEND, L.WAIT_ACK),
        (L.TRANSMIT, In.SEND_POLL): T(A.SEND, L.WAIT_POLL),
        (L.TRANSMIT, In.SEND_SYMBOL): T(A.SEND, L.IDLE),
        # the line is not free and nothing of ours is out yet: what is heard answers nothing
        **stay(A.IGNORE, L.TRANSMIT, In.SCHEDULE, In.TIMEOUT, *answers),
        (L.WAIT_ACK, In.ACK): T(A.ACKED, L.IDLE),
        (L.WAIT_ACK, In.NAK): T(A.NAKED, L.IDLE, frozenset({L.TRANSMIT, L.WAIT_ACK})),
        (L.WAIT_ACK, In.TIMEOUT): T(A.ACK_TIMEOUT, L.IDLE, frozenset({L.TRANSMIT, L.WAIT_ACK})),
        # a slave must not send unpolled (nor DLE EOT)
        **stay(A.IGNORE, L.WAIT_ACK, In.SCHEDULE, *sending, In.EOT, In.MESSAGE, In.BAD),
        (L.WAIT_POLL, In.EOT): T(A.EOT, L.IDLE),
        (L.WAIT_POLL, In.MESSAGE): T(A.MESSAGE, L.TRANSMIT, frozenset({L.IDLE})),  # our DLE ACK
        (L.WAIT_POLL, In.BAD): T(A.BAD_ANSWER, L.IDLE),
        (L.WAIT_POLL, In.NAK): T(A.BAD_ANSWER, L.IDLE),
        (L.WAIT_POLL, In.TIMEOUT): T(A.POLL_TIMEOUT, L.IDLE),
        # a poll is not acknowledged
        **stay(A.IGNORE, L.WAIT_POLL, In.SCHEDULE, *sending, In.ACK),
    }


#: The master's state machine: (state, input) -> (action, next state or the states it may choose).
TRANSITIONS: Final = _master_table()
require_complete(TRANSITIONS, LineState, MasterInput, "half-duplex master")

#: The input that puts the pending bytes on the line, by the state they lead to.
_SEND_INPUT: Final = {
    LineState.WAIT_ACK: MasterInput.SEND_MESSAGE,
    LineState.WAIT_POLL: MasterInput.SEND_POLL,
    LineState.IDLE: MasterInput.SEND_SYMBOL,
}


class HalfDuplexMaster:
    """The master side of a DF1 half-duplex line (see the module docstring)."""

    def __init__(self, line: LineConfig, stations: list[StationConfig]) -> None:
        self.line: Final = line
        self._stations: Final = LineStations(stations)
        self._scheduler: Final = ExchangeScheduler(line, self._stations)
        self._decoder = FrameDecoder(line.checksum, half_duplex=True)
        self._tx: Final = HalfDuplexTransmitter(line)
        self._state = LineState.IDLE
        self._events: deque[MasterEvent] = deque()
        self._ids = itertools.count(1)
        self._send_input = MasterInput.SEND_SYMBOL  #: the input that sends the bytes held in TRANSMIT
        self._deadline: float | None = None
        self._wake: float | None = None  #: IDLE: when the scheduler has something due
        self._current: int | None = None  #: station of the poll in progress
        self._request: MasterRequest | None = None  #: master message in progress
        self._reset_pending = False
        self._message = b""  #: the slave message being handled
        self._grace_used = False  #: the answer deadline was extended once for a frame in progress
        self.ignored = 0

    # ----------------------------------------------------------------------------- public API

    @property
    def state(self) -> LineState:
        return self._state

    @property
    def rts(self) -> bool:
        return self._tx.rts

    @property
    def collisions(self) -> int:
        return self._tx.collisions

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
        and served before other stations' work (:meth:`ExchangeScheduler.next_exchange`)."""
        target = self._stations.target(station, message, "a command packet")
        if self._stations.tns_in_use(tns := duplicate_key(message)[2], self._request):
            wire = tns.to_bytes(2, "little").hex()  # as the TNS bytes go on the line
            raise ValueError(f"TNS {wire} is already in use on this line; allocate TNS per line")
        request_id = next(self._ids)
        if not target.active:
            self._events.append(RequestFailed(request_id, station, FailReason.STATION_DEMOTED, False))
            return request_id
        frame = encode_master_message(station, message, self.line.checksum)
        target.enqueue(MasterRequest(request_id, station, message, frame, urgent=urgent,
                                     write_mark=self._scheduler.write_time(now)))
        self._kick(now)
        return request_id

    def send_reply(self, station: int, message: bytes, now: float) -> int:
        """Queue the PCCC reply to a command ``station`` initiated (:class:`SlaveInitiated`).

        Sent as a master message (``DLE SOH STN ...``; 1770-6.5.16 p. 5-2) ahead of the station's
        queued commands, resent identically while its DLE ACK is missing, as a command is; nothing is
        polled for.  Events: :class:`MessageDelivered` at the ACK, else ``RequestFailed(NO_ACK)``.
        The TNS is the slave's own (its MSG's), so it is not checked against the line's TNS.
        """
        target = self._stations.target(station, message, "a reply packet")
        request_id = next(self._ids)
        frame = encode_master_message(station, message, self.line.checksum)
        target.enqueue(MasterRequest(request_id, station, message, frame, expects_reply=False))
        self._kick(now)
        return request_id

    def reset_link(self, now: float) -> None:
        """Send DLE NAK, the global link reset (Table 2.C): slaves drop their queued messages."""
        self._reset_pending = True
        self._kick(now)

    def data_to_send(self) -> bytes:
        return self._tx.data_to_send()

    def next_event(self) -> MasterEvent | NeedData:
        return self._events.popleft() if self._events else NEED_DATA

    def next_deadline(self) -> float | None:
        times = self._tx.rts_deadlines()
        if self._state is LineState.TRANSMIT:
            times.append(self._tx.tx_at)
        elif self._state is LineState.IDLE:
            if self._wake is not None:
                times.append(self._wake)
        elif self._deadline is not None:
            times.append(self._deadline)
        return min(times) if times else None

    def handle_timeout(self, now: float) -> None:
        self._tx.update_rts(now)
        if self._state is LineState.TRANSMIT and now >= self._tx.tx_at:
            self._step(self._send_input, now)
        elif self._state in (LineState.WAIT_ACK, LineState.WAIT_POLL):
            if self._deadline is not None and now >= self._deadline:
                if self._decoder.in_frame and not self._grace_used:
                    # An answer is arriving: let it finish rather than meet it in the next exchange.
                    self._grace_used = True
                    self._deadline = now + self._answer_timeout()
                    return
                self._decoder.reset()
                self._step(MasterInput.TIMEOUT, now)
        elif self._state is LineState.IDLE:
            self._apply(MasterInput.SCHEDULE, now)

    def receive_data(self, data: bytes, now: float) -> None:
        data = self._tx.heard(data, now, transmitting=self._state is LineState.TRANSMIT)
        if not data:
            return
        self._decoder.feed(data)
        while (event := self._decoder.next_event()) is not NEED_DATA:
            match event:
                case Frame(message=message):
                    self._message = message
                    self._step(MasterInput.MESSAGE, now)
                case EotReceived():
                    self._step(MasterInput.EOT, now)
                case AckReceived():
                    self._step(MasterInput.ACK, now)
                case NakReceived():
                    self._step(MasterInput.NAK, now)
                case BadFrame(master=False):
                    self._step(MasterInput.BAD, now)
                case _:
                    # a poll or master message (damaged or not): another master's, or our own
                    # echo without echo mode (a half-duplex decoder reports no DLE ENQ alone)
                    self.ignored += 1

    # --------------------------------------------------------------------------- the table

    def _step(self, what: MasterInput, now: float) -> None:
        """An input from the line or a timer; a free line then starts the next exchange."""
        if self._apply(what, now) and self._state is LineState.IDLE:
            self._apply(MasterInput.SCHEDULE, now)

    def _apply(self, what: MasterInput, now: float) -> bool:
        """One transition of :data:`TRANSITIONS`; False when the pair is ignored."""
        entry = TRANSITIONS[self._state, what]
        if entry.action is MasterAction.IGNORE:
            self.ignored += 1
            return False
        self._state = entry.next_state
        _MASTER_ACTIONS[entry.action](self, now)
        assert entry.allows(self._state), f"{entry.action.name} ended in {self._state.name}, not in {entry.allowed}"
        return True

    def _on_schedule(self, now: float) -> None:
        """The line is free: a pending link reset, else the scheduler's next exchange."""
        while self._state is LineState.IDLE:
            self._wake = None
            self._current = None
            self._scheduler.mark_overdue(now)
            if self._reset_pending:
                self._reset_pending = False
                self._reset_all()
                self._transmit(NAK_SYMBOL, LineState.IDLE, now)
                continue
            exchange = self._scheduler.next_exchange(now)
            if exchange is None:
                self._wake = self._scheduler.wake
                return
            if isinstance(exchange, PollStation):
                self._send_poll(exchange.station, now, again=exchange.again)
            else:
                self._send_message(exchange.request, now)

    def _on_send(self, now: float) -> None:
        end = self._tx.send(now)
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
            return
        request.poll_at = now + station.config.reply_wait
        request.reply_deadline = now + station.config.reply_timeout
        request.write_mark = self._scheduler.write_time(now)
        station.awaiting.append(request)

    def _on_naked(self, now: float) -> None:
        """DLE NAK from a slave (a reading the manuals leave open, docs/develop/df1-half-duplex-notes.md §5):
        it heard us; resend."""
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
            self._events.append(request.failed(FailReason.NO_ACK, True))
            return
        self._resend_or_fail(request, now)

    def _resend_or_fail(self, request: MasterRequest, now: float) -> None:
        station = self._stations[request.station]
        if request.sends <= self.line.message_resends:
            station.counters.resends += 1
            if not request.urgent and self._scheduler.urgent_waiting(now, besides=request.station):
                # A write waits at another station: it goes first, this copy at the station's next
                # turn.  Other stations' frames do not reach this slave, so its duplicate detection
                # still sees the identical copy next.
                self._take_request()
                station.queue.appendleft(request)
                return
            self._send_message(request, now)  # the identical bytes: same TNS
            return
        self._take_request()
        self._events.append(request.failed(FailReason.NO_ACK, True))

    def _on_eot(self, now: float) -> None:
        station = self._polled()
        station.counters.eots += 1
        self._answered(station)
        station.last_head = None  # no resend can follow an EOT (KA p. 11-17)
        for request in list(station.awaiting):
            request.polls += 1
            if request.polls >= station.config.max_polls or now >= request.reply_deadline:
                self._events.append(station.fail_awaiting(request, FailReason.NO_REPLY))
            else:  # not ready yet: asked for again reply_wait later, as after the ACK
                request.poll_at = max(request.poll_at, now + station.config.reply_wait)
        self._scheduler.poll_again = False

    def _on_message(self, now: float) -> None:
        station = self._polled()
        message = self._message
        self._answered(station)
        self._scheduler.poll_again = True
        self._transmit(ACK_SYMBOL, LineState.IDLE, now)
        event = station.received(message)
        if event is not None:
            self._events.append(event)

    def _on_bad_answer(self, now: float) -> None:
        station = self._polled()
        station.counters.bad_frames += 1
        self._scheduler.poll_again = True  # not acknowledged: the slave resends at the next poll

    def _on_poll_timeout(self, now: float) -> None:
        station = self._polled()
        station.counters.timeouts += 1
        self._scheduler.poll_again = station.active
        self._failed(station, now)

    # ------------------------------------------------------------------------------ helpers

    def _polled(self) -> StationRecord:
        assert self._current is not None
        return self._stations[self._current]

    def _take_request(self) -> MasterRequest:
        request = self._request
        assert request is not None
        self._request = None
        return request

    def _answered(self, station: StationRecord) -> None:
        restored = station.answered()
        if restored is not None:
            self._events.append(restored)

    def _failed(self, station: StationRecord, now: float) -> None:
        events = station.failed(now)
        if events:  # demoted: its turn ends
            self._scheduler.poll_again = False
            self._events.extend(events)

    def _transmit(self, data: bytes, after: LineState, now: float) -> None:
        """Send ``data`` once the line is quiet and RTS is up; the exchange then waits in ``after``."""
        self._send_input = _SEND_INPUT[after]
        self._state = LineState.TRANSMIT
        self._deadline = None
        if self._tx.prepare(data, now):
            self._apply(self._send_input, now)

    def _send_poll(self, number: int, now: float, *, again: bool) -> None:
        self._stations[number].polled(now)
        self._scheduler.polled(number, again=again)
        self._current = number
        self._transmit(encode_poll(number), LineState.WAIT_POLL, now)

    def _send_message(self, request: MasterRequest, now: float) -> None:
        request.sends += 1
        self._stations[request.station].counters.messages_sent += 1
        self._request = request
        self._transmit(request.frame, LineState.WAIT_ACK, now)

    def _kick(self, now: float) -> None:
        if self._state is LineState.IDLE:
            self._apply(MasterInput.SCHEDULE, now)

    def _reset_all(self) -> None:
        """After DLE NAK the slaves' queues are empty: requests awaiting a reply will get none."""
        for station in self._stations:
            station.last_head = None
            self._events.extend(station.fail_awaiting(r, FailReason.LINK_RESET) for r in list(station.awaiting))


#: What each :class:`MasterAction` runs.
_MASTER_ACTIONS: Final[dict[MasterAction, Callable[[HalfDuplexMaster, float], None]]] = {
    MasterAction.SCHEDULE: HalfDuplexMaster._on_schedule,
    MasterAction.SEND: HalfDuplexMaster._on_send,
    MasterAction.ACKED: HalfDuplexMaster._on_acked,
    MasterAction.NAKED: HalfDuplexMaster._on_naked,
    MasterAction.ACK_TIMEOUT: HalfDuplexMaster._on_ack_timeout,
    MasterAction.EOT: HalfDuplexMaster._on_eot,
    MasterAction.MESSAGE: HalfDuplexMaster._on_message,
    MasterAction.BAD_ANSWER: HalfDuplexMaster._on_bad_answer,
    MasterAction.POLL_TIMEOUT: HalfDuplexMaster._on_poll_timeout,
}
