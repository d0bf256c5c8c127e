"""Wire efficiency: how close the gateway's polling comes to what the serial line allows.

The gateway polls its map continuously against paced simulators (every character takes
``bits_per_char / baud`` seconds, both directions independent, as on a full-duplex line):

* SLC 150, ASCII protocol, 9600 7E1, the fixed default map (fast class: 55 two-byte reads);
* SLC 5/04, DF1 full duplex, 19200 8N1, CRC, a realistic map (N7:0-99, T4:0-9 ACC, F8:0-9,
  B3:0-3 bits) - when ``gateway/sim/slc500.py`` exists.

The theoretical maximum for the same frames on the same line: one request is outstanding at a
time, so everything a transaction puts on the line is serialized:

    SLC 100/150:  request + controller turnaround + reply
    DF1:          command frame + DLE ACK + turnaround + reply frame + DLE ACK
                  (full duplex does not help a single outstanding request: the controller's
                  ACK and reply follow the command, and our ACK follows the reply; only our
                  ACK could overlap our next command, but both use the same direction)

measured from the bytes the driver actually sent and received in the window
(``bytes_sent + bytes_received`` = exactly those frames and ACKs) times the character time,
plus the turnaround once per transaction.  efficiency = that ideal busy time / wall time; the
achieved transactions/s and useful data bytes/s divided by their maxima are this same ratio.

By default the simulators run in a helper process (``bench/simfarm.py``) reached over TCP
(``socket://``, as a serial device server), with a ``select()`` loop so that their pacing
timers are exact; ``--in-process`` adds the ``sim://`` in-process simulator for comparison
(its epoll-based timers fire ~0.5 ms late, twice per transaction).

    python bench/wire_efficiency.py [--quick] [--duration S] [--turnaround S] [--in-process]
"""

from __future__ import annotations

import argparse
import asyncio
import time
from dataclasses import dataclass, field

from _benchlib import (
    DF1_CHAR_TIME,
    SLC_CHAR_TIME,
    CompletionLog,
    SimFarm,
    Window,
    df1_link,
    df1_simulator_available,
    gateway_config,
    print_machine,
    result,
    run_bare_host,
    slc_link,
    slc_read_frames,
    table,
)

from gateway.app import Gateway
from gateway.config import parse_config


@dataclass
class Run:
    key: str
    name: str
    char_time: float
    turnaround: float
    window: Window = field(default_factory=Window)
    reaction_p50: float = float("nan")
    reaction_p99: float = float("nan")
    ack_p50: float = float("nan")
    lateness_p50: float = float("nan")

    @property
    def efficiency(self) -> float:
        return self.window.efficiency(self.char_time, self.turnaround)

    @property
    def tps(self) -> float:
        return self.window.transactions / self.window.seconds if self.window.seconds else float("nan")

    def row(self) -> list[object]:
        w = self.window
        n = max(1, w.transactions)
        ideal = w.ideal(self.char_time, self.turnaround)
        return [
            self.name,
            f"{w.sent / n:.1f} + {w.received / n:.1f}",
            self.tps,
            w.transactions / ideal if ideal else float("nan"),
            w.data / w.seconds if w.seconds and w.data else "-",
            w.data / ideal if ideal and w.data else "-",
            self.efficiency,
            self.reaction_p50 * 1e3,
            self.reaction_p99 * 1e3,
            self.ack_p50 * 1e3,
            self.lateness_p50 * 1e3,
            w.errors,
        ]


HEADERS = [
    "link", "bytes/tx out+in", "tx/s", "max tx/s", "data B/s", "max data B/s", "efficiency",
    "gw reaction p50 ms", "p99 ms", "DF1 ACK p50 ms", "sim timer late p50 ms", "errors",
]


async def measure(
    runs: list[Run], links: list[str], farms: list[SimFarm | None], warmup: float, duration: float
) -> None:
    """Run one gateway with ``links`` (one per run) and fill in each run's window figures."""
    gateway = Gateway(parse_config(gateway_config(links)))
    logs = [CompletionLog(unit) for unit in gateway.units]
    async with gateway:
        await asyncio.sleep(warmup)
        for farm in farms:
            if farm is not None:
                farm.stats()  # start the farm's window
        start = time.perf_counter()
        await asyncio.sleep(duration)
        end = time.perf_counter()
        stats = [farm.stats() if farm is not None else None for farm in farms]
    for run, log, stat in zip(runs, logs, stats, strict=True):
        run.window = log.window(start, end)
        if stat is not None:
            gaps = stat.gaps[0]  # the first connection: the gateway's
            run.reaction_p50, run.reaction_p99 = gaps["p50"], gaps["p99"]
            run.ack_p50 = gaps["ack_p50"]
            run.lateness_p50 = stat.lateness_p50


