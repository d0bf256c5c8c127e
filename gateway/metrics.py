"""HTTP ``/metrics`` (Prometheus text format) and ``/healthz`` for the running gateway.

The values are read from the live gateway objects at scrape time: a custom collector on a private
:class:`~prometheus_client.CollectorRegistry` turns the links' and Modbus servers' counters into
metric families when Prometheus asks, so nothing runs in the background and nothing is copied.

The metric families, their labels and help texts are listed in ``docs/reference/metrics.md``, which
``tools/gen_reference.py`` generates from this collector (a test fails when it is stale): per link
(labels ``link``, ``unit``), the line's budget of each polled link (``docs/guide/freshness.md``), the
numbers a driver reports itself (``driver.metrics()``: ``link_<key>_total``, ``link_<key>``,
``link_<key>_seconds``), per Modbus server (label ``server``), the config file and its reloads
(``gateway.reload``), and with ``[sparkplug]`` the edge node's session (``gateway.sparkplug.report``),
with ``[opcua]`` the OPC UA server's sessions (``gateway.opcua.report``).

``/healthz`` answers 200 when every link's verdict is up (``gateway.freshness``: the controller
answers and its fast-class data is younger than its stale limit, ``stale_limit_seconds``), 503
otherwise, with a JSON body naming each link's state (no paths, no
configuration beyond the link names and unit ids).

The same listener serves the status page (``/``) and its JSON API (``/api/...``), read-only:
:mod:`gateway.status`.

The HTTP side is deliberately tiny: one request per connection (``Connection: close``), ``GET``
and ``HEAD`` only, HTTP/1.0 and HTTP/1.1 only (others get 505), a bounded request head, timeouts
on reading and writing, an ``allow`` list of client networks (others are closed at accept, before
a byte is read) and a cap on concurrent connections (``max_connections``; more are closed at
once). Refusals are logged: the first of each cause at once, then a count per interval with the
addresses (:class:`gateway.logutil.RepeatLog`). It is meant for a Prometheus scraper, a container
health check and a status page that asks once a second, not for heavy browsing.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import re
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, Final, Protocol

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric

from gateway.config import parse_listen
from gateway.logutil import RepeatLog
from gateway.modbus.admission import IPNetwork, format_address, host_allowed, peer_host
from gateway.opcua.report import opcua_families
from gateway.sparkplug.report import families as sparkplug_families
from gateway.status import JSON_CONTENT_TYPE, StatusPage, public_error

if TYPE_CHECKING:
    from gateway.config.link import LinkBase
    from gateway.modbus.server import ModbusTcpServer
    from gateway.reload import ConfigStatus
    from gateway.unit import Unit

__all__ = ["GatewayView", "MetricsServer", "health"]

log = logging.getLogger("gateway.metrics")

PREFIX: Final = "slc_gateway_"

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


class GatewayView(Protocol):
    """What the metrics server reads from the gateway (:class:`gateway.app.Gateway` has it)."""

    @property
    def units(self) -> Sequence[Unit[Any, Any]]: ...

    @property
    def servers(self) -> Sequence[ModbusTcpServer]: ...


# --------------------------------------------------------------------------------------------
# Prometheus


def _counter(name: str, documentation: str, labels: Sequence[str]) -> CounterMetricFamily:
    return CounterMetricFamily(PREFIX + name, documentation, labels=labels)


def _gauge(name: str, documentation: str, labels: Sequence[str]) -> GaugeMetricFamily:
    return GaugeMetricFamily(PREFIX + name, documentation, labels=labels)


class _GatewayCollector:
    """Reads the gateway's links and servers at scrape time (runs on the event loop thread)."""

    def __init__(self, gateway: GatewayView, config: ConfigStatus | None = None) -> None:
        self._gateway = gateway
        self._config = config

    def describe(self) -> Iterator[Metric]:
        # The families without samples: lets the registry check names at registration.
        yield from self._link_families((), 0.0)
        yield from self._server_families(())
        yield from _config_families(None)

    def collect(self) -> Iterator[Metric]:
        # Called by generate_latest() on the event loop thread, where the counters live.
        yield from self._link_families(self._gateway.units, asyncio.get_running_loop().time())
        yield from self._server_families(self._gateway.servers)
        if self._config is not None:
            yield from _config_families(self._config)
        yield from sparkplug_families(getattr(self._gateway, "sparkplug", None))
        yield from opcua_families(getattr(self._gateway, "opcua", None))

    @staticmethod
    def _link_families(units: Sequence[Unit[Any, Any]], now: float) -> list[Metric]:
        link = ("link", "unit")
        link_up = _gauge("link_up", "1 if the link is open and the controller answered the last transaction.", link)
        connected = _gauge("link_connected", "1 if the link's port or socket is open.", link)
        age = _gauge("data_age_seconds", "Age of the oldest fast-class value in the cache (+Inf: never read).", link)
        stale = _gauge("stale_after_seconds", "Data older than this is not served (stale_after).", link)
        plain = {
            "transactions": _counter("transactions", "Transactions the controller answered.", link),
            "errors": _counter("errors", "Transactions that failed.", link),
            "timeouts": _counter("timeouts", "Transactions that timed out.", link),
            "crc_errors": _counter("crc_errors", "Replies with a bad CRC or BCC.", link),
            "refusals": _counter("refusals", "Requests the controller refused.", link),
            "faults": _counter("faults", "Faults the controller reported.", link),
            "reconnects": _counter("reconnects", "Times the link was reopened.", link),
        }
        retries = _counter(
            "retries",
            "Protocol retries by kind (each link kind gives its kinds of retry their names).",
            (*link, "kind"),
        )
        byte_count = _counter("bytes", "Bytes on the link by direction.", (*link, "direction"))
        writes = _counter("write_requests", "Modbus writes passed through to the controller.", link)
        write_failures = _counter("write_failures", "Modbus writes that failed.", link)
        partial = _counter("partial_writes", "Modbus writes the controller refused part-way (logged).", link)
        busy = _counter("write_busy", "Modbus writes answered 0x06: the link's write queue was full.", link)
        latency = HistogramMetricFamily(PREFIX + "write_duration_seconds",
                                        "Modbus write requests from arrival to answer (success or exception).",
                                        labels=link)
        budget = _BudgetFamilies(link)
        for unit in units:
            labels = (unit.name, str(unit.unit_id))
            driver = unit.driver
            counters = driver.counters
            verdict = unit.verdict(now)
            link_up.add_metric(labels, 1.0 if verdict.up else 0.0)
            connected.add_metric(labels, 1.0 if driver.connected else 0.0)
            age.add_metric(labels, verdict.age)
            stale.add_metric(labels, unit.stale_after)
            for field, family in plain.items():
                family.add_metric(labels, getattr(counters, field))
            for retry_kind, count in counters.retries_by_kind.items():
                retries.add_metric((*labels, retry_kind), count)
            byte_count.add_metric((*labels, "tx"), counters.bytes_sent)
            byte_count.add_metric((*labels, "rx"), counters.bytes_received)
            writes.add_metric(labels, unit.write_requests)
            write_failures.add_metric(labels, unit.write_failures)
            partial.add_metric(labels, unit.partial_writes)
            busy.add_metric(labels, unit.writes.busy_refusals)
            histogram = unit.write_latency
            latency.add_metric(labels, histogram.cumulative(), histogram.total)
            budget.add(unit, labels, now)
        static: list[Metric] = [link_up, connected, age, stale, *plain.values(), retries, byte_count, writes,
                                write_failures, partial, busy, latency, *budget.families()]
        return static + _driver_families(units, {family.name for family in static})

    @staticmethod
    def _server_families(servers: Sequence[ModbusTcpServer]) -> list[Metric]:
        server_label = ("server",)
        requests = _counter("modbus_requests", "Modbus requests by function code.", (*server_label, "function_code"))
        exceptions = _counter(
            "modbus_exceptions", "Modbus exception replies by exception code.", (*server_label, "exception_code")
        )
        backend_errors = _counter("modbus_backend_errors", "Backend failures answered with exception 4.", server_label)
        connections = _gauge("modbus_connections", "Modbus TCP connections open now.", server_label)
        accepted = _counter("modbus_connections_accepted", "Modbus TCP connections accepted.", server_label)
        refused = _counter(
            "modbus_connections_refused", "Connections refused (allow list, max_connections).", server_label
        )
        dropped = _counter(
            "modbus_connections_dropped", "Connections closed by the server (framing, idle, TLS).", server_label
        )
        evicted = _counter(
            "modbus_connections_evicted",
            "Stalled connections closed to make room (max_connections, max_handshakes).",
            server_label,
        )
        handshakes = _gauge("modbus_tls_handshakes", "TLS handshakes in progress now.", server_label)
        for server in servers:
            name = server.name
            counters = server.counters
            for function_code, count in sorted(counters.requests.items()):
                requests.add_metric((name, str(function_code)), count)
            for code, count in sorted(counters.exceptions.items()):
                exceptions.add_metric((name, str(code)), count)
            backend_errors.add_metric((name,), counters.backend_errors)
            connections.add_metric((name,), server.connection_count)
            accepted.add_metric((name,), counters.connections_accepted)
            refused.add_metric((name,), counters.connections_refused)
            dropped.add_metric((name,), counters.connections_dropped)
            evicted.add_metric((name,), server.admission.evicted)
            handshakes.add_metric((name,), server.admission.handshaking)
        return [requests, exceptions, backend_errors, connections, accepted, refused, dropped, evicted, handshakes]


