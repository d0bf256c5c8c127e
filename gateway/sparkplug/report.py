"""The edge node on ``/api/status``: its MQTT session, what it published, the commands, its store.

``status(node)`` is the ``sparkplug`` member of ``/api/status`` (None without ``[sparkplug]``); the
status page shows it.  The same numbers as Prometheus families are ``gateway.metrics``' (this module
stays free of prometheus_client, so the status page does not pull it in).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gateway.sparkplug.driver import SparkplugNode

__all__ = ["status"]


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
