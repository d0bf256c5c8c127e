"""Sparkplug store and forward: what the store costs per change, how fast it replays, what live data waits.

Beside ``bench/sparkplug_publishing.py``, with its helpers.  Two parts:

* ``store``: ``gateway.sparkplug.store.ChangeStore`` in this process on a temporary directory (the disk
  the benchmark runs on): N changes (realistic: 64 devices, 184 metrics each, int values) added in
  batches of B (a batch is what the driver commits every 0.25 s: B = changes per second / 4), then read
  back and removed as the replay does (64 a batch).  Per change: CPU of the store's thread
  (``time.thread_time``), wall time, and fsync / fdatasync calls (the same run under ``strace -f -c``, a
  second process: strace slows it, so its CPU is not used); disk bytes per change (the SQLite pages in
  use, and the files: database + WAL).
* ``replay``: one gateway process with L DF1 links (the simulator farm, paced 19200 8N1, ladders
  running: nearly every poll brings changed values), mosquitto, and a subscriber (a thread, paho)
  that stamps every DDATA it receives.  Live latency = receipt - the metric's timestamp (the read time
  of its block: the poll-to-publish path, ``batch_interval`` included), p50 / p99, first with no replay
  (``--baseline`` s), then the broker is stopped for ``--outage`` s (the store fills) and started
  again: the replay's rate (historical DDATA and changes per second, until ``/api/status`` shows the
  store empty) and the live latency while it runs.  The issue's target: live p99 during the replay
  within 2 x the p99 without.

    python bench/sparkplug_store.py [--quick] [--part store|replay|both] [--links L] [--outage S] [--baseline S]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import HOST, PYTHON, REPO, SimFarm, percentile, print_machine, result, table, wait_for
from modbus_serving import free_port
from sparkplug_publishing import Broker, config, mosquitto, node_state

from gateway.sparkplug.history import Change
from gateway.sparkplug.payload import decode
from gateway.sparkplug.store import ChangeStore

T0 = 1_765_000_000_000


def changes(count: int) -> list[Change]:
    return [Change(f"plc{(k // 184) % 64:02d}", f"N7:{k % 184}", T0 + k, (k * 7) % 32768, 192) for k in range(count)]


def store_child(directory: str, count: int, batch: int) -> None:
    """One run of the store part (run under strace for the fsyncs); prints its figures."""
    path = Path(directory) / f"store-{batch}.sqlite"
    store = ChangeStore(path, max_bytes=10**10, max_age=10**12)
    store.open()
    rows = changes(count)
    cpu, wall = time.thread_time(), time.perf_counter()
    for start in range(0, count, batch):
        store.add(rows[start:start + batch], T0)
    add_cpu, add_wall = time.thread_time() - cpu, time.perf_counter() - wall
    pages = store.bytes
    files = sum(p.stat().st_size for p in Path(directory).glob(f"store-{batch}.sqlite*"))
    cpu, wall = time.thread_time(), time.perf_counter()
    replayed = 0
    while (got := store.next_batch(64)) is not None:
        store.remove([ident for ident, _ in got[1]])
        replayed += len(got[1])
    read_cpu, read_wall = time.thread_time() - cpu, time.perf_counter() - wall
    store.close()
    print(f"FIGURES {add_cpu} {add_wall} {pages} {files} {read_cpu} {read_wall} {replayed}")


def fsyncs(directory: str, count: int, batch: int) -> int:
    trace = Path(directory) / f"strace-{batch}.txt"
    subprocess.run(["strace", "-f", "-qq", "-e", "trace=fsync,fdatasync", "-o", str(trace), PYTHON, __file__,
                    "--child", directory, str(count), str(batch)], check=True, stdout=subprocess.DEVNULL,
                   cwd=REPO)
    return sum(1 for line in trace.read_text().splitlines() if "sync(" in line)


def store_part(count: int) -> None:
    print(f"\nstore: {count} changes, added in batches of B (one commit each), read back 64 at a time")
    rows = []
    with tempfile.TemporaryDirectory() as directory:
        for batch in (16, 256, 4096):
            out = subprocess.run([PYTHON, __file__, "--child", directory, str(count), str(batch)], check=True,
                                 capture_output=True, text=True, cwd=REPO).stdout
            figures = [float(x) for x in out.split("FIGURES")[1].split()]
            add_cpu, add_wall, pages, files, read_cpu, read_wall, replayed = figures
            syncs = fsyncs(directory, count, batch) if os.path.exists("/usr/bin/strace") else float("nan")
            rows.append([batch, 1e6 * add_cpu / count, 1e6 * add_wall / count, syncs / count, syncs,
                         pages / count, files / count, 1e6 * read_cpu / replayed, replayed / read_wall])
            result(part="store", batch=batch, cpu_us_per_change=1e6 * add_cpu / count,
                   wall_us_per_change=1e6 * add_wall / count, fsyncs_per_change=syncs / count,
                   bytes_per_change=pages / count, file_bytes_per_change=files / count,
                   replay_read_cpu_us_per_change=1e6 * read_cpu / replayed, replay_read_per_s=replayed / read_wall)
    print(table(["batch", "add CPU µs/change", "add wall µs/change", "fsyncs/change", "fsyncs", "bytes/change (pages)",
                 "bytes/change (files)", "read+remove CPU µs/change", "read+remove changes/s"], rows))


class Subscriber(threading.Thread):
    """Every DDATA the broker delivers: (receipt, [(metric timestamp, historical)]) (paho, its own thread)."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.live: list[tuple[float, float]] = []  # (receipt, latency s)
        self.historical: list[tuple[float, int]] = []  # (receipt, metrics)

    def run(self) -> None:
        import paho.mqtt.client as mqtt

        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        client.on_connect = lambda c, *_: c.subscribe("spBv1.0/+/DDATA/#")
        client.on_message = self._message
        client.reconnect_delay_set(0.1, 0.5)
        while True:
            try:
                client.connect(HOST, self.port)
                break
            except OSError:
                time.sleep(0.2)
        client.loop_forever(retry_first_connection=True)

    def _message(self, client: object, userdata: object, message: object) -> None:
        now = time.time()
        payload = decode(message.payload)  # type: ignore[attr-defined]
        history = [m for m in payload.metrics if m.is_historical]
        if history:
            self.historical.append((now, len(history)))
        for metric in payload.metrics:
            if not metric.is_historical and metric.timestamp:
                self.live.append((now, now - metric.timestamp / 1000))


