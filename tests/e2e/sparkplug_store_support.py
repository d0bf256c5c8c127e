"""Store and forward end to end (issue 43), the helpers and the runs of its three test modules
(``test_sparkplug_store.py``: the broker stopped, and a store that fills; ``test_sparkplug_store_silent.py``;
``test_sparkplug_store_sigkill.py``): one module each so that pytest-xdist runs the minute-long outages on
different workers.  No value change is lost while the broker is away.

``slc-gateway run`` in its own process publishes two simulated SLC 5/04s (``press``, ``oven``) to Debian's
mosquitto through a TCP proxy the test controls; the independent host application (tests/peers) records
everything.  The test changes values on the simulators with Modbus writes (each write's confirmed value is
a value change the gateway publishes), before, during and after an outage:

* ``broker``: mosquitto is stopped for ``OUTAGE`` seconds (the gateway's reconnects are refused);
* ``silent``: the gateway's connection is cut silently (the proxy drops every packet both ways, and
  swallows new connections), so only the keepalive finds it: what was published in the last 1.5 x
  keepalive before that is in doubt (QoS 0) and is replayed too;
* ``sigkill``: the broker is stopped, and in the middle of the outage the gateway is killed (SIGKILL)
  and started again (its simulators start again too, from zero).  The kill comes once every value
  written so far is committed to the store's file (the test reads it beside the gateway): a SIGKILL may
  lose the batch not yet committed (the guide says so), which is not what this test is about.  Values are
  written again as soon as the new process serves Modbus, before its links have answered.

Every written value reaches a host once live (DBIRTH or DDATA) or as historical DDATA (``is_historical``,
its original timestamp), per metric in timestamp order within the live and within the historical
stream; the host sees no violation of the specification (seq, bdSeq, births first).  A store that
fills drops the oldest, counts (/api/status) and says so (the log), and the node goes on publishing
live data.  Latency of live data during a replay is measured by ``bench/sparkplug_store.py``, not here.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import urllib.request
from collections.abc import AsyncIterator, Callable, Iterable
from functools import partial
from pathlib import Path
from typing import Any

from cli_support import stop
from modbus_support import connect
from mosquitto_support import HOST, Broker, import_host

from gateway.sparkplug.store import store_path
from tests.net import free_port
from tests.waiting import until

GROUP, NODE = "plant1", "saf"
KEEPALIVE = 5
DEVICES = ("press", "oven")
#: seconds the broker (or the path to it) is away; the issue's acceptance is 60 s
OUTAGE = float(os.environ.get("SLC_GATEWAY_STORE_OUTAGE", "60"))
STARTUP = 40
SparkplugHost = import_host()


class Proxy:
    """A TCP proxy to the broker: ``pass`` forwards, ``refuse`` closes new connections at once, ``silent``
    accepts and forwards nothing either way (a cable cut: only a keepalive finds it)."""

    def __init__(self, target: int) -> None:
        self.target = target
        self.port = free_port()
        self.mode = "pass"
        self._open: set[asyncio.StreamWriter] = set()
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, HOST, self.port)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.mode == "refuse":
            writer.close()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(HOST, self.target)
        except OSError:
            writer.close()
            return
        self._open |= {writer, up_writer}
        with contextlib.suppress(asyncio.CancelledError):  # the test's loop ends with connections open
            await asyncio.gather(self._pipe(reader, up_writer), self._pipe(up_reader, writer), return_exceptions=True)
        for end in (writer, up_writer):
            self._open.discard(end)
            end.close()

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while data := await reader.read(65536):
            if self.mode != "silent":
                writer.write(data)
                await writer.drain()
        writer.close()

    def close_all(self) -> None:
        for end in list(self._open):
            end.close()

    async def stop(self) -> None:
        self.close_all()
        if self._server is not None:
            self._server.close()


def write_config(directory: Path, proxy: int, modbus: int, http: int, *, store_max_mb: float = 100.0) -> Path:
    links = "".join(
        f'[[link]]\nname = "{name}"\nprotocol = "df1"\nport = "sim://slc504?ladder=0&instance={name}"\nunit = {unit}\n'
        '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 40\n\n'
        for unit, name in enumerate(DEVICES, start=1))
    path = directory / "gateway.toml"
    path.write_text(
        f'[modbus]\nlisten = "{HOST}:{modbus}"\n\n[metrics]\nlisten = "{HOST}:{http}"\n\n'
        f'[sparkplug]\nbroker = "mqtt://{HOST}:{proxy}"\ngroup_id = "{GROUP}"\nedge_node_id = "{NODE}"\n'
        f'keepalive = {KEEPALIVE}\nreconnect_min = 0.2\nreconnect_max = 1.0\nstatus_interval = 3600\n'
        f'state_file = "bdseq.json"\nstore_max_mb = {store_max_mb}\n\n{links}',
        encoding="utf-8")
    return path


def start(path: Path) -> subprocess.Popen[bytes]:
    log = open(path.with_suffix(".log"), "ab")
    process = subprocess.Popen([sys.executable, "-m", "gateway", "run", str(path)], stdout=subprocess.DEVNULL,
                               stderr=log, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    log.close()
    return process


def fetch(http: int, path: str) -> bytes:
    with urllib.request.urlopen(f"http://{HOST}:{http}{path}", timeout=5) as reply:
        body: bytes = reply.read()
        return body


async def api_status(http: int) -> dict[str, Any]:
    document: dict[str, Any] = json.loads(await asyncio.to_thread(fetch, http, "/api/status"))
    return document


async def serving(port: int, within: float = STARTUP) -> None:
    """Once the gateway's Modbus listener accepts connections (a restarted process imports and starts for a
    few seconds, longer on a loaded machine)."""

    async def accepts() -> bool:
        try:
            _, writer = await asyncio.open_connection(HOST, port)
        except OSError:
            return False
        writer.close()
        return True

    await until(accepts, within, step=0.2, what=f"the gateway listening on Modbus port {port}")


def stored(path: Path) -> dict[str, set[int]]:
    """device -> the values of N7:1 committed to the store's file (a reader beside the gateway: WAL)."""
    out: dict[str, set[int]] = {name: set() for name in DEVICES}
    with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
        for device, sample in db.execute("SELECT device, sample FROM change WHERE metric = 'N7:1'"):
            value = json.loads(sample)[0]
            if device in out and isinstance(value, int):
                out[device].add(value)
    return out


