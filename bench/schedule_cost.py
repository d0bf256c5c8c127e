"""What the read order costs: CPU of a pick per transaction, and of a read answered from the image.

* ``pick``: ``Schedule.next`` + ``started`` + ``done`` for one transaction of the SLC 150 plan (120
  blocks), a client's set of 64 blocks demanded: the poller's own work per transaction;
* ``read``: ``Unit.read_register_bytes(holding, 0, 32)`` served from the image, which notes the
  request as demand (one dict store): the Modbus read fast path's unit part.

With ``--tree DIR`` (another checkout, e.g. ``git archive 9335d0c | tar -x -C DIR``) the ``read``
figure is measured there too, in alternated rounds, each in its own process, and the ratio of
the medians is reported (1.00 = as fast); ``pick`` has no counterpart before the schedule.

    python bench/schedule_cost.py [--quick] [--rounds N] [--tree DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import timeit
from pathlib import Path

from _benchlib import result

ROOT = Path(__file__).resolve().parents[1]


def measure_read() -> float:
    """Microseconds per ``read_register_bytes(holding, 0, 32)`` (best of 5), in this process's checkout."""
    import asyncio

    from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
    from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
    from gateway.modbus.mapping import Table

    async def run() -> float:
        unit = SlcAsciiUnit(driver=SlcAsciiDriver("sim://slc150?ladder=0"), unit_id=1, name="bench")
        now = asyncio.get_running_loop().time()
        for index, block in enumerate(unit.plan.blocks):
            unit.cache.store(index, bytes(block.size), now + 1000.0)

        def read() -> bytes:
            return unit.read_register_bytes(Table.HOLDING, 0, 32)

        return min(timeit.repeat(read, number=20000, repeat=5)) / 20000 * 1e6

    return asyncio.run(run())


def measure_pick() -> float:
    """Microseconds per transaction of the order's own work (best of 5)."""
    from gateway.modbus.mapping import Scan
    from gateway.schedule import Schedule

    schedule = Schedule([Scan.FAST] * 55 + [Scan.SLOW] * 65, fast_interval=0.0, slow_interval=10.0, stale_after=5.0)
    schedule.begin(0.0)
    schedule.demand([*range(32), *range(55, 87)], 0.0)
    clock = [0.0]

    def step() -> None:
        clock[0] += 0.05
        now = clock[0]
        block = schedule.next(now)
        assert block is not None
        schedule.started(block, now)
        schedule.done(block, now, now + 0.05, True)
        if int(now) % 30 == 0:
            schedule.demand([*range(32), *range(55, 87)], now)

    return min(timeit.repeat(step, number=5000, repeat=5)) / 5000 * 1e6


def in_process(tree: Path, what: str) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, __file__, "--measure-one", what], env=env, check=True,
                         capture_output=True, text=True, cwd=tree).stdout
    return float(json.loads(out.strip().splitlines()[-1])["us"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one round (CI smoke test)")
    parser.add_argument("--rounds", type=int, default=None, help="alternated rounds (default 9; quick 1)")
    parser.add_argument("--tree", type=Path, default=None, help="another checkout: the read measured side by side")
    parser.add_argument("--measure-one", choices=("read", "pick"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure_one:
        us = measure_read() if args.measure_one == "read" else measure_pick()
        print(json.dumps({"us": us}))
        return
    args.rounds = args.rounds or (1 if args.quick else 9)
    picks = [in_process(ROOT, "pick") for _ in range(args.rounds)]
    print(f"pick + start + end of a transaction, SLC 150 plan, 64 blocks demanded: "
          f"median {statistics.median(picks):.2f} us (min {min(picks):.2f})")
    here: list[float] = []
    there: list[float] = []
    for round_ in range(args.rounds):
        order = [(ROOT, here), (args.tree, there)] if round_ % 2 == 0 else [(args.tree, there), (ROOT, here)]
        for tree, results in order:
            if tree is not None:
                results.append(in_process(tree, "read"))
    print(f"read_register_bytes(holding, 0, 32): median {statistics.median(here):.2f} us (min {min(here):.2f})")
    values = {"pick_us": statistics.median(picks), "read_us": statistics.median(here)}
    if there:
        print(f"  other tree {args.tree}: median {statistics.median(there):.2f} us (min {min(there):.2f}); "
              f"ratio this / other {statistics.median(here) / statistics.median(there):.2f}")
        values["read_ratio"] = statistics.median(here) / statistics.median(there)
    result(**values)


if __name__ == "__main__":
    main()