async def measure_reference(runs: list[Run], farms: list[SimFarm], warmup: float, duration: float) -> None:
    """The bare host on each farm's second simulator, all at once."""
    for farm in farms:
        farm.stats()
    windows = await asyncio.gather(
        *(run_bare_host(farm.ports[1], farm.model == "slc504", warmup, duration) for farm in farms)
    )
    for run, window, farm in zip(runs, windows, farms, strict=True):
        run.window = window
        stat = farm.stats()
        gaps = stat.gaps[-1]  # the last connection: the bare host's
        run.reaction_p50, run.reaction_p99, run.ack_p50 = gaps["p50"], gaps["p99"], gaps["ack_p50"]
        run.lateness_p50 = stat.lateness_p50


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few seconds (CI smoke test)")
    parser.add_argument("--duration", type=float, default=0.0, help="measurement window, s (default 30; quick 2)")
    parser.add_argument("--turnaround", type=float, default=0.0, help="simulated controller turnaround, s")
    parser.add_argument("--in-process", action="store_true", help="also measure the in-process sim:// simulator")
    args = parser.parse_args()
    duration = args.duration or (2.0 if args.quick else 30.0)
    warmup = 0.7 if args.quick else 2.0
    print_machine()
    ta = args.turnaround
    slc_req, slc_rep = slc_read_frames(0x00, 2)
    print(f"SLC 100/150 two-byte read: {slc_req} + {slc_rep} characters = "
          f"{(slc_req + slc_rep) * SLC_CHAR_TIME * 1e3:.2f} ms at 9600 7E1 (+ turnaround {ta * 1e3:g} ms)")
    have_df1 = df1_simulator_available()
    farms: list[SimFarm] = []
    try:
        # Each farm serves two simulators: [0] for the gateway, [1] for the reference host.
        slc_farm = SimFarm("slc150", 2, paced=True, turnaround=ta)
        farms.append(slc_farm)
        runs = [Run("slc", "slc150 9600 7E1: gateway", SLC_CHAR_TIME, ta)]
        links = [slc_link("slc", slc_farm.urls()[0], 1)]
        if have_df1:
            df1_farm = SimFarm("slc504", 2, paced=True, turnaround=ta)
            farms.append(df1_farm)
            runs.append(Run("df1", "slc5/04 DF1 19200 8N1: gateway", DF1_CHAR_TIME, ta))
            links.append(df1_link("df1", df1_farm.urls()[0], 2, timeout=1.0))
        else:
            print("DF1: gateway/sim/slc500.py not there yet: DF1 measurement skipped")
        asyncio.run(measure(runs, links, list(farms), warmup, duration))
        # The reference: a bare asyncio host with precomputed frames, same simulators, same line.
        refs = [Run("slc_ref", "slc150 9600 7E1: bare asyncio host", SLC_CHAR_TIME, ta)]
        if have_df1:
            refs.append(Run("df1_ref", "slc5/04 DF1 19200 8N1: bare asyncio host", DF1_CHAR_TIME, ta))
        asyncio.run(measure_reference(refs, farms, warmup, duration))
        runs += refs
        if args.in_process:  # a separate gateway: the in-process simulators load its event loop
            inproc = [Run("slc_inproc", "slc150 sim:// in-process: gateway", SLC_CHAR_TIME, ta)]
            inproc_links = [slc_link("slc-inproc", f"sim://slc150?paced=1&turnaround={ta}&ladder=0", 3)]
            if have_df1:
                inproc.append(Run("df1_inproc", "slc5/04 sim:// in-process: gateway", DF1_CHAR_TIME, ta))
                inproc_links.append(df1_link("df1-inproc", f"sim://slc504?paced=1&turnaround={ta}&ladder=0", 4))
            asyncio.run(measure(inproc, inproc_links, [None] * len(inproc), warmup, duration))
            runs += inproc
    finally:
        for farm in farms:
            farm.close()
    print(table(HEADERS, [run.row() for run in runs]))
    values: dict[str, object] = {"duration": duration}
    for run in runs:
        values[f"{run.key}_tps"] = run.tps
        values[f"{run.key}_eff"] = run.efficiency
    if not have_df1:
        values["df1"] = "skipped"
    values["target_met"] = all(run.efficiency >= 0.95 for run in runs if run.key in ("slc", "df1"))
    if any(run.window.transactions == 0 for run in runs):
        raise SystemExit("a link completed no transaction in the window")
    result(**values)


if __name__ == "__main__":
    main()
