"""Per link: scan the read plan, fast class continuously and slow class every few seconds.

The slow class is read whole at start and after a link loss; its periodic scans are spread
over the fast rounds of half of ``slow_interval`` (a share of it before each fast round), the
first one starting half a ``slow_interval`` after the whole read: so every slow block is read
again within one ``slow_interval`` of its last read.

Every block is one request on the driver's queue at poll priority, so a write waits at most
for the one poll transaction already on the line.  A block that fails keeps its last value
in the cache and ages; the scan goes on with the next block, and the failed one is read again
in its turn (a scan never restarts from its first block, so a long scan completes even when
faults come every few messages).  While the link is down (the driver's own verdict: several
failures in a row, not one) the poller waits for it instead of spinning; when it comes back the
scan resumes where it stopped, and the slow class is read at once.

Data availability (Home Assistant's ``DataUpdateCoordinator`` is the model): ``available`` is
whether the last round of polls read any block (False until the first one does),
``last_success`` the loop time of the last block read, ``last_error`` the last failure (kept
after recovery, for diagnosis).  A round that reads no block and fails at least one makes the
data unavailable; the first block read makes it available again.  Each change is logged once,
never per retry, and never twice with the driver's words:

* the link's own state is the driver's to log (``link X: down: ...`` after several failures in
  a row, ``link X: up`` at the first answer; ``gateway.line_driver``).  When the polls fail
  because of the link (``LinkError``: down, no answer), the poller's change is logged at DEBUG
  only: the driver's line is the one message the operator needs, and one unanswered round on
  a noisy line (not yet a link down) is no news for an operator;
* when the controller answers but no data comes (every read refused, as in program mode, or
  answered with bytes that break the protocol), the driver says the link is up, so only the
  poller can tell: ``link X: unavailable: <error>`` at WARNING once, and ``link X: back online``
  at INFO once the data comes back (also after a link loss in between).

``stagger`` delays the first poll so that links do not all start, and then poll every
``fast_interval``, at the same instant: by default a share of ``fast_interval`` (at most
``MAX_STAGGER``) taken from the link's name, the same on every start; the application may pass
its own (e.g. link i of n: ``i / n`` of the interval), 0 to start at once.
"""

from __future__ import annotations

import asyncio
import logging
import zlib
from collections.abc import Awaitable, Callable, Sequence
from typing import Final

from gateway.cache import BlockCache
from gateway.errors import ControllerRefused, GatewayError, LinkDown, LinkError
from gateway.modbus.mapping import Block, Scan

__all__ = ["MAX_STAGGER", "Poller", "default_stagger"]

log = logging.getLogger("gateway.poller")

ReadBlock = Callable[[Block], Awaitable[bytes]]

#: Seconds before a block the controller refused is tried again (at most the slow interval).
_REFUSED_RETRY = 5.0
#: Keys of the resume positions: the fast class, a whole slow scan, a share of a spread slow scan.
_FAST, _SLOW, _SLOW_SHARE = "fast", "slow", "slow share"
#: Refused blocks logged one by one (program mode refuses every read: one line is enough).
_REFUSALS_LOGGED = 3
#: Seconds: the longest default start-up delay (a slow fast_interval must not hold the first data).
MAX_STAGGER: Final = 1.0


def default_stagger(name: str, fast_interval: float) -> float:
    """A link's start-up delay: a share of ``fast_interval`` (at most ``MAX_STAGGER``) from its name.

    CRC-32 of the name, not ``hash()`` (salted per process): the same delay on every start.
    """
    share = zlib.crc32(name.encode("utf-8")) / 2**32
    return share * min(max(fast_interval, 0.0), MAX_STAGGER)


