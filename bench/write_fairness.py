"""Write fairness: a well-behaved client's write latency and the data age under a write flood.

An SLC 150 simulator paced at 9600 baud (``bench/simfarm.py``, its own process) behind the
gateway (this process).  Per round, two phases in alternating order:

* idle: a client process (``bench/loadgen.py write``) sends FC6 writes to holding 33 (preset of
  902) after a random pause of 0..0.2 s each, and times each from request to response;
* flood: the same client, while another process (``bench/loadgen.py flood``) keeps 16 FC6 writes
  in flight on one connection to holding 0-30 (a new one the moment any reply comes, 0x06 busy
  answers included).

Reported: the well-behaved client's p50/p90 latency in each phase and their ratio flood / idle
(median over rounds), and during the flood the fast-class data age (status register 1001,
sampled every 50 ms in the gateway) and the reads that would answer 0x0B (none expected).

    python bench/write_fairness.py [--quick] [--rounds R] [--writes N]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys

from _benchlib import (
    BENCH_DIR,
    PYTHON,
    REPO,
    SimFarm,
    gateway_config,
    percentile,
    print_machine,
    result,
    slc_link,
    table,
)

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.errors import ModbusExceptionReply
from gateway.modbus.mapping import Table


async def loadgen(*args: str) -> dict[str, object]:
    process = await asyncio.create_subprocess_exec(
        PYTHON, str(BENCH_DIR / "loadgen.py"), *args, stdout=asyncio.subprocess.PIPE, cwd=str(REPO)
    )
    stdout, _ = await process.communicate()
    if process.returncode != 0:
        raise SystemExit(f"loadgen {args[0]} failed")
    answer: dict[str, object] = json.loads(stdout.decode().strip().splitlines()[-1])
    return answer


async def watch(gateway: Gateway, stop: asyncio.Event, ages: list[float], stale: list[int]) -> None:
    unit = gateway.units[0]
    loop = asyncio.get_running_loop()
    while not stop.is_set():
        ages.append(unit.status_values(loop.time())["data_age"] / 10)
        try:
            unit.read_registers(Table.HOLDING, 0, 32)  # the accumulators: fast class
            unit.read_bits(Table.DISCRETE, 701, 64)
        except ModbusExceptionReply as exc:
            stale.append(exc.code)
        await asyncio.sleep(0.05)


async def phase(gateway: Gateway, flood: bool, writes: int) -> dict[str, object]:
    port = str(gateway.port)
    ages: list[float] = []
    stale: list[int] = []
    stop = asyncio.Event()
    watcher = asyncio.create_task(watch(gateway, stop, ages, stale))
    client = loadgen("write", "--port", port, "--address", "33", "--writes", str(writes), "--gap-max", "0.2")
    if flood:
        duration = writes * 0.1 + 3.0  # the well-behaved client's run, with room to spare
        flooder = asyncio.create_task(loadgen("flood", "--port", port, "--duration", f"{duration:g}"))
        await asyncio.sleep(1.0)  # the flood in full swing first
        answer = await client
        outcome = await flooder
    else:
        answer = await client
        outcome = {}
    stop.set()
    await watcher
    latencies = sorted(float(x) for x in answer["latencies_ms"])  # type: ignore[attr-defined]
    return {"p50": percentile(latencies, 50), "p90": percentile(latencies, 90), "max_age": max(ages, default=0.0),
            "stale": len(stale), "exceptions": answer["exceptions"], "flood": outcome}


async def measure(url: str, rounds: int, writes: int) -> list[dict[str, dict[str, object]]]:
    results = []
    async with Gateway(parse_config(gateway_config([slc_link("slc", url, 1)]))) as gateway:
        await loadgen("write", "--port", str(gateway.port), "--address", "33", "--writes", "3", "--gap-max", "0")
        unit = gateway.units[0]
        loop = asyncio.get_running_loop()
        while True:  # every fast block read once
            if unit.status_values(loop.time())["data_age"] < 65535:
                break
            await asyncio.sleep(0.1)
        for r in range(rounds):
            order = [False, True] if r % 2 == 0 else [True, False]
            row = {}
            for flood in order:
                row["flood" if flood else "idle"] = await phase(gateway, flood, writes)
                print(f"round {r + 1} {'flood' if flood else 'idle'}: {row['flood' if flood else 'idle']}",
                      file=sys.stderr)
            results.append(row)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one short round (CI smoke test)")
    parser.add_argument("--rounds", type=int, default=0, help="rounds (default 4; quick 1)")
    parser.add_argument("--writes", type=int, default=0, help="writes per phase (default 80; quick 10)")
    args = parser.parse_args()
    rounds = args.rounds or (1 if args.quick else 4)
    writes = args.writes or (10 if args.quick else 80)
    print_machine()
    with SimFarm("slc150", 1, paced=True) as farm:
        results = asyncio.run(measure(farm.urls()[0], rounds, writes))
    rows = []
    for kind in ("idle", "flood"):
        p50 = statistics.median(float(r[kind]["p50"]) for r in results)  # type: ignore[arg-type]
        p90 = statistics.median(float(r[kind]["p90"]) for r in results)  # type: ignore[arg-type]
        age = max(float(r[kind]["max_age"]) for r in results)  # type: ignore[arg-type]
        stale = sum(int(r[kind]["stale"]) for r in results)  # type: ignore[call-overload]
        rows.append([kind, p50, p90, age, stale])
    ratio50 = statistics.median(float(r["flood"]["p50"]) / float(r["idle"]["p50"]) for r in results)  # type: ignore[arg-type]
    ratio90 = statistics.median(float(r["flood"]["p90"]) / float(r["idle"]["p90"]) for r in results)  # type: ignore[arg-type]
    print(table(["phase", "p50 ms", "p90 ms", "max fast-class age s", "reads 0x0B"], rows))
    print(f"flood / idle (median of {rounds} rounds): p50 x{ratio50:.2f}, p90 x{ratio90:.2f}")
    print("flood replies:", [r["flood"]["flood"] for r in results])
    result(rounds=rounds, writes=writes, idle_p50=rows[0][1], flood_p50=rows[1][1], ratio_p50=ratio50,
           ratio_p90=ratio90, flood_max_age=rows[1][3], flood_stale_reads=rows[1][4])
    sys.stdout.flush()


if __name__ == "__main__":
    main()
