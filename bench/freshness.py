"""Freshness: the share of SCADA reads answered with data when the controllers take their time.

A real controller answers at the end of its program scan (``docs/develop/controller-variants.md``, "Answer
time"), not at once.  This bench runs the whole gateway (in-process, default config, no faults)
against paced simulators whose every answer waits for the end of the scan in progress
(``gateway/sim/scan.py``), and against the independent controllers of ``../shared/interop`` behind
a proxy that holds each of their answers uniform(lo, hi) seconds (and paces the DF1 peer's line).
Clients read through Modbus TCP on a schedule; a read is *with data* unless it is answered
0x0B (or not at all within 3 s).  Each figure is printed beside the line's measured capacity
(transactions/s, the status registers 1003-1004 of each unit, summed), the plan's blocks and the
demanded set's blocks (the blocks holding the registers clients read).

Cases (the targets of issue "Spend the line on what SCADA reads"):

* ``slc``: SLC 150 at 9600 baud, scans of J/2-J (answers within 0-J) for J = 50 and 100 ms; one
  client reads holding 0-31 every 1 s, another 32-63 every 2 s: >= 99 % with data;
* ``slc-acc8``: the same with J = 250 ms, one client reading 8 accumulators (holding 0-7) every 1 s:
  >= 99 %;
* ``startup``: a client asks for holding 0-31 every 50 ms from the moment the Modbus port opens
  (9600 baud, answers at once): the first data within 2.5 s (median of the runs);
* ``load50``: 50 connections reading holding 0-31 or 32-63 from the moment the port opens
  (answers at once): no 0x0B after the first 3 s;
* ``df1``: an SLC 5/04 on DF1 full duplex at 19200 baud, a half-duplex line of 3 stations at 19200,
  and one of 8 stations of which clients read 3 (the whole plan does not fit the line when the
  scans are long, what clients read does); scans of 20-60 ms, a map of 100 + 10 + 20 registers and
  64 coils per controller; per unit read a client reads holding 0-31 every 1 s and 32-63 every 2 s;
* ``peers``: the same workloads against the interop peers (SLC 150 at 9600 with answers held
  uniform(0, 50 / 100 ms); the DF1 peer paced at 19200 by the proxy, answers held 20-60 ms; the
  half-duplex peer at 19200, every answer held 20-60 ms: a slow turnaround rather than a scan);
* ``sparkplug``: the ``slc`` case's SLC 150 and screen at 0-50 and 0-100 ms, with ``[sparkplug]`` off and
  on side by side (a mosquitto the bench starts on a free loopback port, every other Sparkplug key its
  default, ``check_interval`` included): publishing changes the reads with data by at most 1 point
  (>= 99 % at 0-100 ms).  Without mosquitto the case says NOT MEASURED and the run fails (``--quick``:
  only with SLC_GATEWAY_REQUIRE_MOSQUITTO=1, as CI sets);
* ``harsh``: SLC 150 at 9600 answering within 0-250 ms, 1 reply in 4 garbled, 1 in 6 dropped, a power
  cycle every 250 commands, ``stale_after = 4``; one client reads the 31 presets (holding 32-62)
  continuously and writes one (FC6, a value in range) after every fifth read; then the same with 8
  presets (holding 32-39) and ``background_interval = 120``, a set that fits: >= 90 % with data when
  the demanded set fits the line; writes acknowledged / 0x0B counted;
* ``sweep``: reads with data against the controller's longest scan (0 = answers at once), per kind
  (SLC 150, SLC 150 with ``[sparkplug]`` on, SLC 5/04 full duplex, the 3- and 8-station half-duplex
  lines), plotted to ``--png`` (``--compare`` earlier runs' ``--json`` files: their curves dashed).

Beside every row, whether the set fits the line by the sizing rule of ``docs/guide/freshness.md``:
``sum(1 / (stale_after + P))`` over the demanded blocks plus ``1 / (stale_after + B)`` for each other
block (the *needed* transactions/s, from each unit's schedule at the end of the window) against the
line's capacity, ``1 / transaction_time`` (the schedule's measured mean read transaction,
``/api/status`` ``schedule``).

    python bench/freshness.py                      # every case, ~22 min
    python bench/freshness.py --only slc,startup   # some cases
    python bench/freshness.py --only sparkplug,harsh --seconds 60   # the Sparkplug and harsh cases
    python bench/freshness.py --quick              # CI smoke: a few seconds per case, no plot

The plot needs matplotlib: ``pip install -e '.[bench]'`` (the ``bench`` extra of pyproject.toml).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import functools
import json
import random
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import (
    DF1_MAP,
    Broker,
    df1_link,
    free_port,
    mosquitto_path,
    mosquitto_required,
    print_machine,
    result,
    slc_link,
    table,
)

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.modbus.mapping import Table
from gateway.sim.scan import REALISTIC_SCAN, ScanTime

HOST = "127.0.0.1"
ROOT = Path(__file__).resolve().parent.parent
PEERS = ROOT.parent / "shared" / "interop" / "peers"
STALE = 0x0B
TIMEOUT = -1  # no answer within the client's timeout
CLIENT_TIMEOUT = 3.0
DF1_CHAR = 10 / 19200
#: what a SCADA screen reads: (function code, address, count, period s)
SCREEN = ((3, 0, 32, 1.0), (3, 32, 32, 2.0))
ACC8 = ((3, 0, 8, 1.0),)
SWEEP = (0.0, 0.05, 0.1, 0.2, 0.3)
#: the sweep's curve of the SLC 150 simulator with ``[sparkplug]`` on
SPARKPLUG_SWEEP_KIND = "SLC 150, 9600, Sparkplug on"
#: the harsh case: answers within 0-250 ms, 1 reply in 4 garbled, 1 in 6 dropped, a power cycle every 250
#: commands (the SLC 100/150 simulator's fault options, ``gateway/kinds/slc_ascii/sim.py`` ``FaultPlan``)
HARSH_LONGEST = 0.25
HARSH_FAULTS = {"garble": 4, "drop": 6, "power_cycle_every": 250}
HARSH_STALE_AFTER = 4
#: the harsh case's runs, (background_interval or None for its default, the presets read (first, count)): the
#: issue's (31 / 14 + 89 / 64 = 3.6 tx/s needed; the line does 2.4-3.0 at 1 reply in 4 garbled and 1 in 6
#: dropped, each failed try costing a reply timeout), then a set that fits: 8 presets with background_interval
#: 120 (8 / 14 + 112 / 124 = 1.5 tx/s)
HARSH_RUNS: tuple[tuple[float | None, tuple[int, int]], ...] = ((None, (32, 31)), (120.0, (32, 8)))
#: the harsh case's client writes one of the presets it reads after every WRITE_EVERY reads
WRITE_EVERY = 5
#: the links' counters (``gateway/link_health.py`` ``LineCounters``) a faulty line's row reports
LINE_COUNTERS = ("transactions", "errors", "timeouts", "crc_errors", "retries", "reconnects")
#: The sweep's curve of the independent SLC 150 peer (``../shared/interop``), answers held uniform(0, J).
PEER_SWEEP_KIND = "interop SLC 150 peer, 9600"


def scan_for(longest: float) -> ScanTime | None:
    """Answers within 0-``longest``: scans of ``longest``/2 to ``longest`` (None: answers at once)."""
    return ScanTime(longest / 2, longest) if longest > 0 else None


# ------------------------------------------------------------------------------- Modbus clients


class Client:
    """One Modbus TCP connection: reads, answered with data (0), an exception code or TIMEOUT."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer, self.tid = reader, writer, 0

    @classmethod
    async def connect(cls, port: int) -> Client:
        return cls(*await asyncio.open_connection(HOST, port))

    async def read(self, unit: int, fc: int, address: int, count: int) -> tuple[int, bytes]:
        self.tid = (self.tid + 1) & 0xFFFF
        self.writer.write(struct.pack(">HHHBBHH", self.tid, 0, 6, unit, fc, address, count))
        try:
            async with asyncio.timeout(CLIENT_TIMEOUT):
                head = await self.reader.readexactly(7)
                body = await self.reader.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
        except TimeoutError:
            self.close()
            raise
        if body[0] & 0x80:
            return body[1], b""
        return 0, body[2:]

    async def write(self, unit: int, address: int, value: int) -> int:
        """FC6 (its request has a read's shape: address, value): 0 when acknowledged, else the exception code."""
        code, _ = await self.read(unit, 6, address, value)
        return code

    def close(self) -> None:
        self.writer.close()


