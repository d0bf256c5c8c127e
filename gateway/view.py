"""What the gateway's HTTP rooms read of it: one declared view (:class:`gateway.app.Gateway` has it).

The status page (``gateway.status``), Prometheus (``gateway.metrics``) and ``/healthz``
(``gateway.health``) read the gateway through this view and nothing else: its units (each with its
one verdict, ``Unit.verdict``), its Modbus servers, and its optional faces, declared here as members
(None when not configured), never looked up by name.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from gateway.modbus.server import ModbusTcpServer
    from gateway.opcua.server import OpcUaServer
    from gateway.sparkplug.driver import SparkplugNode
    from gateway.unit import Unit

__all__ = ["GatewayView"]


class GatewayView(Protocol):
    """The gateway as its HTTP rooms see it."""

    @property
    def units(self) -> Sequence[Unit[Any, Any]]: ...

    @property
    def servers(self) -> Sequence[ModbusTcpServer]: ...

    @property
    def sparkplug(self) -> SparkplugNode | None:
        """The Sparkplug B edge node (``[sparkplug]``), None when not configured."""

    @property
    def opcua(self) -> OpcUaServer | None:
        """The OPC UA server (``[opcua]``), None when not configured."""
