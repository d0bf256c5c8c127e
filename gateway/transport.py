"""Open a byte stream to a controller from a URL.  The only module that opens serial ports.

URLs:

* ``/dev/ttyUSB0``, ``/dev/ttyS0``, ``COM3`` - a local serial port (pyserial-asyncio-fast).
  DTR is asserted and RTS is not, as the 1745-PCC interface converter needs.
* ``socket://host:port`` - a serial device server in raw TCP mode (plain asyncio TCP).
* ``rfc2217://host:port`` - a serial device server speaking RFC 2217 (pyserial's client).
* ``sim://slc150``, ``sim://slc100``, ``sim://slc504`` - an in-process simulator
  (see ``gateway.sim``); options may follow as a query: ``sim://slc150?garble=5&drop=7``.

Modem lines for half-duplex DF1 (:func:`modem_lines`): a local port gives the driver an
RTS setter and a DTR setter, so the half-duplex core keys a radio or an RS-485 transceiver with RTS
(``rts_send_delay`` before the first byte, ``rts_off_delay`` after the last; 1747-RM001 p. 13-59).
``rs485=True`` instead hands RTS to the kernel's RS-485 mode (pyserial ``rs485_mode``, Linux
TIOCSRS485: RTS on while the UART sends, exact to the bit).  An ``rfc2217://`` port gives setters
too, but each change is a SET-CONTROL command over TCP: RTS follows the data by a network round trip,
too late to key a radio precisely; use the device server's own RTS toggle / RS-485 mode.  A
``socket://`` port (raw TCP) has no modem lines: :func:`modem_lines` returns None and the device
server must drive RTS itself (its "RTS toggle" or automatic RS-485 direction setting).
Echo suppression (2-wire RS-485, the master hears its own bytes) is the half-duplex core's
(``LineConfig.echo``): it strips exactly the bytes it sent, wherever the port is.
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any
from urllib.parse import urlsplit

from gateway.errors import LinkDown
from gateway.frozen import frozen
from gateway.logutil import redact_url
from gateway.streams import MISSING_PORT_HINT, ByteStream, SerialSettings

__all__ = [
    "LOW_7_BITS",
    "ByteStream",
    "ModemLines",
    "ProtocolStream",
    "SerialSettings",
    "SoftwareParityStream",
    "TracingStream",
    "describe_url",
    "enable_rs485",
    "modem_lines",
    "open_stream",
]

log = logging.getLogger(__name__)

try:
    import termios

    _TERMIOS_ERRORS: tuple[type[Exception], ...] = (termios.error,)
except ImportError:  # Windows
    _TERMIOS_ERRORS = ()


class ProtocolStream(ByteStream, asyncio.Protocol):
    """A TCP connection or serial port as an asyncio protocol.

    Bytes are handed to the receiver straight from the transport's callback once
    ``start_push`` was called (no reader task in between: one event-loop pass less per reply),
    or buffered for ``read``.
    """

    def __init__(self, name: str) -> None:
        self._name = name
        self._transport: asyncio.Transport | None = None
        self._buffer = bytearray()
        self._closed_reason = ""
        self._wakeup: asyncio.Future[None] | None = None
        self._receive: Callable[[bytes], None] | None = None
        self._lost: Callable[[str], None] | None = None
        #: the pyserial port of a local or rfc2217 serial port (modem lines), None for TCP
        self.serial_port: Any = None

    # asyncio.Protocol
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        if self._receive is not None:
            self._receive(data)
            return
        self._buffer += data
        self._wake()

    def connection_lost(self, exc: Exception | None) -> None:
        self._closed_reason = str(exc) if exc else "connection closed by the other side"
        if self._lost is not None:
            self._lost(f"{self._name}: {self._closed_reason}")
        self._wake()

    def eof_received(self) -> bool | None:
        return False  # close the transport: connection_lost follows

    def _wake(self) -> None:
        if self._wakeup is not None and not self._wakeup.done():
            self._wakeup.set_result(None)

    # ByteStream
    async def read(self) -> bytes:
        while not self._buffer:
            if self._closed_reason:
                raise LinkDown(f"{self._name}: {self._closed_reason}")
            self._wakeup = asyncio.get_running_loop().create_future()
            await self._wakeup
        data = bytes(self._buffer)
        self._buffer.clear()
        return data

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        if self._buffer:
            receive(bytes(self._buffer))
            self._buffer.clear()
        self._receive, self._lost = receive, lost
        if self._closed_reason:
            lost(f"{self._name}: {self._closed_reason}")
        return True

    def write(self, data: bytes) -> None:
        transport = self._transport
        if transport is None or transport.is_closing():
            raise LinkDown(f"{self._name}: port is closed")
        try:
            transport.write(data)
        except OSError as exc:
            raise LinkDown(f"{self._name}: {exc}") from exc

    async def close(self) -> None:
        self._receive = self._lost = None
        if self._transport is not None and not self._transport.is_closing():
            self._transport.close()

    @property
    def transport(self) -> asyncio.Transport | None:
        return self._transport


_trace_max_bytes = 10_000_000
_trace_backups = 3


def set_trace_limits(max_bytes: int, backups: int) -> None:
    """Size cap of a trace file and rotated copies kept (``[logging] trace_max_bytes``, ``trace_backups``)."""
    global _trace_max_bytes, _trace_backups
    if max_bytes < 1 or backups < 0:
        raise ValueError(f"trace limits must be positive (got {max_bytes}, {backups})")
    _trace_max_bytes, _trace_backups = max_bytes, backups


class TraceFile:
    """An append-only trace file created 0600, rotated at ``max_bytes`` (``path.1`` .. ``path.N``).

    A busy link writes about 0.6 MB/s of trace: without a cap a forgotten trace fills the disk.
    With ``backups = 0`` the file is truncated when full. The file holds what went over the line
    (values, and passwords if a controller is sent any), hence owner-only permissions; an existing
    file's permissions are tightened to 0600 too.
    """

    def __init__(self, path: Path, max_bytes: int | None = None, backups: int | None = None) -> None:
        self.path = path
        self.max_bytes = _trace_max_bytes if max_bytes is None else max_bytes
        self.backups = _trace_backups if backups is None else backups
        self._file = self._open()
        self._size = self._file.tell()

    def _open(self) -> IO[str]:
        descriptor = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        try:
            os.fchmod(descriptor, 0o600)
        except OSError:
            pass
        trace = os.fdopen(descriptor, "a", encoding="ascii")
        trace.seek(0, os.SEEK_END)
        return trace

    def write(self, line: str) -> None:
        if self._size + len(line) > self.max_bytes and self._size:
            self._rotate()
        self._file.write(line)
        self._file.flush()
        self._size += len(line)

    def _rotate(self) -> None:
        self._file.close()
        if self.backups:
            for index in range(self.backups - 1, 0, -1):
                older = self.path.with_name(f"{self.path.name}.{index}")
                if older.exists():
                    os.replace(older, self.path.with_name(f"{self.path.name}.{index + 1}"))
            os.replace(self.path, self.path.with_name(f"{self.path.name}.1"))
        else:
            os.truncate(self.path, 0)
        self._file = self._open()
        self._size = 0

    def close(self) -> None:
        self._file.close()


class TracingStream(ByteStream):
    """Records every byte in both directions with a timestamp, for troubleshooting.

    One line per chunk: ``<unix time> <link> <TX|RX> <hex bytes>  |<printable ASCII>|``.
    """

    def __init__(self, inner: ByteStream, trace: TraceFile | IO[str], link: str) -> None:
        self._inner = inner
        self._trace = trace
        self._link = link

    def _record(self, direction: str, data: bytes) -> None:
        printable = "".join(chr(b) if 32 <= b < 127 else "." for b in data)
        self._trace.write(f"{time.time():.6f} {self._link} {direction} {data.hex(' ')}  |{printable}|\n")
        if not isinstance(self._trace, TraceFile):
            self._trace.flush()

    async def read(self) -> bytes:
        data = await self._inner.read()
        self._record("RX", data)
        return data

    def write(self, data: bytes) -> None:
        self._record("TX", data)
        self._inner.write(data)

    async def close(self) -> None:
        await self._inner.close()
        self._trace.close()

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        def traced(data: bytes) -> None:
            self._record("RX", data)
            receive(data)

        return self._inner.start_push(traced, lost)

    def char_time(self, settings: SerialSettings) -> float:
        return self._inner.char_time(settings)


def _parity_table(odd: bool) -> bytes:
    """``bytes.translate`` table: the low 7 bits of each byte, with the parity bit as bit 7."""
    return bytes((b & 0x7F) | ((bin(b & 0x7F).count("1") + odd) & 1) << 7 for b in range(256))


_EVEN, _ODD = _parity_table(False), _parity_table(True)
#: ``bytes.translate`` table: the low 7 bits of each byte (7 data bits, the parity bit cleared).
LOW_7_BITS = bytes(b & 0x7F for b in range(256))


class SoftwareParityStream(ByteStream):
    """7 data bits with parity over a port opened at 8N1: the parity bit is computed here and sent
    as bit 7, so the wire carries the same bits as 7E1 (7O1); bit 7 of what arrives is dropped.

    For ports that refuse 7 data bits with parity (pseudo-terminals, some USB adapters).  A
    received character's parity is not checked (the protocols check their own CRC / BCC).
    """

    def __init__(self, inner: ByteStream, parity: str) -> None:
        self._inner = inner
        self._table = _ODD if parity == "O" else _EVEN

    async def read(self) -> bytes:
        return (await self._inner.read()).translate(LOW_7_BITS)

    def write(self, data: bytes) -> None:
        self._inner.write(data.translate(self._table))

    async def close(self) -> None:
        await self._inner.close()

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        return self._inner.start_push(lambda data: receive(data.translate(LOW_7_BITS)), lost)

    def char_time(self, settings: SerialSettings) -> float:
        return self._inner.char_time(settings)


#: Ports already reported as refusing 7 data bits with parity (reported once per process).
_SOFTWARE_PARITY_LOGGED: set[str] = set()


@frozen
class ModemLines:
    """RTS / DTR setters of an open serial port (``remote``: an rfc2217 port, changes go over TCP)."""

    set_rts: Callable[[bool], None]
    set_dtr: Callable[[bool], None]
    remote: bool


def modem_lines(stream: ByteStream) -> ModemLines | None:
    """The modem line setters of ``stream`` (through tracing / software-parity wrappers), or None
    when it has none (``socket://``, ``sim://``, a pseudo-terminal without modem lines)."""
    while isinstance(stream, TracingStream | SoftwareParityStream):
        stream = stream._inner
    port = stream.serial_port if isinstance(stream, ProtocolStream) else None
    if port is None:
        return None
    import serial

    errors = (OSError, ValueError, serial.SerialException)

    def setter(name: str) -> Callable[[bool], None]:
        def set_line(on: bool) -> None:
            try:
                setattr(port, name, on)
            except errors as exc:  # a port without the line: say so once, do not fail the link
                if (id(port), name) not in _MODEM_LINE_LOGGED:
                    _MODEM_LINE_LOGGED.add((id(port), name))
                    log.warning("%s: cannot set %s (%s); key the transmitter in hardware", port.port, name.upper(), exc)

        return set_line

    return ModemLines(setter("rts"), setter("dtr"), remote=type(port).__module__.endswith("rfc2217"))


def enable_rs485(stream: ByteStream, *, delay_before_tx: float = 0.0, delay_before_rx: float = 0.0) -> bool:
    """Hand RTS to the kernel's RS-485 mode (RTS on while sending); False when the port cannot."""
    while isinstance(stream, TracingStream | SoftwareParityStream):
        stream = stream._inner
    port = stream.serial_port if isinstance(stream, ProtocolStream) else None
    if port is None:
        return False
    import serial
    import serial.rs485

    try:
        port.rs485_mode = serial.rs485.RS485Settings(
            rts_level_for_tx=True, rts_level_for_rx=False,
            delay_before_tx=delay_before_tx or None, delay_before_rx=delay_before_rx or None,
        )
    except (OSError, ValueError, NotImplementedError, serial.SerialException) as exc:
        log.warning("%s: the kernel RS-485 mode is not available (%s)", port.port, exc)
        return False
    return True


#: (port, line) pairs already reported as not settable.
_MODEM_LINE_LOGGED: set[tuple[int, str]] = set()


def describe_url(url: str) -> str:
    """A URL with any query options and credentials (``user:password@``) removed, for log lines."""
    return redact_url(url.split("?", 1)[0])


async def open_stream(
    url: str,
    settings: SerialSettings,
    *,
    connect_timeout: float = 5.0,
    trace: Path | None = None,
    link_name: str = "",
) -> ByteStream:
    """Open ``url``.  Raises ``LinkDown`` with a one-line reason when it cannot be opened."""
    try:
        stream = await _open(url, settings, connect_timeout)
    except LinkDown as exc:
        redacted = redact_url(str(exc))
        if redacted == str(exc):
            raise
        raise LinkDown(redacted) from exc.__cause__
    if trace is not None:
        try:
            trace_file = TraceFile(trace)
        except OSError as exc:
            await stream.close()
            raise LinkDown(f"{link_name or describe_url(url)}: cannot open trace file {trace}: {exc}") from exc
        return TracingStream(stream, trace_file, link_name or describe_url(url))
    return stream


async def _open(url: str, settings: SerialSettings, connect_timeout: float) -> ByteStream:
    parts = urlsplit(url)
    scheme = parts.scheme.lower() if "://" in url else ""
    if scheme == "sim":
        from gateway.sim import open_sim_stream

        return open_sim_stream(url, settings)
    if scheme == "socket":
        if not parts.hostname or parts.port is None:
            raise LinkDown(f"{url}: expected socket://host:port")
        stream = ProtocolStream(describe_url(url))
        try:
            await asyncio.wait_for(
                asyncio.get_running_loop().create_connection(lambda: stream, parts.hostname, parts.port),
                connect_timeout,
            )
        except TimeoutError as exc:
            raise LinkDown(f"{url}: no answer from the device server within {connect_timeout:g} s") from exc
        except OSError as exc:
            raise LinkDown(f"{url}: {exc.strerror or exc}") from exc
        return stream
    if scheme in ("", "rfc2217", "file") or url.upper().startswith("COM"):
        _check_path(url)
        return await _open_serial(url, settings, connect_timeout)
    raise LinkDown(f"{url}: unsupported port URL (use /dev/tty..., socket://, rfc2217:// or sim://)")


def _check_path(url: str) -> None:
    """``LinkDown`` for a port path with nothing behind it (a stat, not an open: it cannot block)."""
    if url.startswith("/") and not os.path.exists(url):
        raise LinkDown(f"{url}: no such serial port (nothing at this path): {MISSING_PORT_HINT}")


async def _open_serial(url: str, settings: SerialSettings, connect_timeout: float) -> ByteStream:
    if settings.bytesize != 7 or settings.parity not in ("E", "O"):
        return await _open_serial_as(url, settings, connect_timeout)
    try:
        return await _open_serial_as(url, settings, connect_timeout)
    except _LineSettingsRefused as refused:
        # 7E1 refused (a pseudo-terminal, some USB adapters): 8N1 with the parity bit as bit 7
        # puts the same bits on the wire.
        eight = SerialSettings(settings.baudrate, 8, "N", settings.stopbits)
        try:
            stream = await _open_serial_as(url, eight, connect_timeout)
        except _LineSettingsRefused:
            raise LinkDown(str(refused)) from refused
        if url not in _SOFTWARE_PARITY_LOGGED:
            _SOFTWARE_PARITY_LOGGED.add(url)
            log.info(
                "%s refuses %s%s%s: using 8N1 with the parity bit computed in software (the same bits on the wire)",
                url, settings.bytesize, settings.parity, settings.stopbits,
            )
        return SoftwareParityStream(stream, settings.parity)


class _LineSettingsRefused(LinkDown):
    """The port exists but refused the line settings (termios EINVAL)."""


async def _open_serial_as(url: str, settings: SerialSettings, connect_timeout: float) -> ByteStream:
    import serial
    import serial_asyncio_fast

    open_errors: tuple[type[Exception], ...] = (OSError, ValueError, serial.SerialException, *_TERMIOS_ERRORS)

    stream = ProtocolStream(redact_url(url))
    try:
        transport, _ = await asyncio.wait_for(
            serial_asyncio_fast.create_serial_connection(
                asyncio.get_running_loop(),
                lambda: stream,
                url,
                baudrate=settings.baudrate,
                bytesize=settings.bytesize,
                parity=settings.parity,
                stopbits=settings.stopbits,
            ),
            connect_timeout,
        )
    except TimeoutError as exc:
        raise LinkDown(f"{url}: port did not open within {connect_timeout:g} s") from exc
    except open_errors as exc:
        # termios.error (not an OSError): the port refused the line settings, e.g. 7E1 on a pty
        error = _LineSettingsRefused if isinstance(exc, _TERMIOS_ERRORS) else LinkDown
        raise error(f"{url}: cannot open with {settings.baudrate} {settings.bytesize}{settings.parity}"
                    f"{settings.stopbits}: {exc}") from exc
    port = transport.get_extra_info("serial")
    if isinstance(port, serial.SerialBase):
        stream.serial_port = port
        try:
            # 1745-PCC: DTR to the SPACING condition (asserted), RTS to MARKING (not asserted).
            port.dtr = True
            port.rts = False
        except (OSError, ValueError, serial.SerialException):
            pass  # pseudo-terminals and some device servers have no modem lines
    return stream
