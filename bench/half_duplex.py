"""Half-duplex DF1 line: line efficiency with 1, 4 and 16 stations, and the cost of one dead station.

The gateway's half-duplex line master (``gateway.kinds.df1.half.driver``) polls SLC 5/04 stations on the
multi-drop line simulator (``gateway.kinds.df1.sim.df1_multidrop``), which paces every byte at the baud rate
(10 bits a character, 8N1) and lets a slave answer ``--turnaround`` seconds after it heard the last
byte.  Each station's unit reads 10 words (N7:0-9, one protected typed logical read) over and over,
one request in flight per station, for ``--seconds``.

Part 1, line efficiency, for 1, 4 and 16 stations at 9600 and 19200 baud:

* ``busy``: seconds the medium carried a signal (master and slave bytes) over the elapsed time;
* ``reads/s`` against the line-time limit of the same exchanges: the reads per second a line busy
  100 % of the time with nothing but these exchanges' bytes would carry - command frame, DLE ACK,
  poll, reply frame, DLE ACK (the background polls and DLE EOTs are the master's overhead, and so
  is every turnaround).

Part 2, one dead station: three live stations with and without a fourth station that never answers
(demoted after the default 5 answerless polls, polled every ``slow_poll_interval`` 10 s), rounds alternated; the
live stations' data age = the interval between successive fresh reads of a station (median and
95th percentile over all reads of the three), and reads/s.

    python bench/half_duplex.py [--quick] [--full] [--seconds S] [--rounds N] [--turnaround S]

Default: 3 s per configuration, 3 rounds of part 2; ``--full``: 15 s and 5 rounds; ``--quick``: 1 s, 1 round.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import percentile, print_machine, result, table

from gateway.errors import GatewayError
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, Df1Station
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import ACK_SYMBOL, Checksum, encode_frame, encode_master_message, encode_poll
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, encode_command
from gateway.sim.serve import SimStream
from gateway.streams import SerialSettings
from gateway.transport import ByteStream

WORDS = 10
READ = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2 * WORDS)


class PacedSimStream(SimStream):
    """The multi-drop simulator paces itself; the driver is told the real character time so that its
    answer timers start when its last byte has left (as on a real port)."""

    def char_time(self, settings: SerialSettings) -> float:
        return settings.char_time


def exchange_bytes(station: int, checksum: Checksum) -> int:
    """Bytes of one read on a quiet line: command frame, ACK, poll, reply frame, ACK."""
    command = encode_command(READ, dst=station, src=0, tns=0x1234)
    reply = bytes((0, station, 0x4F, 0, 0x34, 0x12)) + bytes(2 * WORDS)
    return (len(encode_master_message(station, command, checksum)) + len(ACK_SYMBOL) + len(encode_poll(station))
            + len(encode_frame(reply, checksum)) + len(ACK_SYMBOL))


async def run_line(stations: int, baud: int, seconds: float, *, dead: bool = False,
                   turnaround: float = 0.002) -> dict[str, float]:
    settings = SerialSettings(baud, 8, "N", 1)
    numbers = tuple(range(1, stations + 1))
    line = MultidropLine(LineOptions(checksum=Checksum.CRC, stations=numbers,
                                     dead=frozenset({numbers[-1]}) if dead else frozenset(),
                                     char_time=settings.char_time, turnaround=turnaround, seed=7))

    async def opener(url: str, _settings: object, **_: object) -> ByteStream:
        return PacedSimStream(line)

    frame_time = 300 * settings.char_time  # the longest frame at this speed, with margin
    configs = [StationConfig(n, poll_timeout=0.05 + turnaround + frame_time / 4, reply_timeout=2.0 + 4 * frame_time,
                             poll_interval=1.0, slow_poll_interval=10.0) for n in numbers]  # demote_after: default
    driver = Df1HalfDuplexLine("sim://line", configs, name="bench", settings=settings, checksum=Checksum.CRC,
                               ack_timeout=0.05 + turnaround + frame_time / 4, retries=1, opener=opener,
                               link_reset=False)
    handles = [driver.station(n) for n in numbers]
    live = handles[:-1] if dead else handles
    reads: dict[int, list[float]] = {h.station: [] for h in live}
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    async def reader(handle: Df1Station) -> None:
        while not stop.is_set():
            try:
                await handle.execute(READ, "read N7:0")
            except GatewayError:
                await asyncio.sleep(0.01)
                continue
            if handle.station in reads:
                reads[handle.station].append(loop.time())

    await handles[0].start()
    started = loop.time()
    demoted_after = float("nan")
    tasks = [asyncio.create_task(reader(h)) for h in handles]
    try:
        await asyncio.sleep(min(1.0, seconds / 3))  # warm up
        if dead:  # measure the steady state: the dead station demoted (its cost until then is ~5 timeouts)
            for _ in range(100):
                if driver.core is not None and not driver.core.is_active(numbers[-1]):
                    demoted_after = loop.time() - started
                    break
                await asyncio.sleep(0.05)
        busy0, t0 = line.counters.busy_time, loop.time()
        for times in reads.values():
            times.clear()
        await asyncio.sleep(seconds)
        busy, t_end = line.counters.busy_time - busy0, loop.time()
        elapsed = t_end - t0
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
    finally:
        stop.set()
        for handle in handles:
            await handle.close()
    window = {n: [t for t in times if t <= t_end] for n, times in reads.items()}  # not the reads finishing later
    count = sum(len(times) for times in window.values())
    ages = sorted(b - a for times in window.values() for a, b in itertools.pairwise(times))
    limit = 1.0 / (exchange_bytes(numbers[0], Checksum.CRC) * settings.char_time)
    return {
        "busy": busy / elapsed,
        "reads_per_s": count / elapsed,
        "limit_per_s": limit,
        "age_median": statistics.median(ages) if ages else float("nan"),
        "age_p95": percentile(ages, 95),
        "age_max": ages[-1] if ages else float("nan"),
        "demoted_after": demoted_after,
    }


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="1 s per configuration, 1 round (smoke test)")
    parser.add_argument("--full", action="store_true", help="15 s per configuration, 5 rounds")
    parser.add_argument("--seconds", type=float, default=None)
    parser.add_argument("--rounds", type=int, default=None)
    parser.add_argument("--turnaround", type=float, default=0.002, help="slave turnaround, seconds")
    args = parser.parse_args()
    seconds = args.seconds or (1.0 if args.quick else 15.0 if args.full else 3.0)
    rounds = args.rounds or (1 if args.quick else 5 if args.full else 3)
    print_machine()
    print(f"{seconds:g} s per configuration, slave turnaround {args.turnaround * 1000:g} ms, CRC, "
          f"{WORDS}-word reads, one in flight per station\n")
    rows = []
    efficiency: dict[str, float] = {}
    for baud in (9600, 19200):
        for stations in (1, 4, 16):
            got = await run_line(stations, baud, seconds, turnaround=args.turnaround)
            share = got["reads_per_s"] / got["limit_per_s"]
            efficiency[f"busy_{stations}st_{baud}"] = got["busy"]
            efficiency[f"limit_share_{stations}st_{baud}"] = share
            rows.append((baud, stations, 100 * got["busy"], got["reads_per_s"], got["limit_per_s"], 100 * share,
                         got["age_median"] * 1000))
    print(table(["baud", "stations", "line busy %", "reads/s", "line-time limit reads/s", "of the limit %",
                 "data age median ms"], rows))
    print()
    with_dead: list[dict[str, float]] = []
    without: list[dict[str, float]] = []
    for k in range(rounds):
        order = (True, False) if k % 2 == 0 else (False, True)
        for dead in order:
            got = await run_line(4 if dead else 3, 19200, seconds, dead=dead, turnaround=args.turnaround)
            (with_dead if dead else without).append(got)

    def med(runs: list[dict[str, float]], key: str) -> float:
        return statistics.median(run[key] for run in runs)

    print(table(["19200 baud, 3 live stations", "reads/s", "data age median ms", "p95 ms", "max ms"], [
        (name, med(runs, "reads_per_s"), 1000 * med(runs, "age_median"), 1000 * med(runs, "age_p95"),
         1000 * med(runs, "age_max"))
        for name, runs in (("alone", without), ("+ 1 dead station (demoted)", with_dead))
    ]))
    cost = med(with_dead, "age_median") / med(without, "age_median")
    print(f"\ndead station: live data age x{cost:.3f} (median of {rounds} rounds, alternated); demoted "
          f"{med(with_dead, 'demoted_after'):.2f} s after the line started (its cost until then: answerless "
          "command resends and polls)")
    result(**efficiency, dead_station_age_ratio=cost,
           dead_station_p95_ratio=med(with_dead, "age_p95") / med(without, "age_p95"))


if __name__ == "__main__":
    asyncio.run(main())
