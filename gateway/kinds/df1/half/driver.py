"""Asyncio driver for a DF1 half-duplex multi-drop line: one line owner, one handle per station.

The sans-I/O master core (:class:`~gateway.protocols.df1.half_duplex.HalfDuplexMaster`) decides
everything on the wire: polling, resends of the identical master frame, demotion of a dead station,
RTS timing, echo suppression.  :class:`Df1HalfDuplexLine` owns the port (reconnects through
:class:`~gateway.line_driver.LineDriver`), feeds the core every byte, runs the one timer the core
asks for (``next_deadline()`` / ``handle_timeout(now)``) and drives RTS when the port can.

Each station on the line gets a :class:`Df1Station` handle with the API a DF1 unit uses on
:class:`~gateway.kinds.df1.full.driver.Df1Driver`: ``execute(request, name)`` -> the reply, plus
``available``, ``counters``, ``last_sts``, ``add_listener``, ``run()`` / ``close()`` and ``probe()``.
Requests of different stations are in the core at the same time; it serves them round robin (writes
first), so a dead or slow station never holds up the others.  The sans-I/O transaction layer
(:class:`~gateway.protocols.df1.half_duplex.transactions.HalfDuplexTransactions`) gives each request
its verdict - read retries with a new TNS, a write's verdict and read-backs
(:mod:`gateway.protocols.df1.write_verdict`, shared with full duplex) - and this driver turns it into
a result:

* done -> the reply;  refused -> :class:`~gateway.protocols.df1.pccc.PcccError`;
* outcome unknown -> :class:`~gateway.kinds.df1.full.driver.WriteOutcomeUnknown`;
* failed (a read without an answer after ``retries + 1`` tries, a write that never left, a station
  demoted to slow poll) -> :class:`~gateway.errors.LinkTimeout` (Modbus 0x0B).

The core resends an unacknowledged master frame identically (same TNS), which a slave with duplicate
detection (the default) ACKs without running it again; for slaves without duplicate detection
(``duplicate_detect=False``) no frame is ever resent.

TNS are allocated per line (the core refuses a TNS already in use on the line).

Messages a slave initiates (MSG instructions, report by exception) are acknowledged by the core
(DLE ACK) and answered here with the PCCC reply decided by
:func:`~gateway.protocols.df1.half_duplex.slave_messages.answer_slave_message`: a write to the gateway's own
station (``source``) lands in the sending station's
:class:`~gateway.protocols.df1.half_duplex.slave_messages.RegisterTable` (``register_tables``, by station) and is
answered STS 00; a write outside it the PCCC target's refusal for that command, anything else STS 10
(1770-6.5.16 p. 8-3).  The reply goes back as a master message
(``HalfDuplexMaster.send_reply``).  Counted per station: ``slave_messages``, ``slave_writes``,
``slave_refused``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Final, Unpack

from gateway.config.link import DEFAULT_RETRIES
from gateway.errors import GatewayError, LinkDown
from gateway.kinds.df1.full.driver import DF1_SETTINGS, transaction_result
from gateway.line_driver import LineDriver, LineDriverOptions, LineLease, run_to_the_end
from gateway.link_health import DEFAULT_DOWN_AFTER, DownAfter, LineQuality, LinkHealth
from gateway.protocols.df1.framing import DEFAULT_CHECKSUM, NEED_DATA, Checksum
from gateway.protocols.df1.full_duplex.transaction import (
    OutcomeUnknown,
    TransactionDone,
    TransactionEvent,
    TransactionFailed,
    TransactionRefused,
)
from gateway.protocols.df1.half_duplex import events as master_events
from gateway.protocols.df1.half_duplex.events import (
    DEFAULT_MESSAGE_RESENDS,
    HALF_DUPLEX_ACK_TIMEOUT,
    FailReason,
    LineConfig,
    StationConfig,
    StationCounters,
)
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable, SlaveMessageVerdict, answer_slave_message
from gateway.protocols.df1.half_duplex.transactions import HalfDuplexTransactions, PcccRequestLike
from gateway.protocols.df1.pccc import DiagnosticStatus, DiagnosticStatusInfo, PcccReply
from gateway.protocols.df1.pccc import is_write as pccc_is_write
from gateway.transport import SerialSettings, describe_url, enable_rs485, modem_lines

__all__ = ["RTS_MODES", "Df1HalfDuplexLine", "Df1Station", "PcccRequestLike", "StationTotals"]

#: ``rts``: ``toggle`` (the core keys RTS around each transmission), ``rs485`` (the kernel's RS-485
#: mode does), ``on`` / ``off`` (held; a full-duplex modem, a 4-wire converter).
RTS_MODES: Final = ("toggle", "rs485", "on", "off")

log = logging.getLogger("gateway.link")

@dataclass(slots=True)
class StationTotals(StationCounters):
    """Per-station counters for metrics, summed over reconnects (the core's own reset with it):
    the core's :class:`StationCounters` and the driver's own."""

    read_retries: int = 0  #: reads sent again with a new TNS
    read_backs: int = 0  #: read-backs sent for writes whose answer was lost
    stray_replies: int = 0
    slave_messages: int = 0  #: messages the station initiated (acknowledged and answered)
    slave_writes: int = 0  #: ... of them writes stored in the station's register table
    slave_refused: int = 0  #: ... of them answered with an error (STS 10, or the target's refusal outside the table)
    slave_replies_lost: int = 0  #: replies to them the station never acknowledged (or pending when the port was lost)

    def add(self, core: StationCounters) -> StationTotals:
        total = StationTotals(**{f.name: getattr(self, f.name) for f in fields(self)})
        for f in fields(core):
            setattr(total, f.name, getattr(total, f.name) + getattr(core, f.name))
        return total


class Df1Station(LinkHealth):
    """One station on a half-duplex line, with the request API of ``Df1Driver``.

    Up and down by the rule of every link (:class:`~gateway.link_health.LinkHealth`): its own
    ``down_after_failures`` / ``down_after_seconds``; a demotion counts as one failure, a
    restoration as an answer, and the line's lost port makes every station down at once.
    """

    def __init__(
        self, line: Df1HalfDuplexLine, config: StationConfig, name: str, down_after: DownAfter = DEFAULT_DOWN_AFTER
    ) -> None:
        super().__init__(name, down_after)
        self.line = line
        self.url = line.url  #: the line's port (for logs)
        self.config = config
        self.station = config.station
        self.last_sts = 0
        self._base = StationTotals()  #: counters of cores before the current one, and the driver's own
        self._closed = False
        self.write_burst = 1  #: set by the unit; not used (see write_session)
        self.poll_burst = 2
        self.last_reply_at: float | None = None  #: loop time of the last reply of this station (any STS)

    # --- state ------------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self.line.connected

    def where(self) -> str:
        return f"station {self.station} on {describe_url(self.url)}"

    @property
    def totals(self) -> StationTotals:
        """Polls, EOTs, retries, demotions ... of this station since the line started."""
        core = self.line.core
        total = self._base.add(core.counters(self.station)) if core is not None else self._base.add(StationCounters())
        txns = self.line.txns.counters(self.station)
        total.read_retries += txns.read_retries
        total.read_backs += txns.read_backs
        return total

    def line_quality(self) -> LineQuality:
        """This station's bad frames, timeouts and master messages sent again (for a missing DLE ACK, or
        a read with a new TNS); a half-duplex master does not count the slave's DLE NAKs."""
        totals = self.totals
        return LineQuality(check_errors=totals.bad_frames, timeouts=totals.timeouts,
                           retransmits=totals.resends + totals.read_retries)

    def data_age(self, now: float | None = None) -> float | None:
        """Seconds since this station last answered a command of ours; None before its first reply."""
        if self.last_reply_at is None:
            return None
        return (asyncio.get_running_loop().time() if now is None else now) - self.last_reply_at

    def metrics(self, now: float | None = None) -> dict[str, float]:
        """Per-station numbers for the integrator's metrics.

        ``polls``, ``eots``, ``retries`` (master frames sent again for a missing ACK), ``read_retries``
        (reads sent again with a new TNS), ``timeouts``, ``bad_frames``, ``duplicates``, ``demotions``,
        ``messages_sent`` / ``messages_received``, ``read_backs``, ``slave_messages`` / ``slave_writes``
        / ``slave_refused``, ``active`` (1 / 0: not demoted) and ``data_age`` seconds (-1 before the
        first reply).  Counters are totals since the line was created (reconnects included).
        """
        values: dict[str, float] = {f.name: getattr(self.totals, f.name) for f in fields(StationTotals)}
        values["retries"] = values.pop("resends")  # the metric keeps its published name
        core = self.line.core
        values["active"] = 1.0 if core is not None and core.is_active(self.station) else 0.0
        age = self.data_age(now)
        values["data_age"] = -1.0 if age is None else age
        return values

    def _bank(self, core: HalfDuplexMaster) -> None:
        """The core is being replaced (reconnect): keep its counts."""
        self._base = self._base.add(core.counters(self.station))

    # --- life cycle (shared line) -------------------------------------------------------------

    async def run(self) -> None:
        """Keep the shared line running (the first station to run starts it) until cancelled."""
        await self.line.run_shared()

    async def start(self, wait: float | None = None) -> None:
        await self.line.start_shared(wait)

    async def first_attempt(self) -> None:
        await self.line.first_attempt()

    async def close(self) -> None:
        if not self._closed:
            self._closed = True
            await self.line.release()

    # --- requests ---------------------------------------------------------------------------

    async def execute(self, request: PcccRequestLike, name: str = "", line: LineLease | None = None) -> PcccReply:
        """Send ``request`` to this station and return the (successful) reply (module docstring); a
        write is what :func:`pccc_is_write` says it is.  ``line``, the lease of :meth:`write_session`,
        holds nothing here: the line's master core orders every request."""
        label = name or type(request).__name__
        is_write = pccc_is_write(request)
        if not is_write:
            return await self._run(request, label, False)
        # a write goes on to its verdict even when its caller gives up (as Df1Driver.submit does)
        return await run_to_the_end(self._run(request, label, True))

    async def _run(self, request: PcccRequestLike, label: str, is_write: bool) -> PcccReply:
        """One transaction; the sans-I/O layer gives its verdict, this turns it into a result."""
        event = await self.line.transact(self, request, is_write)
        if isinstance(event, TransactionDone | TransactionRefused):
            self.last_reply_at = asyncio.get_running_loop().time()
        elif isinstance(event, TransactionFailed) and event.reason.startswith(FailReason.STATION_DEMOTED.value):
            event = replace(event, reason=(
                f"station {self.station} does not answer polls; it is polled every "
                f"{self.config.slow_poll_interval:g} s until it does (check its power, cable and station number)"
            ))
        return transaction_result(self, event, label, request.FNC)

    # --- the write-session API of LineDriver (gateway.writes uses it) ------------------------

    @contextlib.asynccontextmanager
    async def write_session(self) -> AsyncIterator[LineLease]:
        """A run of writes.  On a half-duplex line the core owns the order (each station's commands
        in turn, round robin between stations, polls between them), so a session only checks that
        the line is up, and its lease holds nothing (no burst accounting).  ``write_burst`` /
        ``poll_burst`` are not used: a half-duplex link refuses those keys
        (``Df1LinkConfig.unused_keys``), so the unit sets their defaults here."""
        if not self.line.connected:
            raise LinkDown(f"link {self.name} is down: {self.line.last_error or 'not connected'}")
        yield LineLease()

    async def probe(self) -> DiagnosticStatusInfo:
        reply = await self.execute(DiagnosticStatus(), "diagnostic status")
        return DiagnosticStatusInfo(reply.data)


