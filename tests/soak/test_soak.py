"""Fault soak: both protocols through a fault-injecting proxy while SCADA clients read and write.

::

    pymodbus clients --Modbus TCP--> Gateway --socket://--> FaultProxy --> serve_tcp(simulator)
      readers: holding 0-7                       drops, bit flips, delays, split/merged chunks,
      writers: one per holding 0-5               duplicated chunks, cut connections, outages

Unit 1 is an SLC 150 (ASCII protocol, holding 0-7 = accumulators 901-908); unit 2 an SLC 5/04
(DF1 full duplex, holding 0-7 = N7:10-N7:17).  Both answer at the end of their program scan
(``REALISTIC_SCAN``, 20-60 ms), as real controllers do.  Both ladders are frozen (``ladder=0``): a cell
changes only when a write is applied, or when the test itself changes the marker (holding 7)
during an outage.  Each simulator is wrapped so that every change of a cell is recorded with
the loop time at which the controller made it: the history of every cell.

Checked, for every transaction:

* every value served is one the controller held at some moment in
  ``[t_request - tolerance, t_reply]``, with ``tolerance`` = ``stale_after`` + the fast scan
  period + the longest a reply can take to reach the cache (retries, proxy delays);
* an acknowledged write was applied exactly once (values are unique per cell; compared with
  the simulator's ``applied_writes``); a write answered with an exception (0x0B) or never
  answered was applied at most once; nothing was applied that no client asked for;
* after an acknowledged write, the writer reads its cell back: it gets its own value or 0x0B,
  never an older value (read your writes);
* after an outage of 10 s (the proxy cuts every connection and hangs up on every reconnect),
  the time from its end to the first read of a value changed during the outage (recovery);
* memory: RSS and the Python heap held by ``gateway`` code (tracemalloc) at the start and end.

Quick mode (default, CI): about 45 s.  Long mode: ``pytest tests/soak --soak -s`` (10 min of
faults, 4 outages); ``SOAK_REPORT=path.json`` writes the figures (RELIABILITY.md).
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import gc
import json
import logging
import random
import sys
import time
import tracemalloc
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.sim import create_simulator
from gateway.sim.scan import REALISTIC_SCAN
from gateway.sim.serve import serve_tcp

from .conftest import SoakPlan
from .proxy import FAULT_KINDS, FaultProfile, FaultProxy

HOST = "127.0.0.1"
TARGET_FAILED = 0x0B
CELLS = 8  # holding 0-7 are checked
WRITTEN = 6  # holding 0-5 each have one writer
MARKER = 7  # holding 7: changed by the test during each outage
FIRST_VALUE = 100  # written values start here (above every initial value)
MAX_VALUE = 9999  # the SLC 100/150 word limit
RECOVERY_LIMIT = 35.0  # seconds: the drivers' reconnect backoff is capped at 30 s

#: Per chunk and per direction.  A delay up to 0.4 s exceeds the SLC reply timeout (0.3 s).
PROFILE = FaultProfile(
    drop=0.01,
    flip=0.01,
    delay=0.008,
    max_delay=0.4,
    split=0.05,
    merge=0.03,
    duplicate=0.01,
    cut=0.001,
)


# --------------------------------------------------------------------------------------------
# The controllers' history


class History:
    """The values one cell held, with the loop time each started."""

    __slots__ = ("times", "values")

    def __init__(self, initial: int) -> None:
        self.times = [float("-inf")]
        self.values = [initial]

    def record(self, now: float, value: int) -> None:
        if value != self.values[-1]:
            self.times.append(now)
            self.values.append(value)

    def held_within(self, value: int, low: float, high: float) -> bool:
        first = bisect.bisect_right(self.times, low) - 1
        last = bisect.bisect_right(self.times, high) - 1
        return value in self.values[max(first, 0) : last + 1]

    def around(self, moment: float, span: int = 3) -> list[tuple[float, int]]:
        i = bisect.bisect_right(self.times, moment) - 1
        return list(zip(self.times[max(0, i - span) : i + span + 1], self.values[max(0, i - span) : i + span + 1],
                        strict=True))


class RecordingDevice:
    """A simulator, as ``serve_tcp`` sees it, that records every change of the cells under test."""

    def __init__(self, inner: Any, read_cell: Callable[[int], int], write_cell: Callable[[int, int], None]) -> None:
        self.inner = inner
        self._read_cell = read_cell
        self._write_cell = write_cell
        self.history = [History(read_cell(cell)) for cell in range(CELLS)]

    def _check(self, now: float) -> None:
        for cell, history in enumerate(self.history):
            history.record(now, self._read_cell(cell))

    def receive(self, data: bytes, now: float) -> Sequence[Any]:
        out = self.inner.receive(data, now)
        self._check(now)
        return out  # type: ignore[no-any-return]

    def poll(self, now: float) -> Sequence[Any]:
        out = self.inner.poll(now)
        self._check(now)
        return out  # type: ignore[no-any-return]

    def next_deadline(self) -> float | None:
        return self.inner.next_deadline()  # type: ignore[no-any-return]

    def set_cell(self, cell: int, value: int) -> None:
        """Change a cell behind the gateway's back (the test's own change, recorded)."""
        self._write_cell(cell, value)
        self.history[cell].record(asyncio.get_running_loop().time(), self._read_cell(cell))


# --------------------------------------------------------------------------------------------
# One link under test


@dataclass
class LinkStats:
    reads_ok: int = 0
    reads_stale: int = 0
    reads_other: Counter[str] = field(default_factory=Counter)
    values_checked: int = 0
    wrong_values: list[dict[str, Any]] = field(default_factory=list)
    readbacks: int = 0
    readback_stale: int = 0
    readback_wrong: list[dict[str, Any]] = field(default_factory=list)
    #: per cell: value -> outcome ("ok", "0x0B", "client error: ...")
    writes: list[dict[int, str]] = field(default_factory=lambda: [{} for _ in range(WRITTEN)])
    recoveries: list[float] = field(default_factory=list)
    reconnect_attempts_in_outages: list[int] = field(default_factory=list)


@dataclass
class Link:
    name: str
    protocol: str
    unit: int
    sim: Any
    device: RecordingDevice
    server: asyncio.Server
    proxy: FaultProxy
    stale_after: float
    timeout: float
    retries: int
    fast_interval: float
    applied: Callable[[], list[tuple[int, int]]]
    stats: LinkStats = field(default_factory=LinkStats)

    @property
    def tolerance(self) -> float:
        """How old a served value may be: staleness + scan period + the longest transaction."""
        return (
            self.stale_after
            + self.fast_interval
            + self.timeout * (self.retries + 2)
            + 2 * PROFILE.max_delay
            + 0.5
        )

    def toml(self) -> str:
        lines = [
            "[[link]]",
            f'name = "{self.name}"',
            f'protocol = "{self.protocol}"',
            f'port = "{self.proxy.url}"',
            f"unit = {self.unit}",
            f"timeout = {self.timeout}",
            f"retries = {self.retries}",
            f"stale_after = {self.stale_after}",
            f"fast_interval = {self.fast_interval}",
            "slow_interval = 5.0",
        ]
        if self.protocol == "df1":
            lines += ["", "[[link.map]]", 'table = "holding"', "start = 0", 'address = "N7:10"', f"count = {CELLS}"]
        return "\n".join(lines) + "\n"


async def slc_link(seed: int) -> Link:
    sim = create_simulator("slc150", {"ladder": "0", "seed": str(seed), "scan": REALISTIC_SCAN.text()})

    def read(cell: int) -> int:
        return sim.word(2 * cell) & 0x7FFF  # type: ignore[no-any-return]

    def write(cell: int, value: int) -> None:
        sim.set_word(2 * cell, value)

    def applied() -> list[tuple[int, int]]:
        return [(address // 2, value) for kind, address, value in sim.applied_writes if kind == "word"]

    return await _link("slc", "slc-ascii", 1, sim, read, write, applied, seed, stale_after=2.0, reply_timeout=0.3)


async def df1_link(seed: int) -> Link:
    sim = create_simulator("slc504", {"ladder": "0", "seed": str(seed), "scan": REALISTIC_SCAN.text()})

    def read(cell: int) -> int:
        return sim.word("N7", 10 + cell)  # type: ignore[no-any-return]

    def write(cell: int, value: int) -> None:
        sim.set_word("N7", 10 + cell, value)

    def applied() -> list[tuple[int, int]]:
        out = []
        for kind, address, data in sim.applied_writes:
            if kind == "write" and address.startswith("N7:"):
                out.append((int(address[3:]) - 10, int.from_bytes(data, "little")))
        return out

    return await _link("df1", "df1", 2, sim, read, write, applied, seed + 1, stale_after=3.0, reply_timeout=0.5)


async def _link(
    name: str,
    protocol: str,
    unit: int,
    sim: Any,
    read: Callable[[int], int],
    write: Callable[[int, int], None],
    applied: Callable[[], list[tuple[int, int]]],
    seed: int,
    *,
    stale_after: float,
    reply_timeout: float,
) -> Link:
    device = RecordingDevice(sim, read, write)
    server = await serve_tcp(device, HOST, 0)
    proxy = FaultProxy(server.sockets[0].getsockname()[1], seed=seed, profile=PROFILE)
    await proxy.start()
    return Link(name, protocol, unit, sim, device, server, proxy, stale_after, reply_timeout, 3, 0.05, applied)


# --------------------------------------------------------------------------------------------
# SCADA


async def modbus_client(port: int, reply_timeout: float) -> AsyncModbusTcpClient:
    # retries=0: a client that resends a write on timeout would apply it twice by itself.
    client = AsyncModbusTcpClient(HOST, port=port, timeout=reply_timeout, retries=0)
    assert await client.connect(), "cannot connect to the gateway"
    return client


def check_values(link: Link, registers: Sequence[int], first: int, sent: float, received: float) -> None:
    stats = link.stats
    low = sent - link.tolerance
    for offset, value in enumerate(registers):
        cell = first + offset
        stats.values_checked += 1
        history = link.device.history[cell]
        if not history.held_within(value, low, received):
            stats.wrong_values.append(
                {"cell": cell, "value": value, "sent": round(sent, 3), "received": round(received, 3),
                 "history": history.around(sent)}
            )


async def reader(link: Link, port: int, stop: asyncio.Event, seed: int) -> None:
    rng = random.Random(seed)
    loop = asyncio.get_running_loop()
    client = await modbus_client(port, 10)
    stats = link.stats
    try:
        while not stop.is_set():
            sent = loop.time()
            try:
                reply = await client.read_holding_registers(0, count=CELLS, device_id=link.unit)
            except ModbusException as exc:
                stats.reads_other[f"client error: {type(exc).__name__}"] += 1
                await asyncio.sleep(0.1)
                continue
            received = loop.time()
            if reply.isError():
                if reply.exception_code == TARGET_FAILED:
                    stats.reads_stale += 1
                else:
                    stats.reads_other[f"exception 0x{reply.exception_code:02X}"] += 1
            else:
                stats.reads_ok += 1
                check_values(link, reply.registers, 0, sent, received)
            await asyncio.sleep(rng.uniform(0.005, 0.04))
    finally:
        client.close()


async def writer(link: Link, port: int, cell: int, stop: asyncio.Event, seed: int) -> None:
    rng = random.Random(seed)
    loop = asyncio.get_running_loop()
    client = await modbus_client(port, 60)
    outcomes = link.stats.writes[cell]
    stats = link.stats
    value = FIRST_VALUE
    try:
        while not stop.is_set() and value < MAX_VALUE:
            value += 1
            try:
                if value % 2:
                    reply = await client.write_register(cell, value, device_id=link.unit)
                else:
                    reply = await client.write_registers(cell, [value], device_id=link.unit)
            except ModbusException as exc:
                outcomes[value] = f"client error: {type(exc).__name__}"
                await asyncio.sleep(0.1)
                continue
            if reply.isError():
                outcomes[value] = f"0x{reply.exception_code:02X}"
            else:
                outcomes[value] = "ok"
                # Read your writes: the cell now holds this value until this writer writes again.
                sent = loop.time()
                try:
                    back = await client.read_holding_registers(cell, count=1, device_id=link.unit)
                except ModbusException:
                    back = None
                if back is not None and not back.isError():
                    stats.readbacks += 1
                    if back.registers[0] != value:
                        stats.readback_wrong.append(
                            {"cell": cell, "written": value, "read": back.registers[0], "sent": round(sent, 3),
                             "history": link.device.history[cell].around(sent)}
                        )
                elif back is not None and back.exception_code == TARGET_FAILED:
                    stats.readback_stale += 1
            await asyncio.sleep(rng.uniform(0.2, 1.0))  # a setpoint now and then, as SCADA writes
    finally:
        client.close()


async def measure_recovery(link: Link, port: int, marker: int, ended: float, limit: float) -> float:
    """Seconds from ``ended`` to the first read of the marker value set during the outage."""
    loop = asyncio.get_running_loop()
    client = await modbus_client(port, 5)
    try:
        while loop.time() - ended < limit:
            with contextlib.suppress(ModbusException):
                reply = await client.read_holding_registers(MARKER, count=1, device_id=link.unit)
                if not reply.isError() and reply.registers[0] == marker:
                    return loop.time() - ended
            await asyncio.sleep(0.01)
    finally:
        client.close()
    return float("inf")


async def until_served(link: Link, port: int, limit: float = 15.0) -> None:
    client = await modbus_client(port, 5)
    try:
        async with asyncio.timeout(limit):
            while True:
                reply = await client.read_holding_registers(0, count=CELLS, device_id=link.unit)
                if not reply.isError():
                    return
                await asyncio.sleep(0.05)
    finally:
        client.close()


# --------------------------------------------------------------------------------------------
# Memory


def rss_kib() -> int:
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


#: Allocated by gateway code, and not on behalf of a simulator (its ``applied_writes`` grows by design)
#: or of the test itself: any of the innermost ``TRACE_FRAMES`` frames decides.
_GATEWAY_CODE = [
    tracemalloc.Filter(True, "*/gateway/*"),
    tracemalloc.Filter(False, "*/gateway/sim/*", all_frames=True),
    tracemalloc.Filter(False, "*/tests/*", all_frames=True),
]
TRACE_FRAMES = 8


class Memory:
    """RSS, every traced Python allocation, and those made by gateway code (not the simulators)."""

    def __init__(self) -> None:
        gc.collect()
        self.snapshot = tracemalloc.take_snapshot().filter_traces(_GATEWAY_CODE)
        self.figures = {
            "rss_kib": rss_kib(),
            "traced_kib": tracemalloc.get_traced_memory()[0] // 1024,
            "gateway_traced_kib": sum(stat.size for stat in self.snapshot.statistics("filename")) // 1024,
        }

    def growth_since(self, start: Memory, top: int = 8) -> list[str]:
        """The lines of gateway code whose allocations grew most."""
        differences = self.snapshot.compare_to(start.snapshot, "lineno")
        return [str(d) for d in differences[:top] if d.size_diff > 0]


# --------------------------------------------------------------------------------------------
# The soak


def gateway_config(links: Sequence[Link]) -> Any:
    text = '[modbus]\nlisten = "127.0.0.1:0"\nmax_connections = 64\nidle_timeout = 0\n\n'
    return parse_config(text + "\n".join(link.toml() for link in links))


def write_report(links: Sequence[Link], plan: SoakPlan, started: float, mem: dict[str, Any],
                 gw: Gateway) -> dict[str, Any]:
    report: dict[str, Any] = {
        "mode": plan.name,
        "seed": plan.seed,
        "revision": plan.revision,
        "minutes": round((time.monotonic() - started) / 60, 2),
        "memory": mem,
        "python": sys.version.split()[0],
        "links": {},
    }
    for link, unit in zip(links, gw.units, strict=True):
        stats = link.stats
        counters = unit.driver.counters
        applied = Counter(link.applied())
        outcomes = Counter(o if o in ("ok", "0x0B") else "other" for w in stats.writes for o in w.values())
        report["links"][link.name] = {
            "modbus_reads_ok": stats.reads_ok,
            "modbus_reads_0x0B": stats.reads_stale,
            "modbus_reads_other": dict(stats.reads_other),
            "values_checked": stats.values_checked,
            "wrong_values": len(stats.wrong_values),
            "writes": dict(outcomes),
            "writes_applied": sum(applied.values()),
            "readbacks": stats.readbacks,
            "readbacks_0x0B": stats.readback_stale,
            "readbacks_wrong": len(stats.readback_wrong),
            "controller_transactions": counters.transactions,
            "controller_errors": counters.errors,
            "timeouts": counters.timeouts,
            "retries": counters.retries,
            "crc_errors": counters.crc_errors,
            "reconnects": counters.reconnects,
            "faults_injected": link.proxy.summary(),
            "recovery_seconds": [round(r, 2) for r in stats.recoveries],
            "reconnect_attempts_during_outages": stats.reconnect_attempts_in_outages,
        }
    return report


def write_problems(link: Link) -> list[str]:
    """Lost, duplicated and phantom writes of ``link``."""
    problems: list[str] = []
    applied = Counter(link.applied())
    for cell, outcomes in enumerate(link.stats.writes):
        for value, outcome in outcomes.items():
            times = applied.get((cell, value), 0)
            if outcome == "ok" and times != 1:
                problems.append(f"{link.name}: holding {cell} = {value} acknowledged, applied {times} times")
            elif outcome != "ok" and times > 1:
                problems.append(f"{link.name}: holding {cell} = {value} answered {outcome}, applied {times} times")
    for (cell, value), times in applied.items():
        if not (0 <= cell < WRITTEN) or value not in link.stats.writes[cell]:
            problems.append(f"{link.name}: holding {cell} = {value} applied {times} times, never requested")
    return problems


@pytest.mark.soak
async def test_soak(soak_plan: SoakPlan, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR)  # links going down and up are expected: keep the log short
    plan = soak_plan
    started = time.monotonic()
    if tracemalloc.is_tracing():
        tracemalloc.stop()
    tracemalloc.start(TRACE_FRAMES)
    loop = asyncio.get_running_loop()
    links = [await slc_link(plan.seed), await df1_link(plan.seed)]
    stop = asyncio.Event()
    tasks: list[asyncio.Task[None]] = []
    mem: dict[str, Any] = {}
    memory: dict[str, Memory] = {}
    try:
        async with Gateway(gateway_config(links)) as gw:
            port = gw.port
            await asyncio.gather(*(until_served(link, port) for link in links))
            memory["start"] = Memory()
            mem["start"] = memory["start"].figures
            for n, link in enumerate(links):
                for k in range(2):
                    tasks.append(asyncio.create_task(reader(link, port, stop, plan.seed + 10 * n + k)))
                for cell in range(WRITTEN):
                    tasks.append(asyncio.create_task(writer(link, port, cell, stop, plan.seed + 100 * n + cell)))
            marker = 1000
            for _ in range(plan.cycles):
                for link in links:
                    link.proxy.faults_enabled = True
                await asyncio.sleep(plan.fault_seconds)
                for link in links:
                    link.proxy.faults_enabled = False
                refused_before = [link.proxy.refused_during_outage for link in links]
                await asyncio.gather(*(link.proxy.begin_outage() for link in links))
                marker += 1
                for link in links:
                    link.device.set_cell(MARKER, marker)
                await asyncio.sleep(plan.outage_seconds)
                for link in links:
                    link.proxy.end_outage()
                ended = loop.time()
                recoveries = await asyncio.gather(
                    *(measure_recovery(link, port, marker, ended, 60.0) for link in links)
                )
                for link, recovery, before in zip(links, recoveries, refused_before, strict=True):
                    link.stats.recoveries.append(recovery)
                    link.stats.reconnect_attempts_in_outages.append(link.proxy.refused_during_outage - before)
            await asyncio.sleep(plan.calm_seconds)
            stop.set()
            async with asyncio.timeout(120):
                await asyncio.gather(*tasks)
            # Everything settled: the gateway serves exactly what the controllers hold.
            client = await modbus_client(port, 5)
            try:
                for link in links:
                    await until_served(link, port)
                    reply = await client.read_holding_registers(0, count=CELLS, device_id=link.unit)
                    assert not reply.isError(), (link.name, reply)
                    assert reply.registers == [h.values[-1] for h in link.device.history], link.name
            finally:
                client.close()
            memory["end"] = Memory()
            mem["end"] = memory["end"].figures
            mem["gateway_growth_top"] = memory["end"].growth_since(memory["start"])
            report = write_report(links, plan, started, mem, gw)
    finally:
        stop.set()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for link in links:
            await link.proxy.close()
            link.server.close()
            await link.server.wait_closed()
        tracemalloc.stop()

    text = json.dumps(report, indent=2, default=str)
    print(f"\nsoak report ({plan.name}):\n{text}")
    if plan.report:
        await asyncio.to_thread(Path(plan.report).write_text, text + "\n", "utf-8")

    problems: list[str] = []
    for link in links:
        stats = link.stats
        problems += [f"{link.name}: wrong value served: {w}" for w in stats.wrong_values[:10]]
        problems += [f"{link.name}: read-your-write violated: {w}" for w in stats.readback_wrong[:10]]
        problems += write_problems(link)[:20]
        problems += [f"{link.name}: read answered {k} x{n}" for k, n in stats.reads_other.items()]
        bad_writes = Counter(o for w in stats.writes for o in w.values() if o not in ("ok", "0x0B"))
        problems += [f"{link.name}: write answered {k} x{n}" for k, n in bad_writes.items()]
        # Recovery is bounded by the reconnect backoff (capped at 30 s) plus one scan.
        slow = [round(r, 1) for r in stats.recoveries if r > RECOVERY_LIMIT]
        if slow:
            problems.append(f"{link.name}: recovery after an outage took longer than {RECOVERY_LIMIT:g} s: {slow}")
    assert not problems, "\n".join(problems)

    for link in links:
        figures = report["links"][link.name]
        # The soak really soaked: traffic flowed and every kind of fault was injected.
        assert figures["modbus_reads_ok"] >= 50, figures
        assert figures["writes"].get("ok", 0) >= 20, figures
        injected = link.proxy.summary()
        assert all(injected[kind] > 0 for kind in FAULT_KINDS if kind != "cut"), injected
    # No growth: the gateway's own heap and the process RSS stay flat.
    start, end = mem["start"], mem["end"]
    assert end["gateway_traced_kib"] - start["gateway_traced_kib"] < 1024, mem
    assert end["rss_kib"] - start["rss_kib"] < 64 * 1024, mem
