"""Run a simulated controller in-process, on a TCP port, on a pseudo-terminal or on an existing tty.

A simulated device is sans-I/O: ``receive(data, now) -> [Output(delay, data)]``.  This module
moves its bytes, optionally through a *line model* that paces every character at the line's
baud rate (``bits_per_char / baudrate`` seconds each, both directions independent, as on a
full-duplex serial line) plus the device's turnaround delay.  A device whose class says
``self_paced = True`` (a multi-drop line: it judges collisions on its own clock) is served without
a line model: asking for one is a clear error.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import termios
import tty
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from gateway.errors import GatewayError, LinkDown
from gateway.frozen import frozen
from gateway.streams import ByteStream, SerialSettings

__all__ = ["LineModel", "Output", "SimDevice", "SimOutput", "SimStream", "close_tcp", "serve_pty", "serve_tcp",
           "serve_tty"]

log = logging.getLogger(__name__)


class SimOutput(Protocol):
    @property
    def delay(self) -> float: ...
    @property
    def data(self) -> bytes: ...


@frozen
class Output:
    """A simulated device's :class:`SimOutput`: bytes to put on the line after ``delay`` seconds."""

    delay: float
    data: bytes


class SimDevice(Protocol):
    """A simulated controller.  ``receive`` gets host bytes; ``poll`` runs its timers.

    ``next_deadline()`` says when ``poll(now)`` must be called next (None: no timer running);
    devices without timers return None and an empty list.
    """

    def receive(self, data: bytes, now: float) -> Sequence[SimOutput]: ...

    def poll(self, now: float) -> Sequence[SimOutput]: ...

    def next_deadline(self) -> float | None: ...


@dataclass
class LineModel:
    """One direction of a serial line: characters leave one after another at ``char_time``."""

    char_time: float = 0.0  # 0: unpaced
    free_at: float = 0.0

    def schedule(self, ready: float, length: int) -> float:
        """Bytes ready to go at ``ready`` arrive completely at the returned time."""
        if self.char_time <= 0:
            return ready
        start = max(ready, self.free_at)
        self.free_at = start + length * self.char_time
        return self.free_at


def _line_models(settings: SerialSettings | None) -> tuple[LineModel, LineModel]:
    char_time = settings.char_time if settings is not None else 0.0
    return LineModel(char_time), LineModel(char_time)


def _check_pacing(device: SimDevice, settings: SerialSettings | None, turnaround: float) -> None:
    """A device that paces its own bytes (``self_paced``, e.g. a multi-drop line) takes no line model."""
    if getattr(device, "self_paced", False) and (settings is not None or turnaround):
        raise GatewayError(
            f"{type(device).__name__} paces its own bytes (it judges collisions on its own clock): serve it "
            "without pacing or turnaround; give it char_time=S and turnaround=S options instead"
        )


class _Wire:
    """Delivers device bytes to ``sink`` and host bytes to the device, through the line models."""

    def __init__(
        self,
        device: SimDevice,
        sink: Callable[[bytes], None],
        settings: SerialSettings | None,
        turnaround: float = 0.0,
    ) -> None:
        _check_pacing(device, settings, turnaround)
        self._device = device
        self._sink = sink
        self._to_device, self._to_host = _line_models(settings)
        self._turnaround = turnaround
        self._loop = asyncio.get_running_loop()
        self._handles: set[asyncio.TimerHandle] = set()
        self._timer: asyncio.TimerHandle | None = None
        self.closed = False
        self._arm_timer()  # a device that speaks first (an initiating peer) starts on its own clock

    def _later(self, when: float, callback: Callable[[bytes], None], data: bytes) -> None:
        now = self._loop.time()
        if when <= now:
            callback(data)
            return
        handle: asyncio.TimerHandle

        def fire() -> None:
            self._handles.discard(handle)
            callback(data)

        handle = self._loop.call_at(when, fire)
        self._handles.add(handle)

    def from_host(self, data: bytes) -> None:
        if self.closed:
            return
        arrival = self._to_device.schedule(self._loop.time(), len(data))
        self._later(arrival, self._into_device, data)

    def _into_device(self, data: bytes) -> None:
        if self.closed:
            return
        now = self._loop.time()
        self._emit(now, self._device.receive(data, now))

    def _emit(self, now: float, outputs: Sequence[SimOutput]) -> None:
        for out in outputs:
            arrival = self._to_host.schedule(now + self._turnaround + out.delay, len(out.data))
            self._later(arrival, self._out_to_host, out.data)
        self._arm_timer()

    def _arm_timer(self) -> None:
        deadline = self._device.next_deadline()
        if self._timer is not None:
            if deadline is not None and self._timer.when() == deadline:
                return
            self._timer.cancel()
            self._timer = None
        if deadline is not None and not self.closed:
            self._timer = self._loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        if not self.closed:
            now = self._loop.time()
            self._emit(now, self._device.poll(now))

    def _out_to_host(self, data: bytes) -> None:
        if not self.closed:
            self._sink(data)

    def close(self) -> None:
        self.closed = True
        if self._timer is not None:
            self._timer.cancel()
        for handle in self._handles:
            handle.cancel()
        self._handles.clear()


