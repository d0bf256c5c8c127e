"""What every part of the config schema shares: the strict frozen base model, the problem list a
validator raises, value display for messages, and the small parsers (listen addresses, port URLs,
file paths, networks)."""

from __future__ import annotations

import ipaddress
import os
import re
from datetime import date, datetime, time
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

from pydantic import BaseModel, ConfigDict, ValidationInfo

from gateway.config.writer import toml_value

__all__ = [
    "Loc",
    "Model",
    "Problems",
    "array",
    "check_port_url",
    "is_host",
    "is_port_path",
    "listen_validator",
    "optional_listen_validator",
    "optional_output_path",
    "parse_listen",
    "parse_networks",
    "port_key",
    "resolve_path",
    "show",
    "sim_model",
]

Loc = tuple[str | int, ...]

_HOST_LABEL_RE = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")
_PORT_RE = re.compile(r"[0-9]{1,5}")
_COM_RE = re.compile(r"(?:\\\\\.\\)?COM[1-9][0-9]{0,2}", re.IGNORECASE)
_SIM_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,39}")
#: ``ttyUSB0``: a device's name without its directory (a port given so gets a "did you mean /dev/...")
_DEVICE_NAME_RE = re.compile(r"tty[A-Za-z0-9_.-]{1,40}")


class Model(BaseModel):
    """Frozen, unknown keys forbidden, strict types (TOML is typed: ``unit = "1"`` is an error)."""

    model_config = ConfigDict(
        frozen=True, extra="forbid", strict=True, allow_inf_nan=False, use_attribute_docstrings=True
    )


class Problems(ValueError):
    """Raised by validators: one or more problems, each at a key path relative to the model."""

    def __init__(self, *problems: tuple[Loc, str]) -> None:
        super().__init__("; ".join(message for _, message in problems))
        self.problems = problems


