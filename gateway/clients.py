"""Who sent the request being served: the client identity of a Modbus connection.

The server runs every request of a connection in that connection's ``contextvars`` context,
where ``current_client`` is its :class:`Client`.  The write path reads it to share the line
fairly between connections (``gateway.writes``) and the audit log names it: every write is
logged at INFO on the ``gateway.audit`` logger with the client, unit, function, addresses and
outcome.
"""

from __future__ import annotations

import contextvars
import logging

__all__ = ["Client", "audit_write", "current_client"]

audit_log = logging.getLogger("gateway.audit")


class Client:
    """One connection's identity (compared by identity: two connections are two clients)."""

    __slots__ = ("name",)

    def __init__(self, name: str) -> None:
        #: the certificate subject on TLS, the peer address on plain TCP
        self.name = name

    def __repr__(self) -> str:
        return f"Client({self.name!r})"


current_client: contextvars.ContextVar[Client | None] = contextvars.ContextVar("gateway_client", default=None)


def audit_write(unit: int, function_code: int, table: str, address: int, count: int, outcome: str) -> None:
    """One audit line for one write request (``outcome``: ``ok`` or the exception and why)."""
    client = current_client.get()
    span = f"{address}" if count == 1 else f"{address}-{address + count - 1}"
    audit_log.info("client %s unit %d FC%d %s %s: %s", client.name if client else "(unknown)", unit,
                   function_code, table, span, outcome)
