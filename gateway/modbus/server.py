"""Modbus TCP server: the listener, its lifecycle, its connection limits and its request budget.

The server is split by concern across ``gateway.modbus``:

* :mod:`gateway.modbus.mbap`: the wire (MBAP header, function codes, limits, struct formats);
* :mod:`gateway.modbus.handler`: one request checked, handed to the backend, its reply frame
  built (the only module that imports pymodbus, and why the hot path does not use it);
* :mod:`gateway.modbus.connection`: one client connection (framing, the synchronous read fast
  path, the write tasks, backpressure, timers, the TLS handshake);
* :mod:`gateway.modbus.admission`: who may hold a connection slot, with which rights;
* this module: :class:`ModbusTcpServer`, which binds, admits connections, shares one request
  budget per loop turn between them, and closes gracefully.  The names other modules and tests
  use are importable from here.

Why we own the TCP side
-----------------------
pymodbus 3.16.1's own TCP server mishandles pipelined requests: of two requests that
arrive in one TCP segment the second is dropped, and a request that arrives while
another awaits the backend makes both replies carry the later transaction id. SCADA
masters pipeline, so this package frames MBAP itself on an :class:`asyncio.Protocol`
and answers every request with its own transaction id, as soon as its backend call
completes.

The server takes at most ``_FRAMES_PER_TURN`` requests per turn of the event loop, over all
its connections; the rest wait for the next turn, so a storm of pipelined SCADA requests
delays a serial link's reaction by at most ``_FRAMES_PER_TURN`` requests' work.

Connections (the rules are in :mod:`gateway.modbus.admission`): the allow list, the
per-address cap and, on a TLS listener, the handshake budget are checked when the TCP
connection is accepted, before any TLS byte; ``max_connections`` counts established
connections and, when full, makes room by closing the longest-stalled one. A refused
connection is aborted. Refusals, drops and evictions are logged through a
:class:`~gateway.logutil.RepeatLog`: the first of each cause at once, then one count per
interval with the addresses.  Every module of the server logs on ``gateway.modbus.server``.
"""

from __future__ import annotations

import asyncio
import logging
import os
import ssl
from collections.abc import Sequence
from typing import Final

from gateway.logutil import RepeatLog
from gateway.modbus.admission import Admission, IPNetwork, RolePolicy, bound_port, format_address
from gateway.modbus.connection import Connection
from gateway.modbus.handler import ModbusBackend, ModbusServerCounters, ReadNow, RequestHandler
from gateway.modbus.mbap import FunctionCode

__all__ = [
    "FunctionCode",
    "IPNetwork",
    "ModbusBackend",
    "ModbusServerCounters",
    "ModbusTcpServer",
    "ReadNow",
    "make_tls_context",
]

logger = logging.getLogger(__name__)

#: Requests taken per turn of the event loop, over all connections of a server (about 15 us
#: each): the serial links' callbacks never wait behind more than ~1 ms of Modbus work.  Not
#: lower: every deferral costs a loop turn (8 per turn cost a third of the throughput at 50
#: connections, for no measurable gain in the links' cadence; bench/modbus_serving.py).
_FRAMES_PER_TURN: Final = 64


def make_tls_context(
    cert: str | os.PathLike[str],
    key: str | os.PathLike[str],
    client_ca: str | os.PathLike[str] | None = None,
) -> ssl.SSLContext:
    """Build a server context for Modbus/TCP Security (TLS 1.2 or later).

    ``cert`` and ``key`` are PEM files (the certificate file may hold the chain).
    With ``client_ca``, clients must present a certificate signed by that CA.
    """
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(cert, key)
    if client_ca is not None:
        context.load_verify_locations(cafile=client_ca)
        context.verify_mode = ssl.CERT_REQUIRED
    return context


