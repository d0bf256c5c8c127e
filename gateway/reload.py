"""Reloading the config file of a running gateway (SIGHUP): what changed, and what it takes.

A reload reads the file again (:class:`ConfigSource`, with the command line's overrides applied
as at start) and compares it with the config the gateway runs, section by section:

* ``[[link]]``, *by line*: the links that use one port are one line (``port_key``: the stations of
  a half-duplex line share its runner).  A line whose links are all equal, in the same order, keeps running: its
  units, their images and write queues, and its port are untouched.  Every other line of the old
  file stops and every other line of the new one starts (:func:`line_changes`).
* The keys of :data:`LIVE_KEYS`, which a running listener takes for its next connections (the
  ``allow`` lists, connection limits, timeouts, TLS material and roles), and ``[logging]``, apply at
  once.
* Anything else that changed (a listener's address, a listener added or removed, a section this
  module does not know) needs a restart: :func:`restart_needed` names it, and the gateway logs it.

A file that does not load changes nothing.  :class:`ConfigStatus` is what ``/metrics`` and
``/api/status`` show of it: the SHA-256 of the file served, when it was loaded, the reloads.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from pydantic import BaseModel

from gateway.config import GatewayConfig, LinkBase, load_config_file
from gateway.config._common import port_key, show
from gateway.frozen import frozen

__all__ = [
    "LIVE_KEYS",
    "ConfigSource",
    "ConfigStatus",
    "LineChanges",
    "LoadedConfig",
    "line_changes",
    "lines_of",
    "restart_needed",
]

#: Per section, the keys a running gateway applies at once; a change to any other key of the
#: section, to a section not listed (a section added later included), or a section added or
#: removed, needs a restart.  ``modbus.tls`` is compared on its own.
LIVE_KEYS: Final[Mapping[str, frozenset[str]]] = {
    "modbus": frozenset({"max_connections", "max_connections_per_address", "idle_timeout", "frame_timeout",
                         "allow", "loopback_reads"}),
    "modbus.tls": frozenset({"cert", "key", "client_ca", "handshake_timeout", "max_handshakes", "roles",
                             "default_rights"}),
    "metrics": frozenset({"allow", "max_connections"}),
    "logging": frozenset({"level", "repeat_interval", "trace_max_bytes", "trace_backups"}),
}

#: The digest shown of a config file: the first hex digits of its SHA-256.
SHORT_DIGEST: Final = 12


def _as_given(config: GatewayConfig) -> GatewayConfig:
    return config


@frozen
class LoadedConfig:
    """A config as loaded from its file: the SHA-256 of the file's bytes (hex), the Unix time it was read."""

    config: GatewayConfig
    sha256: str
    loaded_at: float


@frozen
class ConfigSource:
    """Where the running config comes from: its file, and what the command line changes in it
    (``run --listen`` ...), applied again at every reload."""

    path: Path
    adjust: Callable[[GatewayConfig], GatewayConfig] = _as_given

    def load(self) -> LoadedConfig:
        """Read and validate the file; :class:`~gateway.errors.ConfigError` as ``check-config`` gives it."""
        config, digest = load_config_file(self.path)
        return LoadedConfig(self.adjust(config), digest, time.time())


@dataclass(slots=True)
class ConfigStatus:
    """The config the gateway serves and its reloads (``/metrics``, ``/api/status``)."""

    #: SHA-256 (hex) of the file served; None for a config that came from no file
    sha256: str | None
    loaded_at: float
    reloads: int = 0
    reload_failures: int = 0
    #: the reason the last reload failed (None after a reload that succeeded)
    last_failure: str | None = None
    #: what changed in the file but takes a restart to apply
    restart_needed: tuple[str, ...] = ()

    @property
    def short_sha256(self) -> str | None:
        return None if self.sha256 is None else self.sha256[:SHORT_DIGEST]

    def document(self) -> dict[str, object]:
        """The ``config`` object of ``/api/status``."""
        return {
            "sha256": self.short_sha256,
            "loaded_at": round(self.loaded_at, 3),
            "reloads": self.reloads,
            "reload_failures": self.reload_failures,
            "last_failure": self.last_failure,
            "restart_needed": list(self.restart_needed),
        }


