"""Every face on: the SCADA screen's reads with data while Sparkplug, OPC UA and the status page all run.

The guide's lesson: "Every face reads one truth [...] the gateway's own faces (Sparkplug, OPC UA, the page)
peek, only clients demand.  Measure a new face with every other face on."  ``bench/freshness.py`` measures
Sparkplug alone beside Modbus (its ``sparkplug`` case); this measures them all at once:

* the ``sparkplug`` case's controller and screen: an SLC 150 at 9600 baud (paced) answering at the end of
  its scan, scans of J/2-J with J = 50 and 100 ms; one Modbus client reads holding 0-31 every 1 s,
  another 32-63 every 2 s (``freshness.SCREEN``);
* **off**: Modbus only;
* **on**: the same gateway with ``[sparkplug]`` (a mosquitto started for the run, every other key its
  default), ``[metrics]`` with the status page's JSON fetched every second (what ``status.js`` does)
  and ``/metrics`` every 5 s (a Prometheus scraping three times faster than its default), and ``[opcua]``
  (the None endpoint) with an OPC UA client (asyncua's, in the same process as the Modbus clients)
  subscribed at 1 s publishing and 1 s sampling to the tags the screen reads (holding 0-63).  The
  OPC UA client is a client: its monitored items demand the blocks they watch, the same blocks the
  screen reads, so the line's work is the same and any drop is the faces getting in each other's way.

Target: with every face on, the reads with data within 1 point of off, and >= 99 % at 0-100 ms.

    python bench/faces.py                 # 30 s windows after 10 s of warm-up, J = 50 and 100 ms
    python bench/faces.py --quick         # CI smoke: 2 s windows, J = 50 ms
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import tempfile
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

from _benchlib import HOST, fetch, free_port, mosquitto_required, print_machine, result, table
from freshness import (
    HEADERS,
    NO_BROKER,
    SCREEN,
    Figures,
    node_note,
    publishing,
    row,
    scan_for,
    slc_links,
    sparkplug_broker,
    steady,
)

from gateway.app import Gateway
from gateway.modbus.mapping import Table
from gateway.tags import link_tags

#: what the page's JSON and a Prometheus scrape cost: fetched every PAGE_PERIOD and METRICS_PERIOD seconds
PAGE_PERIOD = 1.0
METRICS_PERIOD = 5.0
#: the OPC UA subscription's publishing interval and its items' sampling interval, ms
OPCUA_MS = 1000.0
#: the holding registers the screen reads (freshness.SCREEN): the tags the OPC UA client monitors
SCREEN_HOLDING = range(0, 64)


class Faces:
    """The other faces' clients of one gateway: the page's and Prometheus' fetches and an OPC UA subscription."""

    def __init__(self, metrics_port: int, opcua_url: str) -> None:
        self.metrics_port = metrics_port
        self.opcua_url = opcua_url
        self.page_fetches = 0
        self.metrics_fetches = 0
        self.fetch_errors = 0
        self.monitored = 0
        self.changes = 0

    async def _poll(self, path: str, period: float, count: Callable[[], None]) -> None:
        while True:
            try:
                await asyncio.to_thread(fetch, self.metrics_port, path)
                count()
            except OSError:
                self.fetch_errors += 1
            await asyncio.sleep(period)

    def _page(self) -> None:
        self.page_fetches += 1

    def _metrics(self) -> None:
        self.metrics_fetches += 1

    def datachange_notification(self, *_: object) -> None:
        self.changes += 1

    @contextlib.asynccontextmanager
    async def on(self, gw: Gateway) -> AsyncIterator[Faces]:
        from asyncua import Client, ua

        link = gw.config.link[0]
        # a tag's name is "<link>/<name>" (gateway.tags); its variable is "<link>.<name>" (gateway.opcua.points)
        names = [tag.name[len(link.name) + 1:] for tag in link_tags(link)
                 if tag.table is Table.HOLDING and tag.address in SCREEN_HOLDING]
        async with Client(self.opcua_url, timeout=30) as client:
            ns = await client.get_namespace_index("urn:slc-gateway")
            subscription = await client.create_subscription(OPCUA_MS, self)
            nodes = [client.get_node(ua.NodeId(f"{link.name}.{name}", ns)) for name in names]
            handles = await subscription.subscribe_data_change(nodes, sampling_interval=OPCUA_MS)
            refused = [(n, h) for n, h in zip(nodes, handles, strict=True) if not isinstance(h, int)]
            if refused:
                raise SystemExit(f"faces: the OPC UA server refused {len(refused)} monitored items: {refused[:3]}")
            self.monitored = len(nodes)
            tasks = [asyncio.create_task(self._poll("/api/status", PAGE_PERIOD, self._page)),
                     asyncio.create_task(self._poll("/metrics", METRICS_PERIOD, self._metrics))]
            try:
                yield self
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

    def note(self) -> str:
        errors = f", {self.fetch_errors} FETCH ERRORS" if self.fetch_errors else ""
        return (f"OPC UA {self.monitored} items, {self.changes} changes; page {self.page_fetches} fetches, "
                f"/metrics {self.metrics_fetches}{errors}")


