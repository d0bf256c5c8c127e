"""Sparkplug publishing under load: what 64 links publishing on change cost the Modbus answers.

Beside ``bench/modbus_serving.py``, with its helpers.  Processes:

* the gateway (``python -m gateway run CONFIG``) with 64 DF1 links (SLC 5/04, 19200 8N1 paced,
  the benchmark map: N7:0-99, T4:0-9.ACC, F8:0-9, B3 64 bits) and ``[metrics]``, in two
  configurations: ``off`` (no ``[sparkplug]``) and ``on`` (``[sparkplug]`` to the broker below,
  ``check_interval`` 0.5 s);
* one simulator farm per gateway (``bench/simfarm.py --ladder``): 64 controllers with their ladders
  running, so every poll brings changed values (N7:0 counts, B3:0/0 toggles, T4 ACCs time):
  every link has a DDATA to publish at nearly every poll;
* Debian's mosquitto on a free loopback port, and a subscriber to ``spBv1.0/#`` in this process
  (a thread) counting what the broker delivers;
* the load generator (``bench/loadgen.py``): C raw MBAP connections, each a closed loop of FC3
  reads of 100 holding registers of unit 1.

Both gateways run all the time, each on its own farm of 64 simulators, so the machine carries the
same load whichever is measured; the load generator alternates between them (order rotated per
pair), window after window.  Each row is the configuration's median window: Modbus requests/s,
latency p50 / p99, the gateway's CPU per second and per request, and the Sparkplug messages
published per second by the measured gateway (from ``/metrics``) and delivered to the subscriber
during its window (from the ``on`` gateway, which publishes in both windows).  "Publishing costs no
Modbus answer time" reads as: the ``on`` / ``off`` ratios of p50 and p99, taken per pair (the
two windows next to each other), their median; and, steadier on a shared machine, the edge
node's own CPU on the event loop per second and its longest step (from ``/metrics``:
``sparkplug_cpu_seconds_total``, ``sparkplug_longest_step_seconds``), which bounds what a Modbus
answer can wait behind it.

    python bench/sparkplug_publishing.py [--quick] [--rounds N] [--duration S] [--connections C] [--links N]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from _benchlib import DF1_MAP, HOST, PYTHON, REPO, SimFarm, df1_link, gateway_config, print_machine, result, table
from modbus_serving import free_port, run_load, wait_status

LINKS = 64
READ = (1, 3, 0, 100)  # unit, function, address, count


def mosquitto() -> str | None:
    """The broker; without it the benchmark says so and stops (a failure with SLC_GATEWAY_REQUIRE_MOSQUITTO=1)."""
    path = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
    if path is None:
        print("MOSQUITTO NOT INSTALLED: this benchmark needs a broker (Debian package mosquitto)")
        if os.environ.get("SLC_GATEWAY_REQUIRE_MOSQUITTO") == "1":
            raise SystemExit("mosquitto is required (SLC_GATEWAY_REQUIRE_MOSQUITTO=1)")
        result(skipped="no_mosquitto")
    return path


class Subscriber(threading.Thread):
    """Counts the messages the broker delivers under spBv1.0/# (aiomqtt, in its own thread and loop)."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.count = 0
        self.ready = threading.Event()

    def run(self) -> None:
        asyncio.run(self._run())

    async def _run(self) -> None:
        import aiomqtt

        try:
            async with aiomqtt.Client(HOST, self.port) as client:
                await client.subscribe("spBv1.0/#")
                self.ready.set()
                async for _ in client.messages:
                    self.count += 1
        except aiomqtt.MqttError:
            pass  # the broker stopped: the benchmark is over


def node_figures(metrics_port: int) -> tuple[float, float, float]:
    """(Sparkplug messages handed to the broker, CPU of the edge node's steps, its longest step) so far,
    from the gateway's /metrics (zeros without [sparkplug])."""
    with urllib.request.urlopen(f"http://{HOST}:{metrics_port}/metrics", timeout=5) as reply:
        text = reply.read().decode()

    def values(name: str) -> list[float]:
        return [float(m) for m in re.findall(rf"^slc_gateway_sparkplug_{name}(?:\{{[^}}]*\}})? (\S+)$", text,
                                             re.MULTILINE)]

    return sum(values("messages_published_total")), sum(values("cpu_seconds_total")), \
        max(values("longest_step_seconds"), default=0.0)


def config(farm: SimFarm, links: int, metrics_port: int, broker_port: int | None, state: Path) -> str:
    text = gateway_config([df1_link(f"plc{i:02d}", url, i + 1, DF1_MAP, baudrate=19200, timeout=0.3)
                           for i, url in enumerate(farm.urls()[:links])])
    text = text.replace("[logging]", f'[metrics]\nlisten = "{HOST}:{metrics_port}"\n\n[logging]', 1)
    if broker_port is not None:
        text = text.replace("[logging]", f'[sparkplug]\nbroker = "mqtt://{HOST}:{broker_port}"\ngroup_id = "bench"\n'
                                          f'edge_node_id = "gw"\nstate_file = "{state}"\ncheck_interval = 0.5\n\n'
                                          "[logging]", 1)
    return text