def lines_of(links: Sequence[LinkBase]) -> dict[str, tuple[LinkBase, ...]]:
    """The links by the line they use (``port_key`` of their port), lines and links in file order."""
    lines: dict[str, list[LinkBase]] = {}
    for link in links:
        lines.setdefault(port_key(link.port), []).append(link)
    return {key: tuple(line) for key, line in lines.items()}


@frozen
class LineChanges:
    """What a reload does to the lines (keys: their ports) and, for the log, to the links (names)."""

    kept: tuple[str, ...]
    #: lines of the old file that stop: gone, or any of their links changed
    stopped: tuple[str, ...]
    #: lines of the new file that start: new, or any of their links changed
    started: tuple[str, ...]
    added: tuple[str, ...]
    removed: tuple[str, ...]
    changed: tuple[str, ...]
    #: links that did not change but restart because their line does
    restarted: tuple[str, ...]

    @property
    def none(self) -> bool:
        return not (self.stopped or self.started)

    def summary(self) -> str:
        """``links: 1 added (b), 1 changed (a), 2 unchanged``."""
        parts = [f"{len(names)} {what} ({', '.join(names)})" for what, names in (
            ("added", self.added), ("changed", self.changed), ("removed", self.removed),
            ("restarted with their line", self.restarted)) if names]
        unchanged = len(self.kept)
        return "links: " + ", ".join([*parts, f"{unchanged} line{'s' * (unchanged != 1)} unchanged"])


def line_changes(old: Sequence[LinkBase], new: Sequence[LinkBase]) -> LineChanges:
    """Compare the links of two files line by line (module docstring)."""
    old_lines, new_lines = lines_of(old), lines_of(new)
    kept = tuple(port for port, links in new_lines.items() if old_lines.get(port) == links)
    old_links = {link.name: link for link in old}
    new_links = {link.name: link for link in new}
    changed = tuple(name for name, link in new_links.items() if name in old_links and old_links[name] != link)
    restarted = tuple(
        link.name for port, links in new_lines.items() if port not in kept
        for link in links if old_links.get(link.name) == link
    )
    return LineChanges(
        kept=kept,
        stopped=tuple(port for port in old_lines if port not in kept),
        started=tuple(port for port in new_lines if port not in kept),
        added=tuple(name for name in new_links if name not in old_links),
        removed=tuple(name for name in old_links if name not in new_links),
        changed=changed,
        restarted=restarted,
    )


def restart_needed(old: GatewayConfig, new: GatewayConfig) -> list[str]:
    """What changed from ``old`` to ``new`` that a running gateway cannot apply (module docstring),
    as ``[modbus] listen ("0.0.0.0:5020" -> "127.0.0.1:5021")``, one entry per key."""
    found: list[str] = []
    for name in type(new).model_fields:
        if name != "link":
            found += _changes(name, getattr(old, name, None), getattr(new, name, None))
    return found


def _changes(section: str, old: object, new: object) -> list[str]:
    if old == new:
        return []
    live = LIVE_KEYS.get(section)
    if old is None or new is None or live is None or not isinstance(new, BaseModel):
        return [f"[{section}] {'added' if old is None else 'removed' if new is None else 'changed'}"]
    found: list[str] = []
    for key in type(new).model_fields:
        before, after = getattr(old, key, None), getattr(new, key, None)
        if before == after:
            continue
        if f"{section}.{key}" in LIVE_KEYS:
            found += _changes(f"{section}.{key}", before, after)
        elif key not in live:
            found.append(f"[{section}] {key} ({show(before)} -> {show(after)})")
    return found
