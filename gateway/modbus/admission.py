"""Who may hold a connection slot of the Modbus server, and with which rights.

Admission (:class:`Admission`), checked when a TCP connection is accepted, before any TLS byte:

1. the ``allow`` list (networks); with ``loopback_reads`` a loopback peer outside it is let in
   with read rights only (the container health check reads through it whatever ``allow`` says);
2. ``max_connections_per_address``: connections from one IP address, TLS handshakes included, so
   that one host cannot take every slot;
3. on a TLS listener, ``max_handshakes``: handshakes in progress have their own budget, separate
   from ``max_connections``; when it is full the oldest handshake *of the address with the most
   handshakes in progress* is aborted to make room (a handshake takes milliseconds; a host that
   opens connections and stays silent holds the most, however fast it reconnects);
4. ``max_connections``: established connections (plain ones at accept, TLS ones when their
   handshake completes). When it is full, the connection that *holds its slot without using it*
   the longest is closed to make room: one stalled in the middle of a frame, or one that has not
   completed a single request since it connected (among those, one of the host holding the most
   stalled connections). A connection that has completed a request and
   holds no partial frame is never evicted; if every slot is held by such connections, the new
   one is refused.

Every refusal and eviction is logged through a :class:`~gateway.logutil.RepeatLog`: the first of
each cause at once, then once per interval how many more and from which addresses.

Rights (:class:`RolePolicy`): Modbus/TCP Security (MB-TCP-Security-v36, R-21/R-22) carries the
client's role in an X.509v3 extension of its certificate, OID ``1.3.6.1.4.1.50316.802.1``, whose
value is a DER ``UTF8String``. ``[modbus.tls.roles]`` maps role names to ``"read"`` or
``"read-write"``; ``default_role_rights`` applies to a certificate without the extension (R-23) or
with a role not in the table. A client without write rights gets exception 0x01 (illegal
function) on every write function code and is served reads as usual. Plain TCP clients and TLS
clients when no roles are configured have read-write rights (the ``writable`` ranges and
``read_only`` of each link still apply).

The identity of the client (:class:`gateway.clients.Client`: address, certificate subject, role,
rights) is ``connection.client`` on each connection, current in its requests, so the write path's
audit log says who asked.

The X.509 extension is read with a small DER walker over ``getpeercert(binary_form=True)``: the
standard library's ``getpeercert()`` does not return private extensions, and the ``cryptography``
package is not among the project's dependencies. The certificate has been verified by OpenSSL
before it is walked, so only the path to the extensions is decoded, bounds-checked.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import ssl
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, Literal, Protocol, TypeAlias

from gateway.clients import Client
from gateway.logutil import RepeatLog

__all__ = [
    "ROLE_OID",
    "Admission",
    "IPNetwork",
    "Rights",
    "RolePolicy",
    "bound_port",
    "format_address",
    "host_allowed",
    "peer_host",
    "role_from_certificate",
]

logger = logging.getLogger("gateway.modbus.server")

IPNetwork: TypeAlias = ipaddress.IPv4Network | ipaddress.IPv6Network
Rights = Literal["read", "read-write"]

ROLE_OID: Final = "1.3.6.1.4.1.50316.802.1"
"""Modbus.org private enterprise OID of the role extension (MB-TCP-Security-v36, R-21)."""
_ROLE_OID_DER: Final = bytes.fromhex("2b0601040183890c862201")  # the OID's content octets


# --------------------------------------------------------------------------------------------
# Identity and rights


@dataclass(frozen=True)
class RolePolicy:
    """``[modbus.tls.roles]``: role name -> rights, and the rights of a certificate without a known role."""

    roles: Mapping[str, Rights]
    default: Rights = "read"

    def identify(self, address: str, ssl_object: object) -> Client:
        """The identity of a TLS client from its verified certificate (``ssl_object``: the SSLObject)."""
        subject: str | None = None
        role: str | None = None
        if isinstance(ssl_object, (ssl.SSLObject, ssl.SSLSocket)):
            try:
                der = ssl_object.getpeercert(binary_form=True)
                decoded = ssl_object.getpeercert()
            except (ValueError, ssl.SSLError):
                der, decoded = None, None
            if decoded:
                subject = format_subject(decoded.get("subject", ()))
            if der:
                try:
                    role = role_from_certificate(der)
                except ValueError as error:
                    logger.warning(
                        "client %s: certificate role extension ignored (%s): %s rights", address, error, self.default
                    )
        rights = self.roles.get(role, self.default) if role is not None else self.default
        return Client(address, subject, role, rights == "read-write")


def format_subject(subject: object) -> str | None:
    """``getpeercert()['subject']`` (a tuple of RDNs of (key, value) pairs) as ``CN=x,O=y``."""
    if not isinstance(subject, tuple):
        return None
    parts: list[str] = []
    for rdn in subject:
        if not isinstance(rdn, tuple):
            continue
        for pair in rdn:
            if isinstance(pair, tuple) and len(pair) == 2:
                key = _SHORT_NAMES.get(str(pair[0]), str(pair[0]))
                parts.append(f"{key}={pair[1]}")
    return ",".join(parts) or None


_SHORT_NAMES: Final = {
    "commonName": "CN",
    "organizationName": "O",
    "organizationalUnitName": "OU",
    "countryName": "C",
    "localityName": "L",
    "stateOrProvinceName": "ST",
}


# --------------------------------------------------------------------------------------------
# A DER walker: just enough of X.509 (RFC 5280, 4.1) to find one extension


def _tlv(data: bytes, position: int, end: int) -> tuple[int, int, int]:
    """``(tag, content start, content end)`` of the DER element at ``position`` (before ``end``)."""
    if position + 2 > end:
        raise ValueError("truncated DER element")
    tag = data[position]
    if tag & 0x1F == 0x1F:
        raise ValueError("multi-byte DER tags are not used in X.509")
    length = data[position + 1]
    position += 2
    if length & 0x80:
        octets = length & 0x7F
        if octets == 0 or octets > 4 or position + octets > end:
            raise ValueError("bad DER length")
        length = int.from_bytes(data[position : position + octets], "big")
        position += octets
    if position + length > end:
        raise ValueError("DER element runs past its container")
    return tag, position, position + length


_SEQUENCE: Final = 0x30
_OID: Final = 0x06
_BOOLEAN: Final = 0x01
_OCTET_STRING: Final = 0x04
_UTF8_STRING: Final = 0x0C
_EXTENSIONS: Final = 0xA3  # [3] EXPLICIT in TBSCertificate


def _elements(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """Every DER element from ``start`` to ``end`` in turn, each as :func:`_tlv` gives it."""
    while start < end:
        element = _tlv(data, start, end)
        yield element
        start = element[2]


def _sequence(data: bytes, position: int, end: int, problem: str) -> tuple[int, int]:
    """``(content start, content end)`` of the SEQUENCE at ``position``; ``ValueError(problem)`` if
    it is something else."""
    tag, start, stop = _tlv(data, position, end)
    if tag != _SEQUENCE:
        raise ValueError(problem)
    return start, stop


def role_from_certificate(der: bytes) -> str | None:
    """The Modbus role of a DER certificate: None without the extension.

    Raises ``ValueError`` if the certificate cannot be walked or the extension's value is not
    a DER UTF8String (R-22); per R-65 only the first role extension counts.
    """
    start, end = _sequence(der, 0, len(der), "not a certificate")  # Certificate
    start, end = _sequence(der, start, end, "not a certificate")  # TBSCertificate
    for tag, content, after in _elements(der, start, end):
        if tag == _EXTENSIONS:
            return _role_extension(der, *_sequence(der, content, after, "bad extensions"))  # SEQUENCE OF Extension
    return None


def _role_extension(der: bytes, start: int, end: int) -> str | None:
    """The role in the first role extension among the Extensions from ``start`` to ``end``."""
    for tag, field, extension_end in _elements(der, start, end):
        if tag != _SEQUENCE:
            raise ValueError("bad extension")
        tag, oid_start, oid_end = _tlv(der, field, extension_end)
        if tag != _OID or der[oid_start:oid_end] != _ROLE_OID_DER:
            continue
        tag, value_start, value_end = _tlv(der, oid_end, extension_end)
        if tag == _BOOLEAN:  # critical
            tag, value_start, value_end = _tlv(der, value_end, extension_end)
        if tag != _OCTET_STRING:
            raise ValueError("role extension without an OCTET STRING value")
        tag, text_start, text_end = _tlv(der, value_start, value_end)
        if tag != _UTF8_STRING or text_end != value_end:
            raise ValueError("the role is not a DER UTF8String (MB-TCP-Security R-22)")
        try:
            return der[text_start:text_end].decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError("the role is not valid UTF-8") from None
    return None


# --------------------------------------------------------------------------------------------
# Slots


class Slot(Protocol):
    """What admission needs of a connection."""

    def stalled_since(self) -> float | None:
        """Since when it holds its slot without using it (None: it is using it)."""

    def evict(self, reason: str) -> None:
        """Close it to make room (it then calls :meth:`Admission.release`)."""


def peer_host(peer: object) -> str | None:
    """The IP address of a ``peername`` (IPv4-mapped IPv6 as IPv4), or None."""
    if not isinstance(peer, tuple) or not peer or not isinstance(peer[0], str):
        return None
    try:
        address = ipaddress.ip_address(peer[0].split("%", 1)[0])
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return str(address)


def format_address(address: object) -> str:
    """A ``peername`` / ``sockname`` as ``host:port`` (``[host]:port`` for IPv6), for log lines."""
    if isinstance(address, tuple) and len(address) >= 2:
        host, port = address[0], address[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    return str(address)


def bound_port(server: asyncio.Server | None, name: str) -> int:
    """The TCP port a listener is bound to (the actual one when 0 was asked for)."""
    if server is None or not server.sockets:
        raise RuntimeError(f"{name}: server not started")
    port: int = server.sockets[0].getsockname()[1]
    return port


def host_allowed(host: str | None, allow: Sequence[IPNetwork]) -> bool:
    """Whether ``host`` (a :func:`peer_host`) is inside one of ``allow`` (False for None)."""
    if host is None:
        return False
    address = ipaddress.ip_address(host)
    return any(address in network for network in allow)


class Admission:
    """The slot accounting of one listener (see the module docstring for the rules)."""

    def __init__(
        self,
        name: str,
        *,
        max_connections: int,
        max_per_address: int | None = None,
        max_handshakes: int | None = None,
        allow: Sequence[IPNetwork] | None = None,
        loopback_reads: bool = False,
        repeat_log: RepeatLog | None = None,
    ) -> None:
        self.name = name
        self.max_connections = max_connections
        self.max_per_address = max_per_address
        self.max_handshakes = max_handshakes
        self.allow = None if allow is None else tuple(allow)
        self.loopback_reads = loopback_reads
        self.log = repeat_log or RepeatLog(logger)
        self.refused = 0
        self.evicted = 0
        self._established: dict[Slot, str | None] = {}
        self._handshaking: dict[Slot, tuple[float, str | None]] = {}
        self._per_address: dict[str, int] = {}

    @property
    def established(self) -> int:
        return len(self._established)

    @property
    def handshaking(self) -> int:
        return len(self._handshaking)

    def admit(self, slot: Slot, peer: object, *, handshake_started: float | None = None) -> bool:
        """Count ``slot`` in at accept, or refuse it (False: the caller aborts it, unlogged).

        ``handshake_started``: loop time, for a TLS connection whose handshake starts now.
        """
        host = peer_host(peer)
        if self.allow is not None and not host_allowed(host, self.allow) and not self.read_only(peer):
            return self._refuse("peer not in the allowed networks", peer, host)
        if (
            self.max_per_address is not None
            and host is not None
            and self._per_address.get(host, 0) >= self.max_per_address
        ):
            return self._refuse(f"over max_connections_per_address ({self.max_per_address})", peer, host)
        if handshake_started is not None and self.max_handshakes is not None:
            if len(self._handshaking) >= self.max_handshakes:
                self._evict(self._handshake_victim(), f"TLS handshakes at max_handshakes ({self.max_handshakes})")
            self._handshaking[slot] = (handshake_started, host)
        else:
            if not self._make_room():
                return self._refuse(f"already {self.max_connections} connections, none idle", peer, host)
            self._established[slot] = host
        self._count(host)
        return True

    def read_only(self, peer: object) -> bool:
        """Whether ``peer`` is let in only for reads: loopback outside ``allow`` with ``loopback_reads``."""
        if not self.loopback_reads or self.allow is None:
            return False
        host = peer_host(peer)
        return host is not None and ipaddress.ip_address(host).is_loopback and not host_allowed(host, self.allow)

    def handshake_done(self, slot: Slot, peer: object) -> bool:
        """Move a TLS connection from the handshake budget to the connection slots (False: refused)."""
        entry = self._handshaking.pop(slot, None)
        if entry is not None:
            host = entry[1]
        elif slot in self._established:  # admitted to a slot at once (no handshake budget): counted already
            return True
        else:  # not admitted (or no longer): counted in now, as its release counts it out
            host = peer_host(peer)
            self._count(host)
        if not self._make_room():
            self._uncount(host)
            return self._refuse(f"TLS handshake done but already {self.max_connections} connections", peer, host)
        self._established[slot] = host
        return True

    def release(self, slot: Slot) -> None:
        """Forget a slot (idempotent)."""
        if slot in self._established:
            self._uncount(self._established.pop(slot))
        elif slot in self._handshaking:
            self._uncount(self._handshaking.pop(slot)[1])

    # -- internals ---------------------------------------------------------------------

    def _count(self, host: str | None) -> None:
        if host is not None:
            self._per_address[host] = self._per_address.get(host, 0) + 1

    def _uncount(self, host: str | None) -> None:
        if host is None:
            return
        left = self._per_address.get(host, 0) - 1
        if left > 0:
            self._per_address[host] = left
        else:
            self._per_address.pop(host, None)

    def _handshake_victim(self) -> Slot:
        """The oldest handshake of the address with the most handshakes in progress.

        A host that opens connections and stays silent always has the most, so a client from
        another address is not aborted by its churn, however fast it reconnects.
        """
        by_host: dict[str | None, int] = {}
        for _, host in self._handshaking.values():
            by_host[host] = by_host.get(host, 0) + 1
        most = max(by_host.values())
        return min(
            (slot for slot, (_, host) in self._handshaking.items() if by_host[host] == most),
            key=lambda slot: self._handshaking[slot][0],
        )

    def _make_room(self) -> bool:
        """True if an established slot is free, evicting the longest-stalled connection if needed."""
        while len(self._established) >= self.max_connections:
            stalled = [
                (since, slot, self._established[slot])
                for slot in self._established
                if (since := slot.stalled_since()) is not None
            ]
            if not stalled:
                return False
            # The longest-stalled connection of the host holding the most stalled ones: a host that
            # churns connections evicts its own, not a client from elsewhere that just connected.
            by_host: dict[str | None, int] = {}
            for _, _, host in stalled:
                by_host[host] = by_host.get(host, 0) + 1
            most = max(by_host.values())
            _, victim, _ = min((item for item in stalled if by_host[item[2]] == most), key=lambda item: item[0])
            self._evict(victim, "stalled mid-frame or no request yet, closed to make room")
        return True

    def _evict(self, slot: Slot, reason: str) -> None:
        self.evicted += 1
        self.release(slot)
        slot.evict(reason)

    def _refuse(self, reason: str, peer: object, host: str | None) -> bool:
        self.refused += 1
        self.log.log(
            logging.WARNING,
            f"{self.name}: connection refused, {reason}",
            host,
            "%s: refused connection from %s: %s",
            self.name,
            format_address(peer),
            reason,
        )
        return False
