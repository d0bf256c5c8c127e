"""The configuration file: TOML text -> validated, frozen config objects.

``load_config(path)`` and ``parse_config(text)`` return a :class:`GatewayConfig` or raise ONE
:class:`~gateway.errors.ConfigError` that lists every problem found, each with the file, the line
(where it can be found), the key path in TOML terms and what is wrong::

    plant.toml: 2 errors in the configuration:
      plant.toml:14: link "press-1" (link[0]).timeout: must be greater than 0 (got -1)
      plant.toml:23: link "press-2" (link[1]).map[0].count: missing required key

Indexes in key paths count from 0: ``link[1]`` is the second ``[[link]]`` table of the file.

The models are pydantic v2 models (frozen, unknown keys forbidden, strict types: TOML is typed, so
``unit = "1"`` is an error, not a conversion). Values a consumer needs are resolved here: the
per-protocol serial defaults are filled in, paths are made absolute (relative to the directory of
the config file), ``listen`` strings are normalised and ``writable`` ranges and ``allow`` networks
are parsed. ``GatewayConfig.describe()`` prints every key with its effective value, as TOML that
loads back to the same configuration (except credentials in port URLs, shown as ``***``), and
``GatewayConfig.warnings()`` lists valid settings that are probably not what was meant.
"""

from __future__ import annotations

import difflib
import importlib
import ipaddress
import json
import os
import re
import ssl
import stat
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from datetime import date, datetime, time
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from typing import Any, Literal, NamedTuple, get_args
from urllib.parse import parse_qsl, urlsplit

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import ErrorDetails

from gateway.errors import ConfigError
from gateway.logutil import redact_url

__all__ = [
    "DF1_ONLY_KEYS",
    "PROTOCOL_DEFAULTS",
    "GatewayConfig",
    "LinkConfig",
    "LinkProtocol",
    "LoggingConfig",
    "MapEntry",
    "MetricsConfig",
    "ModbusConfig",
    "Processor",
    "Table",
    "TlsConfig",
    "ValueType",
    "WritableRange",
    "WritableTable",
    "load_config",
    "parse_config",
    "parse_listen",
]

LinkProtocol = Literal["slc-ascii", "df1"]
Rights = Literal["read", "read-write"]
Table = Literal["holding", "input", "coil", "discrete"]
WritableTable = Literal["holding", "coil"]
ValueType = Literal["int16", "uint16", "float32", "bool"]
Processor = Literal["slc500", "slc5/01", "slc5/02", "slc5/03", "slc5/04", "slc5/05", "plc5"]

#: Serial settings that depend on the protocol; filled in when a link does not give them.
PROTOCOL_DEFAULTS: Mapping[str, Mapping[str, object]] = {
    "slc-ascii": {"baudrate": 9600, "bytesize": 7, "parity": "E", "timeout": 0.3},
    "df1": {"baudrate": 19200, "bytesize": 8, "parity": "N", "timeout": 1.0},
}

#: Keys of ``[[link]]`` that only a ``df1`` link may give.
DF1_ONLY_KEYS = ("station", "source", "checksum", "processor", "max_read_bytes", "max_write_bytes", "map")

MAX_CONFIG_BYTES = 1 << 20
"""A config file larger than this is refused (it is not a config file)."""

