"""OPC UA publishing under load: 64 links x 150 tags (9,600 monitored items) at 1 s publishing.

Beside ``bench/sparkplug_publishing.py``, with the same helpers.  Processes:

* one gateway (``python -m gateway run CONFIG``) with 64 DF1 links (SLC 5/04, 19200 8N1 paced) of 150
  tags each (N7:0-99, T4:0-9.ACC, F8:0-9, B3:0/0-29), ``[metrics]`` and ``[opcua]`` (the None endpoint);
* a simulator farm (``bench/simfarm.py --ladder``): the ladders run (N7:0 counts, B3:0/0 toggles, T4
  ACCs time), so nearly every poll brings changed values;
* an OPC UA client (``bench/opcua.py subscribe``, asyncua's client in its own process): one session,
  one subscription at a 1000 ms publishing interval, a monitored item on every one of the 9,600
  variables; it counts the notifications it receives;
* the load generator (``bench/loadgen.py``): C raw MBAP connections, FC3 reads of 100 holding
  registers of unit 1, closed loop and paced (``--rate`` a connection).

The same gateway process is measured with the subscription (``on``: the client connected, its 9,600
items created) and without (``off``: the client gone, its session and subscription deleted, so
the server publishes nothing), window after window, the order rotated per pair.  Per mode: Modbus
requests/s, p50 / p99, the gateway's CPU; ``on``: the data changes handed to the subscription per
second (``slc_gateway_opcua_data_changes_total``), the CPU of the server's publishing passes
(``slc_gateway_opcua_cpu_seconds_total``) and the client's CPU.  **CPU per data change**: the
gateway's CPU on minus off in the paced windows, over the changes per second.  The ratios on / off
of p50 and p99 are per pair, then their median.

Then the same client against a **bare asyncua server** (``bench/opcua.py bare``): 9,600 variables in
64 folders, with no gateway behind them, whose values it changes at the rate the gateway published
(``Server.write_attribute_value`` each 0.1 s, asyncua's own way for a server to change a value): its
CPU per data change with the subscription, and without (the values still written).

    python bench/opcua.py [--quick] [--rounds N] [--duration S] [--connections C] [--links N] [--rate R]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _benchlib import (
    HOST,
    PYTHON,
    REPO,
    SimFarm,
    df1_link,
    fetch,
    gateway_config,
    print_machine,
    result,
    table,
    wait_for,
)
from modbus_serving import free_port, process_cpu, run_load, wait_status

LINKS = 64
RATE = 100.0
READ = (1, 3, 0, 100)  # unit, function, address, count
#: 150 tags a link: N7:0-99, T4:0-9.ACC, F8:0-9 (float32), B3:0/0-29
MAP = [
    dict(table="holding", start=0, address="N7:0", count=100),
    dict(table="input", start=0, address="T4:0.ACC", count=10),
    dict(table="input", start=100, address="F8:0", count=10, type="float32"),
    dict(table="coil", start=0, address="B3:0/0", count=30),
]
TAGS = ([f"N7:{n}" for n in range(100)] + [f"T4:{n}.ACC" for n in range(10)] + [f"F8:{n}" for n in range(10)]
        + [f"B3:{n // 16}/{n % 16}" for n in range(30)])
PUBLISHING_MS = 1000.0


# --- the client and the bare server (subcommands, each its own process) --------------------------


async def subscribe(url: str, links: int) -> None:
    """Subscribe to every tag of ``links`` links; print ``ready``, then the count on each line of stdin."""
    from asyncua import Client, ua

    count = 0

    class Handler:
        def datachange_notification(self, *_: object) -> None:
            nonlocal count
            count += 1

        def status_change_notification(self, status: object) -> None:
            print(json.dumps({"status_change": str(status)}), file=sys.stderr, flush=True)

    async with Client(url, timeout=60) as client:
        ns = await client.get_namespace_index("urn:slc-gateway")
        subscription = await client.create_subscription(PUBLISHING_MS, Handler())
        nodes = [client.get_node(ua.NodeId(f"plc{i:02d}.{tag}", ns)) for i in range(links) for tag in TAGS]
        for first in range(0, len(nodes), 1000):
            await subscription.subscribe_data_change(nodes[first:first + 1000], sampling_interval=PUBLISHING_MS)
        print(json.dumps({"ready": len(nodes)}), flush=True)
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader()
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
        while await reader.readline():
            print(json.dumps({"count": count, "cpu": time.process_time()}), flush=True)


async def bare(port: int, links: int, rate: float) -> None:
    """A bare asyncua server with the same 9,600 variables, changing ``rate`` values a second."""
    from asyncua import Server, ua

    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://{HOST}:{port}")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    ns = await server.register_namespace("urn:slc-gateway")
    ids = []
    for i in range(links):
        name = f"plc{i:02d}"
        folder = await server.nodes.objects.add_folder(ua.NodeId(name, ns), ua.QualifiedName(name, ns))
        for tag in TAGS:
            node_id = ua.NodeId(f"plc{i:02d}.{tag}", ns)
            await folder.add_variable(node_id, ua.QualifiedName(tag, ns), ua.Variant(0, ua.VariantType.Int16))
            ids.append(node_id)
    async with server:
        print(json.dumps({"ready": len(ids)}), flush=True)
        step, k, value = 0.1, 0, 0
        per_step = max(1, round(rate * step))
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        while True:
            next_at += step
            await asyncio.sleep(max(0.0, next_at - loop.time()))
            value = (value + 1) % 30000
            for _ in range(per_step):
                await server.write_attribute_value(ids[k], ua.DataValue(ua.Variant(value, ua.VariantType.Int16)))
                k = (k + 1) % len(ids)


# --- the benchmark ---------------------------------------------------------------------------------


class Subscriber:
    """The client process: started (``on``) and stopped (``off``)."""

    def __init__(self, url: str, links: int) -> None:
        self.url, self.links = url, links
        self.process: subprocess.Popen[str] | None = None

    def start(self) -> float:
        """Start it; the seconds its 9,600 items took to create."""
        started = time.monotonic()
        self.process = subprocess.Popen([PYTHON, __file__, "subscribe", self.url, str(self.links)],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(REPO),
                                        bufsize=1)
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if "ready" not in line:
            raise SystemExit(f"the OPC UA client did not subscribe: {line!r}")
        return time.monotonic() - started

    def figures(self) -> tuple[int, float]:
        """(notifications received, the client's CPU seconds) so far."""
        assert self.process is not None and self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write("?\n")
        self.process.stdin.flush()
        answer = json.loads(self.process.stdout.readline())
        return int(answer["count"]), float(answer["cpu"])

    def stop(self) -> None:
        """Close its standard input: it closes its session (and so its subscription) and exits."""
        if self.process is not None:
            assert self.process.stdin is not None
            self.process.stdin.close()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
            self.process = None


def server_figures(metrics_port: int) -> tuple[float, float, float]:
    """(data changes, CPU of the publishing passes, monitored items) of the gateway's server so far."""
    text = fetch(metrics_port, "/metrics")

    def value(name: str) -> float:
        found = re.search(rf"^slc_gateway_opcua_{name} (\S+)$", text, re.MULTILINE)
        return float(found.group(1)) if found else 0.0

    return value("data_changes_total"), value("cpu_seconds_total"), value("monitored_items")


def listening(port: int) -> bool:
    import socket

    try:
        with socket.create_connection((HOST, port), timeout=1):
            return True
    except OSError:
        return False



def measure(port: int, pid: int, metrics_port: int, subscriber: Subscriber, connections: int, duration: float,
            warmup: float, rate: float) -> dict[str, float]:
    changes0, busy0, _ = server_figures(metrics_port)
    got0, client0 = subscriber.figures() if subscriber.process else (0, 0.0)
    t0 = time.perf_counter()
    unit, function, address, count = READ
    answer = run_load(port, pid, unit, function, address, count, connections, duration, warmup, rate=rate)
    elapsed = time.perf_counter() - t0
    changes, busy, _ = server_figures(metrics_port)
    got, client = subscriber.figures() if subscriber.process else (got0, client0)
    numbers = {key: float(str(answer[key])) for key in ("rps", "p50", "p99", "server_cpu_per_s", "exceptions")}
    return {"rps": numbers["rps"], "p50": numbers["p50"], "p99": numbers["p99"], "cpu": numbers["server_cpu_per_s"],
            "exceptions": numbers["exceptions"], "changes": (changes - changes0) / elapsed,
            "received": (got - got0) / elapsed, "server_cpu": (busy - busy0) / elapsed,
            "client_cpu": (client - client0) / elapsed}


def bare_figures(links: int, rate: float, duration: float) -> dict[str, float]:
    """The bare asyncua server changing ``rate`` values a second: its CPU per change with and without the client."""
    port = free_port()
    server = subprocess.Popen([PYTHON, __file__, "bare", str(port), str(links), str(rate)], stdout=subprocess.PIPE,
                              text=True, cwd=str(REPO))
    try:
        assert server.stdout is not None
        if "ready" not in server.stdout.readline():
            raise SystemExit("the bare asyncua server did not start")
        time.sleep(1.0)
        c0, t0 = process_cpu(server.pid), time.perf_counter()
        time.sleep(duration)
        alone = (process_cpu(server.pid) - c0) / (time.perf_counter() - t0)
        subscriber = Subscriber(f"opc.tcp://{HOST}:{port}", links)
        subscriber.start()
        try:
            time.sleep(2.0)
            got0, _ = subscriber.figures()
            c0, t0 = process_cpu(server.pid), time.perf_counter()
            time.sleep(duration)
            elapsed = time.perf_counter() - t0
            with_client = (process_cpu(server.pid) - c0) / elapsed
            got, _ = subscriber.figures()
        finally:
            subscriber.stop()
    finally:
        server.terminate()
        server.wait(10)
    received = (got - got0) / elapsed
    return {"cpu_with": with_client, "cpu_without": alone, "received": received,
            "us_per_change": 1e6 * with_client / rate, "us_per_change_publishing": 1e6 * (with_client - alone) / rate}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "subscribe":
        asyncio.run(subscribe(sys.argv[2], int(sys.argv[3])))
        return
    if len(sys.argv) > 1 and sys.argv[1] == "bare":
        asyncio.run(bare(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])))
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="8 links, short windows, one pair (smoke test)")
    parser.add_argument("--rounds", type=int, default=0, help="pairs of windows (default 4; quick 1)")
    parser.add_argument("--duration", type=float, default=0.0, help="load window, s (default 3; quick 1)")
    parser.add_argument("--connections", type=int, default=10)
    parser.add_argument("--links", type=int, default=0, help=f"links (default {LINKS}; quick 8)")
    parser.add_argument("--rate", type=float, default=RATE, help=f"paced: requests/s per connection ({RATE:g})")
    args = parser.parse_args()
    rounds = args.rounds or (1 if args.quick else 4)
    duration = args.duration or (1.0 if args.quick else 3.0)
    links = args.links or (8 if args.quick else LINKS)
    warmup = 0.3 if args.quick else 0.5
    print_machine()
    loads = {"closed": 0.0, "paced": args.rate}
    print(f"{links} DF1 links x {len(TAGS)} tags = {links * len(TAGS)} monitored items at {PUBLISHING_MS:g} ms "
          f"publishing (paced 19200 8N1, ladders running); FC3 100 registers of unit 1, {args.connections} "
          f"connections (closed loop; paced: {args.rate:g}/s each), {duration:g} s windows, {rounds} pairs")
    rows: dict[str, dict[str, list[dict[str, float]]]] = {load: {"off": [], "on": []} for load in loads}
    subscribe_seconds: list[float] = []
    with tempfile.TemporaryDirectory() as tmp, SimFarm("slc504", links, paced=True, ladder=True) as farm:
        port, metrics_port, ua_port = free_port(), free_port(), free_port()
        text = gateway_config([df1_link(f"plc{i:02d}", url, i + 1, MAP, baudrate=19200, timeout=0.3)
                               for i, url in enumerate(farm.urls()[:links])], listen=f"{HOST}:{port}")
        text = text.replace("[logging]", f'[metrics]\nlisten = "{HOST}:{metrics_port}"\n\n[opcua]\n'
                                         f'listen = "opc.tcp://{HOST}:{ua_port}"\nsecurity = ["None"]\n\n[logging]', 1)
        path = Path(tmp) / "gateway.toml"
        path.write_text(text, encoding="utf-8")
        gateway = subprocess.Popen([PYTHON, "-m", "gateway", "run", str(path)], cwd=str(REPO),
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        subscriber = Subscriber(f"opc.tcp://{HOST}:{ua_port}", links)
        try:
            wait_status(port, 60)
            # the address space is built after the Modbus listener
            wait_for(lambda: listening(ua_port), 120, "the server")
            for r in range(rounds):
                for mode in (("off", "on") if r % 2 == 0 else ("on", "off")):
                    if mode == "on" and subscriber.process is None:
                        subscribe_seconds.append(subscriber.start())
                        wait_for(lambda: server_figures(metrics_port)[2] == links * len(TAGS), 60, "the server")
                    elif mode == "off":
                        subscriber.stop()
                        wait_for(lambda: server_figures(metrics_port)[2] == 0, 60, "the server")
                    time.sleep(1.5)
                    for load, rate in loads.items():
                        rows[load][mode].append(measure(port, gateway.pid, metrics_port, subscriber,
                                                        args.connections, duration, warmup, rate))
        finally:
            subscriber.stop()
            gateway.terminate()
            try:
                gateway.wait(10)
            except subprocess.TimeoutExpired:
                gateway.kill()
                gateway.wait()
    figures = {load: report(load, by_mode) for load, by_mode in rows.items()}
    paced = rows["paced"]
    changes = statistics.median(r["changes"] for r in paced["on"])
    extra = statistics.median(on["cpu"] - off["cpu"] for on, off in zip(paced["on"], paced["off"], strict=True))
    per_change = 1e6 * extra / changes if changes else float("nan")
    passes = 1e6 * statistics.median(r["server_cpu"] for r in paced["on"]) / changes if changes else float("nan")
    print(f"\ndata changes published: {changes:.0f}/s; gateway CPU on - off (paced, median of pairs): {extra:.3f} s/s "
          f"= {per_change:.0f} us a change (of it the server's publishing passes: {passes:.0f} us); "
          f"{links * len(TAGS)} items created in {statistics.median(subscribe_seconds):.1f} s")
    bare_rate = changes or 100.0
    b = bare_figures(links, bare_rate, duration * 2)
    print(f"bare asyncua server changing {bare_rate:.0f} values/s: CPU {b['cpu_with']:.3f} s/s with the client "
          f"({b['received']:.0f} notifications/s received), {b['cpu_without']:.3f} without: "
          f"{b['us_per_change']:.0f} us a change in all, {b['us_per_change_publishing']:.0f} us for publishing it")
    result(**{f"{load}_{key}": value for load, numbers in figures.items() for key, value in numbers.items()},
           changes_per_s=changes, us_per_change=per_change, passes_us_per_change=passes,
           bare_us_per_change=b["us_per_change"], bare_us_per_change_publishing=b["us_per_change_publishing"])


def report(load: str, rows: dict[str, list[dict[str, float]]]) -> dict[str, float]:
    med = {mode: {key: statistics.median(r[key] for r in runs) for key in runs[0]} for mode, runs in rows.items()}
    keys = ("rps", "p50", "p99", "cpu", "exceptions", "changes", "received", "server_cpu", "client_cpu")
    print(f"\n{load} load:")
    print(table(("opcua", "req/s", "p50 ms", "p99 ms", "CPU s/s", "exceptions", "changes/s", "received/s",
                 "passes CPU s/s", "client CPU s/s"),
                [(mode, *(f"{med[mode][k]:.3g}" for k in keys)) for mode in ("off", "on")]))
    pairs = list(zip(rows["on"], rows["off"], strict=True))
    ratio = {k: statistics.median(on[k] / off[k] if off[k] else float("nan") for on, off in pairs)
             for k in ("rps", "p50", "p99", "cpu")}
    print("pairs (on / off): p50 " + ", ".join(f"{on['p50'] / off['p50']:.2f}" for on, off in pairs)
          + "; p99 " + ", ".join(f"{on['p99'] / off['p99']:.2f}" for on, off in pairs))
    print(f"on / off: req/s {ratio['rps']:.3f}, p50 {ratio['p50']:.3f}, p99 {ratio['p99']:.3f}, CPU {ratio['cpu']:.3f}")
    return {"p50_ratio": ratio["p50"], "p99_ratio": ratio["p99"], "rps_ratio": ratio["rps"], "cpu_ratio": ratio["cpu"]}


if __name__ == "__main__":
    sys.exit(main())
