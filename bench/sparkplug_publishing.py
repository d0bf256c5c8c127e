"""Sparkplug publishing under load: what 64 links publishing on change cost the Modbus answers.

Beside ``bench/modbus_serving.py``, with its helpers.  Processes:

* one gateway (``python -m gateway run CONFIG``) with 64 DF1 links (SLC 5/04, 19200 8N1 paced, the
  benchmark map: N7:0-99, T4:0-9.ACC, F8:0-9, B3 64 bits: 184 metrics a link), ``[metrics]`` and
  ``[sparkplug]`` (``check_interval`` 0.5 s, the other keys their defaults);
* a simulator farm (``bench/simfarm.py --ladder``): the 64 controllers with their ladders running
  (N7:0 counts, B3:0/0 toggles, T4 ACCs time), so nearly every poll brings changed values;
* Debian's mosquitto on a free loopback port, and a subscriber to ``spBv1.0/#`` in this process
  (a thread) counting what the broker delivers;
* the load generator (``bench/loadgen.py``): C raw MBAP connections, each a closed loop of FC3
  reads of 100 holding registers of unit 1.

The same gateway process is measured publishing (``on``: the broker up, the node online) and not
publishing (``off``: the broker stopped, the node waiting to reconnect: its cache listeners still
run, nothing is read, built or sent), window after window, the order rotated per pair; before an
``on`` window the broker is started and the node's births are waited for.  One process, one farm,
windows next to each other: the machine (shared, often loaded) is as alike as it gets for both.

Each mode gets two load windows: closed loop (each connection sends its next request as soon as
the reply is in: the machine's 2 cores are saturated, so req/s and latency show CPU taken from the
answers by anything, the broker and subscriber included) and paced (``--rate`` requests/s per
connection, 1000/s in all by default, well below what the gateway serves: latency there shows
answers waiting, not throughput).  Each row is the mode's median window: Modbus requests/s, latency
p50 / p99, the gateway's CPU per second and per request, and (``on``) the Sparkplug messages
published per second (``/metrics``) and delivered to the subscriber, the edge node's own CPU on the
event loop per second and its longest step (``sparkplug_cpu_seconds_total``,
``sparkplug_longest_step_seconds``: reading the image, building births and DDATA; not paho's
packets and socket writes), which bounds what a Modbus answer can wait behind it, and the CPU the
broker and the subscriber took on the same machine.  "Publishing costs no Modbus answer time" reads
as the ``on`` / ``off`` ratios of p50 and p99, per pair, their median.  ``--source DIR`` runs the
gateway from another tree (an older commit exported with ``git archive``) for a before / after.

    python bench/sparkplug_publishing.py [--quick] [--rounds N] [--duration S] [--connections C] [--links N]
                                         [--rate R] [--source DIR]
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
import threading
import time
from pathlib import Path

from _benchlib import (
    DF1_MAP,
    HOST,
    PYTHON,
    REPO,
    Broker,
    SimFarm,
    df1_link,
    fetch,
    gateway_config,
    mosquitto_path,
    mosquitto_required,
    print_machine,
    result,
    table,
    wait_for,
)
from modbus_serving import free_port, process_cpu, run_load, wait_status

LINKS = 64
#: paced windows: requests per second per connection (10 connections: 1000/s, well below what the gateway serves)
RATE = 100.0
READ = (1, 3, 0, 100)  # unit, function, address, count


def mosquitto() -> str | None:
    """The broker; without it the benchmark says so and stops (a failure with SLC_GATEWAY_REQUIRE_MOSQUITTO=1)."""
    path = mosquitto_path()
    if path is None:
        print("MOSQUITTO NOT INSTALLED: this benchmark needs a broker (Debian package mosquitto)")
        if mosquitto_required():
            raise SystemExit("mosquitto is required (SLC_GATEWAY_REQUIRE_MOSQUITTO=1)")
        result(skipped="no_mosquitto")
    return path


class Subscriber(threading.Thread):
    """Counts the messages the broker delivers under spBv1.0/# (aiomqtt, in its own thread; reconnects)."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.count = 0
        self.clock = time.CLOCK_THREAD_CPUTIME_ID  # until run() takes its own thread's

    def run(self) -> None:
        self.clock = time.pthread_getcpuclockid(threading.get_ident())
        asyncio.run(self._run())

    def cpu(self) -> float:
        """CPU seconds of this thread so far (its share of the machine while the broker delivers)."""
        return time.clock_gettime(self.clock)

    async def _run(self) -> None:
        import aiomqtt

        while True:
            try:
                async with aiomqtt.Client(HOST, self.port) as client:
                    await client.subscribe("spBv1.0/#")
                    async for _ in client.messages:
                        self.count += 1
            except aiomqtt.MqttError:
                await asyncio.sleep(0.1)  # the broker is stopped between windows