_WORD_TABLES = ("holding", "input")
_BIT_TABLES = ("coil", "discrete")
_BAUDRATES = (110, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
_SIM_MODELS: Mapping[str, LinkProtocol] = {"slc100": "slc-ascii", "slc150": "slc-ascii", "slc504": "df1"}
_NAME_RE = re.compile(r"[A-Za-z0-9_.-]{1,40}")
_HOST_LABEL_RE = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")
_PORT_RE = re.compile(r"[0-9]{1,5}")
_COM_RE = re.compile(r"(?:\\\\\.\\)?COM[1-9][0-9]{0,2}", re.IGNORECASE)
_WRITABLE_RE = re.compile(r"\s*([a-z]+)\s*:\s*([0-9]{1,6})\s*(?:-\s*([0-9]{1,6})\s*)?")

Loc = tuple[str | int, ...]


class _Problems(ValueError):
    """Raised by validators: one or more problems, each at a key path relative to the model."""

    def __init__(self, *problems: tuple[Loc, str]) -> None:
        super().__init__("; ".join(message for _, message in problems))
        self.problems = problems


# --------------------------------------------------------------------------------------------
# Small parsers shared by the models


def parse_listen(text: str) -> tuple[str, int]:
    """Split ``host:port`` (IPv6 hosts in brackets: ``[::1]:5020``) into ``(host, port)``.

    The host is returned without brackets. Raises ``ValueError`` with a readable message.
    """
    text = text.strip()
    if text.startswith("["):
        close = text.find("]")
        if close < 0:
            raise ValueError(f"{_show(text)}: missing ']' after the IPv6 address")
        host, rest = text[1:close], text[close + 1 :]
        if not rest.startswith(":"):
            raise ValueError(f"{_show(text)}: expected [IPv6 address]:port, e.g. [::1]:5020")
        port_text = rest[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"{_show(host)} is not an IPv6 address") from None
    else:
        host, colon, port_text = text.rpartition(":")
        if not colon:
            raise ValueError(f"{_show(text)}: expected host:port, e.g. 0.0.0.0:5020")
        if ":" in host:
            raise ValueError(f"{_show(text)}: put an IPv6 address in brackets, e.g. [::1]:5020")
        if not host:
            raise ValueError(f"{_show(text)}: the host is missing (0.0.0.0 listens on every interface)")
        if not _is_host(host):
            raise ValueError(f"{_show(host)} is not an IPv4 address or a host name")
    if not _PORT_RE.fullmatch(port_text) or int(port_text) > 65535:
        raise ValueError(f"{_show(text)}: the port must be a number 0..65535")
    return host, int(port_text)


def _format_listen(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _is_host(host: str) -> bool:
    labels = host.split(".")
    if all(label.isascii() and label.isdigit() for label in labels):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            return False
        return True
    return len(host) <= 253 and all(_HOST_LABEL_RE.fullmatch(label) for label in labels)


def _check_port_url(text: str) -> None:
    """Validate the ``port`` of a link: a serial device, a TCP URL or a simulator URL."""
    if text.startswith("/dev/"):
        if len(text) == len("/dev/") or any(c.isspace() or c == "\0" for c in text):
            raise ValueError(f"{_show(text)} is not a device path")
        return
    if _COM_RE.fullmatch(text):
        return
    scheme, sep, _ = text.partition("://")
    if sep and scheme in ("socket", "rfc2217"):
        parts = urlsplit(text)
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or not port or not _is_host_or_ipv6(parts.hostname):
            raise ValueError(f"{_show(text)}: expected {scheme}://host:port with a port 1..65535")
        return
    if sep and scheme == "sim":
        parts = urlsplit(text)
        if parts.netloc not in _SIM_MODELS or parts.path not in ("", "/") or parts.fragment:
            raise ValueError(
                f"{_show(text)}: expected sim://slc150, sim://slc100 or sim://slc504, "
                "optionally followed by ?option=value&..."
            )
        if parts.query:
            try:
                parse_qsl(parts.query, keep_blank_values=True, strict_parsing=True)
            except ValueError:
                raise ValueError(f"{_show(text)}: the simulator options are not option=value&...") from None
        return
    raise ValueError(
        f"{_show(text)}: expected a serial device (/dev/ttyUSB0, COM3), socket://host:port, "
        "rfc2217://host:port or sim://slc150 | sim://slc100 | sim://slc504"
    )


def _is_host_or_ipv6(host: str) -> bool:
    if ":" in host:
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            return False
        return True
    return _is_host(host)


def _sim_model(port: str) -> str | None:
    if port.startswith("sim://"):
        return urlsplit(port).netloc
    return None


def _resolve_path(value: object, info: ValidationInfo, *, must_exist: bool) -> Path:
    if isinstance(value, Path):
        value = str(value)
    if not isinstance(value, str):
        raise ValueError(f"must be a string (a file path) (got {_show(value)})")
    if not value.strip() or "\0" in value:
        raise ValueError(f"{_show(value)} is not a file path")
    base = info.context.get("base_dir") if isinstance(info.context, dict) else None
    path = Path(value)
    if not path.is_absolute():
        path = Path(base if isinstance(base, (str, Path)) else Path.cwd()) / path
    try:
        if must_exist and not path.is_file():
            raise ValueError(f"file not found: {path}")
        if must_exist and not os.access(path, os.R_OK):
            raise ValueError(f"file not readable: {path}")
        if not must_exist and not path.parent.is_dir():
            raise ValueError(f"directory not found: {path.parent}")
    except OSError as exc:
        raise ValueError(f"cannot use {path}: {exc.strerror or exc}") from None
    return path


# --------------------------------------------------------------------------------------------
# SLC 500 addresses: syntax is checked by gateway.protocols.df1.address; the few properties the
# map rules need (file letter, bit or word) are read here from the text.

_BIT_MNEMONICS = frozenset(
    {"EN", "TT", "DN", "CU", "CD", "OV", "UN", "UA", "EU", "EM", "ER", "UL", "IN", "FD"}
)
"""Timer, counter and control members that are bits (``T4:0.DN``); PRE, ACC, LEN, POS are words."""
_BIT_FILES = frozenset({"B", "N", "I", "O", "S", "R"})
"""Files whose elements are words of addressable bits (SLC 500 addressing reference)."""
_ADDRESS_RE = re.compile(
    r"""\$?(?P<letter>[A-Z]{1,2})(?P<file>[0-9]{0,3})
        (?: :(?P<element>[0-9]{1,4}) (?:\.(?P<sub>[0-9]{1,3}|[A-Z]{2,3}))? (?:/(?P<bit>[0-9]{1,4}|[A-Z]{2}))?
          | /(?P<absolute_bit>[0-9]{1,4}) )""",
    re.VERBOSE | re.IGNORECASE,
)


_NO_BIT_ATTRIBUTE = object()


class _AddressKind(NamedTuple):
    letter: str
    is_bit: bool


def _classify_address(text: str) -> _AddressKind | None:
    match = _ADDRESS_RE.fullmatch(text.strip())
    if match is None:
        return None
    sub = (match["sub"] or "").upper()
    is_bit = bool(match["bit"] or match["absolute_bit"] or sub in _BIT_MNEMONICS)
    return _AddressKind(match["letter"].upper(), is_bit)


def _check_address(text: str) -> tuple[str | None, _AddressKind | None]:
    """``(error, kind)`` of an SLC 500 address: the error message (None: valid) and what it is.

    The syntax is the business of ``gateway.protocols.df1.address.parse_address``, imported late
    so that this module imports without it; without it a local pattern checks the usual forms.
    """
    parse: Callable[[str], object] | None = None
    try:
        module = importlib.import_module("gateway.protocols.df1.address")
    except ImportError:
        module = None
    if module is not None:
        candidate = getattr(module, "parse_address", None)
        if callable(candidate):
            parse = candidate
    kind = _classify_address(text)
    if parse is None:
        if kind is None:
            return f"{_show(text)}: not a valid SLC 500 address (e.g. N7:0, B3:0/5, F8:10, T4:0.ACC)", None
        return None, kind
    try:
        parsed = parse(text)
    except ValueError as exc:  # AddressError is an InvalidRequest, a ValueError
        return f"not a valid SLC 500 address: {exc}", None
    letter = getattr(getattr(parsed, "file_type", None), "letter", None)  # SlcAddress.file_type.letter
    bit = getattr(parsed, "bit", _NO_BIT_ATTRIBUTE)
    if isinstance(letter, str) and bit is not _NO_BIT_ATTRIBUTE:
        return None, _AddressKind(letter, bit is not None)
    return None, kind


# --------------------------------------------------------------------------------------------
# The models


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)


def _listen_validator(value: object) -> object:
    if isinstance(value, str):
        return _format_listen(*parse_listen(value))
    return value


def _optional_listen_validator(value: object) -> object:
    """``listen`` of the plain Modbus listener: ``""`` turns it off (TLS-only operation)."""
    if isinstance(value, str) and not value.strip():
        return ""
    return _listen_validator(value)


def _parse_networks(value: object) -> tuple[IPv4Network | IPv6Network, ...]:
    networks: list[IPv4Network | IPv6Network] = []
    problems: list[tuple[Loc, str]] = []
    for index, item in enumerate(_array(value)):
        if isinstance(item, (IPv4Network, IPv6Network)):
            networks.append(item)
        elif not isinstance(item, str):
            problems.append(((index,), f'must be a string such as "10.0.0.0/8" (got {_show(item)})'))
        else:
            try:
                networks.append(ipaddress.ip_network(item.strip()))
            except ValueError as exc:
                problems.append(((index,), f"not a CIDR network such as 10.0.0.0/8: {exc}"))
    if problems:
        raise _Problems(*problems)
    return tuple(networks)


class TlsConfig(_Model):
    """``[modbus.tls]``: Modbus/TCP Security (Modbus over TLS)."""

    listen: str = "0.0.0.0:802"
    cert: Path
    key: Path
    client_ca: Path | None = None
    handshake_timeout: float = Field(5.0, gt=0, le=60)
    max_handshakes: int = Field(16, ge=1, le=10000)
    roles: dict[str, Rights] = Field(default_factory=dict)
    default_rights: Rights = "read"

    _check_listen = field_validator("listen", mode="before")(_listen_validator)

    @field_validator("roles", mode="before")
    @classmethod
    def _check_roles(cls, value: object) -> object:
        if isinstance(value, dict):
            for name in value:
                if not isinstance(name, str) or not name or len(name) > 128:
                    raise ValueError(f"{_show(name)}: a role name is 1 to 128 characters")
        return value

    @field_validator("cert", "key", "client_ca", mode="before")
    @classmethod
    def _existing_file(cls, value: object, info: ValidationInfo) -> Path:
        return _resolve_path(value, info, must_exist=True)

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


class ModbusConfig(_Model):
    """``[modbus]``: the Modbus TCP server."""

    listen: str = "0.0.0.0:5020"
    max_connections: int = Field(64, ge=1, le=10000)
    max_connections_per_address: int = Field(0, ge=0, le=10000)
    idle_timeout: float = Field(300.0, ge=0)
    frame_timeout: float = Field(5.0, gt=0, le=3600)
    allow: tuple[IPv4Network | IPv6Network, ...] = ()
    loopback_reads: bool = True
    tls: TlsConfig | None = None

    _check_listen = field_validator("listen", mode="before")(_optional_listen_validator)

    @field_validator("allow", mode="before")
    @classmethod
    def _parse_allow(cls, value: object) -> object:
        return _parse_networks(value)

    @model_validator(mode="after")
    def _some_listener(self) -> ModbusConfig:
        if not self.listen and self.tls is None:
            raise _Problems((("listen",), 'listen = "" turns the plain listener off: configure [modbus.tls] too'))
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


class MetricsConfig(_Model):
    """``[metrics]``: HTTP ``/metrics`` (Prometheus) and ``/healthz``."""

    listen: str = "127.0.0.1:9108"
    allow: tuple[IPv4Network | IPv6Network, ...] = ()
    max_connections: int = Field(32, ge=1, le=1000)

    _check_listen = field_validator("listen", mode="before")(_listen_validator)

    @field_validator("allow", mode="before")
    @classmethod
    def _parse_allow(cls, value: object) -> object:
        return _parse_networks(value)

    @property
    def address(self) -> tuple[str, int]:
        """``listen`` as ``(host, port)``."""
        return parse_listen(self.listen)


class LoggingConfig(_Model):
    """``[logging]``."""

    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    repeat_interval: float = Field(60.0, gt=0, le=86400)
    trace_max_bytes: int = Field(10_000_000, ge=4096)
    trace_backups: int = Field(3, ge=0, le=100)

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, value: object) -> object:
        return value.upper() if isinstance(value, str) else value


