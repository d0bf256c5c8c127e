"""The configuration schema: ``[modbus]``, ``[modbus.tls]``, ``[metrics]``, ``[logging]`` and the whole file.

The ``[[link]]`` models live in one module per protocol (``gateway.kinds.slc_ascii.config``,
``gateway.kinds.df1.config``) on a common base (``gateway.config.link``); ``gateway.config.links``
puts them together into the discriminated union a link is validated as.
"""

from __future__ import annotations

import ipaddress
import os
import ssl
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.config._common import (
    Loc,
    Model,
    Problems,
    is_port_path,
    listen_validator,
    optional_listen_validator,
    parse_listen,
    parse_networks,
    resolve_path,
    show,
)
from gateway.config.links import LinkConfig, TaggedLink
from gateway.config.opcua import OpcUaConfig
from gateway.config.sparkplug import SparkplugConfig
from gateway.config.writer import table_lines
from gateway.streams import MISSING_PORT_HINT

__all__ = ["GatewayConfig", "LoggingConfig", "MetricsConfig", "ModbusConfig", "Rights", "TlsConfig"]

Rights = Literal["read", "read-write"]


class TlsConfig(Model):
    """``[modbus.tls]``: Modbus/TCP Security (Modbus over TLS)."""

    listen: str = "0.0.0.0:802"
    """host:port of the Modbus/TCP Security (TLS) listener (802 is the standard port)."""
    cert: Path
    """The server's PEM certificate (a path relative to the config file). Loaded by check-config, so a bad file fails
    there."""
    key: Path
    """The PEM private key of cert."""
    client_ca: Path | None = None
    """PEM CA certificate(s) that client certificates must chain to; set, it requires a client certificate on every
    TLS connection. Unset: TLS encrypts but does not authenticate clients."""
    handshake_timeout: float = Field(5.0, gt=0, le=60)
    """Seconds a TLS handshake may take."""
    max_handshakes: int = Field(16, ge=1, le=10000)
    """TLS handshakes in progress at once, beside max_connections; when full, the oldest of the client address
    holding the most is aborted."""
    roles: dict[str, Rights] = Field(default_factory=dict)
    """[modbus.tls.roles]: the Modbus role in a client certificate (X.509 extension 1.3.6.1.4.1.50316.802.1, a
    UTF8String) -> "read" or "read-write", e.g. operator = "read-write". Without it every certified client may
    write; with it, a "read" role gets exception 0x01 on every write function (5, 6, 15, 16, 22, 23). Needs
    client_ca."""
    default_rights: Rights = "read"
    """The rights of a certificate whose role is not in roles, or that has none (only with roles)."""

    _check_listen = field_validator("listen", mode="before")(listen_validator)

    @field_validator("roles", mode="before")
    @classmethod
    def _check_roles(cls, value: object) -> object:
        if isinstance(value, dict):
            for name in value:
                if not isinstance(name, str) or not name or len(name) > 128:
                    raise ValueError(f"{show(name)}: a role name is 1 to 128 characters")
        return value

    @field_validator("cert", "key", "client_ca", mode="before")
    @classmethod
    def _existing_file(cls, value: object, info: ValidationInfo) -> Path:
        return resolve_path(value, info, must_exist=True)

    @model_validator(mode="after")
    def _usable(self) -> TlsConfig:
        """Load the certificate, key and CA now, so a bad file fails check-config, not run."""
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        try:
            context.load_cert_chain(self.cert, self.key)
        except (ssl.SSLError, OSError) as exc:
            raise ValueError(
                f"cert {self.cert.name} / key {self.key.name}: not a usable PEM certificate and matching key "
                f"({exc.__class__.__name__}: {getattr(exc, 'reason', None) or exc})"
            ) from None
        if self.roles and self.client_ca is None:
            raise ValueError(
                "roles come from client certificates: set client_ca (or remove [modbus.tls.roles])"
            )
        if self.client_ca is not None:
            try:
                context.load_verify_locations(cafile=self.client_ca)
            except (ssl.SSLError, OSError) as exc:
                raise ValueError(
                    f"client_ca {self.client_ca.name}: not a usable PEM CA certificate "
                    f"({getattr(exc, 'reason', None) or exc})"
                ) from None
        return self

    @property
    def address(self) -> tuple[str, int]:
        """``listen`` as ``(host, port)``."""
        return parse_listen(self.listen)


