"""The request side of the Modbus server: check one request, call the backend, build the reply frame.

:class:`RequestHandler` turns the PDU of one request into its whole reply frame (MBAP header
included): at once when the request is refused before the backend (bad count, unknown unit or
function), or when the backend serves reads from memory (``backend.read_now``, see
:data:`ReadNow`); otherwise as a coroutine whose first step is the backend call, so that creating
one task per request in arrival order hands the requests to the backend in arrival order.  A
read the backend answers with :class:`~gateway.errors.StaleRead` (data not read yet or stale, the
link up) becomes an :class:`InOrder` reply that waits at most its ``read_wait`` for the data,
then reads from memory again.  It counts requests, exception replies and backend failures in
:class:`ModbusServerCounters`.
The server (:mod:`gateway.modbus.server`) is a ``RequestHandler``; its connections
(:mod:`gateway.modbus.connection`) call :meth:`RequestHandler._request` for every frame.

This is the only module of slc-gateway that imports pymodbus (pinned to 3.16.1).

Checks before the backend is called: an unknown unit (``has_unit`` false) is answered 0x0A, an
unknown function code 0x01, an illegal count, byte count, PDU length or FC5 value 0x03, and a
range past address 65535 0x02.  A backend exception other than ``ModbusExceptionReply`` is
answered 0x04 and logged with its traceback: at ERROR the first time its type is seen, at DEBUG
afterwards (a failing backend would otherwise log every poll); ``counters.backend_errors``
counts them all.  Every write is logged on ``gateway.audit`` with its outcome
(:func:`gateway.clients.audit_write`).

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
import logging
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Protocol, TypeAlias

from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import ReadCoilsResponse, ReadDiscreteInputsResponse

from gateway.clients import audit_write
from gateway.errors import ModbusExceptionReply, StaleRead
from gateway.modbus import mbap
from gateway.modbus.mapping import FUNCTION_TABLES
from gateway.modbus.mbap import (
    BIT_READS,
    COIL_OFF,
    COIL_ON,
    GATEWAY_PATH_UNAVAILABLE,
    ILLEGAL_DATA_ADDRESS,
    ILLEGAL_DATA_VALUE,
    ILLEGAL_FUNCTION,
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_WRITE_BITS,
    MAX_WRITE_REGISTERS,
    MULTIPLE_WRITES,
    REGISTER_FRAMES,
    REGISTER_READS,
    SERVER_DEVICE_FAILURE,
    SINGLE_WRITES,
    FunctionCode,
)

__all__ = ["InOrder", "ModbusBackend", "ModbusServerCounters", "ReadNow", "Reply", "RequestHandler"]

logger = logging.getLogger("gateway.modbus.server")  # one logger for the whole server


class ModbusBackend(Protocol):
    """What the server asks of the gateway.

    Any method may raise :class:`gateway.errors.ModbusExceptionReply` to answer that
    exception code; any other exception is logged and answered with 0x04. The server
    checks counts and byte counts before calling (see :class:`RequestHandler`).
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

@dataclass(slots=True)
class InOrder:
    """A reply that waits (a read waiting for its data, ``read_wait``): the connection takes no
    further request until it is sent, so its replies keep the order of the requests."""

    body: Coroutine[Any, Any, bytes]


Reply: TypeAlias = bytes | Coroutine[Any, Any, bytes] | InOrder
"""A request's reply frame now, a coroutine (one task's body) that produces it, or one to wait for
in order (:class:`InOrder`)."""


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


# The structs of the hot path are bound here, not imported by name: CPython 3.11 compiles
# ``name.method(...)`` of a name from ``from ... import`` as an attribute load and a call, without
# LOAD_METHOD: 12 % more per request on the read fast path (bench/modbus_fast_path.py).
_MBAP: Final = mbap.MBAP
_ADDRESS_COUNT: Final = mbap.ADDRESS_COUNT
_ADDRESS_COUNT_BYTES: Final = mbap.ADDRESS_COUNT_BYTES
_EXCEPTION_FRAME: Final = mbap.EXCEPTION_FRAME
_READ_HEAD: Final = mbap.READ_HEAD

