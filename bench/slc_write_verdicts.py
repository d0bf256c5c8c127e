"""SLC 100/150 write verdicts on a faulty line: how many writes end UNKNOWN (0x0B) per 1,000.

The transaction core (sans-I/O) against the simulator with its own faults, the options of a
``sim://slc150?...`` URL (``drop=5,garble=5``, ``power_cycle_every=25`` ...), on a fake clock:
no real waits, so 10,000 writes take seconds and every run with the same options and seeds gives
the same figures.  The workload is a SCADA link's: 3 reads (the poll) before each write, presets
901-931, each write a value no other write has.  A write gets ``--budget`` seconds (0.9: the
gateway's ``write_timeout``; ``none``: the core's counts, 3 ``;Z``).  Replies arrive 1 ms after
the controller sends them (an unpaced simulator in-process).

    python bench/slc_write_verdicts.py [drop=5,garble=5] [--seeds 10] [--writes 1000] [--budget 0.9|none]
        [--variant power_up_id=retained,...] [--quick]

Prints the verdicts, UNKNOWN per 1,000 writes, the mean time a write takes, and checks that no
write was applied twice.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import result

from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command
from gateway.protocols.slc_ascii.transaction import Result, SlcSession, SlcVerdict

TIMEOUT = 0.3
TRANSIT = 0.001
PRESETS = [0x40 + 2 * n for n in range(31)]  # 901-931 (932 is protected)


class Line:
    """The core and the simulator on a fake clock; replies keep their order."""

    def __init__(self, sim: SlcAsciiSimulator) -> None:
        self.sim = sim
        self.session = SlcSession(timeout=TIMEOUT, retries=3)
        self.now = 0.0
        self._queue: list[tuple[float, int, bytes]] = []
        self._seq = itertools.count()

    def _send(self) -> bool:
        data = self.session.data_to_send()
        for out in self.sim.receive(data, self.now) if data else []:
            heapq.heappush(self._queue, (self.now + TRANSIT + out.delay, next(self._seq), out.data))
        return bool(data)

    def run(self, command: Command, budget: float | None) -> Result:
        session = self.session
        session.start(command, self.now, until=None if budget is None else self.now + budget)
        while session.result is None:
            if self._send():
                continue
            deadline = session.next_deadline()
            assert deadline is not None
            if self._queue and self._queue[0][0] <= deadline:
                arrival, _, reply = heapq.heappop(self._queue)
                self.now = max(self.now, arrival)
                session.receive_data(reply, self.now)
            else:
                self.now = max(self.now, deadline)
                session.handle_timeout(self.now)
        self._send()
        return session.take_result()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("faults", nargs="?", default="drop=5,garble=5",
                        help="simulator fault options, comma separated (default drop=5,garble=5)")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--writes", type=int, default=1000, help="writes per seed")
    parser.add_argument("--budget", default="0.9", help="a write's time budget in seconds, or none")
    parser.add_argument("--variant", default="", help="simulator variants, comma separated")
    parser.add_argument("--quick", action="store_true", help="1 seed, 100 writes (the smoke test)")
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.writes = 1, 100
    options = dict(item.split("=", 1) for item in args.faults.split(",") if item)
    variants = dict(item.split("=", 1) for item in args.variant.split(",") if item)
    budget = None if args.budget == "none" else float(args.budget)
    verdicts: Counter[str] = Counter()
    reads: Counter[str] = Counter()
    write_seconds = 0.0
    applied_twice = power_cycles = 0
    for seed in range(1, args.seeds + 1):
        sim = SlcAsciiSimulator(faults=FaultPlan.from_options({**options, "seed": str(seed)}), variants=variants)
        line = Line(sim)
        for n in range(args.writes):
            for r in range(3):
                reads[line.run(cmds.read_bytes(PRESETS[(3 * n + r) % len(PRESETS)], 2), None).verdict.name] += 1
            began = line.now
            verdicts[line.run(cmds.write_word(PRESETS[n % len(PRESETS)], 1 + n), budget).verdict.name] += 1
            write_seconds += line.now - began
        applied = Counter((a, v) for kind, a, v in sim.applied_writes if kind == "word")
        applied_twice += sum(1 for times in applied.values() if times > 1)
        power_cycles += sim.counters.power_cycles
    writes = sum(verdicts.values())
    print(f"faults {options} variants {variants or 'default'} budget {budget} seeds {args.seeds}")
    print("writes: " + ", ".join(f"{v.name} {verdicts[v.name]}" for v in SlcVerdict))
    print("reads: " + ", ".join(f"{v.name} {reads[v.name]}" for v in SlcVerdict if reads[v.name]))
    result(writes=writes, unknown_per_1000=round(1000 * verdicts["UNKNOWN"] / writes, 1),
           failed=verdicts["FAILED"], mean_write_ms=round(1000 * write_seconds / writes, 1),
           applied_twice=applied_twice, power_cycles=power_cycles)
    assert applied_twice == 0, "a write was applied twice"


if __name__ == "__main__":
    main()
