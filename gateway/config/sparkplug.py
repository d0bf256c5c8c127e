"""``[sparkplug]``: the gateway as a Sparkplug B 3.0 edge node (off when the section is absent).

Topic elements follow Sparkplug 3.0 §4.1 ("Topic Namespace Elements"): ``group_id``,
``edge_node_id`` and each device id (a link's name) are UTF-8 strings without the characters
``/``, ``+`` and ``#`` (§4.1.2, §4.1.4, §4.1.5).
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.config._common import Model, Problems, resolve_path, show

__all__ = ["BDSEQ_FILE", "SparkplugConfig", "topic_element_problem"]

#: where the bdSeq of the last MQTT session is kept, relative to the config file's directory
BDSEQ_FILE = "sparkplug-bdseq.json"
_DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}


def topic_element_problem(text: str) -> str | None:
    """Why ``text`` cannot be a Sparkplug topic element (§4.1.2, §4.1.4, §4.1.5), or None."""
    if not text:
        return "must not be empty"
    bad = sorted({c for c in text if c in "/+#"})
    if bad:
        return f"{show(text)} contains {' '.join(bad)}: Sparkplug topic elements cannot hold / + #"
    return None


class SparkplugConfig(Model):
    """``[sparkplug]``."""

    broker: str
    group_id: str
    edge_node_id: str
    primary_host_id: str | None = None
    username: str | None = None
    password: str | None = None
    ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    client_id: str | None = None
    keepalive: int = Field(30, ge=5, le=65535)
    reconnect_min: float = Field(1.0, gt=0, le=3600)
    reconnect_max: float = Field(60.0, gt=0, le=3600)
    state_file: Path = Field(Path(BDSEQ_FILE), validate_default=True)
    check_interval: float = Field(0.5, gt=0, le=60)
    batch_interval: float = Field(0.05, ge=0, le=10)
    status_interval: float = Field(5.0, gt=0, le=3600)
    ndeath_on_stop: Literal[True, False] = True

    @field_validator("broker")
    @classmethod
    def _check_broker(cls, value: str) -> str:
        parts = urlsplit(value)
        if parts.scheme not in _DEFAULT_PORTS:
            raise ValueError(f"{show(value)}: the broker is mqtt://host:port or mqtts://host:port")
        if not parts.hostname:
            raise ValueError(f"{show(value)}: no host (mqtt://127.0.0.1:1883)")
        try:
            parts.port  # noqa: B018 (raises on a bad port)
        except ValueError:
            raise ValueError(f"{show(value)}: the port must be 0..65535") from None
        if parts.path not in ("", "/") or parts.query or parts.username:
            raise ValueError(f"{show(value)}: only scheme, host and port (username and password are keys)")
        return value

    @field_validator("group_id", "edge_node_id", "primary_host_id")
    @classmethod
    def _check_element(cls, value: str | None) -> str | None:
        problem = None if value is None else topic_element_problem(value)
        if problem is not None:
            raise ValueError(problem)
        return value

    @field_validator("ca", "cert", "key", mode="before")
    @classmethod
    def _existing_file(cls, value: object, info: ValidationInfo) -> Path | None:
        return None if value is None else resolve_path(value, info, must_exist=True)

    @field_validator("state_file", mode="before")
    @classmethod
    def _state_file(cls, value: object, info: ValidationInfo) -> Path:
        return resolve_path(value, info, must_exist=False)

    @model_validator(mode="after")
    def _check(self) -> SparkplugConfig:
        problems: list[tuple[tuple[str, ...], str]] = []
        tls = self.tls
        if not tls and (self.ca or self.cert or self.key):
            problems.append((("broker",), "ca / cert / key are for an mqtts:// broker"))
        if (self.cert is None) != (self.key is None):
            problems.append((("cert" if self.cert is None else "key",), "cert and key go together"))
        if self.password is not None and self.username is None:
            problems.append((("username",), "a password needs a username"))
        if self.reconnect_max < self.reconnect_min:
            problems.append((("reconnect_max",), f"must be at least reconnect_min ({self.reconnect_min:g})"))
        if tls:
            try:
                self.ssl_context()
            except (ssl.SSLError, OSError) as exc:
                problems.append((("ca",), f"not a usable TLS setup: {getattr(exc, 'reason', None) or exc}"))
        if problems:
            raise Problems(*problems)
        return self

    @property
    def tls(self) -> bool:
        return urlsplit(self.broker).scheme == "mqtts"

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` of the broker."""
        parts = urlsplit(self.broker)
        return parts.hostname or "", parts.port or _DEFAULT_PORTS[parts.scheme]

    def ssl_context(self) -> ssl.SSLContext | None:
        """The client TLS context of an mqtts:// broker (``ca``: its CA; ``cert`` / ``key``: our identity)."""
        if not self.tls:
            return None
        context = ssl.create_default_context(cafile=str(self.ca) if self.ca else None)
        if self.cert is not None and self.key is not None:
            context.load_cert_chain(self.cert, self.key)
        return context
