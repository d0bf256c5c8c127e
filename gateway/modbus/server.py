"""Modbus TCP server: MBAP framing and connection handling are ours, PDUs are pymodbus's.

This is the only module of slc-gateway that imports pymodbus (pinned to 3.16.1).

Why we own the TCP side
-----------------------
pymodbus 3.16.1's own TCP server mishandles pipelined requests: of two requests that
arrive in one TCP segment the second is dropped, and a request that arrives while
another awaits the backend makes both replies carry the later transaction id. SCADA
masters pipeline, so this module frames MBAP itself on an :class:`asyncio.Protocol`
and answers every request with its own transaction id, as soon as its backend call
completes.

Frame layout (Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3)::

    0      2      4      6    7     8
    +------+------+------+----+-----+---------------------+
    | tid  | pid  | len  |unit| fc  | data (len - 2 bytes) |
    +------+------+------+----+-----+---------------------+
     u16 BE u16=0  u16    u8   u8
                   len counts unit + PDU: 2..254 (a PDU is at most 253 bytes)

A wrong protocol id or a length outside 2..254 closes that connection only (the
stream cannot be resynchronised). A partial frame is kept until it is complete.

Per connection, requests are handled in arrival order. Reads of a backend that serves
them from memory (``backend.read_now``, see :data:`ReadNow`) are answered at once,
inside ``data_received``, without a task.  The server takes at most
``_FRAMES_PER_TURN`` requests per turn of the event loop, over all its connections;
the rest wait for the next turn (``call_soon``), so between two turns the loop
always gets back to the serial links polled in it: a storm of pipelined SCADA
requests delays a link's reaction by at most ``_FRAMES_PER_TURN`` requests' work.  A connection
with more than ``_MAX_BACKLOG`` bytes waiting stops being read meanwhile.
Every other request becomes one task, created in arrival order, whose first step is
the backend call, so the backend sees requests in arrival order; the task writes its
reply (one ``transport.write``) as soon as the backend answers. Requests refused
before the backend (bad count, unknown unit or function) are answered at once,
without a task. At
``max_in_flight_per_connection`` the connection stops reading (frames already
received wait in the buffer); it also stops reading while the transport's write
buffer is above its high-water mark, so a client that never reads its replies
cannot make the server buffer without bound. The kernel send buffer is capped
(64 KiB) so that this happens after about a thousand unread replies, not after
megabytes of them; a client left paused for ``write_stall_timeout`` seconds is
dropped.

Every request task runs in its connection's ``contextvars`` context, where
``gateway.clients.current_client`` is the connection's identity (for the write
queue's fairness and the audit log: every write is logged on ``gateway.audit``).

Connections (the rules are in :mod:`gateway.modbus.admission`): the allow list, the
per-address cap and, on a TLS listener, the handshake budget are checked when the TCP
connection is accepted, before any TLS byte (TLS is started per connection with
``loop.start_tls``, under its own ``handshake_timeout``); ``max_connections`` counts
established connections and, when full, makes room by closing the longest-stalled one.
A refused connection is aborted. Refusals, drops and evictions are logged through a
:class:`~gateway.logutil.RepeatLog`: the first of each cause at once, then one count per
interval with the addresses. The idle timer only runs while no request is in flight; the
frame timer (``frame_timeout``) runs while an incomplete frame waits at the head of the
buffer and the server is reading. Nothing is written to a transport that is closing (a
client that pipelines and resets would otherwise make asyncio log one warning per reply).

Rights: a client without write rights (``connection.client.can_write``; roles from TLS
client certificates, or loopback let in past ``allow`` for reads) gets 0x01 for every
write function code before the request is looked at further. Its description (certificate
subject, or address) names it in the write path's audit log through ``gateway.clients``.

A backend exception other than ``ModbusExceptionReply`` is answered 0x04 and logged
with its traceback: at ERROR the first time its type is seen, at DEBUG afterwards
(a failing backend would otherwise log every poll); ``counters.backend_errors``
counts them all.

Where pymodbus is used, and where struct is used instead
--------------------------------------------------------
Measured with ``timeit`` on the development machine (CPython 3.11, pymodbus 3.16.1):

=================================================================  ========  =======
FC3 read, request decoded and whole reply frame encoded             125 regs  10 regs
=================================================================  ========  =======
``DecodePDU.decode`` + ``ReadHoldingRegistersResponse.encode``      13.8 us   3.8 us
request class ``decode`` + response ``encode``                      12.6 us   2.8 us
one precompiled ``struct.Struct`` per register count                1.5 us    0.45 us
=================================================================  ========  =======

pymodbus builds the register reply by concatenating one ``struct.pack`` per register,
so FC3 and FC4, the hot path of a polling SCADA, are decoded and encoded here with
precompiled :class:`struct.Struct` objects (about 8x faster, the whole reply frame
MBAP header included in one ``pack``).

pymodbus stays where it is right: decoding the payload of FC15/FC16 requests
(``DecodePDU(is_server=True)``; 23 us for 123 registers, nothing beside a write to a
serial controller) and encoding the bit payload of FC1/FC2 replies
(``ReadCoilsResponse.encode``; 4.5 us for 16 bits, 170 us for 2000 bits, the same cost
a bare pymodbus server pays). The fixed request headers (address, count, byte count,
FC5/FC6 value) are unpacked here with struct because they must be validated before
decoding: pymodbus accepts 2000 coils for FC15 (the limit is 1968), turns any FC5
value into a bool (only 0xFF00 and 0x0000 are legal) and does not compare byte counts
with quantities, and it logs a warning for every request it cannot decode.
Write replies are echoes of the request bytes, as the specification defines them.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import dataclasses
import ipaddress
import logging
import os
import socket
import ssl
import struct
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, Final, Protocol, TypeAlias, cast

from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import ReadCoilsResponse, ReadDiscreteInputsResponse

from gateway.clients import Client, audit_write, current_client
from gateway.errors import ModbusExceptionReply
from gateway.logutil import RepeatLog
from gateway.modbus.admission import Admission, ClientIdentity, RolePolicy, peer_host

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

IPNetwork: TypeAlias = ipaddress.IPv4Network | ipaddress.IPv6Network


class FunctionCode(IntEnum):
    """Function codes served (Modbus Application Protocol Specification V1.1b3, 6.1-6.12)."""

    READ_COILS = 0x01  # 6.1
    READ_DISCRETE_INPUTS = 0x02  # 6.2
    READ_HOLDING_REGISTERS = 0x03  # 6.3
    READ_INPUT_REGISTERS = 0x04  # 6.4
    WRITE_SINGLE_COIL = 0x05  # 6.5
    WRITE_SINGLE_REGISTER = 0x06  # 6.6
    WRITE_MULTIPLE_COILS = 0x0F  # 6.11
    WRITE_MULTIPLE_REGISTERS = 0x10  # 6.12


class ModbusBackend(Protocol):
    """What the server asks of the gateway.

    Any method may raise :class:`gateway.errors.ModbusExceptionReply` to answer that
    exception code; any other exception is logged and answered with 0x04. The server
    checks counts and byte counts before calling (see :class:`ModbusTcpServer`).
    """

    def has_unit(self, unit: int) -> bool: ...

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]: ...

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]: ...

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]: ...

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]: ...

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        """FC5 (one value) and FC15."""

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        """FC6 (one value) and FC16."""


ReadNow: TypeAlias = Callable[[int, int, int, int], bytes]
"""Optional ``backend.read_now(unit, function_code, address, count)``: the data of a read reply at once.

