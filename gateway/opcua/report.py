"""The OPC UA server on ``/api/status`` and ``/metrics``: sessions, subscriptions, monitored items, the
publish rate, writes and rejected logins.

``opcua_status(server)`` is the ``opcua`` member of ``/api/status`` (None without ``[opcua]``);
``opcua_families(server)`` the Prometheus families (``slc_gateway_opcua_*``; none when ``server`` is None).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Final

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from gateway.opcua.server import OpcUaServer

__all__ = ["opcua_families", "opcua_status"]

_OPCUA_PREFIX: Final = "slc_gateway_opcua_"


def opcua_status(server: OpcUaServer | None) -> dict[str, object] | None:
    """The server's endpoint, what it serves and its counters, for ``/api/status`` and the status page."""
    if server is None:
        return None
    return {
        "listen": server.config.listen,
        "security": list(server.config.security),
        **server.counts(),
        "publish_rate": round(server.publish_rate(), 3),
        "data_changes": server.data_changes,
        "writes": server.writes,
        "write_failures": server.write_failures,
        "rejected_logins": server.rejected_logins,
        "cpu_seconds": round(server.cpu_seconds, 6),
        "links": len(server.links),
    }


def opcua_families(server: OpcUaServer | None) -> Iterator[Metric]:
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
        gauge = GaugeMetricFamily(_OPCUA_PREFIX + key, text)
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
        counter = CounterMetricFamily(_OPCUA_PREFIX + key, text)
        counter.add_metric([], value)
        yield counter
