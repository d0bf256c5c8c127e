"""The status page and its JSON API, a room of the ``[metrics]`` listener (``gateway.http``).

Read-only: nothing here writes to a controller; writes stay on Modbus, where the access rules live.

* ``GET /`` (and ``/status.css``, ``/status.js``): the page, plain files of this package
  (``gateway/web/``), no build step and nothing fetched from elsewhere; it asks the API every second.
* ``GET /api/status``: the gateway and one row per unit (a link, or a station of a half-duplex
  line): name, kind, port (credentials redacted), unit id, whether it is polled, up / stale / down
  and since when (the one verdict: ``gateway.freshness``, :meth:`Unit.verdict`), data age (the oldest
  fast-class value), transactions, errors, retries, the line's quality (``line``: check errors,
  NAKs, timeouts, retransmissions, resyncs; null where the protocol has no such thing:
  :class:`gateway.link_health.LineQuality`), the last error and its time, and the line's budget
  (``schedule``: :func:`schedule_document`).
  ``config``: the config file served (the first 12 hex digits of its SHA-256, when it was loaded,
  reloads done and failed, the last failure, what changed but takes a restart: ``gateway.reload``).
* ``GET /api/units/{unit}/{table}?start=&count=``: ``count`` (1..:data:`MAX_COUNT`) values of
  ``table`` (holding, input, coil, discrete) from ``start``, each with its age and state.  The
  state is the Modbus answer a read of that one address gets now (the unit's own rule, the one
  that answers 0x0B): ``fresh``; ``stale`` (0x0B: the value shown is the last one read);
  ``refused`` (0x04, the controller refuses the block); ``unmapped`` (0x02).

Errors are JSON ``{"error": "..."}`` with 400 (a bad query) or 404 (no such unit or table).
Times are Unix seconds (``time.time()``); ages are seconds, ``null`` when never read.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import re
import time
from collections.abc import Mapping, Sequence
from importlib import resources
from typing import TYPE_CHECKING, Any, Final
from urllib.parse import parse_qs

from gateway import __version__
from gateway.errors import ModbusExceptionReply
from gateway.freshness import Source
from gateway.http import JSON_CONTENT_TYPE, Response, Routes
from gateway.kinds import link_kind
from gateway.logutil import public_error
from gateway.modbus.mapping import Table
from gateway.opcua.report import opcua_status
from gateway.sparkplug.report import status as sparkplug_status
from gateway.tags import Tag, link_tags
from gateway.transport import describe_url
from gateway.view import GatewayView

if TYPE_CHECKING:
    from gateway.config.link import LinkBase
    from gateway.reload import ConfigStatus
    from gateway.unit import Unit

__all__ = [
    "LINE_QUALITY",
    "MAX_COUNT",
    "StatusPage",
    "line_quality",
    "schedule_document",
]

#: The most values one register view request returns (a Modbus read of registers holds 125).
MAX_COUNT: Final = 125
_DEFAULT_COUNT: Final = 16
_UNIT_PATH: Final = re.compile(r"/api/units/([^/]{1,16})/([^/]{1,16})")
_STATES: Final = {
    ModbusExceptionReply.GATEWAY_TARGET_FAILED: "stale",
    ModbusExceptionReply.SERVER_DEVICE_FAILURE: "refused",
    ModbusExceptionReply.ILLEGAL_DATA_ADDRESS: "unmapped",
}
#: the page's files: path -> (file in gateway/web, content type)
_FILES: Final = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/status.css": ("status.css", "text/css; charset=utf-8"),
    "/status.js": ("status.js", "text/javascript; charset=utf-8"),
}
#: the page loads nothing but its own files and the API
_PAGE_HEADERS: Final = [
    ("Content-Security-Policy", "default-src 'none'; script-src 'self'; style-src 'self'; "
                                "connect-src 'self'; img-src 'self'; frame-ancestors 'none'; base-uri 'none'"),
    ("X-Content-Type-Options", "nosniff"),
    ("Referrer-Policy", "no-referrer"),
]

#: the line-quality numbers of a row (``gateway.link_health.LineQuality``), in the page's column order
LINE_QUALITY: Final = ("check_errors", "naks", "timeouts", "retransmits", "resyncs")



def line_quality(unit: Unit[Any, Any]) -> dict[str, int | None]:
    """The unit's line quality by :data:`LINE_QUALITY` (None: not a thing of its protocol)."""
    quality = unit.driver.line_quality()
    return {key: getattr(quality, key) for key in LINE_QUALITY}


