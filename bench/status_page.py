"""Status page: ``GET /api/status`` latency with 64 links; line efficiency with and without the page open.

One gateway (in a child process) polls 64 paced SLC 150 simulators (``bench/simfarm.py``, its own
process) and serves ``[metrics]`` on loopback.  HTTP clients run in yet another process, so their
CPU is not the gateway's:

* latency: ``--requests`` sequential ``GET /api/status`` (a new connection each, as the page does),
  timed by the client from connect to the last byte: p50 / p99 / max; and the handler alone (the
  document built and encoded on the live event loop, no socket), as many times;
* line efficiency (as ``wire_efficiency.py``: line time of the frames exchanged / wall time,
  between two completed transactions) per link, in windows with no page open and with ``--pages``
  pages open (each asks ``/api/status`` and a 125-register view once a second, as ``status.js``),
  the two alternating (off, on, on, off, off, on ...) so that drift hits both alike; the ratio is of
  the medians over links, per pair of windows, and its median over the pairs.

    python bench/status_page.py [--links 64] [--requests 2000] [--pages 1] [--windows 6] [--duration S]

Targets: /api/status p99 < 5 ms with 64 links; efficiency with the page / without >= 0.99.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import subprocess
import sys
import time

from _benchlib import (
    PYTHON,
    SLC_CHAR_TIME,
    CompletionLog,
    SimFarm,
    gateway_config,
    percentile,
    print_machine,
    result,
    slc_link,
    table,
)

# The HTTP client process: sequential requests (latency) or pages polling once a second (load).
CLIENT = r"""
import http.client, json, sys, threading, time
port, mode, n = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
def get(path):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request("GET", path)
    body = conn.getresponse().read()
    conn.close()
    return body
if mode == "latency":
    times = []
    for _ in range(n):
        t0 = time.perf_counter(); get("/api/status"); times.append(time.perf_counter() - t0)
    print(json.dumps(times))
else:
    def page():
        while True:
            t0 = time.monotonic()
            get("/api/status"); get("/api/units/1/holding?start=0&count=125")
            time.sleep(max(0.0, t0 + 1.0 - time.monotonic()))
    for _ in range(n):
        threading.Thread(target=page, daemon=True).start()
    sys.stdin.read()  # until the parent closes it
"""


async def child(count: int, requests: int, pages: int, windows: int, duration: float) -> dict[str, object]:
    from gateway.app import Gateway
    from gateway.config import parse_config

    with SimFarm("slc150", count, paced=True, spin=0.0003) as farm:
        links = [slc_link(f"l{i}", url, i + 1) for i, url in enumerate(farm.urls())]
        text = gateway_config(links).replace("[logging]", '[metrics]\nlisten = "127.0.0.1:0"\n\n[logging]', 1)
        gateway = Gateway(parse_config(text))
        logs = [CompletionLog(unit) for unit in gateway.units]
        async with gateway:
            assert gateway.metrics is not None
            port = gateway.metrics.port
            await asyncio.sleep(3.0)  # warm-up: every link's first slow scan
            latency = await asyncio.create_subprocess_exec(
                PYTHON, "-c", CLIENT, str(port), "latency", str(requests), stdout=subprocess.PIPE)
            out, _ = await latency.communicate()
            times = sorted(json.loads(out))
            handler: list[float] = []  # the server's own work per request: the route, on the live loop
            for _ in range(requests):
                t0 = time.perf_counter()
                gateway.metrics.status.route("/api/status", "")
                handler.append(time.perf_counter() - t0)
                await asyncio.sleep(0.002)
            handler.sort()
            order = ["off", "on", "on", "off"] * ((windows + 3) // 4)
            measured: list[tuple[str, float]] = []
            for phase in order[:windows]:
                load = None
                if phase == "on":
                    load = await asyncio.create_subprocess_exec(
                        PYTHON, "-c", CLIENT, str(port), "pages", str(pages), stdin=subprocess.PIPE)
                    await asyncio.sleep(0.5)
                t0 = time.perf_counter()
                await asyncio.sleep(duration)
                t1 = time.perf_counter()
                if load is not None:
                    assert load.stdin is not None
                    load.stdin.close()
                    load.kill()
                    await load.wait()
                efficiencies = [log.window(t0, t1).efficiency(SLC_CHAR_TIME) for log in logs]
                measured.append((phase, statistics.median(efficiencies)))
            errors = sum(unit.driver.counters.errors for unit in gateway.units)
    ratios = [on / off for (a, off), (b, on) in zip(measured[0::2], measured[1::2], strict=False)
              if a == "off" and b == "on"]
    ratios += [on / off for (a, on), (b, off) in zip(measured[0::2], measured[1::2], strict=False)
               if a == "on" and b == "off"]
    return {
        "links": count, "requests": requests, "p50_ms": percentile(times, 50) * 1e3,
        "p99_ms": percentile(times, 99) * 1e3, "max_ms": times[-1] * 1e3,
        "handler_p50_ms": percentile(handler, 50) * 1e3, "handler_p99_ms": percentile(handler, 99) * 1e3,
        "windows": measured, "ratio_median": statistics.median(ratios), "ratios": ratios, "errors": errors,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--links", type=int, default=64)
    parser.add_argument("--requests", type=int, default=2000, help="sequential GET /api/status (latency)")
    parser.add_argument("--pages", type=int, default=1, help="pages open in the 'on' windows")
    parser.add_argument("--windows", type=int, default=6, help="measurement windows, alternating off/on (even)")
    parser.add_argument("--duration", type=float, default=8.0, help="seconds per window")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        run = child(args.links, args.requests, args.pages, args.windows, args.duration)
        print(json.dumps(asyncio.run(run)), flush=True)
        return
    print_machine()
    command = [PYTHON, __file__, "--child", "--links", str(args.links), "--requests", str(args.requests),
               "--pages", str(args.pages), "--windows", str(args.windows), "--duration", str(args.duration)]
    out = subprocess.run(command, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        print(out.stdout, out.stderr, file=sys.stderr)
        raise SystemExit("the gateway child failed")
    r = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"GET /api/status, {r['links']} links, {r['requests']} sequential requests (client side, new "
          f"connection each): p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms, max {r['max_ms']:.2f} ms; "
          f"the handler alone (building the document): p50 {r['handler_p50_ms']:.3f} ms, "
          f"p99 {r['handler_p99_ms']:.3f} ms")
    print(table(["window", "page", "median link efficiency"],
                [[i + 1, phase, eff] for i, (phase, eff) in enumerate(r["windows"])]))
    print(f"efficiency with {args.pages} page(s) open / without, per adjacent pair: "
          f"{', '.join(f'{x:.4f}' for x in r['ratios'])}; median {r['ratio_median']:.4f}; "
          f"link errors {r['errors']}")
    result(api_status_p50_ms=r["p50_ms"], api_status_p99_ms=r["p99_ms"], handler_p99_ms=r["handler_p99_ms"],
           efficiency_ratio=r["ratio_median"],
           target_met=r["p99_ms"] < 5.0 and r["ratio_median"] >= 0.99)


if __name__ == "__main__":
    main()
