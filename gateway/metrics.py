"""``GET /metrics``: the running gateway in the Prometheus text format (a room of ``gateway.http``).

The values are read from the live gateway objects at scrape time: a custom collector on a private
:class:`~prometheus_client.CollectorRegistry` turns the links' and Modbus servers' counters into
metric families when Prometheus asks, so nothing runs in the background and nothing is copied.

The metric families, their labels and help texts are listed in ``docs/reference/metrics.md``, which
``tools/gen_reference.py`` generates from this collector (a test fails when it is stale): per link
(labels ``link``, ``unit``), the line's budget of each polled link (``docs/guide/freshness.md``), the
numbers a driver reports itself (``driver.metrics()``: ``link_<key>_total``, ``link_<key>``,
``link_<key>_seconds``), per Modbus server (label ``server``), the config file and its reloads
(``gateway.reload``), with ``[sparkplug]`` the edge node's session and its store (``slc_gateway_sparkplug_*``),
and with ``[opcua]`` the OPC UA server's sessions (``slc_gateway_opcua_*``).

Link state and data age are the one verdict's (``gateway.freshness``), read through the declared
view of the gateway (``gateway.view``), Sparkplug's families included.
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, Final

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric

from gateway.http import HttpError, Response
from gateway.view import GatewayView

if TYPE_CHECKING:
    from gateway.modbus.server import ModbusTcpServer
    from gateway.opcua.server import OpcUaServer
    from gateway.reload import ConfigStatus
    from gateway.sparkplug.driver import SparkplugNode
    from gateway.unit import Unit

__all__ = ["Prometheus"]

log = logging.getLogger("gateway.metrics")

PREFIX: Final = "slc_gateway_"
_SPARKPLUG: Final = PREFIX + "sparkplug_"
_OPCUA: Final = PREFIX + "opcua_"


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
        yield from _sparkplug_families(self._gateway.sparkplug)
        yield from _opcua_families(self._gateway.opcua)

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
        resent = _counter("write_commands_resent", "Write commands sent again: a read-back proved them not applied.",
                          link)
        unknown = _counter("write_commands_unknown", "Write commands whose outcome stayed unknown (applied at most "
                           "once; logged).", link)
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
            resent.add_metric(labels, unit.write_tally.retried)
            unknown.add_metric(labels, unit.write_tally.unknown)
            histogram = unit.write_latency
            latency.add_metric(labels, histogram.cumulative(), histogram.total)
            budget.add(unit, labels, now)
        static: list[Metric] = [link_up, connected, age, stale, *plain.values(), retries, byte_count, writes,
                                write_failures, partial, busy, resent, unknown, latency, *budget.families()]
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
# Sparkplug


def _sparkplug_families(node: SparkplugNode | None) -> Iterator[Metric]:
    """``/metrics``: the session (gauges) and the messages and commands (counters)."""
    if node is None:
        return
    state = GaugeMetricFamily(_SPARKPLUG + "session", "1 for the state the MQTT session is in "
                              "(disconnected, connected: waiting for the primary host, online: births published).",
                              labels=["state"])
    sessions = CounterMetricFamily(_SPARKPLUG + "sessions", "MQTT sessions established (each a new bdSeq).")
    published = CounterMetricFamily(_SPARKPLUG + "messages_published", "Sparkplug messages handed to the broker.",
                                    labels=["type"])
    received = CounterMetricFamily(_SPARKPLUG + "commands_received", "NCMD, DCMD and STATE messages received.",
                                   labels=["type"])
    refused = CounterMetricFamily(_SPARKPLUG + "commands_refused",
                                  "Command metrics that changed nothing (unknown or read-only metric, bad "
                                  "payload or value) and DCMD writes that failed.", labels=["reason"])
    born = GaugeMetricFamily(_SPARKPLUG + "devices_online", "Devices (links) with a DBIRTH and no DDEATH since.")
    cpu = CounterMetricFamily(_SPARKPLUG + "cpu_seconds", "CPU the edge node's own steps took on the event loop "
                              "(reading the image, building DDATA; not the MQTT client's own work).")
    longest = GaugeMetricFamily(_SPARKPLUG + "longest_step_seconds", "The longest of those steps (CPU): the most "
                                "a Modbus answer can wait behind the edge node.")
    current = node.session_state
    for name in ("disconnected", "connected", "online"):
        state.add_metric([name], 1.0 if name == current else 0.0)
    sessions.add_metric([], node.sessions)
    for verb, count in sorted(node.sent.items()):
        published.add_metric([verb], count)
    for verb, count in sorted(node.core.received.items()):
        received.add_metric([verb], count)
    for reason, count in sorted(node.core.refused.items()):
        refused.add_metric([reason], count)
    born.add_metric([], sum(1 for device in node.core.devices if device.born))
    cpu.add_metric([], node.busy.seconds)
    longest.add_metric([], node.busy.longest)
    yield from (state, sessions, published, received, refused, born, cpu, longest)
    if node.forward is not None:
        yield from _store_families(node.forward.status())


def _store_families(store: dict[str, object]) -> Iterator[Metric]:
    """Store and forward: what the store holds, what was replayed and dropped."""
    def number(key: str) -> float:
        value = store[key]
        return float(value) if isinstance(value, int | float) else 0.0

    gauges = (
        ("store_messages", "Value changes in the store and forward store (not published yet).", "messages"),
        ("store_bytes", "Bytes the store's pages in use take.", "bytes"),
    )
    for name, text, key in gauges:
        gauge = GaugeMetricFamily(_SPARKPLUG + name, text)
        gauge.add_metric([], number(key))
        yield gauge
    oldest = GaugeMetricFamily(_SPARKPLUG + "store_oldest_timestamp_seconds",
                               "UTC time of the oldest stored change (0: the store is empty).")
    oldest.add_metric([], number("oldest_ms") / 1000)
    yield oldest
    counters = (
        ("store_replayed", "Stored changes replayed as historical DDATA.", "replayed"),
        ("store_dropped", "Stored changes dropped: the store was full (store_max_mb) or they were older than "
                          "store_max_age.", "dropped"),
    )
    for name, text, key in counters:
        counter = CounterMetricFamily(_SPARKPLUG + name, text)
        counter.add_metric([], number(key))
        yield counter


# --------------------------------------------------------------------------------------------
# OPC UA


def _opcua_families(server: OpcUaServer | None) -> Iterator[Metric]:
    """``/metrics``: sessions, subscriptions and monitored items (gauges); data changes, writes, refusals."""
    if server is None:
        return
    counts = server.counts()
    gauges = {
        "sessions": "OPC UA sessions open.",
        "subscriptions": "OPC UA subscriptions.",
        "monitored_items": "Monitored items of every subscription.",
    }
    for key, text in gauges.items():
        gauge = GaugeMetricFamily(_OPCUA + key, text)
        gauge.add_metric([], counts[key])
        yield gauge
    counters = {
        "data_changes": ("Value or status changes handed to the subscriptions (the publish rate is its rate).",
                         server.data_changes),
        "writes": ("Writes of a variable that went to the write path.", server.writes),
        "write_failures": ("Writes the controller did not confirm (refused, timed out, link down).",
                           server.write_failures),
        "rejected_logins": ("Sessions refused: a wrong user name or password, an untrusted client certificate.",
                            server.rejected_logins),
        "cpu_seconds": ("CPU of the server's publishing passes on the event loop (asyncua's own encoding not "
                        "included).", server.cpu_seconds),
    }
    for key, (text, value) in counters.items():
        counter = CounterMetricFamily(_OPCUA + key, text)
        counter.add_metric([], value)
        yield counter


class Prometheus:
    """The ``/metrics`` room of the HTTP listener (``gateway.http``): a private registry with the
    gateway's collector (module docstring)."""

    def __init__(self, gateway: GatewayView, config: ConfigStatus | None = None) -> None:
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(_GatewayCollector(gateway, config))

    def route(self, path: str, query: str) -> Response:
        try:
            body = generate_latest(self.registry)
        except Exception:
            log.exception("metrics: collecting failed")
            raise HttpError(500) from None
        return 200, CONTENT_TYPE_LATEST, body, []