def latency(samples: list[tuple[float, float]], start: float, end: float) -> tuple[float, float, int]:
    inside = sorted(lat for at, lat in samples if start <= at <= end)
    if not inside:
        return float("nan"), float("nan"), 0
    return statistics.median(inside), percentile(inside, 99), len(inside)


def replay_part(links: int, outage: float, baseline: float) -> None:
    broker_path = mosquitto()
    if broker_path is None:
        return
    print(f"\nreplay: {links} DF1 links (paced 19200 8N1, ladders running), broker away {outage:g} s")
    with tempfile.TemporaryDirectory() as tmp, SimFarm("slc504", links, paced=True, ladder=True) as farm:
        directory = Path(tmp)
        broker = Broker(broker_path, directory)
        broker.start()
        subscriber = Subscriber(broker.port)
        subscriber.start()
        port, metrics_port = free_port(), free_port()
        path = directory / "gateway.toml"
        path.write_text(config(farm, links, port, metrics_port, broker.port, directory / "bdseq.json"),
                        encoding="utf-8")
        gateway = subprocess.Popen([PYTHON, "-m", "gateway", "run", str(path)], cwd=REPO, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
        try:
            wait_for(lambda: _quiet(lambda: node_state(metrics_port)["state"] == "online"), 60, "the edge node",
                     step=0.1)
            time.sleep(3)
            start = time.time()
            time.sleep(baseline)
            base = latency(subscriber.live, start, time.time())
            broker.stop()
            time.sleep(outage)
            stored = node_state(metrics_port)["store"]
            broker.start()
            replay_start = time.time()
            wait_for(lambda: _quiet(lambda: node_state(metrics_port)["state"] == "online"), 60, "the edge node",
                     step=0.1)
            wait_for(lambda: _quiet(lambda: node_state(metrics_port)["store"]["messages"] == 0
                                    and node_state(metrics_port)["store"]["replayed"] > 0), 600, "the edge node",
                     step=0.1)
            replay_end = time.time()
            during = latency(subscriber.live, replay_start + 1, replay_end)
            messages = sum(1 for at, _ in subscriber.historical if replay_start <= at <= replay_end)
            metrics = sum(n for at, n in subscriber.historical if replay_start <= at <= replay_end)
            seconds = replay_end - replay_start
        finally:
            gateway.terminate()
            gateway.wait(10)
            broker.stop()
    print(table(["phase", "live p50 ms", "live p99 ms", "live metrics", "historical DDATA/s", "changes/s"], [
        ["no replay", 1e3 * base[0], 1e3 * base[1], base[2], "", ""],
        [f"replay ({seconds:.1f} s)", 1e3 * during[0], 1e3 * during[1], during[2], messages / seconds,
         metrics / seconds]]))
    print(f"stored during the outage: {stored['messages']} changes, {stored['bytes']} bytes, "
          f"{stored['commits']} commits; p99 ratio (replay / none): {during[1] / base[1]:.2f}")
    result(part="replay", links=links, outage=outage, stored=stored["messages"], replay_s=seconds,
           historical_per_s=messages / seconds, changes_per_s=metrics / seconds, live_p50_base_ms=1e3 * base[0],
           live_p99_base_ms=1e3 * base[1], live_p50_replay_ms=1e3 * during[0], live_p99_replay_ms=1e3 * during[1],
           p99_ratio=during[1] / base[1])


def _quiet(check: object) -> bool:
    try:
        return bool(check())  # type: ignore[operator]
    except (OSError, KeyError, TypeError, ValueError):
        return False


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        store_child(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--part", choices=["store", "replay", "both"], default="both")
    parser.add_argument("--links", type=int, default=16)
    parser.add_argument("--outage", type=float, default=60.0)
    parser.add_argument("--baseline", type=float, default=20.0)
    parser.add_argument("--changes", type=int, default=100_000)
    args = parser.parse_args()
    print_machine()
    if args.part in ("store", "both"):
        store_part(5_000 if args.quick else args.changes)
    if args.part in ("replay", "both"):
        replay_part(4 if args.quick else args.links, 10.0 if args.quick else args.outage,
                    5.0 if args.quick else args.baseline)


if __name__ == "__main__":
    main()
