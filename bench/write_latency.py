"""Write latency: Modbus FC6 request to response while the link polls, at line speed.

The gateway polls continuously (fast class, no pause) over paced simulators in a helper
process (``bench/simfarm.py``); a client in another process (``bench/loadgen.py write``) sends
single-register writes (FC6) at random moments (a random pause of 0..0.3 s before each) and
times each from request to response:

* SLC 150 (9600 7E1): holding register 0 = accumulator of 901 (a write-word command);
* SLC 5/04 (DF1 19200 8N1): holding register 0 = N7:0 (a protected typed logical write).

The floor: a write waits for the poll transaction already on the line (writes jump the queue,
so never for more than one), then takes one write transaction.  Arriving at a uniformly random
moment of the scan, the residual of the transaction in flight is uniform over that
transaction's duration, and a transaction is hit in proportion to its duration; so the floor
distribution is that of ``residual + write transaction``, computed here from the frame lengths
of the protocol encoders and the character time (10 bits per character), sampled over the
link's actual read plan.  Measured minus floor is what the gateway, the event loop, loopback
TCP and process wake-ups add.

    python bench/write_latency.py [--quick] [--writes N]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import sys

from _benchlib import (
    BENCH_DIR,
    DF1_CHAR_TIME,
    DF1_MAP,
    PYTHON,
    REPO,
    SLC_CHAR_TIME,
    SimFarm,
    df1_frames,
    df1_link,
    df1_simulator_available,
    gateway_config,
    percentile,
    print_machine,
    result,
    slc_link,
    slc_read_frames,
    slc_write_word_frames,
    table,
)

from gateway.app import Gateway
from gateway.config import parse_config


def slc_times() -> tuple[list[float], float]:
    """(poll transaction durations of one fast scan, write transaction duration), seconds."""
    from gateway.kinds.slc_ascii.plan import slc_ascii_plan
    from gateway.modbus.mapping import Scan

    polls = []
    for block in slc_ascii_plan().blocks:
        if block.scan is Scan.FAST:
            address, count = block.request  # type: ignore[misc]
            request, reply = slc_read_frames(address, count)
            polls.append((request + reply) * SLC_CHAR_TIME)
    request, reply = slc_write_word_frames(0, 1234)
    return polls, (request + reply) * SLC_CHAR_TIME


def df1_times() -> tuple[list[float], float]:
    from gateway.kinds.df1.plan import MapItem, plan_df1
    from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite

    polls = []
    for block in plan_df1([MapItem(**e) for e in DF1_MAP], 236).blocks:  # type: ignore[arg-type]
        r = block.request
        request = ProtectedTypedLogicalRead(r.file_type, r.file_number, r.element, r.sub_element, r.size)  # type: ignore[attr-defined]
        out, back = df1_frames(request, bytes(r.size))  # type: ignore[attr-defined]
        polls.append((out + back) * DF1_CHAR_TIME)
    out, back = df1_frames(ProtectedTypedLogicalWrite(0x89, 7, 0, 0, b"\x01\x00"), b"")
    return polls, (out + back) * DF1_CHAR_TIME


def floor_distribution(polls: list[float], write: float, samples: int = 200_000) -> list[float]:
    """Sorted floor latencies (s): a uniformly random moment of the scan, then one write."""
    rng = random.Random(1)
    edges = []
    total = 0.0
    for duration in polls:
        total += duration
        edges.append(total)
    out = []
    for _ in range(samples):
        t = rng.uniform(0, total)
        end = next(edge for edge in edges if edge >= t)
        out.append(end - t + write)
    out.sort()
    return out


async def client(port: int, unit: int, writes: int, gap_max: float) -> dict[str, object]:
    process = await asyncio.create_subprocess_exec(
        PYTHON, str(BENCH_DIR / "loadgen.py"), "write", "--port", str(port), "--unit", str(unit),
        "--writes", str(writes), "--gap-max", str(gap_max), "--seed", str(unit),
        stdout=asyncio.subprocess.PIPE, cwd=str(REPO),
    )
    stdout, _ = await process.communicate()
    if process.returncode != 0:
        raise SystemExit(f"write client for unit {unit} failed")
    answer: dict[str, object] = json.loads(stdout.decode().strip().splitlines()[-1])
    return answer


async def measure(
    links: list[str], units: list[int], writes: int, gap_max: float
) -> tuple[list[dict[str, object]], list[int]]:
    gateway = Gateway(parse_config(gateway_config(links)))
    async with gateway:
        answers = await asyncio.gather(*(client(gateway.port, unit, writes, gap_max) for unit in units))
        errors = [unit.driver.counters.errors for unit in gateway.units]
    return list(answers), errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few writes (CI smoke test)")
    parser.add_argument("--writes", type=int, default=0, help="writes per link (default 400; quick 15)")
    parser.add_argument("--gap-max", type=float, default=0.3, help="random pause before each write: 0..S s")
    args = parser.parse_args()
    writes = args.writes or (15 if args.quick else 400)
    print_machine()
    have_df1 = df1_simulator_available()
    farms = [SimFarm("slc150", 1, paced=True)]
    links = [slc_link("slc", farms[0].urls()[0], 1)]
    units = [1]
    floors = {"slc": slc_times()}
    if have_df1:
        farms.append(SimFarm("slc504", 1, paced=True))
        links.append(df1_link("df1", farms[1].urls()[0], 2))
        units.append(2)
        floors["df1"] = df1_times()
    else:
        print("DF1: gateway/sim/slc500.py not there yet: DF1 skipped")
    try:
        answers, errors = asyncio.run(measure(links, units, writes, args.gap_max))
    finally:
        for farm in farms:
            farm.close()
    rows = []
    values: dict[str, object] = {"writes": writes}
    for (name, (polls, write)), answer, link_errors in zip(floors.items(), answers, errors, strict=True):
        floor = floor_distribution(polls, write)
        measured = sorted(float(x) for x in answer["latencies_ms"])  # type: ignore[attr-defined]
        f = {q: percentile(floor, q) * 1e3 for q in (50, 90, 99)}
        m = {q: percentile(measured, q) for q in (50, 90, 99)}
        print(f"{name}: write transaction {write * 1e3:.2f} ms, poll transactions "
              f"{min(polls) * 1e3:.2f}-{max(polls) * 1e3:.2f} ms; floor max {(max(polls) + write) * 1e3:.2f} ms")
        rows.append([name, "measured", m[50], m[90], m[99], measured[-1], answer["exceptions"], link_errors])
        rows.append([name, "floor", f[50], f[90], f[99], floor[-1] * 1e3, "", ""])
        rows.append([name, "measured - floor", m[50] - f[50], m[90] - f[90], m[99] - f[99],
                     measured[-1] - floor[-1] * 1e3, "", ""])
        values[f"{name}_p50"] = m[50]
        values[f"{name}_p99"] = m[99]
        values[f"{name}_max"] = measured[-1]
        values[f"{name}_floor_p50"] = f[50]
        values[f"{name}_floor_p99"] = f[99]
        values[f"{name}_exceptions"] = answer["exceptions"]
    if not have_df1:
        values["df1"] = "skipped"
    print(table(["link", "", "p50 ms", "p90 ms", "p99 ms", "max ms", "exceptions", "link errors"], rows))
    result(**values)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