class ModbusConfig(Model):
    """``[modbus]``: the Modbus TCP server."""

    listen: str = "0.0.0.0:5020"
    """host:port of the plain Modbus TCP server; "" turns it off (TLS only: configure [modbus.tls]). Plain Modbus TCP
    has no authentication: a client that reaches it and passes allow may read and write."""
    max_connections: int = Field(64, ge=1, le=10000)
    """Client connections at once (TLS included). When full, a connection stalled mid-frame or that has not sent a
    request yet is closed to make room; otherwise new ones are refused."""
    max_connections_per_address: int = Field(0, ge=0, le=10000)
    """Connections (TLS handshakes included) from one IP address; 0: half of max_connections."""
    idle_timeout: float = Field(300.0, ge=0)
    """Close a connection that sent nothing for this many seconds (0: never)."""
    frame_timeout: float = Field(5.0, gt=0, le=3600)
    """A Modbus frame must be complete this many seconds after its first byte (slow senders cannot hold a slot)."""
    allow: tuple[IPv4Network | IPv6Network, ...] = ()
    """Client networks (CIDR, e.g. ["10.20.0.0/16"]) allowed to connect; empty: anyone."""
    loopback_reads: bool = True
    """Loopback clients outside allow may read, never write (the container health check works whatever allow says)."""
    tls: TlsConfig | None = None
    """[modbus.tls]: Modbus/TCP Security (Modbus over TLS); not configured: no TLS listener."""

    _check_listen = field_validator("listen", mode="before")(optional_listen_validator)

    @field_validator("allow", mode="before")
    @classmethod
    def _parse_allow(cls, value: object) -> object:
        return parse_networks(value)

    @model_validator(mode="after")
    def _some_listener(self) -> ModbusConfig:
        if not self.listen and self.tls is None:
            raise Problems((("listen",), 'listen = "" turns the plain listener off: configure [modbus.tls] too'))
        return self

    @property
    def per_address_cap(self) -> int:
        """``max_connections_per_address``, 0 meaning half of ``max_connections`` (at least 1)."""
        return self.max_connections_per_address or max(1, self.max_connections // 2)

    @property
    def plain_enabled(self) -> bool:
        """False with ``listen = ""`` (TLS-only operation)."""
        return bool(self.listen)

    @property
    def address(self) -> tuple[str, int]:
        """``listen`` as ``(host, port)`` (a ``ValueError`` when the plain listener is off)."""
        return parse_listen(self.listen)

    def is_allowed(self, client: str) -> bool:
        """True if a client at IP address ``client`` may connect (``allow`` empty: everyone)."""
        if not self.allow:
            return True
        try:
            ip = ipaddress.ip_address(client.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip in network for network in self.allow)


class MetricsConfig(Model):
    """``[metrics]``: HTTP ``/metrics`` (Prometheus) and ``/healthz``."""

    listen: str = "127.0.0.1:9108"
    """host:port of the HTTP server of /metrics (Prometheus), /healthz and the status page. Without a [metrics] table
    none of them is served. Keep it on loopback unless allow restricts it (check-config warns otherwise); in a
    container, listen on 0.0.0.0 and publish the port."""
    allow: tuple[IPv4Network | IPv6Network, ...] = ()
    """Client networks (CIDR) allowed to connect; empty: anyone."""
    max_connections: int = Field(32, ge=1, le=1000)
    """Concurrent HTTP connections; refusals are logged."""

    _check_listen = field_validator("listen", mode="before")(listen_validator)

    @field_validator("allow", mode="before")
    @classmethod
    def _parse_allow(cls, value: object) -> object:
        return parse_networks(value)

    @property
    def address(self) -> tuple[str, int]:
        """``listen`` as ``(host, port)``."""
        return parse_listen(self.listen)


class LoggingConfig(Model):
    """``[logging]``."""

    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    """DEBUG, INFO, WARNING or ERROR (any case). Every Modbus write is logged at INFO on the gateway.audit logger."""
    repeat_interval: float = Field(60.0, gt=0, le=86400)
    """Repeated warnings (refused connections, bad frames, failed TLS handshakes): the first of each cause at once,
    then a count with the addresses every this many seconds."""
    trace_max_bytes: int = Field(10_000_000, ge=4096)
    """Trace files (created 0600) rotate at this size."""
    trace_backups: int = Field(3, ge=0, le=100)
    """Old trace files kept when one rotates."""

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, value: object) -> object:
        return value.upper() if isinstance(value, str) else value