class WritableRange(_Model):
    """One entry of ``writable``: Modbus addresses ``first..last`` (inclusive) of ``table``."""

    table: WritableTable
    first: int = Field(ge=0, le=65535)
    last: int = Field(ge=0, le=65535)

    @classmethod
    def parse(cls, text: str) -> WritableRange:
        """Parse ``"holding:0-31"`` or ``"coil:40"``; raises ``ValueError``."""
        match = _WRITABLE_RE.fullmatch(text)
        if match is None:
            raise ValueError(
                f'{_show(text)}: expected "table:first-last" or "table:address", e.g. "holding:0-31"'
            )
        table, first_text, last_text = match.groups()
        if table not in ("holding", "coil"):
            raise ValueError(f"{_show(text)}: the table must be holding or coil (the writable tables)")
        table_name: WritableTable = "holding" if table == "holding" else "coil"
        first = int(first_text)
        last = int(last_text) if last_text is not None else first
        if last > 65535:
            raise ValueError(f"{_show(text)}: Modbus addresses are 0..65535")
        if first > last:
            raise ValueError(f"{_show(text)}: the range is backwards ({first} > {last})")
        return cls(table=table_name, first=first, last=last)

    def __contains__(self, item: object) -> bool:
        """``("holding", 12) in writable_range``."""
        if not (isinstance(item, tuple) and len(item) == 2):
            return False
        table, address = item
        return bool(table == self.table and isinstance(address, int) and self.first <= address <= self.last)

    def __str__(self) -> str:
        if self.first == self.last:
            return f"{self.table}:{self.first}"
        return f"{self.table}:{self.first}-{self.last}"