def node_figures(metrics_port: int) -> tuple[float, float, float]:
    """(Sparkplug messages handed to the broker, CPU of the edge node's steps, its longest step) so far."""
    text = fetch(metrics_port, "/metrics")

    def values(name: str) -> list[float]:
        return [float(m) for m in re.findall(rf"^slc_gateway_sparkplug_{name}(?:\{{[^}}]*\}})? (\S+)$", text,
                                             re.MULTILINE)]

    return sum(values("messages_published_total")), sum(values("cpu_seconds_total")), \
        max(values("longest_step_seconds"), default=0.0)


def node_state(metrics_port: int) -> dict[str, object]:
    state: dict[str, object] = json.loads(fetch(metrics_port, "/api/status"))["sparkplug"]
    return state



def config(farm: SimFarm, links: int, port: int, metrics_port: int, broker_port: int, state: Path) -> str:
    text = gateway_config([df1_link(f"plc{i:02d}", url, i + 1, DF1_MAP, baudrate=19200, timeout=0.3)
                           for i, url in enumerate(farm.urls()[:links])], listen=f"{HOST}:{port}")
    return text.replace("[logging]", f'[metrics]\nlisten = "{HOST}:{metrics_port}"\n\n'
                                      f'[sparkplug]\nbroker = "mqtt://{HOST}:{broker_port}"\ngroup_id = "bench"\n'
                                      f'edge_node_id = "gw"\nstate_file = "{state}"\ncheck_interval = 0.5\n'
                                      "reconnect_min = 0.2\nreconnect_max = 0.5\n\n[logging]", 1)


def prepare(mode: str, metrics_port: int, broker: Broker, links: int) -> None:
    """``on``: the broker up and the births out; ``off``: the broker stopped, the node disconnected."""
    if mode == "on":
        broker.start()
        wait_for(lambda: node_state(metrics_port)["state"] == "online"
                 and node_state(metrics_port)["devices_online"] == links, 30, "the edge node", step=0.1)
    else:
        broker.stop()
        wait_for(lambda: node_state(metrics_port)["state"] == "disconnected", 10, "the edge node", step=0.1)
    time.sleep(0.5)