class GatewayConfig(Model):
    """The whole configuration file."""

    modbus: ModbusConfig = ModbusConfig()
    """[modbus]: the Modbus TCP server."""
    metrics: MetricsConfig | None = None
    """[metrics]: HTTP /metrics, /healthz and the status page; off when the table is absent."""
    logging: LoggingConfig = LoggingConfig()
    """[logging]."""
    sparkplug: SparkplugConfig | None = None
    """[sparkplug]: publish every link as a device of a Sparkplug B edge node over MQTT (off when absent)."""
    opcua: OpcUaConfig | None = None
    """[opcua]: serve every link as a folder of variables of an OPC UA server (off when absent)."""
    link: tuple[TaggedLink, ...] = Field(strict=False)
    """[[link]]: one serial link to one controller, served as one Modbus unit id. At least one."""

    @field_validator("link")
    @classmethod
    def _at_least_one(cls, value: tuple[LinkConfig, ...]) -> tuple[LinkConfig, ...]:
        if not value:
            raise ValueError("at least one [[link]] is required")
        return value

    @model_validator(mode="after")
    def _check(self) -> GatewayConfig:
        problems: list[tuple[Loc, str]] = []
        names: dict[str, int] = {}
        units: dict[int, int] = {}
        for index, link in enumerate(self.link):
            if link.name in names:
                problems.append(
                    (
                        ("link", index, "name"),
                        f"duplicate link name {show(link.name)}: link[{names[link.name]}] has it",
                    )
                )
            names.setdefault(link.name, index)
            if link.unit in units:
                other = self.link[units[link.unit]]
                problems.append(
                    (
                        ("link", index, "unit"),
                        f"duplicate unit id {link.unit}: "
                        f"link {show(other.name)} (link[{units[link.unit]}]) has it",
                    )
                )
            units.setdefault(link.unit, index)
        for model in dict.fromkeys(type(link) for link in self.link):
            problems.extend(model.problems_across(self.link))
        listeners: list[tuple[Loc, str]] = []
        if self.modbus.plain_enabled:
            listeners.append((("modbus", "listen"), self.modbus.listen))
        if self.modbus.tls is not None:
            listeners.append((("modbus", "tls", "listen"), self.modbus.tls.listen))
        if self.metrics is not None:
            listeners.append((("metrics", "listen"), self.metrics.listen))
        for later in range(len(listeners)):
            for earlier in range(later):
                if _same_socket(listeners[earlier][1], listeners[later][1]):
                    problems.append(
                        (
                            listeners[later][0],
                            f"{listeners[later][1]} collides with {_dotted(listeners[earlier][0])} "
                            f"({listeners[earlier][1]}): each listener needs its own port",
                        )
                    )
                    break
        if problems:
            raise Problems(*problems)
        return self

    @property
    def links(self) -> tuple[LinkConfig, ...]:
        """The ``[[link]]`` tables, in file order."""
        return self.link

    def warnings(self) -> list[str]:
        """Valid but probably not what was meant (``check-config`` prints them, ``run`` logs them)."""
        found: list[str] = []
        tls = self.modbus.tls
        if tls is not None and tls.client_ca is not None and self.modbus.plain_enabled:
            host, _ = self.modbus.address
            if not _is_loopback(host):
                found.append(
                    f"[modbus.tls] requires client certificates, but the plain listener "
                    f"(listen = {show(self.modbus.listen)}) serves anyone who can reach it without one: "
                    'set listen = "" for TLS-only operation (or "127.0.0.1:5020" to keep it for local '
                    "health checks only)"
                )
        for link in self.link:
            if is_port_path(link.port) and not os.path.exists(link.port):
                found.append(
                    f"link {show(link.name)}: port {link.port} does not exist (yet): run keeps trying to open it "
                    f"until it appears; {MISSING_PORT_HINT}"
                )
        if self.metrics is not None and not self.metrics.allow and not _is_loopback(self.metrics.address[0]):
            found.append(
                f"[metrics] listens on {self.metrics.listen} with no allow list: anyone who can reach it "
                "reads /metrics and /healthz (set allow = [the scraper's network])"
            )
        opcua = self.opcua
        if opcua is not None and "None" in opcua.security and opcua.writers and not _is_loopback(opcua.address[0]):
            found.append(
                f"[opcua] offers the None endpoint on {opcua.listen} with users who write "
                f"({', '.join(opcua.writers)}): their passwords and writes cross the network unencrypted "
                '(offer security = ["Basic256Sha256-SignAndEncrypt"] only, or listen on 127.0.0.1)'
            )
        return found

    def describe(self) -> str:
        """Every key with its effective value, as TOML (``slc-gateway check-config`` prints it).

        Credentials in port URLs (``socket://user:password@...``) are shown as ``***``.
        """
        lines = ["# slc-gateway configuration, resolved: every key with its effective value", ""]
        lines += table_lines("[modbus]", self.modbus, skip=("tls",))
        if self.modbus.tls is None:
            lines += ["# [modbus.tls] not configured: no Modbus/TCP Security listener", ""]
        else:
            lines += table_lines("[modbus.tls]", self.modbus.tls)
        if self.metrics is None:
            lines += ["# [metrics] not configured: no /metrics or /healthz endpoint", ""]
        else:
            lines += table_lines("[metrics]", self.metrics)
        lines += table_lines("[logging]", self.logging)
        if self.sparkplug is None:
            lines += ["# [sparkplug] not configured: no Sparkplug B edge node", ""]
        else:
            lines += table_lines("[sparkplug]", self.sparkplug.model_copy(
                update={"password": None if self.sparkplug.password is None else "***"}))
        if self.opcua is None:
            lines += ["# [opcua] not configured: no OPC UA server", ""]
        else:
            lines += table_lines("[opcua]", self.opcua, skip=("user",))
            for user in self.opcua.user:
                lines += table_lines("[[opcua.user]]", user.model_copy(update={"password_hash": "***"}))
        for link in self.link:
            lines += link.describe_lines()
        return "\n".join(lines).rstrip("\n") + "\n"


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _same_socket(first: str, second: str) -> bool:
    host_a, port_a = parse_listen(first)
    host_b, port_b = parse_listen(second)
    if port_a != port_b or port_a == 0:
        return False
    wildcards = ("0.0.0.0", "::")
    return host_a == host_b or host_a in wildcards or host_b in wildcards


def _dotted(loc: Loc) -> str:
    return ".".join(str(part) for part in loc)
