"""The edge node on ``/api/status`` and ``/metrics``: its MQTT session, what it published, the commands.

``status(node)`` is the ``sparkplug`` member of ``/api/status`` (None without ``[sparkplug]``);
``families(node)`` the Prometheus families (``slc_gateway_sparkplug_*``; none when ``node`` is None).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Final

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from gateway.sparkplug.driver import SparkplugNode

__all__ = ["families", "status"]

_METRIC_PREFIX: Final = "slc_gateway_sparkplug_"


def status(node: SparkplugNode | None) -> dict[str, object] | None:
    """The session's state and counters, for ``/api/status`` and the status page."""
    if node is None:
        return None
    core = node.core
    return {
        "broker": node.config.broker,
        "group_id": core.group_id,
        "edge_node_id": core.edge_node_id,
        "primary_host_id": core.primary_host_id,
        "state": node.session_state,
        "bd_seq": core.bd_seq,
        "sessions": node.sessions,
        "published": sum(node.sent.values()),
        "published_by_type": dict(sorted(node.sent.items())),
        "commands": sum(core.received.values()),
        "commands_by_type": dict(sorted(core.received.items())),
        "refused": sum(core.refused.values()),
        "refused_by_reason": dict(sorted(core.refused.items())),
        "write_failures": node.write_failures,
        "cpu_seconds": round(node.busy.seconds, 6),
        "longest_step_seconds": round(node.busy.longest, 6),
        "devices_online": sum(1 for device in core.devices if device.born),
        "devices": len(core.devices),
        "store": None if node.forward is None else node.forward.status(),
    }


def families(node: SparkplugNode | None) -> Iterator[Metric]:
    """``/metrics``: the session (gauges) and the messages and commands (counters)."""
    if node is None:
        return
    state = GaugeMetricFamily(_METRIC_PREFIX + "session", "1 for the state the MQTT session is in "
                              "(disconnected, connected: waiting for the primary host, online: births published).",
                              labels=["state"])
    sessions = CounterMetricFamily(_METRIC_PREFIX + "sessions", "MQTT sessions established (each a new bdSeq).")
    published = CounterMetricFamily(_METRIC_PREFIX + "messages_published", "Sparkplug messages handed to the broker.",
                                    labels=["type"])
    received = CounterMetricFamily(_METRIC_PREFIX + "commands_received", "NCMD, DCMD and STATE messages received.",
                                   labels=["type"])
    refused = CounterMetricFamily(_METRIC_PREFIX + "commands_refused",
                                  "Command metrics that changed nothing (unknown or read-only metric, bad "
                                  "payload or value) and DCMD writes that failed.", labels=["reason"])
    born = GaugeMetricFamily(_METRIC_PREFIX + "devices_online", "Devices (links) with a DBIRTH and no DDEATH since.")
    cpu = CounterMetricFamily(_METRIC_PREFIX + "cpu_seconds", "CPU the edge node's own steps took on the event loop "
                              "(reading the image, building DDATA; not the MQTT client's own work).")
    longest = GaugeMetricFamily(_METRIC_PREFIX + "longest_step_seconds", "The longest of those steps (CPU): the most "
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
        gauge = GaugeMetricFamily(_METRIC_PREFIX + name, text)
        gauge.add_metric([], number(key))
        yield gauge
    oldest = GaugeMetricFamily(_METRIC_PREFIX + "store_oldest_timestamp_seconds",
                               "UTC time of the oldest stored change (0: the store is empty).")
    oldest.add_metric([], number("oldest_ms") / 1000)
    yield oldest
    counters = (
        ("store_replayed", "Stored changes replayed as historical DDATA.", "replayed"),
        ("store_dropped", "Stored changes dropped: the store was full (store_max_mb) or they were older than "
                          "store_max_age.", "dropped"),
    )
    for name, text, key in counters:
        counter = CounterMetricFamily(_METRIC_PREFIX + name, text)
        counter.add_metric([], number(key))
        yield counter