A backend whose reads are served from memory (register images) offers it: the server then
answers FC1-FC4 inside ``data_received``, in arrival order, without a task.  It returns the
reply's data bytes (registers big-endian; bits packed LSB first, as the specification's
FC1/FC2 replies), without the byte count, or raises :class:`ModbusExceptionReply`.
"""


@dataclass
class ModbusServerCounters:
    """Counters since start, for a metrics module to read (never reset, never shrink).

    ``requests`` counts frames by function code byte (unknown ones too);
    ``exceptions`` counts exception replies by exception code;
    ``connections_dropped`` counts connections the server closed after accepting them:
    framing errors, idle timeouts and failed TLS handshakes;
    ``backend_errors`` counts backend calls that raised something other than
    :class:`~gateway.errors.ModbusExceptionReply` (each also counted as exception 0x04).
    """

    requests: dict[int, int] = field(default_factory=dict)
    exceptions: dict[int, int] = field(default_factory=dict)
    connections_accepted: int = 0
    connections_refused: int = 0
    connections_dropped: int = 0
    backend_errors: int = 0


_REGISTER_READS: Final = frozenset({FunctionCode.READ_HOLDING_REGISTERS, FunctionCode.READ_INPUT_REGISTERS})
_BIT_READS: Final = frozenset({FunctionCode.READ_COILS, FunctionCode.READ_DISCRETE_INPUTS})
_SINGLE_WRITES: Final = frozenset({FunctionCode.WRITE_SINGLE_COIL, FunctionCode.WRITE_SINGLE_REGISTER})
_MULTIPLE_WRITES: Final = frozenset(
    {FunctionCode.WRITE_MULTIPLE_COILS, FunctionCode.WRITE_MULTIPLE_REGISTERS}
)

# Protocol limits (Modbus Application Protocol Specification V1.1b3, 6.1-6.12).
_MAX_READ_BITS: Final = 2000
_MAX_READ_REGISTERS: Final = 125
_MAX_WRITE_BITS: Final = 1968
_MAX_WRITE_REGISTERS: Final = 123
_COIL_ON: Final = 0xFF00
_COIL_OFF: Final = 0x0000
_MIN_LENGTH: Final = 2  # unit id + function code
_MAX_LENGTH: Final = 254  # unit id + 253-byte PDU

_ILLEGAL_FUNCTION: Final = ModbusExceptionReply.ILLEGAL_FUNCTION
_ILLEGAL_DATA_ADDRESS: Final = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS
_ILLEGAL_DATA_VALUE: Final = ModbusExceptionReply.ILLEGAL_DATA_VALUE
_SERVER_DEVICE_FAILURE: Final = ModbusExceptionReply.SERVER_DEVICE_FAILURE
_GATEWAY_PATH_UNAVAILABLE: Final = ModbusExceptionReply.GATEWAY_PATH_UNAVAILABLE

# Function codes that change data (Modbus Application Protocol V1.1b3, 6.5, 6.6, 6.11, 6.12, 6.16,
# 6.17): a client without write rights gets 0x01 for each, before anything else is checked.
_WRITE_FUNCTION_CODES: Final = frozenset({0x05, 0x06, 0x0F, 0x10, 0x16, 0x17})
_EVERYONE_WRITES: Final = RolePolicy({}, "read-write")  # TLS without [modbus.tls.roles]
_STALL_GRACE: Final = 1.0  # seconds before a connection without a request can be evicted
#: Kernel send buffer of a connection (bytes): replies a client does not read pile up here and
#: in the transport's buffer (64 KiB) before the connection stops being read; without a cap,
#: loopback autotuning lets megabytes of replies be computed for a client that never reads.
_SEND_BUFFER: Final = 64 * 1024

_MBAP: Final = struct.Struct(">HHHB")  # tid, protocol id, length, unit
_ADDRESS_COUNT: Final = struct.Struct(">HH")  # from PDU offset 1: address, count or value
_ADDRESS_COUNT_BYTES: Final = struct.Struct(">HHB")  # from PDU offset 1: FC15/FC16 header
_EXCEPTION_FRAME: Final = struct.Struct(">HHHBBB")  # MBAP, fc | 0x80, exception code
# _REGISTER_FRAMES[n]: a whole FC3/FC4 reply frame of n registers: MBAP, fc, byte count, values.
_REGISTER_FRAMES: Final = [struct.Struct(f">HHHBBB{n}H") for n in range(_MAX_READ_REGISTERS + 1)]
_READ_HEAD: Final = struct.Struct(">HHHBBB")  # MBAP, fc, byte count (the data follows)
#: Requests taken per turn of the event loop, over all connections of a server (about 15 us
#: each): the serial links' callbacks never wait behind more than ~1 ms of Modbus work.  Not
#: lower: every deferral costs a loop turn (8 per turn cost a third of the throughput at 50
#: connections, for no measurable gain in the links' cadence; bench/modbus_serving.py).
_FRAMES_PER_TURN: Final = 64
#: A connection whose unprocessed bytes exceed this stops being read until they are taken.
_MAX_BACKLOG: Final = 65536

_decoder: Final = DecodePDU(is_server=True)
_BIT_RESPONSES: Final[dict[int, type[ReadCoilsResponse]]] = {
    FunctionCode.READ_COILS: ReadCoilsResponse,
    FunctionCode.READ_DISCRETE_INPUTS: ReadDiscreteInputsResponse,
}

_Reply: TypeAlias = bytes | Coroutine[Any, Any, bytes]


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


def _peer_allowed(peer: object, allow: Sequence[IPNetwork]) -> bool:
    """Whether ``peer`` (a ``peername`` extra info) is inside one of ``allow``."""
    if not isinstance(peer, tuple) or not peer or not isinstance(peer[0], str):
        return False
    try:
        address = ipaddress.ip_address(peer[0])
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return any(address in network for network in allow)


class ModbusTcpServer:
    """Modbus TCP (or Modbus/TCP Security over TLS) server answering from a :class:`ModbusBackend`.

    Requests are checked before the backend is called: an unknown unit
    (``has_unit`` false) is answered 0x0A, an unknown function code 0x01, an
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
        self.backend = backend
        self.host = host
        self.name = name
        self.max_connections = max_connections
        self.idle_timeout = idle_timeout
        self.allow = None if allow is None else tuple(allow)
        self.ssl_context = ssl_context
        self.max_in_flight_per_connection = max_in_flight_per_connection
        self.frame_timeout = frame_timeout
        self.handshake_timeout = handshake_timeout
        self.roles = roles
        #: seconds a client may leave its replies unread (we stopped reading it) before it is dropped
        self.write_stall_timeout = write_stall_timeout
        self.counters = ModbusServerCounters()
        self.repeat_log = RepeatLog(logger, log_interval)
        self.admission = Admission(
            name,
            max_connections=max_connections,
            max_per_address=max_connections_per_address,
            max_handshakes=max_handshakes if ssl_context is not None else None,
            allow=self.allow,
            loopback_reads=loopback_reads,
            repeat_log=self.repeat_log,
        )
        self._requested_port = port
        self._server: asyncio.Server | None = None
        self._connections: set[_Connection] = set()
        self._tasks: set[asyncio.Task[None]] = set()
        self._closing = False
        self._stopped_event = asyncio.Event()
        self._all_connections_closed: asyncio.Future[None] | None = None
        self._logged_errors: set[type[BaseException]] = set()
        self._turn_budget = _FRAMES_PER_TURN
        self._turn_reset = False
        read_now = getattr(backend, "read_now", None)
        self._read_now: ReadNow | None = read_now if callable(read_now) else None

    # -- lifecycle ---------------------------------------------------------------------

    async def start(self) -> None:
        """Bind and start accepting connections."""
        if self._server is not None:
            raise RuntimeError(f"{self.name}: server already started")
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: _Connection(self), self.host, self._requested_port, reuse_address=True
        )
        logger.info(
            "%s: serving Modbus %s on %s",
            self.name,
            "TCP over TLS" if self.ssl_context is not None else "TCP",
            ", ".join(_format_address(sock.getsockname()) for sock in self._server.sockets),
        )

    @property
    def port(self) -> int:
        """The bound TCP port (the actual one when 0 was asked for)."""
        if self._server is None or not self._server.sockets:
            raise RuntimeError(f"{self.name}: server not started")
        port: int = self._server.sockets[0].getsockname()[1]
        return port

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

    def _admit(self, connection: _Connection, peer: object, *, handshake: bool) -> bool:
        """Count a new connection in, or refuse it (the caller then aborts it); see admission.py."""
        if self._closing:
            return False
        started = asyncio.get_running_loop().time() if handshake else None
        if not self.admission.admit(connection, peer, handshake_started=started):
            self.counters.connections_refused += 1
            return False
        self._connections.add(connection)
        self.counters.connections_accepted += 1
        logger.debug("%s: connection from %s", self.name, _format_address(peer))
        return True

    def _forget(self, connection: _Connection) -> None:
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

    def _exception(self, tid: int, unit: int, function_code: int, code: int) -> bytes:
        exceptions = self.counters.exceptions
        exceptions[code] = exceptions.get(code, 0) + 1
        return _EXCEPTION_FRAME.pack(tid, 0, 3, unit, function_code | 0x80, code)

    def _backend_failed(self, tid: int, unit: int, function_code: int, error: Exception) -> bytes:
        """Log a backend failure (the first of each type with traceback at ERROR) and answer 0x04."""
        self.counters.backend_errors += 1
        kind = type(error)
        if kind in self._logged_errors:
            level = logging.DEBUG
        else:
            self._logged_errors.add(kind)
            level = logging.ERROR
        logger.log(
            level,
            "%s: backend failed on function %d for unit %d, answering 0x04: %r",
            self.name,
            function_code,
            unit,
            error,
            exc_info=error,
        )
        return self._exception(tid, unit, function_code, _SERVER_DEVICE_FAILURE)

    def _request(self, tid: int, unit: int, pdu: bytes) -> _Reply:
        """Check one request: the reply frame now, or a coroutine that produces it.

        No await happens before the backend call in the coroutine, so creating the
        tasks in arrival order hands the requests to the backend in arrival order.
        """
        function_code = pdu[0]
        requests = self.counters.requests
        requests[function_code] = requests.get(function_code, 0) + 1
        try:
            known = self.backend.has_unit(unit)
        except Exception as error:
            return self._backend_failed(tid, unit, function_code, error)
        if not known:
            return self._exception(tid, unit, function_code, _GATEWAY_PATH_UNAVAILABLE)

        size = len(pdu)
        if function_code in _REGISTER_READS:
            if size != 5:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            address, count = _ADDRESS_COUNT.unpack_from(pdu, 1)
            if not 1 <= count <= _MAX_READ_REGISTERS:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            if address + count > 0x10000:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_ADDRESS)
            if self._read_now is not None:
                return self._read_at_once(tid, unit, function_code, address, count, 2 * count)
            return self._read_registers(tid, unit, function_code, address, count)

        if function_code in _BIT_READS:
            if size != 5:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            address, count = _ADDRESS_COUNT.unpack_from(pdu, 1)
            if not 1 <= count <= _MAX_READ_BITS:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            if address + count > 0x10000:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_ADDRESS)
            if self._read_now is not None:
                return self._read_at_once(tid, unit, function_code, address, count, (count + 7) // 8)
            return self._read_bits(tid, unit, function_code, address, count)

        if function_code in _SINGLE_WRITES:
            if size != 5:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            address, value = _ADDRESS_COUNT.unpack_from(pdu, 1)
            if function_code == FunctionCode.WRITE_SINGLE_REGISTER:
                return self._write_registers(tid, unit, pdu, address, (value,))
            if value != _COIL_ON and value != _COIL_OFF:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            return self._write_coils(tid, unit, pdu, address, (value == _COIL_ON,))

        if function_code in _MULTIPLE_WRITES:
            if size < 6:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            address, count, byte_count = _ADDRESS_COUNT_BYTES.unpack_from(pdu, 1)
            coils = function_code == FunctionCode.WRITE_MULTIPLE_COILS
            if coils:
                valid = 1 <= count <= _MAX_WRITE_BITS and byte_count == (count + 7) // 8
            else:
                valid = 1 <= count <= _MAX_WRITE_REGISTERS and byte_count == 2 * count
            if not valid or size != 6 + byte_count:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            if address + count > 0x10000:
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_ADDRESS)
            decoded = _decoder.decode(pdu)
            if decoded is None:  # not expected after the checks above
                return self._exception(tid, unit, function_code, _ILLEGAL_DATA_VALUE)
            if coils:
                return self._write_coils(tid, unit, pdu[:5], address, decoded.bits[:count])
            return self._write_registers(tid, unit, pdu[:5], address, decoded.registers)

        return self._exception(tid, unit, function_code, _ILLEGAL_FUNCTION)

    def _read_at_once(self, tid: int, unit: int, function_code: int, address: int, count: int, size: int) -> bytes:
        """A read served from memory (``backend.read_now``): the whole reply frame, no task."""
        assert self._read_now is not None
        try:
            data = self._read_now(unit, function_code, address, count)
        except ModbusExceptionReply as reply:
            return self._exception_reply(tid, unit, function_code, reply)
        except Exception as error:
            return self._backend_failed(tid, unit, function_code, error)
        if len(data) != size:
            wrong = ValueError(f"backend returned {len(data)} data bytes for {count} values ({size} expected)")
            return self._backend_failed(tid, unit, function_code, wrong)
        return _READ_HEAD.pack(tid, 0, 3 + size, unit, function_code, size) + data

    # -- the backend calls (each is the body of one task) ------------------------------

    async def _read_registers(
        self, tid: int, unit: int, function_code: int, address: int, count: int
    ) -> bytes:
        try:
            if function_code == FunctionCode.READ_HOLDING_REGISTERS:
                values = await self.backend.read_holding_registers(unit, address, count)
            else:
                values = await self.backend.read_input_registers(unit, address, count)
            if len(values) != count:
                raise ValueError(f"backend returned {len(values)} registers for {count}")
            frame = _REGISTER_FRAMES[count]
            return frame.pack(tid, 0, 3 + 2 * count, unit, function_code, 2 * count, *values)
        except ModbusExceptionReply as reply:
            return self._exception_reply(tid, unit, function_code, reply)
        except Exception as error:
            return self._backend_failed(tid, unit, function_code, error)

    async def _read_bits(self, tid: int, unit: int, function_code: int, address: int, count: int) -> bytes:
        try:
            if function_code == FunctionCode.READ_COILS:
                bits = await self.backend.read_coils(unit, address, count)
            else:
                bits = await self.backend.read_discrete_inputs(unit, address, count)
            if len(bits) != count:
                raise ValueError(f"backend returned {len(bits)} bits for {count}")
            response = _BIT_RESPONSES[function_code](bits=list(bits))
            payload = response.encode()
            return _MBAP.pack(tid, 0, 2 + len(payload), unit) + bytes((function_code,)) + payload
        except ModbusExceptionReply as reply:
            return self._exception_reply(tid, unit, function_code, reply)
        except Exception as error:
            return self._backend_failed(tid, unit, function_code, error)

    async def _write_coils(
        self, tid: int, unit: int, echo: bytes, address: int, values: Sequence[bool]
    ) -> bytes:
        try:
            await self.backend.write_coils(unit, address, values)
        except ModbusExceptionReply as reply:
            frame = self._exception_reply(tid, unit, echo[0], reply)
            audit_write(unit, echo[0], "coil", address, len(values), f"0x{frame[-1]:02X} {reply}")
            return frame
        except Exception as error:
            audit_write(unit, echo[0], "coil", address, len(values), f"0x04 {error!r}")
            return self._backend_failed(tid, unit, echo[0], error)
        audit_write(unit, echo[0], "coil", address, len(values), "ok")
        return _MBAP.pack(tid, 0, 1 + len(echo), unit) + echo

    async def _write_registers(
        self, tid: int, unit: int, echo: bytes, address: int, values: Sequence[int]
    ) -> bytes:
        try:
            await self.backend.write_registers(unit, address, values)
        except ModbusExceptionReply as reply:
            frame = self._exception_reply(tid, unit, echo[0], reply)
            audit_write(unit, echo[0], "holding", address, len(values), f"0x{frame[-1]:02X} {reply}")
            return frame
        except Exception as error:
            audit_write(unit, echo[0], "holding", address, len(values), f"0x04 {error!r}")
            return self._backend_failed(tid, unit, echo[0], error)
        audit_write(unit, echo[0], "holding", address, len(values), "ok")
        return _MBAP.pack(tid, 0, 1 + len(echo), unit) + echo

    def _exception_reply(self, tid: int, unit: int, function_code: int, reply: ModbusExceptionReply) -> bytes:
        if not 1 <= reply.code <= 0xFF:
            return self._backend_failed(tid, unit, function_code, reply)
        return self._exception(tid, unit, function_code, reply.code)