class MapEntry(_Model):
    """``[[link.map]]``: ``count`` values from SLC ``address`` on, at ``table`` addresses from ``start``."""

    table: Table
    start: int = Field(ge=0, le=65535)
    address: str
    count: int = Field(ge=1, le=2000)
    type: ValueType = "int16"
    word_order: Literal["high-first", "low-first"] = "high-first"
    scan: Literal["fast", "slow"] = "fast"

    @model_validator(mode="before")
    @classmethod
    def _bool_by_default_for_bits(cls, data: Any) -> Any:
        if isinstance(data, dict) and "type" not in data and data.get("table") in _BIT_TABLES:
            return {**data, "type": "bool"}
        return data

    @property
    def width(self) -> int:
        """Modbus addresses per value: 2 for float32, else 1."""
        return 2 if self.type == "float32" else 1

    @property
    def size(self) -> int:
        """Modbus addresses covered: ``count * width``."""
        return self.count * self.width

    @property
    def last(self) -> int:
        """The last Modbus address covered (inclusive)."""
        return self.start + self.size - 1

    def describe_range(self) -> str:
        return f"{self.table} {self.start}-{self.last}"

    @model_validator(mode="after")
    def _check(self) -> MapEntry:
        problems: list[tuple[Loc, str]] = []
        bit_table = self.table in _BIT_TABLES
        if bit_table and self.type != "bool":
            problems.append((("type",), f'a {self.table} table holds bits: the type must be "bool"'))
        elif not bit_table and self.type == "bool":
            problems.append(
                (("type",), f'type "bool" is for coil and discrete tables (this is a {self.table} table)')
            )
        type_problem = bool(problems)
        if self.last > 65535:
            problems.append(
                (
                    ("count",),
                    f"the entry ends past Modbus address 65535: start {self.start} + count {self.count}"
                    f" x {self.width} - 1 = {self.last}",
                )
            )
        syntax_error, kind = _check_address(self.address)
        if syntax_error is not None:
            problems.append((("address",), syntax_error))
        elif kind is not None and not type_problem:
            problems.extend(self._address_problems(kind))
        if problems:
            raise _Problems(*problems)
        return self

    def _address_problems(self, kind: _AddressKind) -> list[tuple[Loc, str]]:
        address = _show(self.address)
        if self.table in _BIT_TABLES:
            if kind.letter == "F":
                return [
                    (("address",), f"{address} is a floating-point element: a {self.table} table needs bits")
                ]
            if not kind.is_bit and kind.letter not in _BIT_FILES:
                return [
                    (
                        ("address",),
                        f"{address}: a {self.table} table needs a bit address (e.g. B3:0/0 or N7:0/0) "
                        "or an element of a bit file (B, N, I, O, S, R)",
                    )
                ]
            return []
        if kind.is_bit:
            return [(("address",), f"{address} is a bit address: a {self.table} table needs a word address")]
        if self.type == "float32" and kind.letter != "F":
            return [
                (("address",), f'{address}: type "float32" needs a floating-point file address such as F8:0')
            ]
        if self.type != "float32" and kind.letter == "F":
            return [(("type",), f'{address} is a floating-point element: use type = "float32"')]
        return []


