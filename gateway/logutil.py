"""Bounded logging for what a hostile network can repeat at will, and URL redaction.

:class:`RepeatLog` collapses repeated warnings per *cause*: the first occurrence of a cause in an
interval is logged at once (saying that repeats are summarised); the ones after it in the same
interval are counted, with the addresses they came from (at most :data:`MAX_ADDRESSES` named,
the rest counted), and one summary line per cause is logged when the interval ends::

    WARNING modbus: refused connection from 10.0.0.9:40112: over max_connections_per_address (4)
            (repeats are summarised every 60 s)
    WARNING modbus: connection refused, over max_connections_per_address (4): 118 more in the
            last 60 s, from 10.0.0.9 (118)

So a peer that repeats an offence as fast as it can costs at most two log lines per cause per
interval. Nothing runs while nothing is suppressed: the summary timer is armed by the first
suppressed occurrence (``loop.call_later``) and logs nothing more.

:func:`redact_url` removes ``user:password@`` from URLs (serial device servers take credentials in
``socket://`` and ``rfc2217://`` URLs) before they reach a log line or ``check-config`` output.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

__all__ = ["MAX_ADDRESSES", "RepeatLog", "public_error", "redact_url"]

MAX_ADDRESSES: Final = 8
"""Addresses named in one summary line; more are counted as "and N other addresses"."""

_USERINFO: Final = re.compile(r"(?<=://)[^/@\s?#]*@")


def redact_url(text: str) -> str:
    """``text`` with any ``user:password@`` after a ``scheme://`` replaced by ``***@``."""
    return _USERINFO.sub("***@", text)


#: The longest error text a page or a health answer shows.
_MAX_ERROR_TEXT: Final = 300


def public_error(text: str) -> str:
    """An error for a page or a health answer: credentials in URLs redacted, length capped."""
    text = redact_url(text)
    return text if len(text) <= _MAX_ERROR_TEXT else text[: _MAX_ERROR_TEXT - 3] + "..."


@dataclass
class _Pending:
    level: int
    count: int = 0
    addresses: Counter[str] = field(default_factory=Counter)


class RepeatLog:
    """Log a warning once per cause and interval, then one counted summary per cause.

    ``interval``: seconds; ``clock``: monotonic seconds (the event loop's clock by default when a
    loop runs, for tests a fake one); ``schedule``: how to run the summary ``delay`` seconds
    later (default ``loop.call_later`` of the running loop; without a running loop the summary
    is logged by the next :meth:`log` or :meth:`flush` after the interval).
    """

    def __init__(
        self,
        logger: logging.Logger,
        interval: float = 60.0,
        *,
        clock: Callable[[], float] | None = None,
        schedule: Callable[[float, Callable[[], None]], object] | None = None,
    ) -> None:
        if interval <= 0:
            raise ValueError(f"interval must be positive, not {interval}")
        self.logger = logger
        self.interval = interval
        self._clock = clock
        self._schedule = schedule
        self._window_end: dict[str, float] = {}
        self._pending: dict[str, _Pending] = {}
        self._timer_armed = False
        self.suppressed = 0
        """Occurrences not logged on their own line since start (all causes)."""

    def _now(self) -> float:
        if self._clock is not None:
            return self._clock()
        try:
            return asyncio.get_running_loop().time()
        except RuntimeError:
            import time

            return time.monotonic()

    def log(self, level: int, cause: str, address: str | None, message: str, *args: object) -> bool:
        """Log ``message % args`` unless ``cause`` was logged less than an interval ago.

        Returns True if the line was logged, False if it was counted for the summary.
        ``address`` (a peer address without port, or None) is named in the summary.
        """
        now = self._now()
        self._flush_due(now)
        end = self._window_end.get(cause)
        if end is None or now >= end:
            self._window_end[cause] = now + self.interval
            if self.logger.isEnabledFor(level):
                self.logger.log(
                    level, message + " (repeats are summarised every %g s)", *args, self.interval
                )
            return True
        pending = self._pending.get(cause)
        if pending is None:
            pending = self._pending[cause] = _Pending(level)
        pending.count += 1
        pending.level = max(pending.level, level)
        if address is not None:
            pending.addresses[address] += 1
        self.suppressed += 1
        self._arm(end - now)
        return False

    def flush(self) -> None:
        """Log the summaries of the intervals that have ended."""
        self._flush_due(self._now())

    def flush_all(self) -> None:
        """Log every summary now (on close)."""
        self._flush_due(float("inf"))

    def _arm(self, delay: float) -> None:
        if self._timer_armed:
            return
        schedule = self._schedule
        if schedule is None:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                return
            schedule = loop.call_later
        self._timer_armed = True
        schedule(max(delay, 0.0) + 0.001, self._on_timer)

    def _on_timer(self) -> None:
        self._timer_armed = False
        self.flush()
        if self._pending:
            now = self._now()
            self._arm(min(self._window_end[cause] for cause in self._pending) - now)

    def _flush_due(self, now: float) -> None:
        if not self._pending:
            return
        for cause in [c for c in self._pending if self._window_end.get(c, 0.0) <= now]:
            pending = self._pending.pop(cause)
            # The summary closes this window; the next occurrence opens a new one and is logged.
            self._window_end.pop(cause, None)
            self.logger.log(
                pending.level,
                "%s: %d more in the last %g s%s",
                cause,
                pending.count,
                self.interval,
                _from(pending.addresses),
            )


def _from(addresses: Counter[str]) -> str:
    if not addresses:
        return ""
    named = addresses.most_common(MAX_ADDRESSES)
    text = ", ".join(f"{address} ({count})" for address, count in named)
    others = len(addresses) - len(named)
    if others:
        text += f" and {others} other addresses ({sum(addresses.values()) - sum(c for _, c in named)})"
    return ", from " + text