class _BudgetFamilies:
    """The line's budget of each polled link (module docstring; ``gateway.status.schedule_document``)."""

    def __init__(self, link: Sequence[str]) -> None:
        by_set = (*link, "set")
        self.limit = _gauge("stale_limit_seconds", "Data age above which the link is stale (healthz).", link)
        self.refresh = _gauge("refresh_period_seconds", "Achieved refresh period of a set of blocks.", by_set)
        self.bound = _gauge("age_bound_seconds", "The bound on a block's age the read order guarantees.", by_set)
        self.transaction = _gauge("transaction_seconds", "Mean time of a read transaction.", link)
        self.use = _gauge("line_use_ratio", "Share of the last 10 s the line spent on reads.", link)
        self.blocks = _gauge("plan_blocks", "Blocks of the read plan.", link)
        self.demanded = _gauge("demanded_blocks", "Blocks a client read within demand_hold.", link)
        self.late = _counter("late_reads", "Reads that came after their block's stale limit.", link)
        self.waits = _counter("read_waits", "Modbus reads that waited for their data (read_wait).", link)

    def add(self, unit: Unit[Any, Any], labels: tuple[str, str], now: float) -> None:
        schedule, poller = unit.schedule, unit.poller
        if schedule is None or poller is None:
            return
        budget = schedule.budget(now)
        self.limit.add_metric(labels, unit.freshness.stale_limit())
        for name, value in budget.refresh.items():
            if value is not None and name != "all":
                self.refresh.add_metric((*labels, name), value)
        for name, value in budget.age_bound.items():
            if value is not None:
                self.bound.add_metric((*labels, name), value)
        if budget.transaction_time is not None:
            self.transaction.add_metric(labels, budget.transaction_time)
        if budget.line_use is not None:
            self.use.add_metric(labels, budget.line_use)
        self.blocks.add_metric(labels, budget.blocks)
        self.demanded.add_metric(labels, budget.demanded)
        self.late.add_metric(labels, schedule.late_reads)
        self.waits.add_metric(labels, poller.read_waits)

    def families(self) -> list[Metric]:
        return [self.limit, self.refresh, self.bound, self.transaction, self.use, self.blocks, self.demanded,
                self.late, self.waits]