class _Connection(asyncio.Protocol):
    """One client connection: MBAP framing, one task per request, backpressure, idle timer.

    ``client`` (a :class:`~gateway.modbus.admission.ClientIdentity`) says who is connected and
    with which rights; its description is the name of the connection's
    :class:`gateway.clients.Client`, current in every request task (for fairness and audit).
    """

    __slots__ = (
        "_backlog",
        "_buffer",
        "_client",
        "_connected_at",
        "_context",
        "_eof",
        "_frame_handle",
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

    def __init__(self, server: ModbusTcpServer) -> None:
        self._server = server
        self._loop = asyncio.get_running_loop()
        self._limit = server.max_in_flight_per_connection
        self._transport: asyncio.Transport | None = None
        self._peer: object = None
        self._buffer = b""  # received bytes; those before _offset are consumed
        self._offset = 0
        self._in_flight = 0
        self._backlog = False  # a _next_turn is scheduled (the server's turn budget was spent)
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
        self.client = ClientIdentity("?")
        self._connected_at = 0.0
        self._served = False  # a complete request has been taken from this connection
        self._received_total = 0  # bytes received since connect
        self._partial_position = -1  # stream offset of the incomplete frame being timed
        self._partial_since = 0.0
        self._frame_handle: asyncio.TimerHandle | None = None
        #: the identity of the client; every request task runs in ``_context``, where it is current
        self._client = Client("")
        self._context = contextvars.copy_context()
        self._context.run(current_client.set, self._client)

    # -- asyncio.Protocol --------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.Transport, transport)
        self._peer = transport.get_extra_info("peername")
        server = self._server
        self.client = ClientIdentity(_format_address(self._peer))
        self._client.name = str(self.client)
        _cap_send_buffer(transport)
        if not server._admit(self, self._peer, handshake=server.ssl_context is not None):
            self._released = True
            self._transport.abort()
            self._transport = None
            return
        if server.admission.read_only(self._peer):
            self.client = ClientIdentity(self.client.address, can_write=False)
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
                name=f"{self._server.name}-tls-{_format_address(self._peer)}",
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
                "%s: connection from %s lost: %s", self._server.name, _format_address(self._peer), exc
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
            _format_address(self._peer),
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
        self.client = dataclasses.replace(identity, can_write=identity.can_write and self.client.can_write)
        logger.debug("%s: %s connected", server.name, self.client)
        self._connected_at = self._loop.time()  # stalled_since counts from the end of the handshake
        self._client.name = str(self.client)
        self._ready = True
        self._process()

    def _process(self) -> None:
        """Start the complete requests in the buffer, as many as the limits allow."""
        self._process_frames()
        self._time_partial_frame()

    def _request(self, tid: int, unit: int, pdu: bytes) -> _Reply:
        """One request of this client: refused with 0x01 if it writes without the right to."""
        self._served = True
        if not self.client.can_write and pdu[0] in _WRITE_FUNCTION_CODES:
            server = self._server
            requests = server.counters.requests
            requests[pdu[0]] = requests.get(pdu[0], 0) + 1
            return server._exception(tid, unit, pdu[0], _ILLEGAL_FUNCTION)
        return self._server._request(tid, unit, pdu)

    def _process_frames(self) -> None:
        buffer = self._buffer
        size = len(buffer)
        position = self._offset
        server = self._server
        transport = self._transport
        while size - position >= 7 and self._in_flight < self._limit:
            if self._write_paused or self._stopped or transport is None:
                break
            if not server._spend(self._loop):
                # Let the loop run the links (and other connections) before the rest.
                if not self._backlog:
                    self._backlog = True
                    self._loop.call_soon(self._next_turn)
                break
            tid, protocol, length, unit = _MBAP.unpack_from(buffer, position)
            if protocol != 0 or not _MIN_LENGTH <= length <= _MAX_LENGTH:
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
            else:
                self._in_flight += 1
                task = self._loop.create_task(self._serve(reply), context=self._context)
                server._tasks.add(task)
                task.add_done_callback(server._tasks.discard)
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

    async def _serve(self, reply: Coroutine[Any, Any, bytes]) -> None:
        """Await one backend call and write its reply at once (no done-callback round trip)."""
        try:
            frame = await reply
        finally:
            self._in_flight -= 1
        if self._ready and self._send(frame):
            if self._buffer or self._read_paused or self._eof:
                self._process()

    def _update_reading(self) -> None:
        transport = self._transport
        if transport is None or not self._ready:
            return
        pause = (
            self._in_flight >= self._limit
            or self._write_paused
            or self._stopped
            or (self._backlog and len(self._buffer) - self._offset > _MAX_BACKLOG)
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
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SEND_BUFFER)


def _format_address(address: object) -> str:
    if isinstance(address, tuple) and len(address) >= 2:
        host, port = address[0], address[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    return str(address)