class SimStream(ByteStream):
    """An in-process byte stream to a simulated device (``sim://`` URLs)."""

    def __init__(self, device: SimDevice, settings: SerialSettings | None = None, turnaround: float = 0.0):
        self._paced = settings is not None
        self._queue: asyncio.Queue[bytes] = asyncio.Queue()
        self._receive: Callable[[bytes], None] | None = None
        self._loop = asyncio.get_running_loop()
        self._wire = _Wire(device, self._deliver, settings, turnaround)

    def _deliver(self, data: bytes) -> None:
        if self._receive is None:
            self._queue.put_nowait(data)
        else:
            # never re-entrantly inside the driver's write(): an unpaced device answers at once
            self._loop.call_soon(self._push, data)

    def _push(self, data: bytes) -> None:
        if self._receive is not None and not self._wire.closed:
            self._receive(data)

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        while not self._queue.empty():
            data = self._queue.get_nowait()
            if data:
                receive(data)
        self._receive = receive
        return True

    async def read(self) -> bytes:
        if self._wire.closed and self._queue.empty():
            raise LinkDown("simulator stream closed")
        data = await self._queue.get()
        if not data:
            raise LinkDown("simulator stream closed")
        # Coalesce what is already there, as a serial driver's read would.
        while not self._queue.empty():
            more = self._queue.get_nowait()
            if not more:
                self._queue.put_nowait(b"")
                break
            data += more
        return data

    def char_time(self, settings: SerialSettings) -> float:
        return settings.char_time if self._paced else 0.0  # unpaced: bytes arrive at once

    def write(self, data: bytes) -> None:
        if self._wire.closed:
            raise LinkDown("simulator stream closed")
        self._wire.from_host(data)

    async def close(self) -> None:
        self._receive = None
        if not self._wire.closed:
            self._wire.close()
            self._queue.put_nowait(b"")


class _TcpDeviceProtocol(asyncio.Protocol):
    def __init__(
        self,
        device: SimDevice,
        settings: SerialSettings | None,
        turnaround: float,
        clients: set[asyncio.Transport],
    ) -> None:
        self._device = device
        self._settings = settings
        self._turnaround = turnaround
        self._clients = clients
        self._wire: _Wire | None = None
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        self._clients.add(transport)
        self._wire = _Wire(self._device, self._send, self._settings, self._turnaround)
        log.info("simulator: client connected from %s", transport.get_extra_info("peername"))

    def _send(self, data: bytes) -> None:
        if self._transport is not None and not self._transport.is_closing():
            self._transport.write(data)

    def data_received(self, data: bytes) -> None:
        if self._wire is not None:
            self._wire.from_host(data)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._transport is not None:
            self._clients.discard(self._transport)
        if self._wire is not None:
            self._wire.close()
        log.info("simulator: client disconnected")


#: The client connections of each server made by serve_tcp (closed by close_tcp).
_tcp_clients: weakref.WeakKeyDictionary[asyncio.Server, set[asyncio.Transport]] = weakref.WeakKeyDictionary()


