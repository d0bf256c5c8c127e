"""Store and forward, the sans-I/O part: what the edge node could not publish, and how it is sent later.

No clock, no disk: the caller (``gateway.sparkplug.driver``) passes ``now`` (UTC ms), keeps the
:class:`Change` records in the store (``gateway.sparkplug.store``) and hands them back for replay.

* A :class:`Change` is one metric's value change (device and metric by name, so that a store written
  before a restart is read by the metric's name, whatever alias the new process gives it), with its
  original timestamp.
* :class:`Window`: the changes published as live DDATA in the last ``span`` ms (2 x keepalive + 2 s:
  ``gateway.sparkplug.driver.window_ms``).
  DDATA is QoS 0 (§6.4.22 tck-id-payloads-ddata-qos): a message handed to the MQTT client before the
  loss of the connection was noticed may be gone, and only the keepalive notices a silent loss (the
  client finds a silent loss up to 2 x keepalive after the last packet it received).  When the connection is
  found lost, what the window holds is stored too: replayed, it may reach a host twice, marked
  historical the second time, with its original timestamp.
* Replay (:func:`historical_metrics`): stored changes go out as DDATA whose metrics carry
  ``is_historical`` = true (§6.4.6 "is_historical": "should not be considered a real time/current
  value") and their original timestamps, oldest first.  The chronological-order rule of DDATA
  (§5.16 tck-id-operational-behavior-data-publish-dbirth-order) is for metrics with
  is_historical = false; a historical DDATA is still a DDATA of the session: ``seq`` and ``bdSeq``
  follow the session's rules (§6.4.22 tck-id-payloads-ddata-seq-inc).
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Iterable

from gateway.frozen import frozen
from gateway.sparkplug.payload import Value

__all__ = ["Change", "Window", "sample_text", "sample_value"]


@frozen
class Change:
    """One metric's change: ``value`` None is a null with ``quality`` and ``reason`` (as a ``Sample``)."""

    device: str
    metric: str
    timestamp: int
    value: Value | None
    quality: int
    reason: str = ""


def sample_text(change: Change) -> str:
    """The value, quality and reason of ``change`` as the store keeps them (JSON; NaN and infinities kept)."""
    value: object = change.value
    if isinstance(value, bytes):
        value = {"bytes": value.hex()}
    elif isinstance(value, float) and not math.isfinite(value):
        value = {"float": repr(value)}
    return json.dumps([value, change.quality, change.reason], separators=(",", ":"))


def sample_value(text: str) -> tuple[Value | None, int, str]:
    """The inverse of :func:`sample_text`: (value, quality, reason)."""
    value, quality, reason = json.loads(text)
    if isinstance(value, dict):
        value = bytes.fromhex(value["bytes"]) if "bytes" in value else float(value["float"])
    return value, int(quality), str(reason)


class Window:
    """The changes published in the last ``span`` ms (oldest first)."""

    def __init__(self, span: int) -> None:
        self.span = span
        self._items: deque[tuple[int, Change]] = deque()

    def __len__(self) -> int:
        return len(self._items)

    def add(self, now: int, changes: Iterable[Change]) -> None:
        """``changes`` were handed to the MQTT client at ``now``; forget what is older than the span."""
        items = self._items
        for change in changes:
            items.append((now, change))
        limit = now - self.span
        while items and items[0][0] < limit:
            items.popleft()

    def lost(self, now: int) -> list[Change]:
        """The connection is found lost at ``now``: what was published in the span before it (then empty)."""
        limit = now - self.span
        out = [change for at, change in self._items if at >= limit]
        self._items.clear()
        return out

    def clear(self) -> None:
        """A clean end of the session (the DISCONNECT went out after them): nothing in doubt."""
        self._items.clear()
