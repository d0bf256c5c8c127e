"""Whether a link's controller answers: its counters and the one up/down rule of every driver.

:class:`LinkHealth` is the base of :class:`~gateway.line_driver.LineDriver` (one controller per
port) and of each station's handle on a shared half-duplex line
(``gateway.kinds.df1.half.driver.Df1Station``), so every link goes up and down by the same
rule and logs each change once.
"""

from __future__ import annotations

import asyncio
import logging
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final, NamedTuple, Self

from gateway.frozen import frozen

__all__ = ["DEFAULT_DOWN_AFTER", "DownAfter", "LineCounters", "LineQuality", "LinkHealth"]

log = logging.getLogger("gateway.link")


@dataclass
class LineCounters:
    """Counters of one link.  ``retries`` is the sum of the protocol's retry kinds."""

    transactions: int = 0
    errors: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    #: the protocol's retries, by the names its kind gives them (the ``kind`` label of the retries metric)
    retries_by_kind: dict[str, int] = field(default_factory=dict)
    refusals: int = 0
    faults: int = 0
    reconnects: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0

    @property
    def retries(self) -> int:
        return sum(self.retries_by_kind.values())


@frozen
class LineQuality:
    """How the line is, by the numbers of its protocol (:meth:`LinkHealth.line_quality`), counted
    since the link was created; None: the protocol has no such thing, or its driver does not count it."""

    #: frames or replies received with a bad check (BCC, CRC, checksum)
    check_errors: int
    #: answers that did not come in time, as the protocol counts them (each try, or each request)
    timeouts: int
    #: our frames the peer refused as damaged (a DLE NAK)
    naks: int | None = None
    #: frames sent again because the first did not arrive whole (by either side, as the protocol counts them)
    retransmits: int | None = None
    #: message numbering resynchronised with the controller
    resyncs: int | None = None


class DownAfter(NamedTuple):
    """A link's ``down_after_failures`` and ``down_after_seconds`` (:class:`LinkHealth`)."""

    failures: int = 3
    seconds: float = 5.0


#: The defaults of every driver and of the ``[[link]]`` keys.
DEFAULT_DOWN_AFTER: Final = DownAfter()


class LinkHealth(ABC):
    """Whether a link's controller answers: the one up/down rule of every driver.

    A :class:`~gateway.line_driver.LineDriver` is one (one controller per port), and so is each
    station's handle on a shared half-duplex line (``gateway.kinds.df1.half.driver.Df1Station``).
    One failed transaction does not make a link down (Kepware's auto-demotion is the model): it goes
    down after ``down_after_failures`` failed transactions in a row or ``down_after_seconds`` without
    a valid reply while transactions fail, whichever comes first, and up again at the first answer.
    The very first verdict is taken at once (a link that never answered is down at its first
    failure), and a lost port is a verdict of its own (the driver calls :meth:`_report`).  Each
    change is counted, logged once ("up" / "down") and told to the listeners.
    """

    def __init__(self, name: str, down_after: DownAfter = DEFAULT_DOWN_AFTER) -> None:
        self.name = name
        self.counters = LineCounters()
        self.last_error = ""
        #: None until the controller first answers or the link first fails; then up (True) or down.
        self._state: bool | None = None
        self._listeners: list[Callable[[Self], None]] = []
        #: the link is reported down after this many failed transactions in a row, or this long
        #: without a valid reply while transactions fail (whichever comes first), not on one failure
        self.down_after_failures = max(1, down_after.failures)
        self.down_after_seconds = down_after.seconds
        self._failures_in_row = 0
        self._last_ok: float | None = None
        #: link state changes (each counted and logged once)
        self.state_changes = 0
        #: loop time of the last change of ``available`` (None before the first verdict)
        self.state_since: float | None = None

    @property
    @abstractmethod
    def connected(self) -> bool:
        """The port is open."""

    @property
    def available(self) -> bool:
        """The port is open and the controller answered (by the rule of the class docstring)."""
        return self.connected and self._state is True

    @abstractmethod
    def where(self) -> str:
        """Where the controller is, for the "up" log line (the port, a station on a line)."""

    def line_quality(self) -> LineQuality:
        """The line's check errors, timeouts, NAKs, retransmissions and resyncs (:class:`LineQuality`).

        This one knows only the counters every link has; a kind's driver gives the rest."""
        return LineQuality(check_errors=self.counters.crc_errors, timeouts=self.counters.timeouts)

    def add_listener(self, callback: Callable[[Self], None]) -> None:
        """``callback(link)`` runs whenever the link goes up or down (``available`` changes)."""
        self._listeners.append(callback)

    def _report(self: Self, up: bool, reason: str = "") -> None:
        """Record the link state; log and tell the listeners only when it changes."""
        if reason:
            self.last_error = reason
        if self._state is up:
            return
        self._state = up
        self.state_changes += 1
        self.state_since = asyncio.get_running_loop().time()
        if up:
            self.last_error = ""
            log.info("link %s: up (%s)", self.name, self.where())
        else:
            log.warning("link %s: down: %s", self.name, self.last_error or "unknown reason")
        for callback in self._listeners:
            callback(self)

    def note_result(self, ok: bool, error: str = "") -> None:
        """Count one transaction, answered (``ok``) or failed, and judge the link by it."""
        if ok:
            self.counters.transactions += 1
        else:
            self.counters.errors += 1
        self.judge(ok, error)

    def judge(self, ok: bool, error: str = "") -> None:
        """The rule of the class docstring, for one answer (``ok``) or one failure (``error``).

        :meth:`note_result` calls it for every transaction; a driver calls it alone for what is
        not a transaction of its own but still says whether the controller answers.
        """
        now = asyncio.get_running_loop().time()
        if ok:
            self._failures_in_row = 0
            self._last_ok = now
            if self._state is not True:
                self._report(True)
            return
        self._failures_in_row += 1
        if error:
            self.last_error = error
        silent = self._last_ok is not None and now - self._last_ok >= self.down_after_seconds
        if self._state is None or silent or self._failures_in_row >= self.down_after_failures:
            self._report(False, error)