_decoder: Final = DecodePDU(is_server=True)
#: The most values one read asks for, by function code.
_MOST_READ: Final[dict[int, int]] = {
    **dict.fromkeys(REGISTER_READS, MAX_READ_REGISTERS), **dict.fromkeys(BIT_READS, MAX_READ_BITS)
}
#: A backend's read of one table (``ModbusBackend.read_*``).
_BackendRead: TypeAlias = Callable[[int, int, int], Awaitable[Sequence[int]]]
_BIT_RESPONSES: Final[dict[int, type[ReadCoilsResponse]]] = {
    FunctionCode.READ_COILS: ReadCoilsResponse,
    FunctionCode.READ_DISCRETE_INPUTS: ReadDiscreteInputsResponse,
}


class RequestHandler:
    """Answers requests from a :class:`ModbusBackend`, counting them in ``counters``."""

    def __init__(self, backend: ModbusBackend, name: str) -> None:
        self.backend = backend
        self.name = name
        self.counters = ModbusServerCounters()
        self._logged_errors: set[type[BaseException]] = set()
        read_now = getattr(backend, "read_now", None)
        self._read_now: ReadNow | None = read_now if callable(read_now) else None
        self._reads: dict[int, _BackendRead] = {
            FunctionCode.READ_HOLDING_REGISTERS: backend.read_holding_registers,
            FunctionCode.READ_INPUT_REGISTERS: backend.read_input_registers,
            FunctionCode.READ_COILS: backend.read_coils,
            FunctionCode.READ_DISCRETE_INPUTS: backend.read_discrete_inputs,
        }

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
        return self._exception(tid, unit, function_code, SERVER_DEVICE_FAILURE)

    def _request(self, tid: int, unit: int, pdu: bytes) -> Reply:
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
            return self._exception(tid, unit, function_code, GATEWAY_PATH_UNAVAILABLE)

        size = len(pdu)
        most = _MOST_READ.get(function_code)
        if most is not None:
            if size != 5:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            address, count = _ADDRESS_COUNT.unpack_from(pdu, 1)
            if not 1 <= count <= most:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            if address + count > 0x10000:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_ADDRESS)
            if self._read_now is not None:
                data_bytes = 2 * count if function_code in REGISTER_READS else (count + 7) // 8
                return self._read_at_once(tid, unit, function_code, address, count, data_bytes)
            return self._read(tid, unit, function_code, address, count)

        if function_code in SINGLE_WRITES:
            if size != 5:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            address, value = _ADDRESS_COUNT.unpack_from(pdu, 1)
            if function_code == FunctionCode.WRITE_SINGLE_REGISTER:
                return self._write(tid, unit, pdu, address, (value,), self.backend.write_registers)
            if value != COIL_ON and value != COIL_OFF:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            return self._write(tid, unit, pdu, address, (value == COIL_ON,), self.backend.write_coils)

        if function_code in MULTIPLE_WRITES:
            if size < 6:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            address, count, byte_count = _ADDRESS_COUNT_BYTES.unpack_from(pdu, 1)
            coils = function_code == FunctionCode.WRITE_MULTIPLE_COILS
            if coils:
                valid = 1 <= count <= MAX_WRITE_BITS and byte_count == (count + 7) // 8
            else:
                valid = 1 <= count <= MAX_WRITE_REGISTERS and byte_count == 2 * count
            if not valid or size != 6 + byte_count:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            if address + count > 0x10000:
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_ADDRESS)
            decoded = _decoder.decode(pdu)
            if decoded is None:  # not expected after the checks above
                return self._exception(tid, unit, function_code, ILLEGAL_DATA_VALUE)
            if coils:
                return self._write(tid, unit, pdu[:5], address, decoded.bits[:count], self.backend.write_coils)
            return self._write(tid, unit, pdu[:5], address, decoded.registers, self.backend.write_registers)

        return self._exception(tid, unit, function_code, ILLEGAL_FUNCTION)

    def _read_at_once(
        self, tid: int, unit: int, function_code: int, address: int, count: int, size: int, *, may_wait: bool = True
    ) -> bytes | InOrder:
        """A read served from memory (``backend.read_now``): the whole reply frame, no task; or, for
        data not read yet or stale that the backend lets wait (:class:`~gateway.errors.StaleRead`),
        a reply that waits at most its ``read_wait`` for the data, then reads again (and then serves
        what the link's ``offline`` policy holds, if anything, rather than 0x0B)."""
        assert self._read_now is not None
        try:
            data = self._read_now(unit, function_code, address, count)
        except StaleRead as stale:
            if may_wait and stale.read_wait > 0:
                return InOrder(self._read_after_wait(tid, unit, function_code, address, count, size, stale))
            if stale.held is None:
                return self._exception_reply(tid, unit, function_code, stale)
            data = stale.held  # the link's offline policy: a held (or zero) value rather than 0x0B
        except ModbusExceptionReply as reply:
            return self._exception_reply(tid, unit, function_code, reply)
        except Exception as error:
            return self._backend_failed(tid, unit, function_code, error)
        if len(data) != size:
            wrong = ValueError(f"backend returned {len(data)} data bytes for {count} values ({size} expected)")
            return self._backend_failed(tid, unit, function_code, wrong)
        return _READ_HEAD.pack(tid, 0, 3 + size, unit, function_code, size) + data

    async def _read_after_wait(
        self, tid: int, unit: int, function_code: int, address: int, count: int, size: int, stale: StaleRead
    ) -> bytes:
        """Wait at most ``stale.read_wait`` for the stale data's blocks, then answer from memory."""
        try:
            async with asyncio.timeout(stale.read_wait):
                await stale.wait()
        except TimeoutError:
            pass
        frame = self._read_at_once(tid, unit, function_code, address, count, size, may_wait=False)
        assert isinstance(frame, bytes)
        return frame

    # -- the backend calls (each is the body of one task) ------------------------------

    async def _read(self, tid: int, unit: int, function_code: int, address: int, count: int) -> bytes:
        """FC1-4 through the backend: the reply frame (registers packed here, bits by pymodbus)."""
        try:
            values = await self._reads[function_code](unit, address, count)
            if len(values) != count:
                raise ValueError(f"backend returned {len(values)} values for {count}")
            if function_code in REGISTER_READS:
                frame = REGISTER_FRAMES[count]
                return frame.pack(tid, 0, 3 + 2 * count, unit, function_code, 2 * count, *values)
            payload = _BIT_RESPONSES[function_code](bits=list(map(bool, values))).encode()
            return _MBAP.pack(tid, 0, 2 + len(payload), unit) + bytes((function_code,)) + payload
        except ModbusExceptionReply as reply:
            return self._exception_reply(tid, unit, function_code, reply)
        except Exception as error:
            return self._backend_failed(tid, unit, function_code, error)

    async def _write(
        self,
        tid: int,
        unit: int,
        echo: bytes,
        address: int,
        values: Sequence[bool] | Sequence[int],
        write: Callable[[int, int, Any], Awaitable[None]],
    ) -> bytes:
        """``write`` (``backend.write_coils`` or ``write_registers``), audited (with the table its function
        code writes, ``FUNCTION_TABLES``); the reply echoes ``echo``."""
        table = FUNCTION_TABLES[echo[0]].value
        try:
            await write(unit, address, values)
        except ModbusExceptionReply as reply:
            frame = self._exception_reply(tid, unit, echo[0], reply)
            audit_write(unit, echo[0], table, address, len(values), f"0x{frame[-1]:02X} {reply}")
            return frame
        except Exception as error:
            audit_write(unit, echo[0], table, address, len(values), f"0x04 {error!r}")
            return self._backend_failed(tid, unit, echo[0], error)
        audit_write(unit, echo[0], table, address, len(values), "ok")
        return _MBAP.pack(tid, 0, 1 + len(echo), unit) + echo

    def _exception_reply(self, tid: int, unit: int, function_code: int, reply: ModbusExceptionReply) -> bytes:
        if not 1 <= reply.code <= 0xFF:
            return self._backend_failed(tid, unit, function_code, reply)
        return self._exception(tid, unit, function_code, reply.code)

