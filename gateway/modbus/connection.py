"""One Modbus TCP client connection: MBAP framing, the read fast path, backpressure and timers.

A :class:`Connection` is the :class:`asyncio.Protocol` of one accepted socket.  It cuts the
received bytes into MBAP frames (:mod:`gateway.modbus.mbap`); a wrong protocol id or a length
outside 2..254 closes the connection (the stream cannot be resynchronised); a partial frame is
kept until it is complete.  Every request of the connection gets its reply with its own
transaction id, as soon as it is ready (SCADA masters pipeline).

Per connection, requests are handled in arrival order. Reads of a backend that serves
them from memory (``backend.read_now``, see :data:`~gateway.modbus.handler.ReadNow`) are
answered at once, inside ``data_received``, without a task.  A read whose data is not read yet
or stale may wait for it (``read_wait``, :class:`~gateway.modbus.handler.InOrder`): it becomes a
task, and the requests of the same connection after it wait until it is answered, so that the
replies of a connection keep the order of its requests; other connections do not wait.  The server takes at most
``_FRAMES_PER_TURN`` requests per turn of the event loop, over all its connections
(``host._spend``); the rest wait for the next turn (``call_soon``), so between two turns the loop
always gets back to the serial links polled in it.  A connection with more than ``_MAX_BACKLOG``
bytes waiting stops being read meanwhile.
Every other request becomes one task, created in arrival order, whose first step is
the backend call, so the backend sees requests in arrival order; the task writes its
reply (one ``transport.write``) as soon as the backend answers. Requests refused
before the backend (bad count, unknown unit or function) are answered at once,
without a task. At ``max_in_flight_per_connection`` the connection stops reading (frames
already received wait in the buffer); it also stops reading while the transport's write
buffer is above its high-water mark, so a client that never reads its replies
cannot make the server buffer without bound. The kernel send buffer is capped
(64 KiB) so that this happens after about a thousand unread replies, not after
megabytes of them; a client left paused for ``write_stall_timeout`` seconds is
dropped.

Every request task runs in the connection's ``contextvars`` context, where
``gateway.clients.current_client`` is the connection's identity (for the write
queue's fairness and the audit log: every write is logged on ``gateway.audit``).

TLS is started per connection with ``loop.start_tls``, under its own ``handshake_timeout``,
after admission (:mod:`gateway.modbus.admission`) let the TCP connection in. The idle timer
only runs while no request is in flight; the frame timer (``frame_timeout``) runs while an
incomplete frame waits at the head of the buffer and the server is reading. Nothing is written
to a transport that is closing (a client that pipelines and resets would otherwise make asyncio
log one warning per reply). Drops are logged through the server's
:class:`~gateway.logutil.RepeatLog`: the first of each cause at once, then one count per interval.

Rights: a client without write rights (``connection.client.can_write``; roles from TLS
client certificates, or loopback let in past ``allow`` for reads) gets 0x01 for every
write function code before the request is looked at further.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import dataclasses
import logging
import socket
import ssl
from collections.abc import Coroutine
from typing import Any, Final, Protocol, cast

from gateway.clients import Client, current_client
from gateway.logutil import RepeatLog
from gateway.modbus import mbap
from gateway.modbus.admission import Admission, RolePolicy, format_address, peer_host
from gateway.modbus.handler import InOrder, ModbusServerCounters, Reply
from gateway.modbus.mbap import ILLEGAL_FUNCTION, MAX_LENGTH, MIN_LENGTH, WRITE_FUNCTION_CODES

__all__ = ["Connection", "ConnectionHost"]

logger = logging.getLogger("gateway.modbus.server")  # one logger for the whole server

# The structs of the hot path are bound here, not imported by name: CPython 3.11 compiles
# ``name.method(...)`` of a name from ``from ... import`` as an attribute load and a call, without
# LOAD_METHOD: 12 % more per request on the read fast path (bench/modbus_fast_path.py).
_MBAP: Final = mbap.MBAP

_EVERYONE_WRITES: Final = RolePolicy({}, "read-write")  # TLS without [modbus.tls.roles]
_STALL_GRACE: Final = 1.0  # seconds before a connection without a request can be evicted
#: Kernel send buffer of a connection (bytes): replies a client does not read pile up here and
#: in the transport's buffer (64 KiB) before the connection stops being read; without a cap,
#: loopback autotuning lets megabytes of replies be computed for a client that never reads.
_SEND_BUFFER: Final = 64 * 1024
#: A connection whose unprocessed bytes exceed this stops being read until they are taken.
_MAX_BACKLOG: Final = 65536


class ConnectionHost(Protocol):
    """What a connection needs of its server (:class:`gateway.modbus.server.ModbusTcpServer`).

    The underscored members are the server's side of this package-private interface: they are
    not part of the server's public API.
    """

    name: str
    ssl_context: ssl.SSLContext | None
    idle_timeout: float | None
    frame_timeout: float | None
    write_stall_timeout: float | None
    handshake_timeout: float
    max_in_flight_per_connection: int
    roles: RolePolicy | None
    admission: Admission
    counters: ModbusServerCounters
    repeat_log: RepeatLog
    _tasks: set[asyncio.Task[None]]

    def _admit(self, connection: Connection, peer: object, *, handshake: bool) -> bool:
        """Count a new connection in (False: refused, the connection aborts itself)."""

    def _forget(self, connection: Connection) -> None:
        """The connection is gone (called once)."""

    def _spend(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Take one request in this turn of the loop (False: wait for the next turn)."""

    def _request(self, tid: int, unit: int, pdu: bytes) -> Reply:
        """The reply frame of one request, or a coroutine that produces it."""

    def _exception(self, tid: int, unit: int, function_code: int, code: int) -> bytes:
        """An exception reply frame (counted)."""


