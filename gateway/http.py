"""The ``[metrics]`` listener: one small HTTP/1.1 server with a path -> handler table.

Its rooms sit side by side, each a handler of its own paths (``gateway.app`` builds the table):
the status page and its JSON (``gateway.status``), Prometheus ``/metrics`` (``gateway.metrics``)
and ``/healthz`` (``gateway.health``).  Each reads the gateway through one declared view
(``gateway.view``) and the one verdict (``gateway.freshness``); this module knows none of them.

Deliberately tiny: one request per connection (``Connection: close``), ``GET`` and ``HEAD`` only,
HTTP/1.0 and HTTP/1.1 only (others get 505), a bounded request head, timeouts on reading and
writing, an ``allow`` list of client networks (others are closed at accept, before a byte is read)
and a cap on concurrent connections (``max_connections``; more are closed at once).  Refusals are
logged: the first of each cause at once, then a count per interval with the addresses
(:class:`gateway.logutil.RepeatLog`).  It is meant for a Prometheus scraper, a container health
check and a status page that asks once a second, not for heavy browsing.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Callable, Sequence
from typing import Final

from gateway.config import parse_listen
from gateway.logutil import RepeatLog
from gateway.modbus.admission import IPNetwork, bound_port, format_address, host_allowed, peer_host

__all__ = ["JSON_CONTENT_TYPE", "HttpError", "HttpServer", "Response", "Routes"]

log = logging.getLogger("gateway.http")

#: (status, content type, body, extra headers) of one answer
Response = tuple[int, str, bytes, list[tuple[str, str]]]
#: a room's handler: (path, query string) -> its response
Handler = Callable[[str, str], Response]

#: The Content-Type of the JSON answers (the status API, /healthz).
JSON_CONTENT_TYPE: Final = "application/json"
_MAX_HEAD: Final = 8192
"""Largest request head (request line + headers) accepted; larger gets 431."""
_MAX_CONNECTIONS: Final = 32
"""Concurrent HTTP connections by default; more are closed at once."""
_TEXT: Final = "text/plain; charset=utf-8"
_REASONS: Final = {
    200: "OK",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    408: "Request Timeout",
    431: "Request Header Fields Too Large",
    500: "Internal Server Error",
    503: "Service Unavailable",
    505: "HTTP Version Not Supported",
}
_REQUEST_LINE: Final = re.compile(rb"([A-Z]{1,16}) (\S{1,2048}) HTTP/(\d)\.(\d)")


class HttpError(Exception):
    """An answer with an error status (its reason phrase, or ``message``, as the text body)."""

    def __init__(self, status: int, message: str = "") -> None:
        super().__init__(message or _REASONS[status])
        self.status = status


class Routes:
    """The path -> handler table: exact paths, then patterns (a path matching a pattern whole)."""

    def __init__(self) -> None:
        self._exact: dict[str, Handler] = {}
        self._patterns: list[tuple[re.Pattern[str], Handler]] = []
        #: the paths as the start-up log line names them (a pattern by its label)
        self._names: list[str] = []

    def add(self, path: str | re.Pattern[str], handler: Handler, label: str = "") -> None:
        """``handler`` answers ``path`` (a pattern: every path it matches whole, named ``label``)."""
        if isinstance(path, str):
            if path in self._exact:
                raise ValueError(f"{path} has a handler already")
            self._exact[path] = handler
        else:
            self._patterns.append((path, handler))
        self._names.append(label or (path if isinstance(path, str) else path.pattern))

    def find(self, path: str) -> Handler | None:
        handler = self._exact.get(path)
        if handler is not None:
            return handler
        return next((h for pattern, h in self._patterns if pattern.fullmatch(path)), None)

    def described(self) -> str:
        """The paths served, for the start-up log line."""
        return ", ".join(self._names)


class HttpServer:
    """One HTTP listener answering the paths of ``routes`` (module docstring), one request per connection.

    ``name``: the config section it serves, in its log lines.  ``request_timeout``: seconds a client
    has to send its request head, and again to take the reply.
    """

    def __init__(
        self,
        routes: Routes,
        listen: str,
        *,
        name: str = "metrics",
        request_timeout: float = 5.0,
        allow: Sequence[IPNetwork] | None = None,
        max_connections: int = _MAX_CONNECTIONS,
        log_interval: float = 60.0,
    ) -> None:
        self.routes = routes
        self.name = name
        self.host, self._requested_port = parse_listen(listen)
        self.request_timeout = request_timeout
        self.refused = 0
        self.repeat_log = RepeatLog(log, log_interval)
        self.reconfigure(allow=allow, max_connections=max_connections, log_interval=log_interval)
        self._server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[None]] = set()

    def reconfigure(self, *, allow: Sequence[IPNetwork] | None, max_connections: int, log_interval: float) -> None:
        """Settings for the requests from now on (a config reload): the ``allow`` list and the connection cap."""
        self.allow = None if allow is None else tuple(allow)
        self.max_connections = max_connections
        self.repeat_log.interval = log_interval

    @property
    def port(self) -> int:
        """The bound TCP port (the actual one when 0 was asked for)."""
        return bound_port(self._server, self.name)

    async def start(self) -> None:
        """Bind and start answering."""
        if self._server is not None:
            raise RuntimeError(f"{self.name}: server already started")
        self._server = await asyncio.start_server(
            self._handle, self.host, self._requested_port, limit=_MAX_HEAD, reuse_address=True
        )
        log.info(
            "%s: serving %s on http://%s", self.name, self.routes.described(),
            ", ".join(format_address(sock.getsockname()) for sock in self._server.sockets),
        )

    async def close(self) -> None:
        """Stop accepting and end the connections still open (idempotent)."""
        server, self._server = self._server, None
        if server is None:
            return
        server.close()
        for task in list(self._handlers):
            task.cancel()
        if self._handlers:
            await asyncio.wait(set(self._handlers))
        await server.wait_closed()
        self.repeat_log.flush_all()

    # -- one connection ----------------------------------------------------------------

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        peer = writer.get_extra_info("peername")
        host = peer_host(peer)
        reason = None
        if self.allow is not None and not host_allowed(host, self.allow):
            reason = "peer not in the allowed networks"
        elif task is None or len(self._handlers) >= self.max_connections:
            reason = f"already {self.max_connections} connections (max_connections)"
        if reason is not None:
            self.refused += 1
            self.repeat_log.log(
                logging.WARNING,
                f"{self.name}: connection refused, {reason}",
                host,
                f"{self.name}: refused connection from %s: %s",
                format_address(peer),
                reason,
            )
            writer.transport.abort()
            return
        assert task is not None
        self._handlers.add(task)
        try:
            await self._exchange(reader, writer)
        except (ConnectionError, TimeoutError):
            pass
        finally:
            self._handlers.discard(task)
            writer.transport.abort()  # a no-op after a clean close

    async def _exchange(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head_only = False
        try:
            async with asyncio.timeout(self.request_timeout):
                head = await _read_head(reader)
            method, path = _parse_head(head)
            head_only = method == "HEAD"
            status, content_type, body, extra = self._route(method, path)
        except HttpError as error:
            status, content_type, body = error.status, _TEXT, f"{error}\n".encode()
            extra = [("Allow", "GET, HEAD")] if error.status == 405 else []
        except TimeoutError:
            status, content_type, body, extra = 408, _TEXT, b"request timeout\n", []
        headers = [
            ("Content-Type", content_type),
            ("Content-Length", str(len(body))),
            ("Cache-Control", "no-store"),
            ("Connection", "close"),
            *extra,
        ]
        lines = [f"HTTP/1.1 {status} {_REASONS[status]}", *(f"{k}: {v}" for k, v in headers), "", ""]
        writer.write("\r\n".join(lines).encode("latin-1"))
        if not head_only:
            writer.write(body)
        async with asyncio.timeout(self.request_timeout):
            await writer.drain()
            writer.close()
            await writer.wait_closed()

    def _route(self, method: str, target: str) -> Response:
        path, _, query = target.partition("?")
        handler = self.routes.find(path)
        if handler is None:
            raise HttpError(404)
        if method not in ("GET", "HEAD"):
            raise HttpError(405)
        try:
            return handler(path, query)
        except HttpError:
            raise
        except Exception:
            log.exception("%s: %s failed", self.name, path)
            raise HttpError(500) from None


async def _read_head(reader: asyncio.StreamReader) -> bytes:
    """The request line and headers, up to the blank line (the reader's limit bounds the size)."""
    try:
        return await reader.readuntil(b"\r\n\r\n")
    except asyncio.LimitOverrunError:
        raise HttpError(431) from None
    except asyncio.IncompleteReadError:
        raise ConnectionResetError("client closed before the end of its request") from None


def _parse_head(head: bytes) -> tuple[str, str]:
    """``(method, target)`` of a request head: the target is the path with its query string."""
    request_line = head.split(b"\r\n", 1)[0]
    match = _REQUEST_LINE.fullmatch(request_line)
    if match is None:
        raise HttpError(400, "malformed request line")
    method, target, major, minor = match.groups()
    if major != b"1" or minor not in (b"0", b"1"):
        raise HttpError(505)
    return method.decode("ascii"), target.decode("ascii", "replace")