def schedule_document(unit: Unit[Any, Any], now: float) -> dict[str, object] | None:
    """The line's budget as the schedule achieves it (``/api/status``: a link's ``schedule``); None
    for a unit that is not polled."""
    schedule, poller = unit.schedule, unit.poller
    if schedule is None or poller is None:
        return None
    budget = schedule.budget(now)

    def seconds(values: Mapping[str, float | None]) -> dict[str, float | None]:
        return {key: None if value is None else _finite(value) for key, value in values.items() if key != "all"}

    return {
        "blocks": budget.blocks,
        "demanded": budget.demanded,
        "transaction_time": None if budget.transaction_time is None else _finite(budget.transaction_time),
        "line_use": None if budget.line_use is None else round(budget.line_use, 3),
        "refresh": seconds(budget.refresh),
        "age_bound": seconds(budget.age_bound),
        "stale_limit": _finite(unit.freshness.stale_limit()),
        "late_reads": schedule.late_reads,
        "read_waits": poller.read_waits,
        "behind": poller.behind,
    }


class _BadRequest(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def _finite(seconds: float) -> float | None:
    return round(seconds, 3) if math.isfinite(seconds) else None


class StatusPage:
    """Answers ``/``, its files and ``/api/...`` for the metrics server (module docstring).

    ``links``: the ``[[link]]`` tables, in the order of ``gateway.units``, for each row's kind and
    the register view's tag names (without them the page shows neither).
    """

    def __init__(self, gateway: GatewayView, links: Sequence[LinkBase] = (),
                 config: ConfigStatus | None = None) -> None:
        self.gateway = gateway
        self.config = config
        self._files = {path: resources.files("gateway").joinpath("web", name).read_bytes()
                       for path, (name, _) in _FILES.items()}
        self.set_links(links)

    def set_links(self, links: Sequence[LinkBase]) -> None:
        """The ``[[link]]`` tables of the units (at start, and after a config reload)."""
        self._links = {link.name: link for link in links}
        self._tags: dict[str, dict[tuple[Table, int], Tag]] = {}

    def add_routes(self, routes: Routes) -> None:
        """Its paths in the HTTP listener's table (``gateway.http``): the page's files and the API."""
        for path in (*_FILES, "/api/status"):
            routes.add(path, self.route)
        routes.add(_UNIT_PATH, self.route, label="/api/units/{unit}/{table}")

    def route(self, path: str, query: str) -> Response:
        """The response to a GET of ``path`` (one of those :meth:`add_routes` gave the listener)."""
        if path in _FILES:
            return 200, _FILES[path][1], self._files[path], list(_PAGE_HEADERS)
        loop_now, wall_now = asyncio.get_running_loop().time(), time.time()
        try:
            if path == "/api/status":
                document = self.status(loop_now, wall_now)
            else:
                match = _UNIT_PATH.fullmatch(path)
                assert match is not None
                document = self.registers(match[1], match[2], query, loop_now, wall_now)
            status = 200
        except _BadRequest as error:
            status, document = error.status, {"error": str(error)}
        body = (json.dumps(document, separators=(",", ":"), allow_nan=False) + "\n").encode()
        return status, JSON_CONTENT_TYPE, body, [("X-Content-Type-Options", "nosniff")]

    # --- /api/status ----------------------------------------------------------------------

    def _kind(self, name: str) -> tuple[str, str]:
        """(protocol, controllers) of a link, from the kind registry."""
        link = self._links.get(name)
        if link is None:
            return "", ""
        kind = link_kind(link.protocol)
        return kind.name, kind.controllers

    def status(self, now: float, wall: float) -> dict[str, object]:
        """The document of ``/api/status`` at loop time ``now`` (Unix time ``wall``)."""

        def at(loop_time: float | None) -> float | None:
            return None if loop_time is None else round(wall - (now - loop_time), 3)

        rows: list[dict[str, object]] = []
        up_count = 0
        for unit in self.gateway.units:
            driver = unit.driver
            counters = driver.counters
            verdict = unit.verdict(now)
            up_count += verdict.fresh
            kind, controllers = self._kind(unit.name)
            error = unit.last_error
            rows.append({
                "name": unit.name,
                "kind": kind,
                "controllers": controllers,
                "port": describe_url(driver.url),
                "unit": unit.unit_id,
                "polled": unit.poller is not None,
                "state": verdict.state.value,
                "since": at(verdict.since),
                "data_age": _finite(verdict.age),
                "stale_after": _finite(unit.stale_after),  # null: never stale
                "transactions": counters.transactions,
                "errors": counters.errors,
                "retries": counters.retries,
                "line": line_quality(unit),
                "last_error": public_error(str(error)) if error is not None else public_error(driver.last_error),
                "last_error_at": at(unit.last_error_at) if error is not None else None,
                "schedule": schedule_document(unit, now),
            })
        servers = [{
            "name": server.name,
            "connections": server.connection_count,
            "requests": sum(server.counters.requests.values()),
            "exceptions": sum(server.counters.exceptions.values()),
        } for server in self.gateway.servers]
        document: dict[str, object] = {"version": __version__, "time": round(wall, 3), "links": rows,
                                       "up": up_count, "servers": servers,
                                       "sparkplug": sparkplug_status(self.gateway.sparkplug),
                                       "opcua": opcua_status(self.gateway.opcua)}
        if self.config is not None:
            document["config"] = self.config.document()
        return document

    # --- /api/units/{unit}/{table} --------------------------------------------------------

    def _unit(self, text: str) -> Unit[Any, Any]:
        units = {unit.unit_id: unit for unit in self.gateway.units}
        known = ", ".join(str(u) for u in sorted(units))
        if not text.isdigit() or int(text) not in units:
            raise _BadRequest(404, f"no unit {text}: the units are {known}")
        return units[int(text)]

    def _tags_of(self, unit: Unit[Any, Any]) -> Mapping[tuple[Table, int], Tag]:
        """The tags of a unit's link by (table, first address), built at the first view of the unit."""
        tags = self._tags.get(unit.name)
        if tags is None:
            link = self._links.get(unit.name)
            if link is None:
                tags = {}
            else:
                tags = {(tag.table, tag.address): tag for tag in link_tags(link)}
            self._tags[unit.name] = tags
        return tags

    def registers(self, unit_text: str, table_text: str, query: str, now: float, wall: float) -> dict[str, object]:
        """The document of ``/api/units/{unit}/{table}`` (module docstring)."""
        unit = self._unit(unit_text)
        try:
            table = Table(table_text)
        except ValueError:
            raise _BadRequest(404, f"no table {table_text!r}: the tables are holding, input, coil, discrete") from None
        start = _query_int(query, "start", 0, 0, 65535)
        count = _query_int(query, "count", _DEFAULT_COUNT, 1, MAX_COUNT)
        if start + count > 65536:
            raise _BadRequest(400, f"start {start} + count {count} runs past address 65535")
        registers = table in (Table.HOLDING, Table.INPUT)
        tags = self._tags_of(unit)
        values = []
        for address, (value, state, block) in enumerate(_read(unit, table, start, count, now), start):
            age = None if block is None else _finite(now - unit.cache.stamps[block])
            entry: dict[str, object] = {"address": address, "value": value, "state": state, "age": age}
            tag = tags.get((table, address))
            if tag is not None:
                entry["tag"] = tag.name[len(tag.link) + 1 :]
                entry["type"] = tag.type
                if tag.word_order:
                    entry["word_order"] = tag.word_order
            values.append(entry)
        return {"unit": unit.unit_id, "link": unit.name, "table": table.value, "start": start, "count": count,
                "registers": registers, "polled": unit.poller is not None, "stale_after": _finite(unit.stale_after),
                "time": round(wall, 3), "values": values}


def _query_int(query: str, key: str, default: int, low: int, high: int) -> int:
    try:
        fields = parse_qs(query, keep_blank_values=True, strict_parsing=bool(query), max_num_fields=8)
    except ValueError:
        raise _BadRequest(400, f"malformed query string {query[:80]!r}") from None
    texts = fields.get(key)
    if not texts:
        return default
    text = texts[-1].strip()
    if not text.isdigit() or not low <= int(text) <= high:
        raise _BadRequest(400, f"{key} must be a whole number {low}-{high}, not {text[:20]!r}")
    return int(text)


def _read(unit: Unit[Any, Any], table: Table, start: int, count: int,
          now: float) -> list[tuple[int | None, str, int | None]]:
    """Per address: (value, state, block).  The view is a client's read: its range counts as demand,
    as a Modbus read of it would (``Source.SERVE``).  The state is the truth whatever the link's
    ``offline`` policy serves: what a peek of that address answers now (``Source.PEEK``, the one
    verdict of ``gateway.freshness``); a stale value is the one last read (``Images.peek``)."""
    registers = table in (Table.HOLDING, Table.INPUT)
    images = unit.images
    out: list[tuple[int | None, str, int | None]] = []
    with contextlib.suppress(ModbusExceptionReply):
        (unit.read_register_bytes if registers else unit.read_bit_bytes)(table, start, count, Source.SERVE)
    try:
        if registers:
            raw = unit.read_register_bytes(table, start, count, Source.PEEK)
            fresh = [int.from_bytes(raw[2 * k : 2 * k + 2], "big") for k in range(count)]
        else:
            bits = int.from_bytes(unit.read_bit_bytes(table, start, count, Source.PEEK), "little")
            fresh = [bits >> k & 1 for k in range(count)]
    except ModbusExceptionReply:
        fresh = []  # something in the range is not served: ask address by address
    for k, address in enumerate(range(start, start + count)):
        seen = images.peek(table, address)
        block = None if seen is None else seen[1]
        if fresh:
            out.append((fresh[k], "fresh", block))
            continue
        try:
            if registers:
                value: int | None = int.from_bytes(unit.read_register_bytes(table, address, 1, Source.PEEK), "big")
            else:
                value = unit.read_bit_bytes(table, address, 1, Source.PEEK)[0] & 1
            out.append((value, "fresh", block))
        except ModbusExceptionReply as exc:
            state = _STATES.get(exc.code, "error")
            never = block is None or not math.isfinite(unit.cache.stamps[block])
            value = None if seen is None or never else seen[0]
            out.append((value, state, block))
    return out