class ModbusTcpServer(RequestHandler):
    """Modbus TCP (or Modbus/TCP Security over TLS) server answering from a :class:`ModbusBackend`.

    Requests are checked before the backend is called (see :class:`RequestHandler`): an unknown
    unit (``has_unit`` false) is answered 0x0A, an unknown function code 0x01, an
    illegal count, byte count, PDU length or FC5 value 0x03, and a range past
    address 65535 0x02.

    ``allow``: peers outside these networks are closed at connect (``None``: everyone).
    ``idle_timeout``: seconds without a byte received (and nothing in flight) after
    which a connection is closed (``None``: never).
    ``write_stall_timeout``: seconds a client may leave its replies unread (the
    connection paused, its buffers full) before it is dropped (``None``: never).
    """


    def __init__(
        self,
        backend: ModbusBackend,
        host: str | None,
        port: int,
        *,
        max_connections: int = 64,
        idle_timeout: float | None = 300.0,
        allow: Sequence[IPNetwork] | None = None,
        ssl_context: ssl.SSLContext | None = None,
        max_in_flight_per_connection: int = 16,
        write_stall_timeout: float | None = 10.0,
        name: str = "modbus",
        max_connections_per_address: int | None = None,
        frame_timeout: float | None = 5.0,
        handshake_timeout: float = 5.0,
        max_handshakes: int = 16,
        roles: RolePolicy | None = None,
        log_interval: float = 60.0,
        loopback_reads: bool = False,
    ) -> None:
        if max_connections < 1:
            raise ValueError(f"max_connections must be at least 1, not {max_connections}")
        if max_in_flight_per_connection < 1:
            raise ValueError(
                f"max_in_flight_per_connection must be at least 1, not {max_in_flight_per_connection}"
            )
        if idle_timeout is not None and idle_timeout <= 0:
            raise ValueError(f"idle_timeout must be positive or None, not {idle_timeout}")
        if frame_timeout is not None and frame_timeout <= 0:
            raise ValueError(f"frame_timeout must be positive or None, not {frame_timeout}")
        if handshake_timeout <= 0 or max_handshakes < 1:
            raise ValueError("handshake_timeout must be positive and max_handshakes at least 1")
        super().__init__(backend, name)
        self.host = host
        self.max_in_flight_per_connection = max_in_flight_per_connection
        #: seconds a client may leave its replies unread (we stopped reading it) before it is dropped
        self.write_stall_timeout = write_stall_timeout
        self.repeat_log = RepeatLog(logger, log_interval)
        self.admission = Admission(name, max_connections=max_connections, repeat_log=self.repeat_log)
        self.ssl_context = ssl_context
        self.reconfigure(
            max_connections=max_connections,
            max_connections_per_address=max_connections_per_address,
            idle_timeout=idle_timeout,
            frame_timeout=frame_timeout,
            allow=allow,
            loopback_reads=loopback_reads,
            log_interval=log_interval,
            ssl_context=ssl_context,
            handshake_timeout=handshake_timeout,
            max_handshakes=max_handshakes,
            roles=roles,
        )
        self._requested_port = port
        self._server: asyncio.Server | None = None
        self._connections: set[Connection] = set()
        self._tasks: set[asyncio.Task[None]] = set()
        self._closing = False
        self._stopped_event = asyncio.Event()
        self._all_connections_closed: asyncio.Future[None] | None = None
        self._turn_budget = _FRAMES_PER_TURN
        self._turn_reset = False

    def reconfigure(
        self,
        *,
        max_connections: int,
        max_connections_per_address: int | None,
        idle_timeout: float | None,
        frame_timeout: float | None,
        allow: Sequence[IPNetwork] | None,
        loopback_reads: bool,
        log_interval: float,
        ssl_context: ssl.SSLContext | None = None,
        handshake_timeout: float = 5.0,
        max_handshakes: int = 16,
        roles: RolePolicy | None = None,
    ) -> None:
        """Settings for the connections accepted from now on (a config reload); the connections
        open keep theirs, and stay.  A TLS listener takes a new ``ssl_context`` (renewed
        certificates); a plain one stays plain."""
        if (ssl_context is None) != (self.ssl_context is None):
            raise ValueError(f"{self.name}: a listener cannot switch between plain TCP and TLS")
        self.max_connections = max_connections
        self.idle_timeout = idle_timeout
        self.frame_timeout = frame_timeout
        self.allow = None if allow is None else tuple(allow)
        self.ssl_context = ssl_context
        self.handshake_timeout = handshake_timeout
        self.roles = roles
        self.repeat_log.interval = log_interval
        admission = self.admission
        admission.max_connections = max_connections
        admission.max_per_address = max_connections_per_address
        admission.max_handshakes = max_handshakes if ssl_context is not None else None
        admission.allow = self.allow
        admission.loopback_reads = loopback_reads

    # -- lifecycle ---------------------------------------------------------------------

    async def start(self) -> None:
        """Bind and start accepting connections."""
        if self._server is not None:
            raise RuntimeError(f"{self.name}: server already started")
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: Connection(self), self.host, self._requested_port, reuse_address=True
        )
        logger.info(
            "%s: serving Modbus %s on %s",
            self.name,
            "TCP over TLS" if self.ssl_context is not None else "TCP",
            ", ".join(format_address(sock.getsockname()) for sock in self._server.sockets),
        )

    @property
    def port(self) -> int:
        """The bound TCP port (the actual one when 0 was asked for)."""
        return bound_port(self._server, self.name)

    @property
    def connection_count(self) -> int:
        """Connections currently open (TLS handshakes in progress included)."""
        return len(self._connections)

    async def serve_forever(self) -> None:
        """Start if needed and serve until :meth:`close` (or until cancelled, which closes)."""
        if self._server is None:
            await self.start()
        try:
            await self._stopped_event.wait()
        finally:
            await self.close()

    async def close(self, grace: float = 2.0) -> None:
        """Stop accepting, let requests in flight finish (up to ``grace`` s), close connections."""
        if self._closing:
            await self._stopped_event.wait()
            return
        self._closing = True
        try:
            if self._server is not None:
                self._server.close()
            for connection in list(self._connections):
                connection.stop_reading()
            if self._tasks:
                _, pending = await asyncio.wait(set(self._tasks), timeout=grace)
                for task in pending:
                    task.cancel()
                if pending:
                    logger.warning(
                        "%s: cancelled %d requests still in flight after %.1f s",
                        self.name,
                        len(pending),
                        grace,
                    )
                    await asyncio.wait(pending, timeout=grace)
            if self._connections:
                self._all_connections_closed = asyncio.get_running_loop().create_future()
                for connection in list(self._connections):
                    connection.close()
                try:
                    await asyncio.wait_for(asyncio.shield(self._all_connections_closed), grace)
                except TimeoutError:
                    for connection in list(self._connections):
                        connection.abort()
            if self._server is not None:
                await self._server.wait_closed()
        finally:
            self._stopped_event.set()
            self.repeat_log.flush_all()
        logger.info("%s: closed", self.name)

    # -- called by connections ---------------------------------------------------------

    def _admit(self, connection: Connection, peer: object, *, handshake: bool) -> bool:
        """Count a new connection in, or refuse it (the caller then aborts it); see admission.py."""
        if self._closing:
            return False
        started = asyncio.get_running_loop().time() if handshake else None
        if not self.admission.admit(connection, peer, handshake_started=started):
            self.counters.connections_refused += 1
            return False
        self._connections.add(connection)
        self.counters.connections_accepted += 1
        logger.debug("%s: connection from %s", self.name, format_address(peer))
        return True

    def _forget(self, connection: Connection) -> None:
        self.admission.release(connection)
        self._connections.discard(connection)
        if (
            not self._connections
            and self._all_connections_closed is not None
            and not self._all_connections_closed.done()
        ):
            self._all_connections_closed.set_result(None)

    def _spend(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Take one request in this turn of the loop, or False: the turn's budget is spent."""
        if self._turn_budget <= 0:
            return False
        self._turn_budget -= 1
        if not self._turn_reset:
            self._turn_reset = True
            loop.call_soon(self._new_turn)  # runs first in the next turn, before its I/O callbacks
        return True

    def _new_turn(self) -> None:
        self._turn_budget = _FRAMES_PER_TURN
        self._turn_reset = False