def measure(port: int, pid: int, metrics_port: int, broker: Broker, subscriber: Subscriber, connections: int,
            duration: float, warmup: float, rate: float) -> dict[str, float]:
    """One load window (``rate`` requests/s per connection; 0: closed loop) in the mode prepared."""
    broker_pid = broker.process.pid if broker.process is not None else 0
    (sent0, busy0, _), got0, t0 = node_figures(metrics_port), subscriber.count, time.perf_counter()
    mosquitto0, subscriber0 = process_cpu(broker_pid) if broker_pid else 0.0, subscriber.cpu()
    unit, function, address, count = READ
    answer = run_load(port, pid, unit, function, address, count, connections, duration, warmup, rate=rate)
    elapsed = time.perf_counter() - t0
    sent, busy, longest = node_figures(metrics_port)
    numbers = {key: float(str(answer[key])) for key in ("rps", "p50", "p99", "server_cpu_per_s",
                                                          "server_us_per_request", "exceptions")}
    return {"rps": numbers["rps"], "p50": numbers["p50"], "p99": numbers["p99"], "cpu": numbers["server_cpu_per_s"],
            "us": numbers["server_us_per_request"], "exceptions": numbers["exceptions"],
            "published": (sent - sent0) / elapsed, "delivered": (subscriber.count - got0) / elapsed,
            "node_cpu": (busy - busy0) / elapsed, "longest_ms": longest * 1e3 if broker_pid else 0.0,
            "others_cpu": ((process_cpu(broker_pid) - mosquitto0 if broker_pid else 0.0)
                           + subscriber.cpu() - subscriber0) / elapsed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="8 links, short windows, one pair (smoke test)")
    parser.add_argument("--rounds", type=int, default=0, help="pairs of windows (default 6; quick 1)")
    parser.add_argument("--duration", type=float, default=0.0, help="load window, s (default 3; quick 1)")
    parser.add_argument("--connections", type=int, default=10)
    parser.add_argument("--links", type=int, default=0, help=f"links (default {LINKS}; quick 8)")
    parser.add_argument("--rate", type=float, default=RATE,
                        help=f"paced windows: requests/s per connection (default {RATE:g}; 0: no paced windows)")
    parser.add_argument("--source", type=Path, default=REPO,
                        help="the gateway's source tree to run (default this one; e.g. an older commit, "
                             "exported with git archive, for a before / after)")
    args = parser.parse_args()
    broker_path = mosquitto()
    if broker_path is None:
        return
    rounds = args.rounds or (1 if args.quick else 6)
    duration = args.duration or (1.0 if args.quick else 3.0)
    links = args.links or (8 if args.quick else LINKS)
    warmup = 0.3 if args.quick else 0.5
    print_machine()
    loads = {"closed": 0.0, "paced": args.rate} if args.rate else {"closed": 0.0}
    print(f"{links} DF1 links (paced 19200 8N1, ladders running), FC3 100 registers of unit 1, "
          f"{args.connections} connections (closed loop; paced: {args.rate:g} requests/s each), "
          f"{duration:g} s windows, {rounds} pairs, gateway from {args.source}")
    rows: dict[str, dict[str, list[dict[str, float]]]] = {load: {"off": [], "on": []} for load in loads}
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        broker = Broker(broker_path, directory)
        broker.start()
        subscriber = Subscriber(broker.port)
        subscriber.start()
        with SimFarm("slc504", links, paced=True, ladder=True) as farm:
            port, metrics_port = free_port(), free_port()
            path = directory / "gateway.toml"
            path.write_text(config(farm, links, port, metrics_port, broker.port, directory / "bdseq.json"),
                            encoding="utf-8")
            gateway = subprocess.Popen([PYTHON, "-m", "gateway", "run", str(path)], cwd=str(args.source),
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                wait_status(port)
                for r in range(rounds):
                    for mode in (("off", "on") if r % 2 == 0 else ("on", "off")):
                        prepare(mode, metrics_port, broker, links)
                        for load, rate in loads.items():
                            rows[load][mode].append(measure(port, gateway.pid, metrics_port, broker, subscriber,
                                                            args.connections, duration, warmup, rate))
            finally:
                gateway.terminate()
                try:
                    gateway.wait(10)
                except subprocess.TimeoutExpired:
                    gateway.kill()
                    gateway.wait()
                broker.stop()
    figures = {load: report(load, by_mode) for load, by_mode in rows.items()}
    result(**{f"{load}_{key}": value for load, numbers in figures.items() for key, value in numbers.items()})


def report(load: str, rows: dict[str, list[dict[str, float]]]) -> dict[str, float]:
    med = {mode: {key: statistics.median(r[key] for r in runs) for key in runs[0]} for mode, runs in rows.items()}
    keys = ("rps", "p50", "p99", "cpu", "us", "exceptions", "published", "delivered", "node_cpu", "longest_ms",
            "others_cpu")
    print(f"\n{load} load:")
    print(table(("sparkplug", "req/s", "p50 ms", "p99 ms", "CPU s/s", "CPU us/req", "exceptions",
                 "published/s", "delivered/s", "edge node CPU s/s", "longest step ms", "broker+subscriber CPU s/s"),
                [(mode, *(f"{med[mode][k]:.3g}" for k in keys)) for mode in ("off", "on")]))
    # the ratio of each pair (two windows next to each other), then their median
    pairs = list(zip(rows["on"], rows["off"], strict=True))
    ratio = {k: statistics.median(on[k] / off[k] if off[k] else float("nan") for on, off in pairs)
             for k in ("rps", "p50", "p99", "cpu")}
    print("pairs (on / off, p50): " + ", ".join(f"{on['p50'] / off['p50']:.2f}" for on, off in pairs))
    print(f"on / off: req/s {ratio['rps']:.3f}, p50 {ratio['p50']:.3f}, p99 {ratio['p99']:.3f}, "
          f"CPU {ratio['cpu']:.3f}")
    return {"published_per_s": med["on"]["published"], "delivered_per_s": med["on"]["delivered"],
            "node_cpu_per_s": med["on"]["node_cpu"], "longest_step_ms": max(r["longest_ms"] for r in rows["on"]),
            "others_cpu_per_s": med["on"]["others_cpu"], "p50_ratio": ratio["p50"], "p99_ratio": ratio["p99"],
            "rps_ratio": ratio["rps"], "cpu_ratio": ratio["cpu"]}


if __name__ == "__main__":
    sys.exit(main())