async def serve_tcp(
    device: SimDevice,
    host: str,
    port: int,
    *,
    settings: SerialSettings | None = None,
    turnaround: float = 0.0,
) -> asyncio.Server:
    """Serve ``device`` on a TCP port, as a serial device server in raw mode would."""
    _check_pacing(device, settings, turnaround)
    loop = asyncio.get_running_loop()
    clients: set[asyncio.Transport] = set()
    server = await loop.create_server(
        lambda: _TcpDeviceProtocol(device, settings, turnaround, clients), host, port
    )
    _tcp_clients[server] = clients
    return server


async def close_tcp(server: asyncio.Server) -> None:
    """Stop a server made by :func:`serve_tcp` and drop its client connections.

    ``asyncio.Server.close()`` only stops listening: the clients would go on talking to the
    simulator (and from Python 3.12 ``wait_closed()`` waits for them).  A device server that is
    switched off drops them, and so does this.
    """
    server.close()
    for transport in list(_tcp_clients.get(server, ())):
        transport.abort()
    await server.wait_closed()


class PtyServer:
    """``device`` on a tty: a new pseudo-terminal (``port`` None: a serial client opens ``path`` as if
    it were a port), or an existing one, ``port``: a serial port, or one end of a pty pair (socat's)."""

    def __init__(self, device: SimDevice, settings: SerialSettings | None, turnaround: float, *,
                 port: str | None = None, line: SerialSettings | None = None) -> None:
        self._slave: int | None = None
        if port is None:
            self._master, slave = os.openpty()
            tty.setraw(slave)
            self.path = os.ttyname(slave)
            self._slave = slave  # kept open so the pty survives clients closing and reopening it
        else:
            try:
                self._master = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            except OSError as exc:
                raise GatewayError(f"{port}: cannot open: {exc.strerror or exc}") from None
            self.path = port
            try:
                tty.setraw(self._master)
                if line is not None:
                    _set_line(self._master, line)
            except termios.error as exc:
                os.close(self._master)
                raise GatewayError(f"{port}: not a tty ({exc.args[-1]})") from None
        os.set_blocking(self._master, False)
        self._wire = _Wire(device, self._send, settings, turnaround)
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self._master, self._readable)

    def _readable(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        if data:
            self._wire.from_host(data)

    def _send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self._master, data)

    def close(self) -> None:
        self._loop.remove_reader(self._master)
        self._wire.close()
        os.close(self._master)
        if self._slave is not None:
            os.close(self._slave)


def _set_line(fd: int, line: SerialSettings) -> None:
    """Put ``line``'s speed and character format on the raw tty ``fd`` (a pseudo-terminal takes them
    and ignores them; a serial port sends them)."""
    attributes = termios.tcgetattr(fd)
    cflag = attributes[2] & ~(termios.CSIZE | termios.PARENB | termios.PARODD | termios.CSTOPB)
    cflag |= termios.CS7 if line.bytesize == 7 else termios.CS8
    if line.parity != "N":
        cflag |= termios.PARENB | (termios.PARODD if line.parity == "O" else 0)
    if line.stopbits == 2:
        cflag |= termios.CSTOPB
    attributes[2] = cflag | termios.CLOCAL | termios.CREAD
    speed = getattr(termios, f"B{line.baudrate}", None)
    if speed is not None:
        attributes[4] = attributes[5] = speed
    termios.tcsetattr(fd, termios.TCSANOW, attributes)


def serve_pty(device: SimDevice, *, settings: SerialSettings | None = None, turnaround: float = 0.0) -> PtyServer:
    """``device`` on a new pseudo-terminal (its ``path``)."""
    return PtyServer(device, settings, turnaround)


def serve_tty(device: SimDevice, port: str, line: SerialSettings, *, settings: SerialSettings | None = None,
              turnaround: float = 0.0) -> PtyServer:
    """``device`` on the existing tty ``port``, set to ``line`` (``GatewayError`` when it cannot be opened)."""
    return PtyServer(device, settings, turnaround, port=port, line=line)