class LinkConfig(_Model):
    """``[[link]]``: one serial link to one controller, served as one Modbus unit id."""

    name: str
    protocol: LinkProtocol
    port: str
    unit: int = Field(ge=1, le=247)
    baudrate: int = 9600
    bytesize: int = 7
    parity: Literal["N", "E", "O"] = "E"
    stopbits: int = 1
    timeout: float = Field(0.3, gt=0, le=60)
    retries: int = Field(3, ge=0, le=10)
    stale_after: float = Field(5.0, gt=0)
    down_after_failures: int = Field(3, ge=1, le=1000)
    down_after_seconds: float = Field(5.0, gt=0)
    read_only: bool = False
    writable: tuple[WritableRange, ...] = ()
    fast_interval: float = Field(0.0, ge=0)
    slow_interval: float = Field(10.0, ge=0)
    #: write transactions in a row before waiting polls get the line, for poll_burst transactions
    write_burst: int = Field(1, ge=1, le=100)
    poll_burst: int = Field(2, ge=1, le=100)
    #: writes that may wait for the line, per client connection and in all (beyond: 0x06)
    write_queue_per_client: int = Field(8, ge=1, le=1000)
    write_queue_per_link: int = Field(32, ge=1, le=10000)
    trace: Path | None = None
    # df1 only
    station: int = Field(1, ge=0, le=254)
    source: int = Field(0, ge=0, le=254)
    checksum: Literal["bcc", "crc"] = "crc"
    processor: Processor = "slc5/04"
    max_read_bytes: int = Field(0, ge=0, le=240)
    max_write_bytes: int = Field(0, ge=0, le=240)
    map: tuple[MapEntry, ...] = Field((), strict=False)

    @model_validator(mode="before")
    @classmethod
    def _fill_protocol_defaults(cls, data: Any) -> Any:
        if isinstance(data, dict):
            protocol = data.get("protocol")
            if isinstance(protocol, str) and protocol in PROTOCOL_DEFAULTS:
                return {**PROTOCOL_DEFAULTS[protocol], **data}
        return data

    @field_validator("name")
    @classmethod
    def _check_name(cls, value: str) -> str:
        if not _NAME_RE.fullmatch(value):
            raise ValueError(f"{_show(value)}: a link name is 1 to 40 characters from A-Z a-z 0-9 _ . -")
        return value

    @field_validator("port")
    @classmethod
    def _check_port(cls, value: str) -> str:
        _check_port_url(value)
        return value

    @field_validator("baudrate")
    @classmethod
    def _check_baudrate(cls, value: int) -> int:
        if value not in _BAUDRATES:
            raise ValueError(f"{value} is not a standard baud rate ({', '.join(map(str, _BAUDRATES))})")
        return value

    @field_validator("bytesize")
    @classmethod
    def _check_bytesize(cls, value: int) -> int:
        if value not in (7, 8):
            raise ValueError(f"must be 7 or 8 (got {value})")
        return value

    @field_validator("stopbits")
    @classmethod
    def _check_stopbits(cls, value: int) -> int:
        if value not in (1, 2):
            raise ValueError(f"must be 1 or 2 (got {value})")
        return value

    @field_validator("writable", mode="before")
    @classmethod
    def _parse_writable(cls, value: object) -> object:
        ranges: list[WritableRange] = []
        problems: list[tuple[Loc, str]] = []
        for index, item in enumerate(_array(value)):
            if isinstance(item, WritableRange):
                ranges.append(item)
            elif not isinstance(item, str):
                problems.append(((index,), f'must be a string such as "holding:0-31" (got {_show(item)})'))
            else:
                try:
                    ranges.append(WritableRange.parse(item))
                except ValueError as exc:
                    problems.append(((index,), str(exc)))
        if problems:
            raise _Problems(*problems)
        return tuple(ranges)

    @field_validator("trace", mode="before")
    @classmethod
    def _trace_path(cls, value: object, info: ValidationInfo) -> Path | None:
        if value is None or value == "":
            return None
        return _resolve_path(value, info, must_exist=False)

    @model_validator(mode="after")
    def _check(self) -> LinkConfig:
        problems: list[tuple[Loc, str]] = []
        if self.protocol == "slc-ascii":
            for key in DF1_ONLY_KEYS:
                if key not in self.model_fields_set:
                    continue
                if key == "map":
                    problems.append((("map",), "slc-ascii links use the fixed default map"))
                else:
                    problems.append(((key,), "only for df1 links (this link's protocol is slc-ascii)"))
        elif not self.map:
            problems.append((("map",), "a df1 link needs at least one [[link.map]] entry"))
        model = _sim_model(self.port)
        if model is not None and _SIM_MODELS[model] != self.protocol:
            problems.append(
                (
                    ("port",),
                    f"sim://{model} simulates a controller that speaks {_SIM_MODELS[model]}, "
                    f"but this link's protocol is {self.protocol}",
                )
            )
        if self.read_only and self.writable:
            problems.append((("writable",), "a read_only link accepts no writes: drop writable or read_only"))
        problems.extend(_overlaps(self.map))
        if problems:
            raise _Problems(*problems)
        return self

    @property
    def is_simulated(self) -> bool:
        return self.port.startswith("sim://")

    def is_writable(self, table: str, address: int) -> bool:
        """Whether a Modbus write to ``table`` ``address`` passes ``read_only`` and ``writable``.

        Whether the address is mapped at all is the mapping's business, not this method's.
        """
        if self.read_only or table not in ("holding", "coil"):
            return False
        return not self.writable or any((table, address) in r for r in self.writable)