class Connection(asyncio.Protocol):
    """One client connection: MBAP framing, one task per request, backpressure, idle timer.

    ``client`` (a :class:`gateway.clients.Client`) says who is connected and with which rights;
    it is ``current_client`` in every request task (for the write queue's fairness and audit).
    """

    __slots__ = (
        "_backlog",
        "_buffer",
        "_connected_at",
        "_context",
        "_eof",
        "_frame_handle",
        "_held",
        "_idle_handle",
        "_in_flight",
        "_last_received",
        "_limit",
        "_loop",
        "_offset",
        "_open",
        "_partial_position",
        "_partial_since",
        "_peer",
        "_read_paused",
        "_ready",
        "_received_total",
        "_released",
        "_served",
        "_server",
        "_stall_handle",
        "_stopped",
        "_tls_task",
        "_transport",
        "_write_paused",
        "client",
    )

    def __init__(self, server: ConnectionHost) -> None:
        self._server = server
        self._loop = asyncio.get_running_loop()
        self._limit = server.max_in_flight_per_connection
        self._transport: asyncio.Transport | None = None
        self._peer: object = None
        self._buffer = b""  # received bytes; those before _offset are consumed
        self._offset = 0
        self._in_flight = 0
        self._backlog = False  # a _next_turn is scheduled (the server's turn budget was spent)
        self._held = False  # a read waits for its data: the requests after it wait (InOrder)
        self._open = False  # admitted, and not closed by us
        self._ready = False  # requests may be processed (after the TLS handshake)
        self._released = False  # forgotten by the server
        self._stopped = False  # the server is closing: take no new request
        self._eof = False  # the peer has shut down its sending side
        self._read_paused = False
        self._write_paused = False
        self._stall_handle: asyncio.TimerHandle | None = None
        self._last_received = 0.0
        self._idle_handle: asyncio.TimerHandle | None = None
        self._tls_task: asyncio.Task[None] | None = None
        self._connected_at = 0.0
        self._served = False  # a complete request has been taken from this connection
        self._received_total = 0  # bytes received since connect
        self._partial_position = -1  # stream offset of the incomplete frame being timed
        self._partial_since = 0.0
        self._frame_handle: asyncio.TimerHandle | None = None
        #: every request task runs in ``_context``, where ``client`` is ``current_client``
        self._context = contextvars.copy_context()
        self.client = Client("?")

    # -- asyncio.Protocol --------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.Transport, transport)
        self._peer = transport.get_extra_info("peername")
        server = self._server
        self._identify(Client(format_address(self._peer)))
        _cap_send_buffer(transport)
        if not server._admit(self, self._peer, handshake=server.ssl_context is not None):
            self._released = True
            self._transport.abort()
            self._transport = None
            return
        if server.admission.read_only(self._peer):
            self._identify(Client(self.client.address, can_write=False))
        self._open = True
        self._last_received = self._connected_at = self._loop.time()
        if self._server.idle_timeout is not None:
            self._idle_handle = self._loop.call_at(
                self._last_received + self._server.idle_timeout, self._check_idle
            )
        if self._server.ssl_context is None:
            self._ready = True
        else:
            # The allow list and the connection limit are checked before any TLS handshake.
            self._transport.pause_reading()
            self._tls_task = self._loop.create_task(
                self._start_tls(self._transport, self._server.ssl_context),
                name=f"{self._server.name}-tls-{format_address(self._peer)}",
            )

    def data_received(self, data: bytes) -> None:
        if not self._open:
            return
        self._last_received = self._loop.time()
        self._received_total += len(data)
        if self._offset:
            self._buffer = self._buffer[self._offset :] + data
            self._offset = 0
        elif self._buffer:
            self._buffer += data
        else:
            self._buffer = data
        if self._ready:
            self._process()

    def eof_received(self) -> bool | None:
        self._eof = True
        if (self._in_flight or self._backlog) and self._server.ssl_context is None:
            return True  # keep the transport open to send the replies still in flight
        return None  # close (TLS transports always do)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._open:
            logger.debug(
                "%s: connection from %s lost: %s", self._server.name, format_address(self._peer), exc
            )
        self._open = False
        self._ready = False
        self._transport = None
        self._release()

    def pause_writing(self) -> None:
        self._write_paused = True
        self._update_reading()
        timeout = self._server.write_stall_timeout
        if timeout is not None and self._stall_handle is None:
            self._stall_handle = self._loop.call_later(timeout, self._stalled)

    def resume_writing(self) -> None:
        self._write_paused = False
        if self._stall_handle is not None:
            self._stall_handle.cancel()
            self._stall_handle = None
        if self._ready:
            self._process()

    # -- used by the server ------------------------------------------------------------

    def stop_reading(self) -> None:
        """Take no new request (the server is closing); requests in flight still get replies."""
        self._stopped = True
        self._update_reading()

    def close(self) -> None:
        """Close after sending what is buffered; replies still in flight are dropped."""
        self._open = False
        self._ready = False
        self._cancel_timers()
        if self._tls_task is not None and not self._tls_task.done():
            self._tls_task.cancel()  # aborts the handshake and releases
        elif self._transport is not None:
            self._transport.close()

    def abort(self) -> None:
        """Close at once and forget the connection."""
        self.close()
        if self._transport is not None:
            self._transport.abort()
            self._transport = None
        self._release()

    # -- used by admission (gateway.modbus.admission.Slot) --------------------------------

    def stalled_since(self) -> float | None:
        """Since when this connection holds its slot without using it (None: it uses it).

        Stalled: an incomplete frame has waited for its end, or no complete request has come
        since the connection was made (or its TLS handshake ended), for at least a grace period
        (1 s, or half of ``frame_timeout`` if shorter): a client that has just connected, or
        whose frame is split across TCP segments, is not stalled.
        """
        if not self._open:
            return None
        if self._partial_position >= 0:
            since = self._partial_since
        elif not self._served:
            since = self._connected_at
        else:
            return None
        timeout = self._server.frame_timeout
        grace = min(_STALL_GRACE, timeout / 2) if timeout is not None else _STALL_GRACE
        return since if self._loop.time() - since >= grace else None

    def evict(self, reason: str) -> None:
        """Close to make room for a new connection."""
        if self._open:
            self._drop(reason, cause="connections closed to make room")

    # -- internals ---------------------------------------------------------------------

    def _identify(self, client: Client) -> None:
        """Who the connection is from now on, also as ``current_client`` of its requests.

        Set before the first request is taken (at connect, and when the TLS handshake ends), so
        that all requests of a connection see one client.
        """
        self.client = client
        self._context.run(current_client.set, client)

    def _stalled(self) -> None:
        """Paused (its replies unread) for ``write_stall_timeout``: drop it, buffers and all."""
        self._stall_handle = None
        if self._open and self._write_paused:
            self._drop(f"its replies unread for {self._server.write_stall_timeout:g} s")
            if self._transport is not None:
                self._transport.abort()  # close() would wait for the unread replies to drain

    def _cancel_timers(self) -> None:
        if self._idle_handle is not None:
            self._idle_handle.cancel()
            self._idle_handle = None
        if self._frame_handle is not None:
            self._frame_handle.cancel()
            self._frame_handle = None
        if self._stall_handle is not None:
            self._stall_handle.cancel()
            self._stall_handle = None

    def _release(self) -> None:
        """Forget the connection (idempotent)."""
        self._cancel_timers()
        self._buffer = b""
        self._offset = 0
        if not self._released:
            self._released = True
            self._server._forget(self)

    def _drop(self, reason: str, cause: str | None = None) -> None:
        """Close a connection that broke the protocol, timed out or failed its TLS handshake.

        Logged at most once per ``cause`` (default: ``reason``) and interval, then summarised.
        """
        server = self._server
        server.repeat_log.log(
            logging.WARNING,
            f"{server.name}: {cause or reason}",
            peer_host(self._peer),
            "%s: closing connection from %s: %s",
            server.name,
            format_address(self._peer),
            reason,
        )
        server.counters.connections_dropped += 1
        self.close()

    def _send(self, frame: bytes) -> bool:
        """Write one reply unless the transport is closing (False then: stop processing).

        Writing to a transport that lost its connection makes asyncio log "socket.send() raised
        exception." for every write after the fifth: a client that pipelines requests and resets
        would make the server log one line per request.
        """
        transport = self._transport
        if transport is None or transport.is_closing():
            return False
        transport.write(frame)
        return True

    def _time_partial_frame(self) -> None:
        """Start, keep or stop the clock of the incomplete frame at the head of the buffer."""
        timeout = self._server.frame_timeout
        if timeout is None or not self._open:
            return
        pending = len(self._buffer) - self._offset
        if self._read_paused:
            # Not reading (requests in flight at the limit, or replies not taken): the rest of
            # the frame cannot arrive, so its clock restarts when reading resumes.
            self._partial_position = -1
            return
        incomplete = 0 < pending and (
            pending < 7 or 6 + _MBAP.unpack_from(self._buffer, self._offset)[2] > pending
        )
        if not incomplete:
            self._partial_position = -1
            return
        position = self._received_total - pending
        if position != self._partial_position:
            self._partial_position = position
            self._partial_since = self._loop.time()
            if self._frame_handle is None:
                self._frame_handle = self._loop.call_at(self._partial_since + timeout, self._check_frame)

    def _check_frame(self) -> None:
        self._frame_handle = None
        timeout = self._server.frame_timeout
        if not self._open or timeout is None or self._partial_position < 0:
            return
        deadline = self._partial_since + timeout
        if deadline <= self._loop.time():
            self._drop(f"incomplete frame for {timeout:g} s", cause="incomplete frames timed out")
            return
        self._frame_handle = self._loop.call_at(deadline, self._check_frame)

    async def _start_tls(self, raw: asyncio.Transport, context: ssl.SSLContext) -> None:
        try:
            transport = await self._loop.start_tls(
                raw, self, context, server_side=True, ssl_handshake_timeout=self._server.handshake_timeout
            )
        except asyncio.CancelledError:
            self._tls_task = None
            raw.abort()
            self._transport = None
            self._release()
            raise
        except Exception as error:
            # start_tls closed the raw transport; connection_lost may never reach us.
            self._tls_task = None
            self._transport = None
            if self._open:
                self._drop(f"TLS handshake failed: {error!r}", cause="TLS handshakes failed")
            self._release()
            return
        self._tls_task = None
        if transport is None or not self._open:
            if transport is not None:
                transport.abort()
            self._transport = None
            self._release()
            return
        self._transport = transport
        server = self._server
        if not server.admission.handshake_done(self, self._peer):
            server.counters.connections_refused += 1
            self._open = False
            transport.abort()
            self._transport = None
            self._release()
            return
        # The certificate's subject and role name the client in audit lines even without roles.
        identity = (server.roles or _EVERYONE_WRITES).identify(
            self.client.address, transport.get_extra_info("ssl_object")
        )
        self._identify(dataclasses.replace(identity, can_write=identity.can_write and self.client.can_write))
        logger.debug("%s: %s connected", server.name, self.client)
        self._connected_at = self._loop.time()  # stalled_since counts from the end of the handshake
        self._ready = True
        self._process()

    def _process(self) -> None:
        """Start the complete requests in the buffer, as many as the limits allow."""
        self._process_frames()
        self._time_partial_frame()

    def _request(self, tid: int, unit: int, pdu: bytes) -> Reply:
        """One request of this client: refused with 0x01 if it writes without the right to."""
        self._served = True
        if not self.client.can_write and pdu[0] in WRITE_FUNCTION_CODES:
            server = self._server
            requests = server.counters.requests
            requests[pdu[0]] = requests.get(pdu[0], 0) + 1
            return server._exception(tid, unit, pdu[0], ILLEGAL_FUNCTION)
        return self._server._request(tid, unit, pdu)

    def _process_frames(self) -> None:
        buffer = self._buffer
        size = len(buffer)
        position = self._offset
        server = self._server
        transport = self._transport
        while size - position >= 7 and self._in_flight < self._limit and not self._held:
            if self._write_paused or self._stopped or transport is None:
                break
            if not server._spend(self._loop):
                # Let the loop run the links (and other connections) before the rest.
                if not self._backlog:
                    self._backlog = True
                    self._loop.call_soon(self._next_turn)
                break
            tid, protocol, length, unit = _MBAP.unpack_from(buffer, position)
            if protocol != 0 or not MIN_LENGTH <= length <= MAX_LENGTH:
                self._drop(f"bad MBAP header (protocol id {protocol}, length {length})", cause="bad MBAP headers")
                return
            end = position + 6 + length
            if end > size:
                break
            reply = self._request(tid, unit, buffer[position + 7 : end])
            position = end
            if isinstance(reply, bytes):
                if not self._send(reply):
                    break
                continue
            in_order = isinstance(reply, InOrder)
            self._in_flight += 1
            body = reply.body if isinstance(reply, InOrder) else reply
            task = self._loop.create_task(self._serve(body, in_order), context=self._context)
            server._tasks.add(task)
            task.add_done_callback(server._tasks.discard)
            if in_order:
                # A read waiting for its data: the requests after it wait for its reply.
                self._held = True
                break
        if position == size:
            self._buffer = b""
            self._offset = 0
        else:
            self._offset = position
        if self._eof and not self._in_flight and not self._backlog and transport is not None:
            transport.close()
            return
        if transport is not None and transport.is_closing():
            return
        self._update_reading()

    def _next_turn(self) -> None:
        self._backlog = False
        if self._ready and self._transport is not None:
            self._process()
        elif self._eof and not self._in_flight and self._transport is not None:
            self._transport.close()

    async def _serve(self, reply: Coroutine[Any, Any, bytes], in_order: bool = False) -> None:
        """Await one backend call and write its reply at once (no done-callback round trip);
        ``in_order``: the requests after it were held until now."""
        try:
            frame = await reply
        finally:
            self._in_flight -= 1
            if in_order:
                self._held = False
        if self._ready and self._send(frame):
            if self._buffer or self._read_paused or self._eof or in_order:
                self._process()

    def _update_reading(self) -> None:
        transport = self._transport
        if transport is None or not self._ready:
            return
        pause = (
            self._in_flight >= self._limit
            or self._write_paused
            or self._stopped
            or ((self._backlog or self._held) and len(self._buffer) - self._offset > _MAX_BACKLOG)
        )
        if pause != self._read_paused:
            self._read_paused = pause
            if pause:
                transport.pause_reading()
            else:
                transport.resume_reading()

    def _check_idle(self) -> None:
        self._idle_handle = None
        timeout = self._server.idle_timeout
        if not self._open or timeout is None:
            return
        now = self._loop.time()
        if self._in_flight:
            deadline = now + timeout
        else:
            deadline = self._last_received + timeout
            if deadline <= now:
                self._drop(f"idle for {timeout:g} s")
                return
        self._idle_handle = self._loop.call_at(deadline, self._check_idle)


def _cap_send_buffer(transport: asyncio.BaseTransport) -> None:
    """Cap the kernel send buffer of a connection at ``_SEND_BUFFER`` (see there why)."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SEND_BUFFER)