def all_stored(path: Path, values: dict[str, list[int]]) -> bool:
    """Whether every value of ``values`` (device -> values written) is committed to the store."""
    if not path.exists():
        return False
    held = stored(path)
    return all(set(values[name]) <= held[name] for name in DEVICES)


async def store_until(http: int, check: Callable[[dict[str, Any]], bool], within: float = 30.0) -> dict[str, Any]:
    """The store as ``/api/status`` shows it once ``check`` holds (polled every 0.25 s, bounded)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within
    while True:
        store: dict[str, Any] = (await api_status(http))["sparkplug"]["store"]
        if check(store):
            return store
        if loop.time() > deadline:
            raise AssertionError(f"the store never showed the condition within {within} s: {store}")
        await asyncio.sleep(0.25)


class Writer:
    """Modbus writes of known values to N7:1 of each device: the value changes the host must see."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.next = 1
        #: device -> the values written and confirmed
        self.written: dict[str, list[int]] = {name: [] for name in DEVICES}

    async def write(self, count: int, pause: float) -> None:
        async with connect(self.port) as client:
            for _ in range(count):
                for unit, name in enumerate(DEVICES, start=1):
                    value = self.next
                    self.next += 1
                    reply = await client.write_register(1, value, device_id=unit)
                    assert not reply.isError(), reply
                    self.written[name].append(value)
                await asyncio.sleep(pause)

    async def write_for(self, seconds: float, pause: float = 0.25) -> None:
        await self.write(max(1, int(seconds / pause)), pause)


def seen(hosts: Iterable[Any]) -> dict[str, list[tuple[int, int, bool, str]]]:
    """device -> (value, timestamp, historical, message type) of every N7:1 the hosts received, in order."""
    out: dict[str, list[tuple[int, int, bool, str]]] = {name: [] for name in DEVICES}
    for host in hosts:
        for message in host.messages:
            if message.message_type not in ("DBIRTH", "DDATA") or message.edge_node_id != NODE:
                continue
            for metric in message.metrics:
                if metric.resolved_name == "N7:1" and not metric.is_null:
                    out[message.device_id].append((metric.value, metric.timestamp, metric.is_historical,
                                                   message.message_type))
    return out


def missing(writer: Writer, hosts: Iterable[Any]) -> dict[str, list[int]]:
    got = seen(hosts)
    return {name: sorted(set(writer.written[name]) - {v for v, *_ in got[name]}) for name in DEVICES}


async def all_received(writer: Writer, hosts: list[Any], within: float) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within
    while any(missing(writer, hosts).values()):
        if loop.time() > deadline:
            raise AssertionError(f"never received: {missing(writer, hosts)}")
        await asyncio.sleep(0.2)


def check_order_and_once(writer: Writer, hosts: list[Any]) -> None:
    for name, got in seen(hosts).items():
        live = [(v, ts) for v, ts, historical, _ in got if not historical]
        history = [(v, ts) for v, ts, historical, _ in got if historical]
        written = set(writer.written[name])
        live_values = [v for v, _ in live if v in written]
        assert len(live_values) == len(set(live_values)), f"{name}: a value published live twice"
        for stream in (live, history):
            stamps = [ts for _, ts in stream]
            # per metric in timestamp order (a replay after a second outage may repeat older ones: duplicates)
            assert all(a <= b or (v in dict(stream[: i + 1])) for i, ((v, _), a, b) in
                       enumerate(zip(stream[1:], stamps, stamps[1:], strict=False))), f"{name}: out of order {stream}"
        # a value written and seen more than once was replayed: the copies after the first are historical
        for value in written:
            copies = [h for v, _, h, _ in got if v == value]
            assert len(copies) >= 1 and sum(not h for h in copies) <= 1, (name, value, copies)