class Poller:
    def __init__(
        self,
        name: str,
        blocks: Sequence[Block],
        cache: BlockCache,
        read_block: ReadBlock,
        *,
        fast_interval: float = 0.0,
        slow_interval: float = 10.0,
        down_wait: float = 0.2,
        stagger: float | None = None,
        responding: Callable[[], bool] | None = None,
        ready: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        self.name = name
        self.blocks = list(blocks)
        self.cache = cache
        self.fast = [i for i, b in enumerate(self.blocks) if b.scan is Scan.FAST]
        self.slow = [i for i, b in enumerate(self.blocks) if b.scan is Scan.SLOW]
        self._read_block = read_block
        self.fast_interval = fast_interval
        self.slow_interval = slow_interval
        self._down_wait = down_wait
        #: seconds before the first poll (module docstring)
        self.stagger = default_stagger(name, fast_interval) if stagger is None else max(0.0, stagger)
        self._responding = responding
        #: awaited before the first poll: the driver's first attempt to open its port (a poll before it
        #: would fail with "not connected", an error of nobody's)
        self._ready = ready
        self.scans = 0
        self.block_errors = 0
        #: blocks the controller refuses to read (a file too short, program mode ...): the
        #: refusal and when it came; retried every slow_interval, not every scan
        self.refused: dict[int, tuple[ControllerRefused, float]] = {}
        #: per scan class: the position to resume at after the link went down mid-scan
        self._resume = {_FAST: 0, _SLOW: 0, _SLOW_SHARE: 0}
        #: the last round of polls read a block (False until the first one does)
        self.available = False
        #: loop time of the last block read, None before the first
        self.last_success: float | None = None
        #: the last failure of a block read (kept after recovery, for diagnosis)
        self.last_error: GatewayError | None = None
        #: loop time of ``last_error`` (the end of the round it came in), None before the first
        self.last_error_at: float | None = None
        #: changes of ``available`` (the first data included)
        self.availability_changes = 0
        self._warned = False  # the current unavailability was logged at WARNING
        self._round_read = 0  # blocks read in this round
        self._round_error: GatewayError | None = None  # the last failure of this round

    async def _scan(self, indexes: Sequence[int], scan: str = _FAST) -> bool:
        """Read ``indexes``; False when the link is down (the scan stops and resumes there later)."""
        loop = asyncio.get_running_loop()
        start = self._resume[scan] if self._resume[scan] < len(indexes) else 0
        for position in range(start, len(indexes)):
            index = indexes[position]
            refused = self.refused.get(index)
            if refused is not None and loop.time() - refused[1] < min(self.slow_interval, _REFUSED_RETRY):
                continue
            try:
                data = await self._read_block(self.blocks[index])
            except LinkDown as exc:
                self._round_error = exc
                self._resume[scan] = position
                return False
            except ControllerRefused as exc:
                self._round_error = exc
                self.block_errors += 1
                if refused is None and len(self.refused) < _REFUSALS_LOGGED:
                    log.warning("link %s: the controller refuses to read %s: %s", self.name,
                                self.blocks[index].label, exc)
                elif refused is None and len(self.refused) == _REFUSALS_LOGGED:
                    log.warning("link %s: more blocks refused; not logging each", self.name)
                self.refused[index] = (exc, loop.time())
                continue
            except GatewayError as exc:
                self._round_error = exc
                self.block_errors += 1
                log.debug("link %s: block %s failed: %s", self.name, self.blocks[index].label, exc)
                if self._responding is not None and not self._responding():
                    # The driver reports the link down (several failures in a row): probe it
                    # with one block per round instead of waiting out the retries of every
                    # block; the scan resumes after this block.
                    self._resume[scan] = position + 1
                    return False
                continue
            if refused is not None:
                del self.refused[index]
                log.info("link %s: %s is read again", self.name, self.blocks[index].label)
            now = loop.time()
            self.cache.store(index, data, now)
            self._round_read += 1
            self.last_success = now
            if not self.available:
                self._went_available()
        self._resume[scan] = 0
        return True

    # --- data availability (module docstring) -----------------------------------------------

    def _went_available(self) -> None:
        self.available = True
        self.availability_changes += 1
        if self._warned:
            log.info("link %s: back online", self.name)
        else:
            log.debug("link %s: data available", self.name)
        self._warned = False

    def _end_round(self) -> None:
        """After a round of polls: no block read and one failed -> unavailable (logged once)."""
        error, self._round_error = self._round_error, None
        read, self._round_read = self._round_read, 0
        if error is None:
            return
        self.last_error = error
        self.last_error_at = asyncio.get_running_loop().time()
        if read:
            return
        changed = self.available or self.availability_changes == 0  # (the first round too)
        if changed:
            self.available = False
            self.availability_changes += 1
        if isinstance(error, LinkError):
            # The link's trouble: the driver logs it (down after several failures in a row).
            if changed:
                log.debug("link %s: unavailable: %s", self.name, error)
        elif not self._warned:
            log.warning("link %s: unavailable: %s (the controller answers, but no block of the map could "
                        "be read)", self.name, error)
            self._warned = True

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        if self.stagger > 0:
            await asyncio.sleep(self.stagger)
        if self._ready is not None:
            await self._ready()
        next_slow = loop.time()
        whole_slow = True  # at start and after a loss: the whole slow class first
        pending_slow: list[int] = []  # the rest of a periodic slow scan, spread over fast rounds
        last_round = 0.0
        while True:
            started = loop.time()
            ok = True
            if started >= next_slow and self.slow and not pending_slow:
                next_slow = started + self.slow_interval
                if whole_slow or not self.fast or self.slow_interval <= 0:
                    ok = await self._scan(self.slow, _SLOW)
                    whole_slow = not ok
                    if ok and self.fast:
                        # the first spread scan reads its last blocks by one slow_interval
                        # after this whole read, as every later one does after the one before
                        next_slow = started + self.slow_interval / 2
                else:
                    pending_slow = list(self.slow)
            if ok and pending_slow:
                # A periodic slow scan is spread over the fast rounds of half the slow interval,
                # so the fast class is not held up by the whole slow class at once (when writes
                # share the line, that alone would age it past stale_after), and each slow block
                # is read again one slow_interval after its last read.
                rounds = self.slow_interval / 2
                share = max(1, -(-len(self.slow) * max(last_round, self.fast_interval) // rounds))
                chunk, pending_slow = pending_slow[: int(share)], pending_slow[int(share) :]
                ok = await self._scan(chunk, _SLOW_SHARE)
            if ok:
                ok = await self._scan(self.fast, _FAST)
            self._end_round()
            if not ok:
                # The link was lost: the controller may come back power-cycled or replaced, so
                # read the slow class first when it returns instead of serving pre-loss values.
                next_slow = loop.time()
                whole_slow = True
                pending_slow = []
                await asyncio.sleep(self._down_wait)
                continue
            last_round = loop.time() - started
            self.scans += 1
            if self.fast_interval > 0:
                await asyncio.sleep(max(0.0, started + self.fast_interval - loop.time()))
            elif not self.fast:
                await asyncio.sleep(max(0.0, next_slow - loop.time()))
            else:
                await asyncio.sleep(0)  # let other links and the server run