def sections(sparkplug: str, metrics_port: int, opcua_port: int, directory: Path) -> str:
    """``[sparkplug]``, ``[metrics]`` and ``[opcua]`` (the None endpoint, anonymous reading, its certificate
    generated in ``directory``)."""
    return f"""{sparkplug}
[metrics]
listen = "{HOST}:{metrics_port}"

[opcua]
listen = "opc.tcp://{HOST}:{opcua_port}"
security = ["None"]
anonymous = "read"
certificate = "{directory / 'cert.der'}"
private_key = "{directory / 'key.pem'}"
trusted_clients = "{directory / 'trusted'}"
"""


async def case(args: argparse.Namespace, sparkplug: str, longest: float, rows: list[list[object]],
               figures: dict[str, object]) -> None:
    ms = int(longest * 1000)
    off = await steady(slc_links(scan_for(longest)), SCREEN, args.seconds, args.warmup)
    rows.append(row("SLC 150 9600, Modbus only: holding 0-31 / 1 s, 32-63 / 2 s", f"scan {longest / 2:g}-{longest:g} s",
                    off, f">= 99 %: {'met' if off.share >= 0.99 else 'not met'}"))
    print(rows[-1], flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        metrics_port, opcua_port = free_port(), free_port()
        faces = Faces(metrics_port, f"opc.tcp://{HOST}:{opcua_port}")
        on: Figures = await steady(slc_links(scan_for(longest)), SCREEN, args.seconds, args.warmup,
                                   sections(sparkplug, metrics_port, opcua_port, Path(tmp)), faces=faces.on)
    delta = 100 * (on.share - off.share)
    met = abs(delta) <= 1 and (on.share >= 0.99 or longest < 0.1) and publishing(on) and faces.changes > 0
    answers = f"scan {longest / 2:g}-{longest:g} s"
    target = (f"at most 1 point from off{', >= 99 %' if longest >= 0.1 else ''}: "
              f"{'met' if met else 'NOT MET'} ({delta:+.1f} points)")
    rows.append(row(f"SLC 150 9600, every face on ({node_note(on)}; {faces.note()})", answers, on, target))
    print(rows[-1], flush=True)
    if on.misses:
        print(f"  reads without data, every face on: {on.misses[:10]}", flush=True)
    figures.update({f"faces_off_{ms}ms": off.share, f"faces_on_{ms}ms": on.share, f"faces_delta_{ms}ms": delta,
                    f"faces_met_{ms}ms": met, f"faces_opcua_changes_{ms}ms": faces.changes})


async def main_async(args: argparse.Namespace, sparkplug: str) -> dict[str, object]:
    rows: list[list[object]] = []
    figures: dict[str, object] = {}
    for longest in (0.05,) if args.quick else (0.05, 0.1):
        await case(args, sparkplug, longest, rows, figures)
    print(table(HEADERS, rows))
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CI smoke: 2 s windows, J = 50 ms only")
    parser.add_argument("--seconds", type=float, help="measuring window per run (default 30; quick 2)")
    parser.add_argument("--warmup", type=float, help="seconds after start before counting (default 10; quick 1)")
    args = parser.parse_args()
    args.seconds = args.seconds if args.seconds is not None else (2.0 if args.quick else 30.0)
    args.warmup = args.warmup if args.warmup is not None else (1.0 if args.quick else 10.0)
    print_machine()
    figures: dict[str, Any]
    with sparkplug_broker(True) as sparkplug:
        if sparkplug is None:
            if args.quick and not mosquitto_required():
                print(f"faces: {NO_BROKER}: nothing measured", flush=True)
                result(faces=NO_BROKER)
                return
            sys.exit(f"{NO_BROKER}: bench/faces.py needs a broker for Sparkplug")
        figures = asyncio.run(main_async(args, sparkplug))
    result(**figures)


if __name__ == "__main__":
    main()
