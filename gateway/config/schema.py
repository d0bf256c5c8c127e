"""The configuration schema: ``[modbus]``, ``[modbus.tls]``, ``[metrics]``, ``[logging]`` and the whole file.

The ``[[link]]`` models live in one module per protocol (``gateway.kinds.slc_ascii.config``,
``gateway.kinds.df1.config``) on a common base (``gateway.config.link``); ``gateway.config.links``
puts them together into the discriminated union a link is validated as.
"""

from __future__ import annotations

import ipaddress
import ssl
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.config._common import (
    Loc,
    Model,
    Problems,
    listen_validator,
    optional_listen_validator,
    parse_listen,
    parse_networks,
    resolve_path,
    show,
)
from gateway.config.links import LinkConfig, TaggedLink
from gateway.config.sparkplug import SparkplugConfig
from gateway.config.writer import table_lines

__all__ = ["GatewayConfig", "LoggingConfig", "MetricsConfig", "ModbusConfig", "Rights", "TlsConfig"]

Rights = Literal["read", "read-write"]


class TlsConfig(Model):
    """``[modbus.tls]``: Modbus/TCP Security (Modbus over TLS)."""

    listen: str = "0.0.0.0:802"
    cert: Path
    key: Path
    client_ca: Path | None = None
    handshake_timeout: float = Field(5.0, gt=0, le=60)
    max_handshakes: int = Field(16, ge=1, le=10000)
    roles: dict[str, Rights] = Field(default_factory=dict)
    default_rights: Rights = "read"

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
    max_connections: int = Field(64, ge=1, le=10000)
    max_connections_per_address: int = Field(0, ge=0, le=10000)
    idle_timeout: float = Field(300.0, ge=0)
    frame_timeout: float = Field(5.0, gt=0, le=3600)
    allow: tuple[IPv4Network | IPv6Network, ...] = ()
    loopback_reads: bool = True
    tls: TlsConfig | None = None

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
    allow: tuple[IPv4Network | IPv6Network, ...] = ()
    max_connections: int = Field(32, ge=1, le=1000)

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
    repeat_interval: float = Field(60.0, gt=0, le=86400)
    trace_max_bytes: int = Field(10_000_000, ge=4096)
    trace_backups: int = Field(3, ge=0, le=100)

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, value: object) -> object:
        return value.upper() if isinstance(value, str) else value


class GatewayConfig(Model):
    """The whole configuration file."""

    modbus: ModbusConfig = ModbusConfig()
    metrics: MetricsConfig | None = None
    logging: LoggingConfig = LoggingConfig()
    sparkplug: SparkplugConfig | None = None
    link: tuple[TaggedLink, ...] = Field(strict=False)

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
        if self.metrics is not None and not self.metrics.allow and not _is_loopback(self.metrics.address[0]):
            found.append(
                f"[metrics] listens on {self.metrics.listen} with no allow list: anyone who can reach it "
                "reads /metrics and /healthz (set allow = [the scraper's network])"
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