_METRIC_KEY: Final = re.compile(r"[a-z][a-z0-9_]{0,62}")
_warned_keys: set[tuple[str, str]] = set()


def _config_families(config: ConfigStatus | None) -> list[Metric]:
    """The config file served and its reloads (``gateway.reload``)."""
    info = _gauge("config_info", "The config file served: the first 12 hex digits of its SHA-256 (always 1).",
                  ["sha256"])
    loaded = _gauge("config_loaded_timestamp_seconds", "Unix time the config served was loaded.", [])
    reloads = _counter("config_reloads", "Reloads of the config file (SIGHUP), by result.", ["result"])
    restart = _gauge("config_restart_needed", "Settings changed in the file that take a restart to apply.", [])
    if config is not None:
        if config.short_sha256 is not None:
            info.add_metric([config.short_sha256], 1)
        loaded.add_metric([], config.loaded_at)
        reloads.add_metric(["ok"], config.reloads)
        reloads.add_metric(["failed"], config.reload_failures)
        restart.add_metric([], len(config.restart_needed))
    return [info, loaded, reloads, restart]


def _driver_family(key: str, link: Sequence[str]) -> Metric:
    """``link_<key>``: a gauge for a state (``active``) or an age (``..._seconds``), else a counter."""
    name = "link_" + key
    if key.endswith("age"):
        return _gauge(name + "_seconds", f"{key} of the station or line, seconds (+Inf: never answered).", link)
    if key == "active" or key.endswith("_active"):
        return _gauge(name, f"{key}: 1 yes, 0 no (reported by the link's driver).", link)
    return _counter(name, f"{key} (reported by the link's driver), since the link was created.", link)