@dataclass
class Reader:
    """A client reading ``count`` registers at ``address`` of ``unit`` every ``period`` seconds."""

    unit: int
    fc: int
    address: int
    count: int
    period: float
    results: list[tuple[float, int]] = field(default_factory=list)  #: (sent, s after the port opened; code)

    async def run(self, port: int, opened: float, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        client = await Client.connect(port)
        start, k = loop.time(), 0
        try:
            while not stop.is_set():
                await asyncio.sleep(max(0.0, start + k * self.period - loop.time()))
                sent = loop.time()
                try:
                    code, _ = await client.read(self.unit, self.fc, self.address, self.count)
                except TimeoutError:
                    code = TIMEOUT
                    client = await Client.connect(port)
                self.results.append((sent - opened, code))
                k = max(k + 1, int((loop.time() - start) / self.period) + 1)  # a late answer skips its turns
        finally:
            client.close()

    def share(self, since: float = 0.0) -> tuple[int, int]:
        """(reads with data, reads) sent ``since`` seconds after the port opened."""
        codes = [code for sent, code in self.results if sent >= since]
        return sum(code == 0 for code in codes), len(codes)


@dataclass
class PresetWriter(Reader):
    """Reads ``count`` holding registers at ``address`` continuously (the next read as soon as the answer is
    in) and after every ``write_every`` reads writes one of them (FC6, in turn, a value of 1-9999, in range
    for a preset)."""

    write_every: int = WRITE_EVERY
    writes: list[tuple[float, int]] = field(default_factory=list)  #: (sent, s after the port opened; code)

    async def run(self, port: int, opened: float, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        rng = random.Random(1)
        client = await Client.connect(port)

        async def answer(request: Callable[[Client], Awaitable[int]]) -> tuple[float, int]:
            nonlocal client
            sent = loop.time() - opened
            try:
                return sent, await request(client)
            except TimeoutError:  # the client closed the connection: a new one for the next request
                client = await Client.connect(port)
                return sent, TIMEOUT

        async def read(c: Client) -> int:
            return (await c.read(self.unit, self.fc, self.address, self.count))[0]

        try:
            while not stop.is_set():
                for _ in range(self.write_every):
                    self.results.append(await answer(read))
                address, value = self.address + len(self.writes) % self.count, rng.randint(1, 9999)
                self.writes.append(await answer(lambda c, a=address, v=value: c.write(self.unit, a, v)))
        finally:
            client.close()

    def write_codes(self, since: float = 0.0) -> collections.Counter[int]:
        """Writes sent ``since`` s after the port opened, by answer (0 acknowledged, 0x0B, ..., TIMEOUT)."""
        return collections.Counter(code for sent, code in self.writes if sent >= since)


async def transactions(port: int, units: Sequence[int]) -> int:
    """Transactions so far, summed over ``units`` (input registers 1003-1004 of each)."""
    client = await Client.connect(port)
    try:
        total = 0
        for unit in units:
            code, data = await client.read(unit, 4, 1003, 2)
            total += int.from_bytes(data, "big") if code == 0 else 0
        return total
    finally:
        client.close()


# ------------------------------------------------------------------------------------ gateways


def config(links: str, connections: int = 16, sections: str = "") -> Any:
    return parse_config(f"""
[modbus]
listen = "{HOST}:0"
max_connections = {connections + 16}
max_connections_per_address = {connections + 16}

[logging]
level = "ERROR"

{sections}

{links}""")


def sparkplug_section(broker: Broker, directory: Path) -> str:
    """``[sparkplug]`` publishing to ``broker``; every other key its default (``check_interval`` included)."""
    return f"""[sparkplug]
broker = "mqtt://{HOST}:{broker.port}"
group_id = "bench"
edge_node_id = "freshness"
state_file = "{directory / 'sparkplug-bdseq.json'}"
"""


def instance() -> str:
    return f"instance={uuid.uuid4().hex}"


#: a gateway's links: (config text, its units, the units the clients read)
Links = tuple[str, list[int], list[int]]


def slc_links(scan: ScanTime | None, port: str = "", faults: dict[str, int] | None = None, **keys: object) -> Links:
    """An SLC 150 (``faults``: the simulator's fault options; ``keys``: more keys of the link)."""
    options = [f"{key}={value}" for key, value in (faults or {}).items()]
    query = "&".join(["paced=1", "seed=1", instance(), *options] + ([f"scan={scan.text()}"] if scan else []))
    return slc_link("slc", port or f"sim://slc150?{query}", 1, **keys), [1], [1]


def df1_full_links(scan: ScanTime | None, port: str = "") -> Links:
    query = "&".join(["paced=1", "seed=1", instance()] + ([f"scan={scan.text()}"] if scan else []))
    return df1_link("df1", port or f"sim://slc504?{query}", 1, baudrate=19200), [1], [1]


def df1_half_links(scan: ScanTime | None, port: str = "", stations: int = 3, read: int = 3) -> Links:
    numbers = list(range(1, stations + 1))
    query = "&".join([f"stations={','.join(map(str, numbers))}", f"char_time={DF1_CHAR:.9f}", "seed=1", instance()]
                     + ([f"scan={scan.text()}"] if scan else []))
    port = port or f"sim://df1line?{query}"
    links = [df1_link(f"station-{n}", port, n, DF1_MAP, duplex="half", station=n, baudrate=19200) for n in numbers]
    return "\n".join(links), numbers, numbers[:read]


def df1_line8_links(scan: ScanTime | None, port: str = "") -> Links:
    """8 stations on the line, clients reading 3 of them: the whole plan does not fit a slow line."""
    return df1_half_links(scan, port, stations=8, read=3)


KINDS: dict[str, Callable[[ScanTime | None, str], Links]] = {
    "SLC 150, 9600": slc_links,
    "SLC 5/04 DF1 full duplex, 19200": df1_full_links,
    "3 stations, DF1 half duplex, 19200": df1_half_links,
    "8 stations (3 read), DF1 half duplex, 19200": df1_line8_links,
}


@dataclass
class Figures:
    with_data: int
    reads: int
    tx_per_s: float
    plan_blocks: int
    demanded_blocks: int
    #: reads without data: (s after the port opened, unit, address, count, code), the first few
    misses: list[tuple[float, int, int, int, int]] = field(default_factory=list)
    #: the sizing rule at the window's end: (transactions/s the set needs, the schedules' mean read transaction s)
    needed: float = float("nan")
    tx_time: float = float("nan")
    #: the blocks the schedules count as demanded at the window's end (clients' and any other reader's)
    scheduled_demand: int = 0
    #: with [sparkplug]: the node's state at the window's end and the messages it published in the window
    sparkplug: tuple[str, int] | None = None
    #: the links' counters from start to the window's end, summed over the units (LINE_COUNTERS)
    line: dict[str, int] = field(default_factory=dict)

    @property
    def capacity(self) -> float:
        """The line's transactions/s when it only reads: 1 / the mean read transaction."""
        return 1 / self.tx_time if self.tx_time > 0 else float("nan")

    @property
    def fits(self) -> bool:
        return self.needed < self.capacity

    @property
    def share(self) -> float:
        return self.with_data / self.reads if self.reads else float("nan")


def demanded(gw: Gateway, readers: Sequence[Reader]) -> tuple[int, int]:
    """(blocks of every unit's plan, blocks holding the registers the readers read)."""
    plans = {unit.unit_id: unit.plan for unit in gw.units}
    blocks = {(reader.unit, plans[reader.unit].registers(Table.HOLDING)[address].block)
              for reader in readers for address in range(reader.address, reader.address + reader.count)
              if address in plans[reader.unit].registers(Table.HOLDING)}
    return sum(len(plan.blocks) for plan in plans.values()), len(blocks)


def sizing(gw: Gateway, now: float) -> tuple[float, float, int]:
    """(transactions/s the demanded set needs by the guide's rule, the mean read transaction s, the demanded
    blocks) of the polled units: ``sum(1 / (stale_after + P))`` over demanded blocks plus
    ``1 / (stale_after + B)`` over the others."""
    needed, times, count = 0.0, [], 0
    for unit in gw.units:
        schedule = unit.schedule
        if schedule is None:
            continue
        wanted = set(schedule.demanded(now))
        count += len(wanted)
        needed += sum(1 / (schedule.stale_after + (schedule.period if i in wanted else schedule.background)[i])
                      for i in range(len(schedule.scans)))
        tx_time = schedule.budget(now).transaction_time
        if tx_time is not None:
            times.append(tx_time)
    return needed, statistics.fmean(times) if times else float("nan"), count


async def steady(links: Links, screen: Sequence[tuple[int, int, int, float]], seconds: float, warmup: float,
                 sections: str = "", readers: Sequence[Reader] = (),
                 faces: Callable[[Gateway], contextlib.AbstractAsyncContextManager[object]] | None = None) -> Figures:
    """Readers of ``screen`` on every unit read (or ``readers``); the share with data after ``warmup``.
    ``sections``: more config (``[sparkplug]``); ``faces``: the other faces' clients, for the gateway's life
    (``bench/faces.py``)."""
    text, units, read = links
    readers = readers or [Reader(unit, fc, address, count, period) for unit in read
                          for fc, address, count, period in screen]
    async with Gateway(config(text, sections=sections)) as gw, (
            faces(gw) if faces is not None else contextlib.nullcontext()):
        loop = asyncio.get_running_loop()
        opened, stop = loop.time(), asyncio.Event()
        tasks = [asyncio.create_task(reader.run(gw.port, opened, stop)) for reader in readers]
        await asyncio.sleep(warmup)
        published0 = sum(gw.sparkplug.sent.values()) if gw.sparkplug else 0
        tx0, t0 = await transactions(gw.port, units), loop.time()
        await asyncio.sleep(seconds)
        rate = (await transactions(gw.port, units) - tx0) / (loop.time() - t0)
        needed, tx_time, scheduled = sizing(gw, loop.time())
        line = {name: sum(getattr(unit.driver.counters, name) for unit in gw.units) for name in LINE_COUNTERS}
        node = None if gw.sparkplug is None else (gw.sparkplug.session_state,
                                                  sum(gw.sparkplug.sent.values()) - published0)
        stop.set()
        await asyncio.gather(*tasks)
        plan_blocks, demanded_blocks = demanded(gw, readers)
    good = sum(reader.share(warmup)[0] for reader in readers)
    total = sum(reader.share(warmup)[1] for reader in readers)
    misses = sorted((sent, reader.unit, reader.address, reader.count, code) for reader in readers
                    for sent, code in reader.results if sent >= warmup and code != 0)
    return Figures(good, total, rate, plan_blocks, demanded_blocks, misses, needed, tx_time, scheduled, node, line)


async def startup(links: Links, limit: float = 15.0) -> float:
    """Seconds from the port opening to the first read of holding 0-31 answered with data."""
    async with Gateway(config(links[0])) as gw:
        loop = asyncio.get_running_loop()
        opened = loop.time()
        client = await Client.connect(gw.port)
        try:
            while loop.time() < opened + limit:
                code, _ = await client.read(1, 3, 0, 32)
                if code == 0:
                    return loop.time() - opened
                await asyncio.sleep(0.05)
        finally:
            client.close()
    return float("inf")


async def load50(links: Links, seconds: float, connections: int = 50) -> tuple[int, int, int, int]:
    """(0x0B, reads) in the first 3 s and after, of ``connections`` clients reading from the port's opening."""
    readers = [Reader(1, 3, 32 * (n % 2), 32, 0.1) for n in range(connections)]
    async with Gateway(config(links[0], connections)) as gw:
        loop = asyncio.get_running_loop()
        opened, stop = loop.time(), asyncio.Event()
        tasks = [asyncio.create_task(reader.run(gw.port, opened, stop)) for reader in readers]
        await asyncio.sleep(seconds)
        stop.set()
        await asyncio.gather(*tasks)
    early = [code for reader in readers for sent, code in reader.results if sent < 3.0]
    late = [code for reader in readers for sent, code in reader.results if sent >= 3.0]
    return sum(c != 0 for c in early), len(early), sum(c != 0 for c in late), len(late)


# ----------------------------------------------------------------------------------- the peers


class AnswerDelayProxy:
    """A TCP proxy in front of a peer: every answer (the controller's bytes after a host write) is held
    uniform(``lo``, ``hi``) seconds, order kept; with ``char_time`` both ways are paced as a serial line."""

    def __init__(self, upstream: int, lo: float, hi: float, *, char_time: float = 0.0, seed: int = 1) -> None:
        self.upstream, self.lo, self.hi, self.char_time = upstream, lo, hi, char_time
        self.rng = random.Random(seed)
        self.server: asyncio.Server | None = None
        self.port = 0

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._session, HOST, 0)
        self.port = self.server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        if self.server is not None:
            self.server.close()
            with contextlib.suppress(Exception):
                await self.server.wait_closed()

    async def _session(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(HOST, self.upstream)
        answer = {"new": False}
        pumps = [asyncio.create_task(self._pump(reader, up_writer, answer, up=True)),
                 asyncio.create_task(self._pump(up_reader, writer, answer, up=False))]
        await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        for pump in pumps:
            pump.cancel()
        for w in (writer, up_writer):
            w.close()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, answer: dict[str, bool], *,
                    up: bool) -> None:
        loop = asyncio.get_running_loop()
        free_at = shift = 0.0
        while data := await reader.read(4096):
            if up:
                answer["new"] = True
            elif answer["new"]:
                answer["new"] = False
                shift = self.rng.uniform(self.lo, self.hi)
            start = max(loop.time() + (0.0 if up else shift), free_at)
            free_at = start + len(data) * self.char_time
            await asyncio.sleep(max(0.0, free_at - loop.time()))
            writer.write(data)


@contextlib.contextmanager
def peer(script: str, *args: str) -> Iterator[int]:
    port = free_port()
    proc = subprocess.Popen([sys.executable, str(PEERS / script), "--port", str(port), *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError), socket.create_connection((HOST, port), timeout=1):
                break
            time.sleep(0.1)
        yield port
    finally:
        proc.terminate()
        proc.wait(10)


async def through_peer(script: str, args: Sequence[str], lo: float, hi: float, char_time: float,
                       links: Callable[[ScanTime | None, str], Links], seconds: float,
                       warmup: float) -> Figures:
    with peer(script, *args) as upstream:
        proxy = AnswerDelayProxy(upstream, lo, hi, char_time=char_time)
        await proxy.start()
        try:
            return await steady(links(None, f"socket://{HOST}:{proxy.port}"), SCREEN, seconds, warmup)
        finally:
            await proxy.close()


# ------------------------------------------------------------------------------------ reporting


def misses(fig: Figures, limit: int = 8) -> str:
    """The first reads without data: ``t s unit/holding address+count (0x0B | timeout)``."""
    shown = [f"{t:.1f}s u{unit} {address}+{count} {'timeout' if code == TIMEOUT else f'0x{code:02X}'}"
             for t, unit, address, count, code in fig.misses[:limit]]
    more = f" (+{len(fig.misses) - limit})" if len(fig.misses) > limit else ""
    return "; ".join(shown) + more


async def median_of(rounds: int, measure: Callable[[], Awaitable[Figures]]) -> tuple[Figures, list[float]]:
    """``rounds`` measurements: the one of median share, and every share."""
    figs = []
    for _ in range(rounds):
        figs.append(await measure())
        if figs[-1].misses:
            print(f"  reads without data: {misses(figs[-1])}", flush=True)
    figs.sort(key=lambda fig: fig.share)
    return figs[len(figs) // 2], [fig.share for fig in figs]


def fit(fig: Figures) -> str:
    """The sizing rule's verdict: ``yes: needed / capacity`` transactions/s."""
    return f"{'yes' if fig.fits else 'NO'}: {fig.needed:.1f} / {fig.capacity:.1f} ({fig.scheduled_demand} demanded)"


def row(case: str, answers: str, fig: Figures, target: str, shares: Sequence[float] = ()) -> list[object]:
    each = f" (rounds {', '.join(f'{100 * share:.1f}' for share in shares)})" if len(shares) > 1 else ""
    return [case, answers, f"{100 * fig.share:.1f} %{each}", f"{fig.with_data}/{fig.reads}", fig.tx_per_s,
            fig.plan_blocks, fig.demanded_blocks, fit(fig), target]


HEADERS = ["case", "controller answers", "reads with data", "with data / reads", "line tx/s", "plan blocks",
           "demanded blocks", "fits (needed / capacity tx/s)", "target"]


#: a sweep's points per kind: (longest scan s, share of reads with data, line transactions/s)
Points = dict[str, list[tuple[float, float, float]]]


def plot(points: Points, path: Path, title: str, before: Points | None = None,
         labels: tuple[str, str] = ("", "")) -> None:
    """Reads with data (top) and the line's transactions/s (bottom) against the longest scan."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"no plot: matplotlib is not installed; install it with: pip install -e '.[bench]' "
              f"(then rerun to write {path})")
        return
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.5, 7.5), sharex=True, height_ratios=(3, 2))
    for n, (kind, values) in enumerate(points.items()):
        runs = [(values, "o", "-", 1.0, labels[1])]
        if before and kind in before:
            runs.append((before[kind], "x", "--", 0.6, labels[0]))
        for series, marker, style, alpha, label in runs:
            xs = [1000 * x for x, _, _ in series]
            style_of = dict(marker=marker, linestyle=style, color=f"C{n}", alpha=alpha)
            top.plot(xs, [100 * y for _, y, _ in series], label=f"{kind} {label}".strip(), **style_of)
            bottom.plot(xs, [tx for _, _, tx in series], **style_of)
    top.axhline(99, color="grey", linestyle=":", linewidth=1, label="target 99 %")
    top.set_ylabel("reads answered with data, %")
    top.set_ylim(0, 103)
    top.set_title(title, fontsize=10)
    top.legend(fontsize=7, loc="lower left")
    bottom.set_ylabel("line transactions / s")
    bottom.set_xlabel("controller's longest scan, ms (answers within 0 to it; scans of half to all of it)")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"plot written to {path}")


CASES = ("slc", "slc-acc8", "startup", "load50", "df1", "peers", "sparkplug", "harsh", "sweep")
#: what a case's row or figure says when mosquitto is missing: loud, never a pass
NO_BROKER = "NOT MEASURED: MOSQUITTO NOT INSTALLED"


def cases(args: argparse.Namespace) -> set[str]:
    return set(args.only.split(",")) if args.only else set(CASES)


def sweep_kinds(args: argparse.Namespace) -> list[str]:
    """The sweep's simulated kinds (the SLC 150 with [sparkplug] on among them), as ``--quick`` and ``--kinds`` say."""
    if args.quick:
        return list(KINDS)[:1]
    names = [*KINDS, SPARKPLUG_SWEEP_KIND]
    return [k for k in names if not args.kinds or any(part in k for part in args.kinds.split(","))]


def wants_broker(args: argparse.Namespace) -> bool:
    only = cases(args)
    return "sparkplug" in only or ("sweep" in only and SPARKPLUG_SWEEP_KIND in sweep_kinds(args))


@contextlib.contextmanager
def sparkplug_broker(wanted: bool) -> Iterator[str | None]:
    """The ``[sparkplug]`` section of a mosquitto started for the run; None when not wanted, or (said loudly)
    when mosquitto is not installed."""
    if not wanted:
        yield None
        return
    path = mosquitto_path()
    if path is None:
        for stream in (sys.stdout, sys.stderr):
            print(f"!!! {NO_BROKER}: the sparkplug case and the sweep's Sparkplug curve need a broker "
                  "(Debian package mosquitto: apt-get install mosquitto) !!!", file=stream, flush=True)
        yield None
        return
    with tempfile.TemporaryDirectory() as tmp:
        broker = Broker(path, Path(tmp))
        broker.start()
        try:
            yield sparkplug_section(broker, Path(tmp))
        finally:
            broker.stop()


def publishing(fig: Figures) -> bool:
    """The edge node of a Sparkplug-on run was online at the window's end and published in it."""
    return fig.sparkplug is not None and fig.sparkplug[0] == "online" and fig.sparkplug[1] > 0


def node_note(fig: Figures) -> str:
    """The edge node of a Sparkplug-on run: ``online, N messages``, or loudly why the run measured nothing."""
    if fig.sparkplug is None:
        return ""
    state, published = fig.sparkplug
    if not publishing(fig):
        return f"NODE NOT PUBLISHING ({state}, {published} messages): NOT A MEASUREMENT"
    return f"{state}, {published} messages"


async def sparkplug_case(args: argparse.Namespace, sparkplug: str, longest: float, rows: list[list[object]],
                         figures: dict[str, object]) -> None:
    """The ``slc`` case at answers within 0-``longest`` with [sparkplug] off, then on: the rows side by side."""
    ms, shares_by_mode = int(longest * 1000), {}
    for mode, sections in (("off", ""), ("on", sparkplug)):
        fig, shares = await median_of(args.rounds, lambda sections=sections: steady(
            slc_links(scan_for(longest)), SCREEN, args.seconds, args.warmup, sections))
        shares_by_mode[mode] = fig.share
        note = node_note(fig)
        if mode == "off":
            target = f">= 99 %: {'met' if fig.share >= 0.99 else 'not met'}"
        else:
            delta = 100 * (fig.share - shares_by_mode["off"])
            met = abs(delta) <= 1 and (fig.share >= 0.99 or longest < 0.1) and publishing(fig)
            target = f"at most 1 point from off{', >= 99 %' if longest >= 0.1 else ''}: " \
                     f"{'met' if met else 'NOT MET'} ({delta:+.1f} points)"
            figures[f"sparkplug_delta_{ms}ms"] = delta
            figures[f"sparkplug_met_{ms}ms"] = met
        rows.append(row(f"SLC 150 9600, Sparkplug {mode}{f' ({note})' if note else ''}: holding 0-31 / 1 s, "
                        "32-63 / 2 s", f"scan {longest / 2:g}-{longest:g} s", fig, target, shares))
        figures[f"sparkplug_{mode}_{ms}ms"] = fig.share
        print(rows[-1], flush=True)


async def harsh_case(args: argparse.Namespace, rows: list[list[object]], figures: dict[str, object]) -> None:
    """The presets read continuously and written on a harsh line, beside the line's capacity: as the
    issue gives it (the defaults: its set needs about as much as the line has), and with the
    ``background_interval`` and fewer presets, a set that fits by the guide's sizing rule."""
    for background, presets in HARSH_RUNS:
        await _harsh_run(args, rows, figures, background, presets)


async def _harsh_run(args: argparse.Namespace, rows: list[list[object]], figures: dict[str, object],
                     background: float | None, presets: tuple[int, int]) -> None:
    writer = PresetWriter(1, 3, *presets, period=0.0)
    keys: dict[str, object] = {"stale_after": HARSH_STALE_AFTER}
    if background is not None:
        keys["background_interval"] = background
    links = slc_links(scan_for(HARSH_LONGEST), faults=HARSH_FAULTS, **keys)
    fig = await steady(links, (), args.seconds, args.warmup, readers=[writer])
    suffix = "" if background is None else f"_bg{background:g}_{presets[1]}"
    if fig.misses:
        print(f"  reads without data: {misses(fig)}", flush=True)
    met = fig.share >= 0.9 and fig.fits
    faults = ", ".join(f"{key} {value}" for key, value in HARSH_FAULTS.items())
    setting = "" if background is None else f", background_interval {background:g}"
    rows.append(row(f"SLC 150 9600, {faults} (1 in N), stale_after {HARSH_STALE_AFTER}{setting}: holding "
                    f"{presets[0]}-{sum(presets) - 1} continuously, FC6 after every {WRITE_EVERY}th read",
                    f"scan {HARSH_LONGEST / 2:g}-{HARSH_LONGEST:g} s", fig,
                    f">= 90 % with a set that fits: {'met' if met else 'NOT MET'}"))
    print(rows[-1], flush=True)
    writes = writer.write_codes(args.warmup)
    others = {code: n for code, n in writes.items() if code not in (0, STALE, TIMEOUT)}
    print(f"harsh: read transaction {1000 * fig.tx_time:.0f} ms (capacity {fig.capacity:.2f} tx/s), "
          f"{fig.scheduled_demand} demanded blocks of {fig.plan_blocks}, the set needs {fig.needed:.2f} tx/s: "
          f"{'fits' if fig.fits else 'DOES NOT FIT'}; writes {writes.total()}: acknowledged {writes[0]}, "
          f"0x0B {writes[STALE]}, timeouts {writes[TIMEOUT]}, other exceptions {others or 0}; the line from start: "
          f"{', '.join(f'{key} {value}' for key, value in fig.line.items())}", flush=True)
    found = dict(reads_with_data=fig.share, reads=fig.reads, tx_time_s=fig.tx_time, capacity=fig.capacity,
                 needed=fig.needed, demanded=fig.scheduled_demand, fits=fig.fits, met=met, writes=writes.total(),
                 writes_acked=writes[0], writes_0x0B=writes[STALE],
                 **{f"line_{key}": value for key, value in fig.line.items()})
    figures.update({f"harsh{suffix}_{key}": value for key, value in found.items()})


async def main_async(args: argparse.Namespace, sparkplug: str | None = None) -> tuple[dict[str, object], Points]:
    only = cases(args)
    seconds, warmup = args.seconds, args.warmup
    rows: list[list[object]] = []
    figures: dict[str, object] = {}
    points: Points = {}
    slc_cases = (0.05,) if args.quick else (0.05, 0.1)
    if "slc" in only:
        for longest in slc_cases:
            fig, shares = await median_of(args.rounds, lambda longest=longest: steady(
                slc_links(scan_for(longest)), SCREEN, seconds, warmup))
            rows.append(row("SLC 150 9600: holding 0-31 / 1 s, 32-63 / 2 s", f"scan {longest / 2:g}-{longest:g} s",
                            fig, ">= 99 %", shares))
            figures[f"slc_{int(longest * 1000)}ms"] = fig.share
            print(rows[-1], flush=True)
    if "slc-acc8" in only:
        fig, shares = await median_of(args.rounds, lambda: steady(slc_links(scan_for(0.25)), ACC8, seconds, warmup))
        rows.append(row("SLC 150 9600: holding 0-7 / 1 s", "scan 0.125-0.25 s", fig, ">= 99 %", shares))
        figures["slc_acc8_250ms"] = fig.share
        print(rows[-1], flush=True)
    if "df1" in only:
        for name in [k for k in list(KINDS)[1:] if not args.kinds or any(p in k for p in args.kinds.split(","))]:
            fig = await steady(KINDS[name](REALISTIC_SCAN, ""), SCREEN, seconds, warmup)
            if fig.misses:
                print(f"  reads without data: {misses(fig)}", flush=True)
            rows.append(row(f"{name}: per unit read holding 0-31 / 1 s, 32-63 / 2 s",
                            f"scan {REALISTIC_SCAN.text()} s", fig, "fresh whenever it fits"))
            figures["df1_line8" if "8 stations" in name else "df1_half" if "half" in name else "df1_full"] = fig.share
            print(rows[-1], flush=True)
    if "peers" in only and PEERS.exists():
        peer_cases = [
            ("interop SLC 150 9600", "slc_ascii_peer.py", ["--model", "150", "--baud", "9600"], 0.0, 0.05, 0.0,
             slc_links),
            ("interop SLC 150 9600", "slc_ascii_peer.py", ["--model", "150", "--baud", "9600"], 0.0, 0.1, 0.0,
             slc_links),
            ("interop SLC 5/04 DF1 full duplex, paced 19200 by the proxy", "df1_peer.py", ["--crc"], 0.02, 0.06,
             DF1_CHAR, df1_full_links),
            ("interop 3 stations DF1 half duplex 19200", "df1_halfduplex_peer.py",
             ["--stations", "1,2,3", "--crc", "--baud", "19200"], 0.02, 0.06, 0.0, df1_half_links),
        ]
        for name, script, peer_args, lo, hi, char_time, links in peer_cases[: 1 if args.quick else None]:
            measure = functools.partial(through_peer, script, peer_args, lo, hi, char_time, links, seconds, warmup)
            fig, shares = await median_of(args.rounds if "SLC 150" in name else 1, measure)
            rows.append(row(f"{name}: holding 0-31 / 1 s, 32-63 / 2 s", f"held uniform {lo:g}-{hi:g} s", fig,
                            ">= 99 %" if "SLC 150" in name else "fresh whenever it fits", shares))
            figures[f"peer_{script.removesuffix('.py')}_{int(hi * 1000)}ms"] = fig.share
            print(rows[-1], flush=True)
    elif "peers" in only:
        print(f"interop peers not found at {PEERS}: measuring the simulators only")
    if "sparkplug" in only and sparkplug is None:
        rows.append(["SLC 150 9600, Sparkplug on", NO_BROKER, "-", "-", "-", "-", "-", "-", NO_BROKER])
        figures["sparkplug"] = NO_BROKER
    elif "sparkplug" in only:
        for longest in slc_cases:
            await sparkplug_case(args, sparkplug, longest, rows, figures)
    if "harsh" in only:
        await harsh_case(args, rows, figures)
    print(table(HEADERS, rows))
    if "startup" in only:
        runs = [await startup(slc_links(None)) for _ in range(1 if args.quick else args.repeats)]
        median = statistics.median(runs)
        print(f"start-up, SLC 150 9600 answering at once: first data for holding 0-31 after "
              f"{', '.join(f'{r:.2f}' for r in runs)} s (median {median:.2f} s; target <= 2.5 s)")
        figures["startup_s"] = median
    if "load50" in only:
        early_bad, early, late_bad, late = await load50(slc_links(None), 6.0 if args.quick else max(seconds, 10.0))
        print(f"50 connections from the start, SLC 150 9600 answering at once: 0x0B {early_bad}/{early} in the "
              f"first 3 s, {late_bad}/{late} after (target 0 after)")
        figures["load50_0x0B_after_3s"] = late_bad
    if "sweep" in only:
        sweep = (SWEEP[0], SWEEP[-1]) if args.quick else SWEEP
        kinds = sweep_kinds(args)
        if SPARKPLUG_SWEEP_KIND in kinds and sparkplug is None:
            print(f"!!! sweep: {SPARKPLUG_SWEEP_KIND}: {NO_BROKER} !!!", flush=True)
            figures["sweep_sparkplug"] = NO_BROKER
            kinds.remove(SPARKPLUG_SWEEP_KIND)
        # the independent SLC 150 peer, its every answer held uniform(0, J) by the proxy (the issue's own
        # measure of a controller that "answers within J")
        peer_sweep = not args.quick and PEERS.exists() and (not args.kinds or any(
            part in PEER_SWEEP_KIND for part in args.kinds.split(",")))
        sweep_rows = []
        for name in [*kinds, *([PEER_SWEEP_KIND] if peer_sweep else [])]:
            for longest in sweep:
                if name == PEER_SWEEP_KIND:
                    fig = await through_peer("slc_ascii_peer.py", ["--model", "150", "--baud", "9600"], 0.0, longest,
                                             0.0, slc_links, seconds, warmup)
                elif name == SPARKPLUG_SWEEP_KIND:
                    fig = await steady(slc_links(scan_for(longest)), SCREEN, seconds, warmup, sparkplug or "")
                else:
                    fig = await steady(KINDS[name](scan_for(longest), ""), SCREEN, seconds, warmup)
                points.setdefault(name, []).append((longest, fig.share, fig.tx_per_s))
                sweep_rows.append([f"{name}{f' ({note})' if (note := node_note(fig)) else ''}", f"{1000 * longest:g}",
                                   f"{100 * fig.share:.1f} %", fig.tx_per_s, fig.plan_blocks, fig.demanded_blocks,
                                   fit(fig)])
                if fig.misses:
                    print(f"  reads without data: {misses(fig)}", flush=True)
                print(sweep_rows[-1], flush=True)
        print(table(["kind", "longest scan ms", "reads with data", "line tx/s", "plan blocks", "demanded blocks",
                     "fits (needed / capacity tx/s)"], sweep_rows))
    return figures, points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CI smoke: short windows, one point per case, no plot")
    parser.add_argument("--seconds", type=float, help="measuring window per case (default 30; quick 2)")
    parser.add_argument("--warmup", type=float, help="seconds after start before counting (default 10; quick 1)")
    parser.add_argument("--repeats", type=int, default=3, help="start-up runs (median; default 3)")
    parser.add_argument("--rounds", type=int, default=1, help="rounds of each SLC 150 case with a 99 %% target: "
                                                               "the median is reported, every round beside it")
    parser.add_argument("--only", default="", help=f"comma-separated cases: {', '.join(CASES)}")
    parser.add_argument("--kinds", default="", help="the sweep's and the df1 case's kinds whose name contains one "
                                                     "of these (comma-separated; default every kind)")
    parser.add_argument("--png", default=str(ROOT / "bench" / "freshness.png"), help="the sweep's plot")
    parser.add_argument("--json", default="", help="write the figures and the sweep's points to this file")
    parser.add_argument("--compare", default="",
                        help="--json files of earlier runs (comma-separated): their sweeps drawn dashed")
    parser.add_argument("--label", default="", help="the legend's label of this run's curves (e.g. 'after')")
    parser.add_argument("--compare-label", default="before", help="the legend's label of --compare's curves")
    parser.add_argument("--plot-only", default="",
                        help="--json files (comma-separated) whose sweeps are this run's curves: plot, measure nothing")
    parser.add_argument("--title", default="Reads with data vs controller answer time (default config, no faults)")
    args = parser.parse_args()
    args.seconds = args.seconds if args.seconds is not None else (2.0 if args.quick else 30.0)
    args.warmup = args.warmup if args.warmup is not None else (1.0 if args.quick else 10.0)
    def sweeps(files: str) -> Points:
        merged: Points = {}
        for name in files.split(","):
            sweep = json.loads(Path(name).read_text())["sweep"]
            merged.update({kind: [(x, y, tx) for x, y, tx in values] for kind, values in sweep.items()})
        return merged

    if args.plot_only:
        figures: dict[str, object] = {}
        points = sweeps(args.plot_only)
    else:
        print_machine()
        with sparkplug_broker(wants_broker(args)) as sparkplug:
            figures, points = asyncio.run(main_async(args, sparkplug))
    if args.json:
        Path(args.json).write_text(json.dumps({"figures": figures, "sweep": points}, indent=1))
    if args.png and points and not args.quick:
        before = sweeps(args.compare) if args.compare else None
        plot(points, Path(args.png), args.title, before, (args.compare_label, args.label))
    if figures:
        result(**figures)
    if NO_BROKER in figures.values() and (mosquitto_required() or not args.quick):
        sys.exit(f"{NO_BROKER}: a Sparkplug figure was asked for and none was measured")


if __name__ == "__main__":
    main()