class Df1HalfDuplexLine(LineDriver):
    """The master of one half-duplex line (module docstring).  ``station(n)`` gives the handles."""

    def __init__(
        self,
        url: str,
        stations: Sequence[StationConfig],
        *,
        settings: SerialSettings = DF1_SETTINGS,
        checksum: Checksum = DEFAULT_CHECKSUM,
        source: int = 0,
        ack_timeout: float = HALF_DUPLEX_ACK_TIMEOUT,
        message_retries: int = DEFAULT_MESSAGE_RESENDS,
        retries: int = DEFAULT_RETRIES,
        pre_transmit_delay: float = 0.0,
        rts_send_delay: float = 0.0,
        rts_off_delay: float = 0.0,
        echo: bool = False,
        duplicate_detect: bool = True,
        link_reset: bool = True,
        rts: Callable[[bool], None] | None = None,
        rts_mode: str = "toggle",
        dtr: bool = True,
        station_names: dict[int, str] | None = None,
        down_after: Mapping[int, DownAfter] | None = None,
        register_tables: Mapping[int, RegisterTable] | None = None,
        first_tns: int | None = None,
        **line: Unpack[LineDriverOptions],
    ) -> None:
        super().__init__(url, settings=settings, **line)
        if not stations:
            raise ValueError(f"line {self.name}: a half-duplex line needs at least one station")
        self.source = source
        self.retries = retries
        # Without duplicate detection in the slaves (RM p. 13-59 "Duplicate Packet Detect" unchecked) a
        # resent master frame whose first copy arrived is executed again: then no frame is ever resent
        # (reads are retried with a new TNS, writes settled by a read-back), so a write runs once.
        self.duplicate_detect = duplicate_detect
        #: the core's line tunables but ``char_time``, which each connection sets (``_line_config``)
        self.tunables = LineConfig(
            checksum,
            ack_timeout=ack_timeout,
            message_resends=message_retries if duplicate_detect else 0,
            pre_transmit_delay=pre_transmit_delay,
            rts_send_delay=rts_send_delay,
            rts_off_delay=rts_off_delay,
            echo=echo,
        )
        self.link_reset = link_reset
        if rts_mode not in RTS_MODES:
            raise ValueError(f"line {self.name}: rts = {rts_mode!r}: choose {', '.join(RTS_MODES)}")
        self.rts_mode = rts_mode
        self.dtr = dtr
        self._rts_given = rts  #: an explicit RTS setter (tests, a GPIO); else the port's, per connection
        self._rts = rts
        self._rts_state: bool | None = None
        self._rts_warned = False
        self._configs = list(stations)
        HalfDuplexMaster(self._line_config(), self._configs)  # validate now: unique stations, tunables
        names = station_names or {}
        rules = down_after or {}
        self.stations: dict[int, Df1Station] = {
            c.station: Df1Station(self, c, names.get(c.station, f"{self.name}/{c.station}"),
                                  rules.get(c.station, DEFAULT_DOWN_AFTER))
            for c in stations
        }
        first = random.randrange(1, 0x10000) if first_tns is None else first_tns
        self.txns = HalfDuplexTransactions(source=source, retries=retries, first_tns=first)
        self.core: HalfDuplexMaster | None = None
        self._waiting: dict[int, asyncio.Future[TransactionEvent]] = {}  #: by transaction handle
        self._users = 0
        self.stray_replies = 0
        #: writes of each station to the gateway's own address (report by exception), by station
        self.register_tables: dict[int, RegisterTable] = dict(register_tables or {})
        self._replies: dict[int, int] = {}  #: request id of a reply to a slave's message -> station

    def station_metrics(self, now: float | None = None) -> dict[int, dict[str, float]]:
        """:meth:`Df1Station.metrics` of every station on the line, by station number."""
        return {number: handle.metrics(now) for number, handle in self.stations.items()}

    def station(self, number: int) -> Df1Station:
        try:
            return self.stations[number]
        except KeyError:
            raise ValueError(f"line {self.name}: no station {number} (stations: {sorted(self.stations)})") from None

    def _line_config(self) -> LineConfig:
        return replace(self.tunables, char_time=self.char_time)

    def _report(self, up: bool, reason: str = "") -> None:
        """The line's own state (the port); a lost port makes every station on it down at once."""
        super()._report(up, reason)
        if not up:
            for handle in self.stations.values():
                handle._report(False, self.last_error)

    # --- shared life cycle ------------------------------------------------------------------

    async def run_shared(self) -> None:
        """Every station's ``run()``: one line task, started by the first, awaited by all."""
        self._users += 1
        if self._run_task is None:
            self._run_task = asyncio.create_task(self.run(), name=f"{self.name}-line")
        await asyncio.shield(self._run_task)

    async def start_shared(self, wait: float | None = None) -> None:
        self._users += 1
        if self._run_task is None:
            await self.start(wait)

    async def release(self) -> None:
        """A station is done with the line; the last one closes it."""
        self._users -= 1
        if self._users <= 0:
            await self.close()

    # --- protocol hooks ---------------------------------------------------------------------

    def on_connect(self) -> None:
        loop = asyncio.get_running_loop()
        if self.core is not None:
            for handle in self.stations.values():
                handle._bank(self.core)
        self._setup_modem_lines()
        self.core = HalfDuplexMaster(self._line_config(), self._configs)
        lost = f"line {self.name}: reconnected; the request was lost with the line"
        self.txns.attach(self.core, loop.time(), reason=lost)
        self.core.start(loop.time(), link_reset=self.link_reset)
        self._pump()

    def _setup_modem_lines(self) -> None:
        """RTS / DTR of a local (or rfc2217) port for this connection (``gateway.transport`` docstring).

        ``toggle``: the core keys RTS around each transmission; ``rs485``: the kernel does (exact
        to the bit); ``on`` / ``off``: held.  A port without modem lines (``socket://``) is logged
        once: its device server must key the transmitter.
        """
        self._rts_state = None
        if self._rts_given is not None or self._stream is None:
            return
        self._rts = None
        lines = modem_lines(self._stream)
        if lines is None:
            if self.rts_mode in ("toggle", "rs485", "on") and not self._rts_warned and self.url.startswith("socket:"):
                self._rts_warned = True
                log.warning("line %s: %s has no modem lines: set the device server to key RTS itself "
                            "(RTS toggle / RS-485 auto direction)", self.name, self.url)
            return
        lines.set_dtr(self.dtr)
        if lines.remote and self.rts_mode == "toggle" and not self._rts_warned:
            self._rts_warned = True
            log.warning("line %s: RTS over RFC 2217 follows the data by a network round trip; prefer the "
                        "device server's RTS toggle for a radio", self.name)
        tunables = self.tunables
        if self.rts_mode == "rs485" and enable_rs485(self._stream, delay_before_tx=tunables.rts_send_delay,
                                                     delay_before_rx=tunables.rts_off_delay):
            return
        if self.rts_mode in ("toggle", "rs485"):  # rs485 refused by the port: the core keys RTS
            self._rts = lines.set_rts
        else:
            lines.set_rts(self.rts_mode == "on")

    def abort(self, exc: GatewayError) -> None:
        for waiter in self._waiting.values():
            if not waiter.done():
                waiter.set_exception(exc)
        self._waiting.clear()
        # replies to stations' messages still waiting for their DLE ACK go with the line's core
        for station in self._replies.values():
            self.stations[station]._base.slave_replies_lost += 1
        self._replies.clear()

    def data_received(self, data: bytes) -> None:
        if self.core is not None:
            self.txns.receive_data(data, asyncio.get_running_loop().time())
            self._pump()

    def _pump(self) -> None:
        core = self.core
        if core is None:
            return
        if self._rts is not None and core.rts != self._rts_state:  # RTS before the bytes it keys up
            self._rts_state = core.rts
            self._rts(core.rts)
        out = core.data_to_send()
        if out and self.connected:
            self.send(out)
        while (event := self.txns.next_event()) is not NEED_DATA:
            self._dispatch(event)
        self.follow_deadline(core.next_deadline())

    def _dispatch(self, event: TransactionEvent | master_events.MasterEvent) -> None:
        if isinstance(event, TransactionDone | TransactionRefused | OutcomeUnknown | TransactionFailed):
            waiter = self._waiting.pop(event.handle, None)
            if waiter is not None and not waiter.done():
                waiter.set_result(event)
        elif isinstance(event, master_events.RequestFailed) and event.request_id in self._replies:
            station = self._replies.pop(event.request_id)
            self.stations[station]._base.slave_replies_lost += 1
            log.debug("line %s: station %d never acknowledged the reply to its message", self.name, station)
        elif isinstance(event, master_events.StationDemoted):
            handle = self.stations[event.station]
            handle.judge(False, f"station {event.station} does not answer polls (demoted to slow poll)")
        elif isinstance(event, master_events.StationRestored):
            self.stations[event.station].judge(True)
        elif isinstance(event, master_events.SlaveInitiated):
            self._answer(event)
        elif isinstance(event, master_events.MessageDelivered):  # only replies are sent without a reply
            del self._replies[event.request_id]
        elif isinstance(event, master_events.StrayReply):
            self.stray_replies += 1
            self.stations[event.station]._base.stray_replies += 1

    def _answer(self, event: master_events.SlaveInitiated) -> None:
        """Store a slave's write to us and queue the PCCC reply its MSG waits for (module docstring)."""
        assert self.core is not None
        now = asyncio.get_running_loop().time()
        totals = self.stations[event.station]._base
        totals.slave_messages += 1
        table = self.register_tables.get(event.station)
        verdict, reply = answer_slave_message(event.message, own_station=self.source, table=table, now=now)
        if verdict is SlaveMessageVerdict.STORED:
            totals.slave_writes += 1
        elif reply is not None:
            totals.slave_refused += 1
            log.debug("line %s: station %d sent %s: %s", self.name, event.station, event.message.hex(" "),
                      verdict.value)
        if reply is not None:
            self._replies[self.core.send_reply(event.station, reply, now)] = event.station

    def on_deadline(self, now: float) -> None:
        if self.core is not None:
            self.txns.handle_timeout(now)
            self._pump()

    # --- requests ---------------------------------------------------------------------------

    async def transact(self, handle: Df1Station, request: PcccRequestLike, write: bool) -> TransactionEvent:
        """Run one transaction for ``handle``'s station; its verdict event."""
        txns = self.txns
        if self.core is None or not self.connected:
            raise LinkDown(f"link {handle.name} is down: {self.last_error or 'not connected'}")
        loop = asyncio.get_running_loop()
        waiter: asyncio.Future[TransactionEvent] = loop.create_future()
        txn = txns.start(handle.station, request, loop.time(), write=write)
        self._waiting[txn] = waiter
        self._pump()
        try:
            return await waiter
        finally:
            self._waiting.pop(txn, None)