def _driver_numbers(unit: Unit[Any, Any]) -> dict[str, float]:
    """``unit.driver.metrics()`` if the driver has the hook; {} without it or when it fails (logged once)."""
    hook = getattr(unit.driver, "metrics", None)
    if not callable(hook):
        return {}
    try:
        numbers = hook()
    except Exception as exc:  # a driver's bug must not cost the scrape
        if (unit.name, "") not in _warned_keys:
            _warned_keys.add((unit.name, ""))
            log.warning("metrics: link %s: its driver's metrics() failed: %r", unit.name, exc)
        return {}
    if not isinstance(numbers, dict):
        return {}
    good: dict[str, float] = {}
    for key, number in numbers.items():
        if isinstance(key, str) and _METRIC_KEY.fullmatch(key) and isinstance(number, int | float):
            good[key] = float(number)
        elif (unit.name, str(key)) not in _warned_keys:
            _warned_keys.add((unit.name, str(key)))
            log.warning("metrics: link %s: driver metric %r = %r skipped: keys are lower-case names "
                        "([a-z][a-z0-9_]*), values numbers", unit.name, key, number)
    return good


def _driver_families(units: Sequence[Unit[Any, Any]], taken: set[str]) -> list[Metric]:
    """The ``link_<key>`` families of the drivers that report their own numbers (module docstring).

    A key whose family name is already one of the static families' is skipped (logged once).
    """
    link = ("link", "unit")
    families: dict[str, Metric] = {}
    for unit in units:
        labels = (unit.name, str(unit.unit_id))
        for key, number in sorted(_driver_numbers(unit).items()):
            family = families.get(key)
            if family is None:
                family = _driver_family(key, link)
                if family.name in taken:
                    if (unit.name, key) not in _warned_keys:
                        _warned_keys.add((unit.name, key))
                        log.warning("metrics: link %s: driver metric %r would shadow %s; skipped",
                                    unit.name, key, family.name)
                    continue
                families[key] = family
            if key.endswith("age") and number < 0:
                number = math.inf
            assert isinstance(family, CounterMetricFamily | GaugeMetricFamily)
            family.add_metric(labels, number)
    return list(families.values())


# --------------------------------------------------------------------------------------------
# Health


def health(gateway: GatewayView, now: float) -> tuple[bool, dict[str, object]]:
    """``(healthy, body)`` of ``/healthz`` at loop time ``now``."""
    links: dict[str, object] = {}
    healthy = True
    for unit in gateway.units:
        verdict = unit.verdict(now)
        age = verdict.age
        healthy = healthy and verdict.fresh
        links[unit.name] = {
            "unit": unit.unit_id,
            "up": verdict.up,
            "fresh": verdict.fresh,
            "age_seconds": round(age, 3) if math.isfinite(age) else None,
            "last_error": public_error(unit.driver.last_error),
        }
    return healthy, {"status": "ok" if healthy else "degraded", "links": links}


# --------------------------------------------------------------------------------------------
# HTTP


class _HttpError(Exception):
    def __init__(self, status: int, message: str = "") -> None:
        super().__init__(message or _REASONS[status])
        self.status = status


