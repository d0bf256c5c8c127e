"""Scale: 1 to 64 paced links in ONE gateway process - CPU, per-link wire efficiency, memory.

For each link count N, a fresh child process runs one gateway with N links (each polling its
map continuously) against N paced simulators served over TCP by a helper process
(``bench/simfarm.py``: its CPU is not the gateway's).  Over a measurement window the child
takes its own CPU time (``getrusage``: user + system, all threads) and, per link, the wire
efficiency as in ``wire_efficiency.py`` (the line time of the frames the link exchanged,
serialized, divided by the wall time, between two completed transactions).  RSS is read from
``/proc/self/status`` before the gateway is built and at the end of the window.

    python bench/scale.py [--quick] [--links 1,8,32,64] [--protocol slc|df1|both] [--duration S]
                          [--turnaround S] [--jitter S] [--profile] [--reference]

"bunched" is the share of transaction completions (all links together) that follow the previous
one by less than 0.1 ms: links whose phases are independent would give the figure in the next
column; a much larger share means the links have phase-locked (see BENCHMARKS.md).

Target: 64 links at >= 0.95 efficiency each, within half of one core (0.5 CPU s/s).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import io
import itertools
import json
import math
import pstats
import statistics
import subprocess
import sys
import time

from _benchlib import (
    BENCH_DIR,
    DF1_CHAR_TIME,
    PYTHON,
    SLC_CHAR_TIME,
    CompletionLog,
    SimFarm,
    cpu_seconds,
    df1_link,
    df1_simulator_available,
    gateway_config,
    print_machine,
    result,
    rss_mib,
    run_bare_host,
    slc_link,
    table,
)


async def child_run(
    protocol: str, count: int, warmup: float, duration: float, spin: float, turnaround: float, jitter: float,
    profile: bool = False, reference: bool = False,
) -> dict[str, object]:
    from gateway.app import Gateway
    from gateway.config import parse_config

    rss_before = rss_mib()
    model = "slc504" if protocol == "df1" else "slc150"
    char_time = DF1_CHAR_TIME if protocol == "df1" else SLC_CHAR_TIME
    with SimFarm(model, count, paced=True, spin=spin, turnaround=turnaround, jitter=jitter) as farm:
        if reference:  # the bare asyncio host of wire_efficiency.py on every link, no gateway
            farm.stats()
            cpu0 = cpu_seconds()
            windows = await asyncio.gather(
                *(run_bare_host(port, protocol == "df1", warmup, duration) for port in farm.ports)
            )
            cpu = cpu_seconds() - cpu0
            efficiencies = [w.efficiency(char_time, turnaround + jitter / 2) for w in windows]
            return {"links": count, "protocol": f"{protocol} bare host", "cpu_per_s": cpu / (warmup + duration),
                    "tps": sum(w.transactions / w.seconds for w in windows),
                    "eff_min": min(efficiencies), "eff_median": statistics.median(efficiencies),
                    "links_below_095": sum(e < 0.95 for e in efficiencies)}
        if protocol == "df1":
            links = [df1_link(f"l{i}", url, i + 1) for i, url in enumerate(farm.urls())]
        else:
            links = [slc_link(f"l{i}", url, i + 1) for i, url in enumerate(farm.urls())]
        gateway = Gateway(parse_config(gateway_config(links)))
        logs = [CompletionLog(unit) for unit in gateway.units]
        async with gateway:
            await asyncio.sleep(warmup)
            farm_before = farm.stats()
            profiler = cProfile.Profile(time.process_time) if profile else None  # CPU, not waiting
            cpu0, t0 = cpu_seconds(), time.perf_counter()
            if profiler is not None:
                profiler.enable()
            await asyncio.sleep(duration)
            if profiler is not None:
                profiler.disable()
            cpu1, t1 = cpu_seconds(), time.perf_counter()
            farm_after = farm.stats()
            rss_after = rss_mib()
            errors = sum(unit.driver.counters.errors for unit in gateway.units)
    if profiler is not None:
        out = io.StringIO()
        pstats.Stats(profiler, stream=out).sort_stats("tottime").print_stats(20)
        text = out.getvalue()
        print(text[text.find("   ncalls") :].rstrip(), flush=True)
    windows = [log.window(t0, t1) for log in logs]
    # the mean turnaround: with jitter the ideal is known to ~0.1 % over a few hundred transactions
    efficiencies = [w.efficiency(char_time, turnaround + jitter / 2) for w in windows]
    # Phase locking: the share of completed transactions (all links together) that follow the
    # previous one by < 0.1 ms; with independent phases it would be about 1 - exp(-0.1 ms * rate).
    completions = sorted(s[0] for log in logs for s in log.samples if t0 <= s[0] <= t1)
    close = sum(b - a < 1e-4 for a, b in itertools.pairwise(completions))
    rate = len(completions) / (t1 - t0)
    reactions = [g["p50"] for g in farm_after.gaps if g["n"]]
    return {
        "links": count,
        "protocol": protocol,
        "cpu_per_s": (cpu1 - cpu0) / (t1 - t0),
        "tps": sum(w.transactions for w in windows) / (t1 - t0),
        "eff_min": min(efficiencies),
        "eff_median": statistics.median(efficiencies),
        "eff_mean": statistics.fmean(efficiencies),
        "links_below_095": sum(e < 0.95 for e in efficiencies),
        "rss_before": rss_before,
        "rss_after": rss_after,
        "farm_cpu_per_s": (farm_after.cpu - farm_before.cpu) / (t1 - t0),
        "sim_late_p50_ms": farm_after.lateness_p50 * 1e3,
        "reaction_p50_ms": statistics.median(reactions) * 1e3 if reactions else float("nan"),
        "errors": errors,
        "bunched": close / max(1, len(completions) - 1),
        "bunched_if_independent": 1 - math.exp(-1e-4 * rate),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="1 and 8 links, 2 s windows (CI smoke test)")
    parser.add_argument("--links", default="", help="comma-separated link counts (default 1,8,32,64)")
    parser.add_argument("--protocol", choices=("slc", "df1", "both"), default="both")
    parser.add_argument("--duration", type=float, default=0.0, help="measurement window, s (default 20; quick 2)")
    parser.add_argument("--spin", type=float, default=0.0003, help="simulator loop spin before timers, s")
    parser.add_argument("--turnaround", type=float, default=0.0, help="simulated controller turnaround, s")
    parser.add_argument("--jitter", type=float, default=0.0, help="plus a random 0..S s per reply")
    parser.add_argument("--profile", action="store_true",
                        help="then profile the gateway at the largest link count (cProfile, top 20)")
    parser.add_argument("--child-profile", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--reference", action="store_true",
                        help="also run the bare asyncio host (no gateway) at the largest link count")
    parser.add_argument("--child-reference", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child", default="", help=argparse.SUPPRESS)  # protocol:count (internal)
    args = parser.parse_args()
    duration = args.duration or (2.0 if args.quick else 20.0)
    if args.child:
        protocol, count = args.child.split(":")
        warmup = 1.0 if args.quick else 3.0
        run = child_run(protocol, int(count), warmup, duration, args.spin, args.turnaround, args.jitter,
                        args.child_profile, args.child_reference)
        print(json.dumps(asyncio.run(run)), flush=True)
        return
    print_machine()
    print(f"turnaround {args.turnaround * 1e3:g} ms + random 0..{args.jitter * 1e3:g} ms; window {duration:g} s")
    counts = [int(c) for c in args.links.split(",")] if args.links else ([1, 8] if args.quick else [1, 8, 32, 64])
    protocols = ["slc", "df1"] if args.protocol == "both" else [args.protocol]
    if "df1" in protocols and not df1_simulator_available():
        print("DF1: gateway/sim/slc500.py not there yet: DF1 skipped")
        protocols.remove("df1")
    if args.quick:
        protocols = protocols[:1]
    rows = []
    for protocol in protocols:
        for count in counts:
            command = [PYTHON, str(BENCH_DIR / "scale.py"), "--child", f"{protocol}:{count}",
                       "--duration", str(duration), "--spin", str(args.spin),
                       "--turnaround", str(args.turnaround), "--jitter", str(args.jitter)]
            if args.quick:
                command.append("--quick")
            out = subprocess.run(command, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                print(out.stdout, out.stderr, file=sys.stderr)
                raise SystemExit(f"child {protocol}:{count} failed")
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            r = rows[-1]
            print(f"{protocol} {count:3d} links: cpu {r['cpu_per_s']:.3f} s/s, eff min {r['eff_min']:.4f}, "
                  f"rss {r['rss_after']:.1f} MiB", flush=True)
    headers = ["protocol", "links", "gateway CPU s/s", "tx/s total", "eff min", "eff median", "links < 0.95",
               "RSS MiB (before gw)", "RSS MiB", "KiB/link", "gw reaction p50 ms", "bunched", "(if independent)",
               "sim CPU s/s", "errors"]
    print(table(headers, [[r["protocol"], r["links"], r["cpu_per_s"], r["tps"], r["eff_min"], r["eff_median"],
                           r["links_below_095"], r["rss_before"], r["rss_after"],
                           (r["rss_after"] - r["rss_before"]) * 1024 / r["links"], r["reaction_p50_ms"],
                           r["bunched"], r["bunched_if_independent"], r["farm_cpu_per_s"], r["errors"]] for r in rows]))
    values: dict[str, object] = {}
    for r in rows:
        key = f"{r['protocol']}{r['links']}"
        values[f"{key}_cpu"] = r["cpu_per_s"]
        values[f"{key}_effmin"] = r["eff_min"]
        values[f"{key}_rss"] = r["rss_after"]
    if args.reference:
        for protocol in protocols:
            command = [PYTHON, str(BENCH_DIR / "scale.py"), "--child", f"{protocol}:{max(counts)}",
                       "--child-reference", "--duration", str(duration), "--spin", str(args.spin),
                       "--turnaround", str(args.turnaround), "--jitter", str(args.jitter)]
            out = subprocess.run(command, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                raise SystemExit(f"reference child failed: {out.stderr[-2000:]}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"reference, {r['protocol']}, {r['links']} links (no gateway): {r['tps']:.0f} tx/s, "
                  f"eff min {r['eff_min']:.4f}, median {r['eff_median']:.4f}, {r['links_below_095']} below 0.95")
    if args.profile:
        for protocol in protocols:
            command = [PYTHON, str(BENCH_DIR / "scale.py"), "--child", f"{protocol}:{max(counts)}", "--child-profile",
                       "--duration", str(duration), "--spin", str(args.spin),
                       "--turnaround", str(args.turnaround), "--jitter", str(args.jitter)]
            out = subprocess.run(command, capture_output=True, text=True, check=False)
            lines = out.stdout.strip().splitlines()
            profiled = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}
            print(f"\n--- cProfile of the gateway, {protocol}, {max(counts)} links "
                  f"(profiled: {profiled.get('tps', float('nan')):.0f} tx/s, "
                  f"CPU {profiled.get('cpu_per_s', float('nan')):.3f} s/s): top 20 by own time ---")
            print("\n".join(lines[:-1]))
    biggest = [r for r in rows if r["links"] == max(counts)]
    values["target_met"] = all(r["eff_min"] >= 0.95 and r["cpu_per_s"] <= 0.5 for r in biggest)
    result(**values)


if __name__ == "__main__":
    main()