class Gateway:
    """A gateway process (``python -m gateway run``) on its own simulator farm, with or without [sparkplug]."""

    def __init__(self, mode: str, directory: Path, links: int, broker_port: int) -> None:
        self.mode = mode
        self.farm = SimFarm("slc504", links, paced=True, ladder=True)
        self.port, self.metrics_port = free_port(), free_port()
        path = directory / f"{mode}.toml"
        text = config(self.farm, links, self.metrics_port, broker_port if mode == "on" else None,
                      directory / "bdseq.json")
        path.write_text(text.replace(f'listen = "{HOST}:0"', f'listen = "{HOST}:{self.port}"', 1), encoding="utf-8")
        self.process = subprocess.Popen([PYTHON, "-m", "gateway", "run", str(path)], cwd=str(REPO),
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def close(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.farm.close()


def measure(gateway: Gateway, subscriber: Subscriber, connections: int, duration: float,
            warmup: float) -> dict[str, float]:
    """One load window on ``gateway`` (the other one runs on meanwhile, unloaded)."""
    (sent0, busy0, _), got0, t0 = node_figures(gateway.metrics_port), subscriber.count, time.perf_counter()
    unit, function, address, count = READ
    answer = run_load(gateway.port, gateway.process.pid, unit, function, address, count, connections, duration,
                      warmup)
    elapsed = time.perf_counter() - t0
    sent, busy, longest = node_figures(gateway.metrics_port)
    got = subscriber.count - got0
    numbers = {key: float(str(answer[key])) for key in ("rps", "p50", "p99", "server_cpu_per_s",
                                                          "server_us_per_request", "exceptions")}
    return {"rps": numbers["rps"], "p50": numbers["p50"], "p99": numbers["p99"], "cpu": numbers["server_cpu_per_s"],
            "us": numbers["server_us_per_request"], "exceptions": numbers["exceptions"],
            "published": (sent - sent0) / elapsed, "delivered": got / elapsed, "node_cpu": (busy - busy0) / elapsed,
            "longest_ms": longest * 1e3}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="8 links, short windows, one pair (smoke test)")
    parser.add_argument("--rounds", type=int, default=0, help="pairs of windows (default 6; quick 1)")
    parser.add_argument("--duration", type=float, default=0.0, help="load window, s (default 3; quick 1)")
    parser.add_argument("--connections", type=int, default=10)
    parser.add_argument("--links", type=int, default=0, help=f"links (default {LINKS}; quick 8)")
    args = parser.parse_args()
    broker_path = mosquitto()
    if broker_path is None:
        return
    rounds = args.rounds or (1 if args.quick else 6)
    duration = args.duration or (1.0 if args.quick else 3.0)
    links = args.links or (8 if args.quick else LINKS)
    warmup = 0.3 if args.quick else 0.5
    print_machine()
    print(f"{links} DF1 links per gateway (paced 19200 8N1, ladders running), FC3 100 registers of unit 1, "
          f"{args.connections} connections, {duration:g} s windows, {rounds} pairs")
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        broker_port = free_port()
        (directory / "mosquitto.conf").write_text(f"listener {broker_port} {HOST}\nallow_anonymous true\n"
                                                  "persistence false\nlog_dest none\n", encoding="utf-8")
        broker = subprocess.Popen([broker_path, "-c", str(directory / "mosquitto.conf")],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        gateways: list[Gateway] = []
        try:
            time.sleep(0.5)
            subscriber = Subscriber(broker_port)
            subscriber.start()
            if not subscriber.ready.wait(10):
                raise SystemExit("cannot subscribe to the broker")
            gateways = [Gateway(mode, directory, links, broker_port) for mode in ("off", "on")]
            for gateway in gateways:
                wait_status(gateway.port)
            time.sleep(3.0)  # the links' first polls, the births
            rows: dict[str, list[dict[str, float]]] = {"off": [], "on": []}
            for r in range(rounds):
                for gateway in (gateways if r % 2 == 0 else gateways[::-1]):
                    rows[gateway.mode].append(measure(gateway, subscriber, args.connections, duration, warmup))
        finally:
            for gateway in gateways:
                gateway.close()
            broker.terminate()
            broker.wait(5)
    report(rows)


def report(rows: dict[str, list[dict[str, float]]]) -> None:
    med = {mode: {key: statistics.median(r[key] for r in runs) for key in runs[0]} for mode, runs in rows.items()}
    keys = ("rps", "p50", "p99", "cpu", "us", "exceptions", "published", "delivered", "node_cpu", "longest_ms")
    print(table(("sparkplug", "req/s", "p50 ms", "p99 ms", "CPU s/s", "CPU us/req", "exceptions",
                 "published/s", "delivered/s", "edge node CPU s/s", "longest step ms"),
                [(mode, *(f"{med[mode][k]:.3g}" for k in keys)) for mode in ("off", "on")]))
    # the ratio of each pair (two windows next to each other, the same load on the machine), then their median
    ratio = {k: statistics.median(on[k] / off[k] if off[k] else float("nan") for on, off in zip(rows["on"], rows["off"],
                                                                                                  strict=True))
             for k in ("rps", "p50", "p99", "cpu")}
    print("pairs (on / off, p50): " + ", ".join(f"{on['p50'] / off['p50']:.2f}" for on, off in
                                                zip(rows["on"], rows["off"], strict=True)))
    print(f"on / off: req/s {ratio['rps']:.3f}, p50 {ratio['p50']:.3f}, p99 {ratio['p99']:.3f}, "
          f"CPU {ratio['cpu']:.3f}")
    result(published_per_s=med["on"]["published"], delivered_per_s=med["on"]["delivered"],
           node_cpu_per_s=med["on"]["node_cpu"], longest_step_ms=max(r["longest_ms"] for r in rows["on"]),
           p50_ratio=ratio["p50"], p99_ratio=ratio["p99"], rps_ratio=ratio["rps"], cpu_ratio=ratio["cpu"])


if __name__ == "__main__":
    sys.exit(main())
