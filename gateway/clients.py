"""Who sent the request being served: the identity of a Modbus client connection.

:class:`Client` says who is on the other end of one connection (address, certificate subject and
role, rights); ``gateway.modbus.admission`` builds it (from a TLS certificate, with the rights
its role gives) and each connection holds one.  The server runs every request of a connection
in that connection's ``contextvars`` context, where ``current_client`` is its :class:`Client`.
The write path reads it to share the line fairly between connections (``gateway.writes``) and
the audit log names it: every write is logged at INFO on the ``gateway.audit`` logger with the
client, unit, function, addresses and outcome.
"""

from __future__ import annotations

import contextvars
import logging
from dataclasses import dataclass

__all__ = ["Client", "audit_write", "current_client"]

audit_log = logging.getLogger("gateway.audit")


@dataclass(frozen=True, slots=True, eq=False)
class Client:
    """Who is on the other end of a connection; compared by identity (two connections are two clients).

    ``address``: ``host:port`` of the peer; ``subject``: the verified certificate's subject as
    ``CN=...,O=...`` (None on plain TCP or without a client certificate); ``role``: the Modbus
    role from the certificate (None without one); ``can_write``: the rights it was given.
    ``str(client)`` (also ``client.name``) is what an audit line names: the subject if there is
    one, else the address.
    """

    address: str
    subject: str | None = None
    role: str | None = None
    can_write: bool = True

    def __str__(self) -> str:
        if self.subject is None:
            return self.address
        role = f", role {self.role}" if self.role is not None else ""
        return f"{self.subject} ({self.address}{role})"

    @property
    def name(self) -> str:
        """The client as audit lines name it (``str(client)``)."""
        return str(self)


current_client: contextvars.ContextVar[Client | None] = contextvars.ContextVar("gateway_client", default=None)


def audit_write(unit: int, function_code: int, table: str, address: int, count: int, outcome: str) -> None:
    """One audit line for one write request (``outcome``: ``ok`` or the exception and why)."""
    client = current_client.get()
    span = f"{address}" if count == 1 else f"{address}-{address + count - 1}"
    audit_log.info("client %s unit %d FC%d %s %s: %s", client.name if client else "(unknown)", unit,
                   function_code, table, span, outcome)