def show(value: object, limit: int = 60) -> str:
    """A value as it would be written in TOML, shortened, for messages."""
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, (list, tuple)):
        return "an array"
    if isinstance(value, (datetime, date, time)):
        text = value.isoformat()
    elif isinstance(value, (bool, int, float, str)):
        text = toml_value(value)
    else:
        text = str(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def array(value: object) -> list[object]:
    if isinstance(value, (list, tuple)):
        return list(value)
    raise ValueError(f"must be an array (got {show(value)})")


# --------------------------------------------------------------------------------------------
# Listen addresses and port URLs


def parse_listen(text: str) -> tuple[str, int]:
    """Split ``host:port`` (IPv6 hosts in brackets: ``[::1]:5020``) into ``(host, port)``.

    The host is returned without brackets. Raises ``ValueError`` with a readable message.
    """
    text = text.strip()
    if text.startswith("["):
        close = text.find("]")
        if close < 0:
            raise ValueError(f"{show(text)}: missing ']' after the IPv6 address")
        host, rest = text[1:close], text[close + 1 :]
        if not rest.startswith(":"):
            raise ValueError(f"{show(text)}: expected [IPv6 address]:port, e.g. [::1]:5020")
        port_text = rest[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"{show(host)} is not an IPv6 address") from None
    else:
        host, colon, port_text = text.rpartition(":")
        if not colon:
            raise ValueError(f"{show(text)}: expected host:port, e.g. 0.0.0.0:5020")
        if ":" in host:
            raise ValueError(f"{show(text)}: put an IPv6 address in brackets, e.g. [::1]:5020")
        if not host:
            raise ValueError(f"{show(text)}: the host is missing (0.0.0.0 listens on every interface)")
        if not is_host(host):
            raise ValueError(f"{show(host)} is not an IPv4 address or a host name")
    if not _PORT_RE.fullmatch(port_text) or int(port_text) > 65535:
        raise ValueError(f"{show(text)}: the port must be a number 0..65535")
    return host, int(port_text)


def _format_listen(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def is_host(host: str) -> bool:
    labels = host.split(".")
    if all(label.isascii() and label.isdigit() for label in labels):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            return False
        return True
    return len(host) <= 253 and all(_HOST_LABEL_RE.fullmatch(label) for label in labels)


def _is_host_or_ipv6(host: str) -> bool:
    if ":" in host:
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            return False
        return True
    return is_host(host)


def listen_validator(value: object) -> object:
    if isinstance(value, str):
        return _format_listen(*parse_listen(value))
    return value


def optional_listen_validator(value: object) -> object:
    """``listen`` of the plain Modbus listener: ``""`` turns it off (TLS-only operation)."""
    if isinstance(value, str) and not value.strip():
        return ""
    return listen_validator(value)


def check_port_url(text: str, sim_models: tuple[str, ...] = ()) -> None:
    """Validate the ``port`` of a link: a serial device, a TCP URL or a simulator URL.

    A ``sim://`` URL is checked for its form only; ``sim_models`` (the simulators of the link's
    protocol) are named in the messages. Whether the model exists and speaks the link's protocol
    is checked by ``gateway.config.links``, which knows every link kind.
    """
    simulators = " or ".join(f"sim://{name}" for name in sim_models) or "sim://model"
    if text.startswith("/"):
        # Any absolute path: a device under /dev, a socat pty, a symlink in /tmp.  Whether it
        # exists is not a rule of the file: a missing one is a warning (GatewayConfig.warnings)
        # and the link keeps trying to open it.
        if text.endswith("/") or any(c.isspace() or c == "\0" for c in text):
            raise ValueError(f"{show(text)} is not a path to a serial port")
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
            raise ValueError(f"{show(text)}: expected {scheme}://host:port with a port 1..65535")
        return
    if sep and scheme == "sim":
        parts = urlsplit(text)
        if not _SIM_NAME_RE.fullmatch(parts.netloc) or parts.path not in ("", "/") or parts.fragment:
            raise ValueError(f"{show(text)}: expected {simulators}, optionally followed by ?option=value&...")
        if parts.query:
            try:
                parse_qsl(parts.query, keep_blank_values=True, strict_parsing=True)
            except ValueError:
                raise ValueError(f"{show(text)}: the simulator options are not option=value&...") from None
        return
    hint = f" (did you mean {show('/dev/' + text)}?)" if _DEVICE_NAME_RE.fullmatch(text) else ""
    raise ValueError(
        f"{show(text)}{hint}: expected a serial port by its absolute path (/dev/ttyUSB0, /tmp/ttyV0) or COM3, "
        f"socket://host:port, rfc2217://host:port or {simulators.replace(' or ', ' | ')}"
    )


def is_port_path(port: str) -> bool:
    """Whether a link's ``port`` is a path (a serial port or a pty), not a URL or a COM port."""
    return port.startswith("/")


def port_key(port: str) -> str:
    """The same key for ports that name the same line: a local device is case-sensitive, a URL's
    scheme and host and a COM port's name are not."""
    if "://" in port:
        scheme, rest = port.split("://", 1)
        host, _, tail = rest.partition("/")
        return f"{scheme.lower()}://{host.lower()}/{tail}"
    return port.upper() if port.upper().startswith("COM") else port


def sim_model(port: str) -> str | None:
    """The model of a ``sim://model?...`` port, None for other ports."""
    if port.startswith("sim://"):
        return urlsplit(port).netloc
    return None


# --------------------------------------------------------------------------------------------
# Paths and networks


def resolve_path(value: object, info: ValidationInfo, *, must_exist: bool) -> Path:
    """A path from the config, made absolute against the config file's directory."""
    if isinstance(value, Path):
        value = str(value)
    if not isinstance(value, str):
        raise ValueError(f"must be a string (a file path) (got {show(value)})")
    if not value.strip() or "\0" in value:
        raise ValueError(f"{show(value)} is not a file path")
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


def optional_output_path(value: object, info: ValidationInfo) -> Path | None:
    """A file the gateway writes (a trace, a target's table), ``resolve_path`` without ``must_exist``;
    None when not given or empty."""
    if value is None or value == "":
        return None
    return resolve_path(value, info, must_exist=False)


def parse_networks(value: object) -> tuple[IPv4Network | IPv6Network, ...]:
    networks: list[IPv4Network | IPv6Network] = []
    problems: list[tuple[Loc, str]] = []
    for index, item in enumerate(array(value)):
        if isinstance(item, (IPv4Network, IPv6Network)):
            networks.append(item)
        elif not isinstance(item, str):
            problems.append(((index,), f'must be a string such as "10.0.0.0/8" (got {show(item)})'))
        else:
            try:
                networks.append(ipaddress.ip_network(item.strip()))
            except ValueError as exc:
                problems.append(((index,), f"not a CIDR network such as 10.0.0.0/8: {exc}"))
    if problems:
        raise Problems(*problems)
    return tuple(networks)