@contextlib.asynccontextmanager
async def host_on(port: int) -> AsyncIterator[Any]:
    async with SparkplugHost(HOST, port) as host:
        yield host


async def born(host: Any, since: int = 0) -> None:
    await host.wait_for(lambda m: m.message_type == "NBIRTH" and m.edge_node_id == NODE, STARTUP, since=since)
    for name in DEVICES:
        await host.wait_for(lambda m, n=name: m.message_type == "DBIRTH" and m.device_id == n, 10, since=since)


async def run_outage(broker: Broker, tmp_path: Path, outage: str) -> None:
    """One outage of the module docstring, start to end, with its checks."""
    proxy = Proxy(broker.port)
    await proxy.start()
    modbus, http = free_port(), free_port()
    path = write_config(tmp_path, proxy.port, modbus, http)
    writer = Writer(modbus)
    hosts: list[Any] = []
    process = start(path)
    try:
        async with host_on(broker.port) as first:
            hosts.append(first)
            await born(first)
            await writer.write(5, 0.2)  # live
            await all_received(writer, hosts, 20)
            if outage == "silent":
                proxy.mode = "silent"  # the broker stays; the host sees the will NDEATH after 1.5 x keepalive
                cut = len(first.messages)
                await writer.write_for(OUTAGE)
                await first.wait_for(lambda m: m.message_type == "NDEATH", 1.5 * KEEPALIVE + 5, since=cut)
                proxy.close_all()
                mark = len(first.messages)
                proxy.mode = "pass"
                await born(first, since=mark)
                await writer.write(10, 0.1)  # live during the replay
                await all_received(writer, hosts, 60 + OUTAGE)
        if outage != "silent":
            proxy.mode = "refuse"
            proxy.close_all()
            broker.stop()
            if outage == "sigkill":
                first = {name: len(values) for name, values in writer.written.items()}
                await writer.write_for(OUTAGE / 2)
                during = {name: values[first[name]:] for name, values in writer.written.items()}
                # committed (one batch, 0.25 s, is what a SIGKILL may lose; on a loaded machine a batch
                # comes later): every value written so far is in the store's file, read beside the gateway
                store_file = store_path(tmp_path / "bdseq.json")
                await until(partial(all_stored, store_file, during), 30, step=0.25,
                            what="every value written before the kill committed to the store")
                process.send_signal(signal.SIGKILL)
                process.wait(5)
                process = start(path)
                await serving(modbus)  # the new process serves Modbus again
                await writer.write_for(OUTAGE / 2)
            else:
                await writer.write_for(OUTAGE)
            broker.start()
            async with host_on(broker.port) as second:
                hosts.append(second)
                proxy.mode = "pass"
                await born(second)
                await writer.write(10, 0.1)  # live during the replay
                await all_received(writer, hosts, 60 + OUTAGE)
                await asyncio.sleep(0.5)
                assert second.violations == [], "\n".join(second.violations)
        check_order_and_once(writer, hosts)
        assert hosts[0].violations == [], "\n".join(hosts[0].violations)
        historical = sum(h for got in seen(hosts).values() for _, _, h, _ in got)
        assert historical > 0
        store = (await api_status(http))["sparkplug"]["store"]
        assert store["failed"] is None and store["replayed"] > 0 and store["dropped"] == 0
    finally:
        stop(process, wait=10)
        await proxy.stop()


async def run_full_store(broker: Broker,
                                                                           tmp_path: Path) -> None:
    proxy = Proxy(broker.port)
    await proxy.start()
    modbus, http = free_port(), free_port()
    path = write_config(tmp_path, proxy.port, modbus, http, store_max_mb=0.03)
    writer = Writer(modbus)
    process = start(path)
    try:
        async with host_on(broker.port) as first:
            await born(first)
        proxy.mode = "refuse"
        proxy.close_all()
        broker.stop()
        async with connect(modbus) as client:  # many changes: 40 registers a write
            for k in range(60):
                for unit in (1, 2):
                    reply = await client.write_registers(0, [(k * 40 + i) % 30000 for i in range(40)],
                                                         device_id=unit)
                    assert not reply.isError(), reply
        # dropped, and back within store_max_mb (read while a commit trims, the store can be over it)
        await store_until(http, lambda store: store["dropped"] > 0 and store["bytes"] <= 0.03e6)
        broker.start()
        async with host_on(broker.port) as second:
            proxy.mode = "pass"
            await born(second)
            await writer.write(5, 0.1)  # live data goes on
            await all_received(writer, [second], 30)
            assert any(not h for got in seen([second]).values() for _, _, h, _ in got)
            assert second.violations == [], "\n".join(second.violations)
        log = path.with_suffix(".log").read_text(encoding="utf-8")
        assert "dropping the oldest stored changes" in log
        assert "were dropped (store full" in log
        metrics = (await asyncio.to_thread(fetch, http, "/metrics")).decode()
        assert "slc_gateway_sparkplug_store_dropped_total" in metrics
    finally:
        stop(process, wait=10)
        await proxy.stop()