class MetricsServer:
    """The ``[metrics]`` listener: ``/metrics``, ``/healthz`` and the status page over HTTP/1.1, one
    request per connection.

    ``request_timeout``: seconds a client has to send its request head, and again to take the reply.
    ``links``: the ``[[link]]`` tables of the units, for the status page (``gateway.status.StatusPage``).
    """

    def __init__(
        self,
        gateway: GatewayView,
        listen: str,
        *,
        request_timeout: float = 5.0,
        allow: Sequence[IPNetwork] | None = None,
        max_connections: int = _MAX_CONNECTIONS,
        log_interval: float = 60.0,
        links: Sequence[LinkBase] = (),
        config: ConfigStatus | None = None,
    ) -> None:
        self.gateway = gateway
        self.status = StatusPage(gateway, links, config)
        self.host, self._requested_port = parse_listen(listen)
        self.request_timeout = request_timeout
        self.refused = 0
        self.repeat_log = RepeatLog(log, log_interval)
        self.reconfigure(allow=allow, max_connections=max_connections, log_interval=log_interval, links=links)
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(_GatewayCollector(gateway, config))
        self._server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[None]] = set()

    def reconfigure(self, *, allow: Sequence[IPNetwork] | None, max_connections: int, log_interval: float,
                    links: Sequence[LinkBase]) -> None:
        """Settings for the requests from now on (a config reload): the ``allow`` list, the connection
        cap, and the links the status page describes."""
        self.allow = None if allow is None else tuple(allow)
        self.max_connections = max_connections
        self.repeat_log.interval = log_interval
        self.status.set_links(links)

    @property
    def port(self) -> int:
        """The bound TCP port (the actual one when 0 was asked for)."""
        if self._server is None or not self._server.sockets:
            raise RuntimeError("metrics: server not started")
        port: int = self._server.sockets[0].getsockname()[1]
        return port

    async def start(self) -> None:
        """Bind and start answering."""
        if self._server is not None:
            raise RuntimeError("metrics: server already started")
        self._server = await asyncio.start_server(
            self._handle, self.host, self._requested_port, limit=_MAX_HEAD, reuse_address=True
        )
        log.info(
            "metrics: serving /metrics, /healthz and the status page on http://%s",
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
                f"metrics: connection refused, {reason}",
                host,
                "metrics: refused connection from %s: %s",
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
        except _HttpError as error:
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

    def _route(self, method: str, target: str) -> tuple[int, str, bytes, list[tuple[str, str]]]:
        path, _, query = target.partition("?")
        if path not in ("/metrics", "/healthz") and not self.status.handles(path):
            raise _HttpError(404)
        if method not in ("GET", "HEAD"):
            raise _HttpError(405)
        if path not in ("/metrics", "/healthz"):
            try:
                return self.status.route(path, query)
            except Exception:
                log.exception("metrics: the status page failed")
                raise _HttpError(500) from None
        if path == "/metrics":
            try:
                body = generate_latest(self.registry)
            except Exception:
                log.exception("metrics: collecting failed")
                raise _HttpError(500) from None
            return 200, CONTENT_TYPE_LATEST, body, []
        healthy, document = health(self.gateway, asyncio.get_running_loop().time())
        body = (json.dumps(document, separators=(",", ":")) + "\n").encode()
        return (200 if healthy else 503), JSON_CONTENT_TYPE, body, []


async def _read_head(reader: asyncio.StreamReader) -> bytes:
    """The request line and headers, up to the blank line (the reader's limit bounds the size)."""
    try:
        return await reader.readuntil(b"\r\n\r\n")
    except asyncio.LimitOverrunError:
        raise _HttpError(431) from None
    except asyncio.IncompleteReadError:
        raise ConnectionResetError("client closed before the end of its request") from None


def _parse_head(head: bytes) -> tuple[str, str]:
    """``(method, target)`` of a request head: the target is the path with its query string."""
    request_line = head.split(b"\r\n", 1)[0]
    match = _REQUEST_LINE.fullmatch(request_line)
    if match is None:
        raise _HttpError(400, "malformed request line")
    method, target, major, minor = match.groups()
    if major != b"1" or minor not in (b"0", b"1"):
        raise _HttpError(505)
    return method.decode("ascii"), target.decode("ascii", "replace")
