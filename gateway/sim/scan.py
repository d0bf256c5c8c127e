"""A controller's scan, for the simulators: answers come at the end of the scan, not at once.

A controller runs its program in scans, one after another, and services its communication
channel at the end of each scan: a command that arrives during a scan is answered when that scan
ends (SLC 500 and PLC-5 processors; the Micro800 manual's DF1 ACK timeout adds the "average slave
program scan time (20 ms)" for it, 2080-UM002N appendix G).  So an answer comes anywhere from at
once to one scan after its command.  The SLC 100/150 manual bounds it: "Normally the SLC will
respond within 0.3 seconds to any transmission" (*Format of Transmission*).

This module is the one place for that model, for every simulated controller:

* :data:`ANSWER_BOUND` - the manual's 0.3 s: no scan may be longer (answers after it are the
  ``late_replies`` reading of the SLC 100/150 simulator, not a scan time);
* :data:`REALISTIC_SCAN` - the scan the availability tests and benchmarks give every simulated
  controller unless they say otherwise;
* :class:`ScanTime` - a scan of fixed length (``scan=0.05``), or one whose length varies from scan
  to scan within a range (``scan=0.02-0.06``: a program with branches, I/O and interrupts); the
  ``scan`` option of every ``sim://`` model and of ``slc-gateway simulate --option scan=...``;
* :class:`ScanClock` - the scans of one controller: ``answer_at(now)`` is the end of the scan in
  progress at ``now``.  Sans-I/O: the caller passes ``now`` and the seeded generator, so tests are
  deterministic with a fake clock.

A fixed scan against a host that sends its next command as soon as it has the answer locks to the
host's rhythm (every answer then takes about the same time), as a real controller can; a scan whose
length varies spreads the answers over ``(0, longest]``.

No scan (the default of every simulator): answers at once, as the tests of the wire's rules want.
"""

from __future__ import annotations

import math
import random
from typing import Final

from gateway.frozen import frozen

__all__ = ["ANSWER_BOUND", "REALISTIC_SCAN", "SCAN_OPTION", "ScanClock", "ScanTime", "parse_scan", "scan_clock"]

#: "Normally the SLC will respond within 0.3 seconds to any transmission" (SLC 100/150 manual).
ANSWER_BOUND: Final = 0.3
#: the ``sim://`` option (and ``simulate --option``) that gives a controller its scan
SCAN_OPTION: Final = "scan"
#: after this many scans without a command the clock starts a fresh scan at a random phase
_IDLE_SCANS: Final = 1000


@frozen
class ScanTime:
    """A controller's scan: each scan lasts ``shortest`` to ``longest`` seconds (equal: a fixed scan)."""

    shortest: float
    longest: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.shortest) and math.isfinite(self.longest)):
            raise ValueError(f"scan {self}: seconds, not {self.shortest} / {self.longest}")
        if not 0 < self.shortest <= self.longest:
            raise ValueError(f"scan {self.text()}: give 0 < shortest <= longest seconds (e.g. scan=0.02-0.06)")
        if self.longest > ANSWER_BOUND:
            raise ValueError(
                f"scan {self.text()}: a scan longer than {ANSWER_BOUND} s makes answers later than the manual's "
                f"\"normally within {ANSWER_BOUND} seconds\"; give at most {ANSWER_BOUND} (late answers are the "
                "SLC 100/150 simulator's late_replies variant)")

    @classmethod
    def parse(cls, text: str) -> ScanTime:
        """``"0.05"`` (a fixed scan) or ``"0.02-0.06"`` (seconds); ValueError with a reason."""
        first, sep, second = text.strip().partition("-")
        try:
            shortest = float(first)
            longest = float(second) if sep else shortest
        except ValueError:
            raise ValueError(f"scan={text!r}: give seconds, S or MIN-MAX (e.g. scan=0.05 or scan=0.02-0.06)") from None
        return cls(shortest, longest)

    def text(self) -> str:
        """The option's text (``parse(text())`` gives the same scan)."""
        if self.shortest == self.longest:
            return f"{self.shortest:g}"
        return f"{self.shortest:g}-{self.longest:g}"

    def draw(self, rng: random.Random) -> float:
        """The length of one scan."""
        if self.shortest == self.longest:
            return self.shortest
        return rng.uniform(self.shortest, self.longest)


#: the scan of a realistic program: 20-60 ms (a small SLC program scans in a few ms, one with I/O,
#: communication and math in tens of ms; the Micro800 manual's example takes 20 ms on average).
REALISTIC_SCAN: Final = ScanTime(0.02, 0.06)


class ScanClock:
    """The scans of one controller (module doc).  ``answer_at(now)``: when a command that arrived
    at ``now`` is answered, the end of the scan in progress.  ``now`` never goes back from one call
    to the next (the scans already run are not kept).  Not thread-safe."""

    def __init__(self, scan: ScanTime, rng: random.Random) -> None:
        self.scan = scan
        self._rng = rng
        self._end: float | None = None  #: the end of the scan in progress (None: not started)

    def answer_at(self, now: float) -> float:
        """The end of the scan in progress at ``now`` (later than ``now``, at most a scan later)."""
        end = self._end
        if end is None or now - end > _IDLE_SCANS * self.scan.longest:
            # the first command (or one after a long silence) finds a scan at a random point of its run
            length = self.scan.draw(self._rng)
            end = now + self._rng.uniform(0.0, length)
            if end <= now:
                end = now + length
        while end <= now:
            end += self.scan.draw(self._rng)
        self._end = end
        return end

    def delay(self, now: float) -> float:
        """Seconds from ``now`` to the end of the scan in progress."""
        return self.answer_at(now) - now


def parse_scan(text: str | None) -> ScanTime | None:
    """A ``scan=`` option's text: None when it is not given or empty (answers at once)."""
    if text is None or not text.strip():
        return None
    return ScanTime.parse(text)


def scan_clock(scan: ScanTime | None, seed: int, *, salt: str = "") -> ScanClock | None:
    """The clock of a controller with ``scan`` (None: answers at once); its generator is seeded from
    ``seed`` and ``salt`` (one per station of a line), apart from the controller's fault generator."""
    if scan is None:
        return None
    return ScanClock(scan, random.Random(f"scan:{seed}:{salt}"))
