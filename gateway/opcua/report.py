"""The OPC UA server on ``/api/status``: sessions, subscriptions, monitored items, the publish rate,
writes and rejected logins.

``opcua_status(server)`` is the ``opcua`` member of ``/api/status`` (None without ``[opcua]``); the
status page shows it.  The same numbers as Prometheus families are ``gateway.metrics``' (this module
stays free of prometheus_client).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gateway.opcua.server import OpcUaServer

__all__ = ["opcua_status"]


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
