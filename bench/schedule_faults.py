"""The read order on a faulty line, on a fake clock: the share of demanded reads answered with data.

Issue 39, item 3: an SLC 150 whose answers take 0-250 ms, 1 reply in 4 garbled, 1 in 6 dropped,
a power cycle every 250 requests, ``stale_after = 4``; a client reads the 31 presets (holding
32-62: 31 slow blocks) and writes one every fifth read.  This models such a line at the level of
:class:`gateway.schedule.Schedule`, with virtual time (no I/O, no sleeping), as the poller drives it:

* the plan of an SLC 150: 55 fast blocks (``fast_interval = 0``), 65 slow ones (``slow_interval =
  10``), ``background_interval = 60``;
* every read attempt holds the line ``uniform(lo, hi)`` seconds (``--tx``) and fails with
  probability ``--fail`` (the driver's retries exhausted);
* every ``--loss-every`` attempts the link is lost as the poller sees it: the attempt is untried
  (``Schedule.untry``), ``Schedule.lost``, ``down_wait`` 0.2 s, and no value read before the loss
  is served until its block is read again (``BlockCache.expire_before``);
* the client reads the 31 blocks every ``--period`` seconds (0: back to back): each read demands
  them; one that finds a block stale asks for the stale blocks (``Schedule.bump``) and waits for
  them up to ``read_wait`` (0.5 s), as the Modbus server does (``Poller.wait_for``); it is *with
  data* when every block is fresh when it is answered.  Every fifth read is followed by a write,
  which holds the line one transaction before the next poll; the client goes on when it is answered.

Printed per seed: the share of client reads with data, the share of time the demanded blocks are
within their stale limit (mean over the blocks), the longest demanded refresh interval, the
line's use; then the sizing rule of ``docs/guide/freshness.md`` with the time a read that stored
data costs (failed attempts included), plus the writes' share: below 0.9 the set fits.

    python bench/schedule_faults.py                        # 1 read in 2.5 fails, a client every 1 s
    python bench/schedule_faults.py --loss-every 250       # and a link loss every 250 reads
    python bench/schedule_faults.py --period 0 --fail 0.2  # a client reading back to back
    python bench/schedule_faults.py --quick                # CI smoke
"""

from __future__ import annotations

import argparse
import math
import random
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gateway.modbus.mapping import Scan
from gateway.schedule import NEVER, Schedule

READ_WAIT = 0.5
DOWN_WAIT = 0.2
CLIENT_GAP = 0.02  # between the answer of a client read and the next one
SAMPLE = 0.1  # seconds between samples of the demanded blocks' freshness


@dataclass
class Line:
    """What the harsh line does: attempt times, failures, losses."""

    tx: tuple[float, float] = (0.05, 0.55)
    fail: float = 0.4
    loss_every: int = 250
    write_every: int = 5
    period: float = 0.0  # seconds from one client read to the next (0: back to back)
    fast: int = 55
    slow: int = 65
    demanded: range = range(55, 86)  # the 31 presets
    stale_after: float = 4.0
    slow_interval: float = 10.0
    background: float = 60.0


@dataclass
class Result:
    reads: int
    with_data: float  # share of client reads answered with data
    fresh_time: float  # mean share of time a demanded block is within its stale limit
    refresh_max: float  # longest interval between two reads of a demanded block (no loss between)
    tx_time: float  # mean seconds of an attempt
    ok_share: float  # share of attempts that stored data
    write_share: float  # share of the time the line spent on the client's writes
    read_share: float  # share of the time the line spent on reads