def _overlaps(entries: Sequence[MapEntry]) -> list[tuple[Loc, str]]:
    problems: list[tuple[Loc, str]] = []
    for later in range(len(entries)):
        b = entries[later]
        for earlier in range(later):
            a = entries[earlier]
            if a.table != b.table or a.last < b.start or b.last < a.start:
                continue
            low, high = max(a.start, b.start), min(a.last, b.last)
            where = f"{low}-{high}" if low != high else f"{low}"
            problems.append(
                (
                    ("map", later),
                    f"{b.describe_range()} overlaps map[{earlier}] ({a.describe_range()}) "
                    f"at {b.table} {where}",
                )
            )
            break
    return problems


class GatewayConfig(_Model):
    """The whole configuration file."""

    modbus: ModbusConfig = ModbusConfig()
    metrics: MetricsConfig | None = None
    logging: LoggingConfig = LoggingConfig()
    link: tuple[LinkConfig, ...] = Field(strict=False)

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
                        f"duplicate link name {_show(link.name)}: link[{names[link.name]}] has it",
                    )
                )
            names.setdefault(link.name, index)
            if link.unit in units:
                other = self.link[units[link.unit]]
                problems.append(
                    (
                        ("link", index, "unit"),
                        f"duplicate unit id {link.unit}: "
                        f"link {_show(other.name)} (link[{units[link.unit]}]) has it",
                    )
                )
            units.setdefault(link.unit, index)
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
            raise _Problems(*problems)
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
                    f"(listen = {_show(self.modbus.listen)}) serves anyone who can reach it without one: "
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
        lines += _table_lines("[modbus]", self.modbus, skip=("tls",))
        if self.modbus.tls is None:
            lines += ["# [modbus.tls] not configured: no Modbus/TCP Security listener", ""]
        else:
            lines += _table_lines("[modbus.tls]", self.modbus.tls)
        if self.metrics is None:
            lines += ["# [metrics] not configured: no /metrics or /healthz endpoint", ""]
        else:
            lines += _table_lines("[metrics]", self.metrics)
        lines += _table_lines("[logging]", self.logging)
        for link in self.link:
            if link.protocol == "df1":
                lines += _table_lines("[[link]]", link, skip=("map",))
                for entry in link.map:
                    lines += _table_lines("[[link.map]]", entry, indent="  ")
            else:
                lines += _table_lines("[[link]]", link, skip=DF1_ONLY_KEYS)
                lines[-1:-1] = ["# map: the fixed SLC 100/150 default map"]
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


def _array(value: object) -> list[object]:
    if isinstance(value, (list, tuple)):
        return list(value)
    raise ValueError(f"must be an array (got {_show(value)})")


# --------------------------------------------------------------------------------------------
# Rendering values as TOML


