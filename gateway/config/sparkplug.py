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
    """The MQTT broker: mqtt://host:port, or mqtts://host:port for TLS (ports 1883 / 8883 when left out)."""
    group_id: str
    """The Sparkplug group of the edge node (a topic element: no / + #)."""
    edge_node_id: str
    """The edge node: the gateway (a topic element: no / + #). Each link is a device of it, named as the link."""
    primary_host_id: str | None = None
    """The primary host application whose STATE online the node waits for before its births, and with which it goes
    offline (Sparkplug 3.0 §5.4, §5.5). Unset: publish as soon as connected."""
    username: str | None = None
    """MQTT user name."""
    password: str | None = None
    """MQTT password; needs username."""
    ca: Path | None = None
    """mqtts:// only: the broker's CA certificate file (unset: the system's CAs)."""
    cert: Path | None = None
    """mqtts:// only: the gateway's client certificate file (with key)."""
    key: Path | None = None
    """mqtts:// only: the private key of cert."""
    client_id: str | None = None
    """MQTT client identifier (unset: slc-gateway-<group_id>-<edge_node_id>)."""
    keepalive: int = Field(30, ge=5, le=65535)
    """MQTT keepalive, seconds: the broker publishes the NDEATH within 1.5 x keepalive of the gateway's
    disappearance."""
    reconnect_min: float = Field(1.0, gt=0, le=3600)
    """Seconds before the first reconnect to the broker; the wait doubles up to reconnect_max."""
    reconnect_max: float = Field(60.0, gt=0, le=3600)
    """The longest wait between reconnects, seconds."""
    state_file: Path = Field(Path(BDSEQ_FILE), validate_default=True)
    """Where bdSeq is kept across restarts (relative: to the config file's directory, which must be writable)."""
    check_interval: float = Field(0.5, gt=0, le=60)
    """Seconds between checks for values going stale and links going up or down."""
    batch_interval: float = Field(0.05, ge=0, le=10)
    """Seconds from a new read to its DDATA: the reads of that time go out as one DDATA per device (0: each read)."""
    demand: bool = False
    """Whether the node's reads count as client demand, as a Modbus client's do (docs/guide/freshness.md): true
    keeps every published tag demanded, so it is read at its class period (fast_interval, slow_interval) at the
    cost of the line's priority for what SCADA reads; false (the default): the node publishes what the schedule
    reads, tags nobody else reads at least every background_interval."""
    status_interval: float = Field(5.0, gt=0, le=3600)
    """Seconds between publishing the status block's metrics (when they changed)."""
    ndeath_on_stop: Literal[True, False] = True
    """Publish the NDEATH before a clean stop (false: the broker publishes the will when the connection closes)."""
    store: Literal[True, False] = True
    """Store and forward: keep the value changes the node could not publish (no MQTT session) on disk, in SQLite
    beside state_file (<state_file stem>-store.sqlite), and send them after the births of the next session as DDATA
    marked is_historical with their original timestamps (docs/guide/sparkplug.md#store-and-forward)."""
    store_max_mb: float = Field(100.0, gt=0, le=1_000_000)
    """The most the store may hold, MB (the SQLite pages in use); past it the oldest changes are dropped, counted and
    logged."""
    store_max_age: float = Field(86400.0, gt=0)
    """Seconds a stored change is kept; older ones are dropped, counted and logged (default 24 h)."""
    replay_rate: float = Field(50.0, gt=0, le=10_000)
    """Historical DDATA messages per second, at most, while the store is replayed (each up to 64 changes of one
    device); live DDATA always goes first."""

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