def simulate(line: Line, seconds: float, seed: int) -> Result:
    rng = random.Random(seed)
    scans = [Scan.FAST] * line.fast + [Scan.SLOW] * line.slow
    s = Schedule(scans, fast_interval=0.0, slow_interval=line.slow_interval, stale_after=line.stale_after,
                 background_interval=line.background)
    n = len(scans)
    demanded = list(line.demanded)
    stamp = [NEVER] * n  # read time of the value served (NEVER: none, or expired by a loss)
    limit = [math.inf] * n  # the stale limit it was read with
    now = 0.0
    s.begin(now)

    def fresh(block: int, at: float) -> bool:
        return at - stamp[block] <= limit[block]

    # the client: the read waiting (its start, its bumped blocks), the next read's time
    client_next = client_start = 0.0
    waiting: tuple[float, set[int]] | None = None
    reads = with_data = 0
    write_due = False
    samples = fresh_samples = 0
    next_sample = 0.0
    attempts = oks = 0
    busy = writing = 0.0
    refresh_max = 0.0
    last_ok = [NEVER] * n

    def answer(at: float) -> None:
        nonlocal reads, with_data, client_next, waiting, write_due
        reads += 1
        with_data += all(fresh(b, at) for b in demanded)
        waiting = None
        if line.write_every and reads % line.write_every == 0:
            write_due, client_next = True, math.inf  # the client waits for its write's answer
        else:
            client_next = max(at + CLIENT_GAP, client_start + line.period)

    def advance(to: float) -> None:
        """Client reads and samples up to ``to`` (the line does nothing meanwhile)."""
        nonlocal next_sample, samples, fresh_samples, waiting, client_start
        while True:
            t_wait = waiting[0] + READ_WAIT if waiting is not None else math.inf
            t_client = client_next if waiting is None else math.inf
            t = min(next_sample, t_wait, t_client)
            if t > to:
                return
            if t == next_sample:
                samples += 1
                fresh_samples += sum(fresh(b, t) for b in demanded)
                next_sample += SAMPLE
            elif t == t_wait:
                answer(t)
            else:
                client_start = t
                s.demand(demanded, t)
                stale = {b for b in demanded if not fresh(b, t)}
                if stale:
                    s.bump(stale)
                    waiting = (t, stale)
                else:
                    answer(t)

    while now < seconds:
        advance(now)
        if write_due:  # a write goes before the next poll; the client goes on when it is answered
            write_due = False
            took = rng.uniform(*line.tx)
            advance(now + took)
            now += took
            writing += took
            client_next = max(now + CLIENT_GAP, client_start + line.period)
            continue
        block = s.next(now)
        if block is None:
            due = min(s.next_due(now), client_next if waiting is None else waiting[0] + READ_WAIT)
            advance(max(due, now))
            now = max(due, now + 1e-6)
            continue
        attempts += 1
        took = rng.uniform(*line.tx)
        if line.loss_every and attempts % line.loss_every == 0:
            s.started(block, now)
            advance(now + took)
            now += took
            s.untry(block, now)
            s.lost(now)
            for b in range(n):  # expire_before: nothing read before the loss is served
                stamp[b] = NEVER
                last_ok[b] = NEVER
            if waiting is not None:
                answer(now)  # a lost link ends every wait
            advance(now + DOWN_WAIT)
            now += DOWN_WAIT
            continue
        ok = rng.random() >= line.fail
        s.started(block, now)
        advance(now + took)
        start, now = now, now + took
        busy += took
        s.done(block, start, now, ok)
        if ok:
            oks += 1
            stamp[block], limit[block] = now, s.max_age[block]
            if block in line.demanded and last_ok[block] != NEVER:
                refresh_max = max(refresh_max, now - last_ok[block])
            last_ok[block] = now
        if waiting is not None:
            waiting[1].discard(block)
            if not waiting[1]:
                answer(now)
    return Result(reads=reads, with_data=with_data / max(1, reads),
                  fresh_time=fresh_samples / max(1, samples * len(demanded)), refresh_max=refresh_max,
                  tx_time=busy / max(1, attempts), ok_share=oks / max(1, attempts), write_share=writing / now,
                  read_share=busy / now)


def sizing(line: Line, tx_time: float) -> float:
    """Transactions/s the plan needs by the guide's rule, times ``tx_time``: < 1 fits."""
    others = line.fast + line.slow - len(line.demanded)
    need = len(line.demanded) / (line.stale_after + line.slow_interval) + others / (line.stale_after + line.background)
    return need * tx_time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tx", default="0.05-0.2", help="seconds of an attempt, lo-hi (uniform)")
    parser.add_argument("--fail", type=float, default=0.4, help="share of attempts that fail")
    parser.add_argument("--loss-every", type=int, default=0, help="attempts between link losses (0: none)")
    parser.add_argument("--period", type=float, default=1.0, help="seconds between client reads (0: back to back)")
    parser.add_argument("--seconds", type=float, default=1200.0, help="virtual seconds per run")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    lo, hi = (float(x) for x in args.tx.split("-"))
    line = Line(tx=(lo, hi), fail=args.fail, loss_every=args.loss_every, period=args.period)
    seconds, seeds = (300.0, 1) if args.quick else (args.seconds, args.seeds)
    results = [simulate(line, seconds, seed) for seed in range(seeds)]
    for seed, r in enumerate(results):
        print(f"seed {seed}: {r.reads} reads, {100 * r.with_data:.1f} % with data; demanded blocks fresh "
              f"{100 * r.fresh_time:.1f} % of the time; longest demanded refresh {r.refresh_max:.1f} s; "
              f"attempt {r.tx_time:.3f} s, {100 * r.ok_share:.0f} % stored; line: reads {100 * r.read_share:.0f} %, "
              f"writes {100 * r.write_share:.0f} %")
    tx = statistics.mean(r.tx_time for r in results)
    ok = statistics.mean(r.ok_share for r in results)
    writes = statistics.mean(r.write_share for r in results)
    print(f"sizing rule: {sizing(line, tx / ok):.2f} of the line at {tx / ok:.3f} s a read that stored data "
          f"({tx:.3f} s an attempt), + {writes:.2f} writes = {sizing(line, tx / ok) + writes:.2f} (< 0.9: fits)")
    print(f"RESULT with_data={100 * statistics.mean(r.with_data for r in results):.1f}% "
          f"fresh_time={100 * statistics.mean(r.fresh_time for r in results):.1f}%")


if __name__ == "__main__":
    main()