def _toml_string(text: str) -> str:
    out = ['"']
    for char in text:
        if char in '"\\':
            out.append("\\" + char)
        elif char == "\n":
            out.append("\\n")
        elif char == "\t":
            out.append("\\t")
        elif ord(char) < 0x20 or ord(char) == 0x7F:
            out.append(f"\\u{ord(char):04X}")
        else:
            out.append(char)
    out.append('"')
    return "".join(out)


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return _toml_string(redact_url(value))
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_string(str(k))} = {_toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, (Path, IPv4Network, IPv6Network, WritableRange)):
        return _toml_string(str(value))
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    return _toml_string(str(value))


def _table_lines(header: str, model: BaseModel, *, skip: Iterable[str] = (), indent: str = "") -> list[str]:
    skipped = set(skip)
    lines = [indent + header]
    for key in type(model).model_fields:
        if key in skipped:
            continue
        value = getattr(model, key)
        if value is None and key == "trace":
            lines.append(f'{indent}trace = ""')
        elif value is None:
            lines.append(f"{indent}# {key} not set")
        else:
            lines.append(f"{indent}{key} = {_toml_value(value)}")
    lines.append("")
    return lines


def _show(value: object, limit: int = 60) -> str:
    """A value as it would be written in TOML, shortened, for messages."""
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, (list, tuple)):
        return "an array"
    if isinstance(value, (datetime, date, time)):
        text = value.isoformat()
    elif isinstance(value, (bool, int, float, str)):
        text = _toml_value(value)
    else:
        text = str(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _dotted(loc: Loc) -> str:
    return ".".join(str(part) for part in loc)


# --------------------------------------------------------------------------------------------
# Turning pydantic errors into one ConfigError

_TYPE_MESSAGES = {
    "int_type": "must be an integer",
    "int_parsing": "must be an integer",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "tuple_type": "must be an array",
    "list_type": "must be an array",
    "dict_type": "must be a table",
    "model_type": "must be a table",
    "model_attributes_type": "must be a table",
    "is_instance_of": "must be a string",
}


def _message(error: ErrorDetails) -> str:
    kind = error["type"]
    if kind == "missing":
        return "missing required key"
    if kind == "extra_forbidden":
        return "unknown key" + _suggestion(tuple(error["loc"]))
    message = error["msg"]
    if kind in ("value_error", "assertion_error"):
        return message.removeprefix("Value error, ").removeprefix("Assertion failed, ")
    message = _TYPE_MESSAGES.get(kind) or message.replace("Input should be", "must be").replace("'", '"')
    return f"{message} (got {_show(error['input'])})"


def _suggestion(loc: Loc) -> str:
    if not loc or not isinstance(loc[-1], str):
        return ""
    model: type[BaseModel] | None = GatewayConfig
    for part in loc[:-1]:
        if isinstance(part, int) or model is None:
            continue
        field = model.model_fields.get(part)
        model = _model_in(field.annotation) if field is not None else None
    if model is None:
        return ""
    close = difflib.get_close_matches(loc[-1], list(model.model_fields), n=1, cutoff=0.6)
    return f' (did you mean "{close[0]}"?)' if close else ""


def _model_in(annotation: object) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for argument in get_args(annotation):
        found = _model_in(argument)
        if found is not None:
            return found
    return None


def _render_path(loc: Loc, link_names: Mapping[int, str]) -> str:
    if not loc:
        return "(top level)"
    parts: list[str] = []
    rest = loc
    if len(loc) >= 2 and loc[0] == "link" and isinstance(loc[1], int):
        name = link_names.get(loc[1])
        index = f"link[{loc[1]}]"
        parts.append(f"link {_show(name, 42)} ({index})" if name is not None else index)
        rest = loc[2:]
    for part in rest:
        if isinstance(part, int):
            parts.append(f"[{part}]")
        else:
            key = part if re.fullmatch(r"[A-Za-z0-9_-]+", part) else _toml_string(part)
            parts.append(("." if parts else "") + key)
    return "".join(parts)


_HEADER_RE = re.compile(r"\s*(\[\[?)\s*(.*?)\s*(\]\]?)\s*(?:#.*)?")
_KEY_PART = r'(?:[A-Za-z0-9_-]+|"(?:[^"\\]|\\.)*"|\'[^\']*\')'
_KEY_LINE_RE = re.compile(rf"\s*({_KEY_PART}(?:\s*\.\s*{_KEY_PART})*)\s*=")
_KEY_PART_RE = re.compile(_KEY_PART)


def _split_key(text: str) -> tuple[str, ...]:
    parts = []
    for match in _KEY_PART_RE.finditer(text):
        part = match.group()
        if part.startswith('"'):
            try:
                part = json.loads(part)
            except ValueError:
                part = part[1:-1]
        elif part.startswith("'"):
            part = part[1:-1]
        parts.append(part)
    return tuple(parts)


class _LineIndex:
    """Best-effort map from key paths to line numbers, by scanning the TOML text line by line."""

    def __init__(self, text: str) -> None:
        self.lines: dict[Loc, int] = {}
        arrays: dict[Loc, int] = {}  # array-of-tables path -> index of its last table
        current: Loc = ()
        quote: str | None = None
        for number, line in enumerate(text.split("\n"), start=1):
            if quote is not None:  # inside a multi-line string
                if line.count(quote) % 2 == 1:
                    quote = None
                continue
            header = _HEADER_RE.fullmatch(line)
            if header is not None and len(header[1]) == len(header[3]):
                current = self._resolve(_split_key(header[2]), arrays, is_array=header[1] == "[[")
                self.lines.setdefault(current, number)
                continue
            key = _KEY_LINE_RE.match(line)
            if key is not None:
                self.lines.setdefault(current + _split_key(key[1]), number)
                value = line[key.end() :]
                for candidate in ('"""', "'''"):
                    if value.count(candidate) % 2 == 1:
                        quote = candidate
                        break

    @staticmethod
    def _resolve(keys: tuple[str, ...], arrays: dict[Loc, int], *, is_array: bool) -> Loc:
        path: Loc = ()
        for position, key in enumerate(keys):
            path += (key,)
            if is_array and position == len(keys) - 1:
                arrays[path] = arrays.get(path, -1) + 1
            if path in arrays:
                path += (arrays[path],)
        return path

    def find(self, loc: Loc) -> int | None:
        for length in range(len(loc), 0, -1):
            number = self.lines.get(loc[:length])
            if number is not None:
                return number
        return None


def _config_error(source: str, problems: list[tuple[int | None, str]]) -> ConfigError:
    def line(number: int | None, text: str) -> str:
        return f"{source}:{number}: {text}" if number is not None else f"{source}: {text}"

    ordered = sorted(problems, key=lambda item: (item[0] is None, item[0] or 0))
    if len(ordered) == 1:
        return ConfigError(line(*ordered[0]))
    body = "\n".join("  " + line(number, text) for number, text in ordered)
    return ConfigError(f"{source}: {len(ordered)} errors in the configuration:\n{body}")


def _validate(data: dict[str, Any], text: str, source: str, base_dir: Path) -> GatewayConfig:
    try:
        return GatewayConfig.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        raw_links = data.get("link")
        link_names: dict[int, str] = {}
        if isinstance(raw_links, list):
            for index, raw in enumerate(raw_links):
                if isinstance(raw, dict) and isinstance(raw.get("name"), str):
                    link_names[index] = raw["name"]
        line_index = _LineIndex(text)
        problems: list[tuple[int | None, str]] = []
        for error in exc.errors(include_url=False):
            loc: Loc = tuple(error["loc"])
            cause = error.get("ctx", {}).get("error")
            found = cause.problems if isinstance(cause, _Problems) else (((), _message(error)),)
            for sub_loc, message in found:
                full = loc + sub_loc
                problems.append((line_index.find(full), f"{_render_path(full, link_names)}: {message}"))
        raise _config_error(source, problems) from None


# --------------------------------------------------------------------------------------------
# Entry points


def parse_config(text: str, source: str = "<string>", *, base_dir: str | Path | None = None) -> GatewayConfig:
    """Parse and validate TOML ``text``; ``source`` names it in error messages.

    Relative paths in the config (TLS files, traces) are relative to ``base_dir`` (default: the
    current directory). Raises :class:`ConfigError`, never anything else, for any bad text.
    """
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    if "\0" in text:
        raise ConfigError(f"{source}: contains NUL characters: not a text file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        where = re.search(r"\s*\(at line (\d+), column (\d+)\)$", message)
        if where is not None:
            message = message[: where.start()]
            raise ConfigError(f"{source}:{where[1]}:{where[2]}: not valid TOML: {message}") from None
        raise ConfigError(f"{source}: not valid TOML: {message}") from None
    except RecursionError:
        raise ConfigError(f"{source}: not valid TOML: nested too deeply") from None
    return _validate(data, text, source, base)


def load_config(path: str | Path) -> GatewayConfig:
    """Read, parse and validate the config file at ``path``. Raises :class:`ConfigError`."""
    path = Path(path)
    source = str(path)
    try:
        if not stat.S_ISREG(path.stat().st_mode):
            raise ConfigError(f"{source}: not a regular file")
        with path.open("rb") as file:
            data = file.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read the config file: {exc.strerror or exc}") from None
    except ValueError as exc:  # a NUL in the path
        raise ConfigError(f"{source}: cannot read the config file: {exc}") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{source}: larger than {MAX_CONFIG_BYTES} bytes: not a config file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{source}:{line}: not UTF-8 text (byte 0x{data[exc.start]:02X} at offset {exc.start}): "
            "is this a binary file?"
        ) from None
    return parse_config(text, source, base_dir=path.absolute().parent)
