"""Modbus serving: the gateway against bare pymodbus 3.16.1, three maps, 1/10/50 connections.

Processes, so nobody's CPU is charged to anybody else:

* the gateway (``python -m gateway run CONFIG``, the production entry point) with two paced
  links that it polls *while it serves*: an SLC 150 (default map, unit 1, 9600 7E1) and an
  SLC 5/04 on DF1 (unit 2, 19200 8N1, N7:0-99 as holding 0-99, T4 / F8 / B3 beside);
* one simulator farm per link (``bench/simfarm.py``), each in its own process;
* two bare pymodbus 3.16.1 TCP servers, each in its own process: a ``ModbusDeviceContext`` of
  ``ModbusSequentialDataBlock``s, and the newer ``SimDevice`` datastore (the table says which
  one is faster; the ratio is taken against the faster of the two, per round);
* the load generator (``bench/loadgen.py``): C raw MBAP connections, each a closed loop.

Three maps (the same request to every server):

* ``slc-60``: FC3, 60 holding registers from 0 (the SLC 100/150 default map, unit 1);
* ``df1-100``: FC3, 100 holding registers from 0 (the DF1 map, unit 2);
* ``coils-64``: FC1, 64 coils from 701 (the SLC 100/150 relays, unit 1).

For every map and C = 1, 10, 50 the three servers are measured one after the other, the order
rotated each round, for several rounds; each row is a server's median round.  Reported:
requests/s, latency p50 / p99, the server process's CPU per request (``/proc/PID/stat`` at the
generator's START/STOP marks), the generator's own CPU (near 1.0 s/s it is the limit).

**Line efficiency under load**: during every gateway window, and during idle windows of the
same length, the links' poll transactions are counted from their status blocks (input
registers 1003-1004).  Efficiency under load / idle = the links' transaction rates loaded /
idle (same transactions, so the same ratio as wire efficiency).  Both links are in the loaded
process whatever map is read, so each window gives both links' ratios.

**Memory per link**: ``--memory`` (also run by full mode) builds 20 SLC and 20 DF1 units with a
full cache and reports tracemalloc bytes per unit (DF1 twice: 20 units sharing one map, and 20
units each with a map of its own); ``--memory-tree DIR`` measures another
checkout the same way (e.g. ``git archive 7bd7acd | tar -x -C /tmp/base``) for the comparison.

    python bench/modbus_serving.py [--quick] [--duration S] [--rounds N] [--connections 1,10,50]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _benchlib import (
    BENCH_DIR,
    DF1_MAP,
    HOST,
    PYTHON,
    REPO,
    SimFarm,
    df1_link,
    gateway_config,
    print_machine,
    result,
    slc_link,
    table,
)

_TICKS = os.sysconf("SC_CLK_TCK")

#: map name -> (gateway unit, function code, address, count)
MAPS = {
    "slc-60": (1, 3, 0, 60),
    "df1-100": (2, 3, 0, 100),
    "coils-64": (1, 1, 701, 64),
}
SERVERS = ("gateway", "pm-context", "pm-simdevice")
LINK_UNITS = {"slc": 1, "df1": 2}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind((HOST, 0))
        port: int = sock.getsockname()[1]
        return port


def process_cpu(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (from /proc; 1/CLK_TCK resolution)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICKS


def process_rss(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


# --- the bare pymodbus servers (child processes) ------------------------------------------


async def serve_pymodbus(port: int, kind: str) -> None:
    from pymodbus.server import StartAsyncTcpServer

    registers, bits = 200, 1000
    if kind == "simdevice":
        from pymodbus.simulator import DataType, SimData, SimDevice

        device = SimDevice(id=0, simdata=(
            [SimData(0, count=bits, values=True, datatype=DataType.BITS)],
            [SimData(0, count=bits, values=False, datatype=DataType.BITS)],
            [SimData(0, count=registers, values=7, datatype=DataType.REGISTERS)],
            [SimData(0, count=registers, values=7, datatype=DataType.REGISTERS)],
        ))
        await StartAsyncTcpServer(context=device, address=(HOST, port))
        return
    from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext

    # pymodbus numbers data block addresses from 1: block address 1 is protocol address 0.
    context = ModbusServerContext(devices=ModbusDeviceContext(
        co=ModbusSequentialDataBlock(1, [True] * bits),
        di=ModbusSequentialDataBlock(1, [False] * bits),
        hr=ModbusSequentialDataBlock(1, list(range(registers))),
        ir=ModbusSequentialDataBlock(1, list(range(registers))),
    ), single=True)
    await StartAsyncTcpServer(context=context, address=(HOST, port))


# --- probes ------------------------------------------------------------------------------


def link_transactions(port: int, unit: int) -> int:
    """The link's poll transactions so far, from the gateway's status block (input 1003-1004)."""
    with socket.create_connection((HOST, port), timeout=5) as sock:
        sock.sendall(struct.pack(">HHHBBHH", 1, 0, 6, unit, 4, 1003, 2))
        reply = b""
        while len(reply) < 13:
            chunk = sock.recv(64)
            if not chunk:
                raise SystemExit("gateway closed the status read")
            reply += chunk
    if reply[7] & 0x80:
        raise SystemExit(f"status read of unit {unit} answered exception {reply[8]:#x}")
    high, low = struct.unpack_from(">HH", reply, 9)
    return high << 16 | low


def link_rates(gw_port: int, start: dict[str, int], t0: float) -> dict[str, float]:
    elapsed = time.perf_counter() - t0
    return {name: (link_transactions(gw_port, unit) - start[name]) / elapsed for name, unit in LINK_UNITS.items()}


def run_load(port: int, pid: int, unit: int, function: int, address: int, count: int, connections: int,
             duration: float, warmup: float, gw_port: int = 0, rate: float = 0.0) -> dict[str, object]:
    """One window of the load generator against ``port``; with ``gw_port``: the links' tx/s in it;
    ``rate``: requests per second per connection (0: closed loop)."""
    command = [PYTHON, str(BENCH_DIR / "loadgen.py"), "read", "--port", str(port), "--unit", str(unit),
               "--function", str(function), "--address", str(address), "--count", str(count),
               "--connections", str(connections), "--duration", str(duration), "--warmup", str(warmup), "--marks",
               "--rate", str(rate)]
    generator = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, cwd=str(REPO))
    assert generator.stdout is not None
    cpu0 = cpu1 = 0.0
    t0 = t1 = 0.0
    tx0: dict[str, int] = {}
    tx_rates: dict[str, float] = {}
    answer: dict[str, object] = {}
    for line in generator.stdout:
        line = line.strip()
        if line == "START":
            if gw_port:
                tx0 = {name: link_transactions(gw_port, u) for name, u in LINK_UNITS.items()}
            cpu0, t0 = process_cpu(pid), time.perf_counter()
        elif line == "STOP":
            cpu1, t1 = process_cpu(pid), time.perf_counter()
            if gw_port:
                tx_rates = link_rates(gw_port, tx0, t0)
        elif line.startswith("{"):
            answer = json.loads(line)
    if generator.wait() != 0 or not answer:
        raise SystemExit(f"load generator failed against port {port}")
    answer["server_cpu_per_s"] = (cpu1 - cpu0) / (t1 - t0)
    requests = int(answer["requests"])  # type: ignore[call-overload]
    answer["server_us_per_request"] = (cpu1 - cpu0) / requests * 1e6 if requests else float("nan")
    answer["tx_rates"] = tx_rates
    return answer


def wait_status(port: int, patience: float = 20.0) -> None:
    deadline = time.monotonic() + patience
    while True:
        try:
            link_transactions(port, 1)
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def idle_rates(gw_port: int, duration: float) -> dict[str, float]:
    start = {name: link_transactions(gw_port, unit) for name, unit in LINK_UNITS.items()}
    t0 = time.perf_counter()
    time.sleep(duration)
    return link_rates(gw_port, start, t0)


# --- memory per link ---------------------------------------------------------------------


def memory_per_link(units: int = 20) -> dict[str, float]:
    """tracemalloc bytes per unit (plan, cache, images, poller), full cache, for SLC and DF1 units."""
    import gc
    import tracemalloc

    from gateway.kinds.df1.full.driver import Df1Driver
    from gateway.kinds.df1.plan import MapItem
    from gateway.kinds.df1.unit import Df1Unit
    from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
    from gateway.kinds.slc_ascii.unit import SlcAsciiUnit

    def slc(i: int) -> object:
        return SlcAsciiUnit(driver=SlcAsciiDriver("sim://slc150"), unit_id=1, name=f"slc{i}")

    def df1(i: int) -> object:
        return Df1Unit(driver=Df1Driver("sim://slc504"), items=[MapItem(**e) for e in DF1_MAP],  # type: ignore[arg-type]
                       max_read_bytes=236, unit_id=1, name=f"df1{i}")

    def df1_own(i: int) -> object:
        # a map of its own: the same entries at Modbus addresses shifted by i, so no two units share
        # a plan (a checkout without shared plans builds one per unit either way)
        items = [MapItem(**{**e, "start": int(e["start"]) + i}) for e in DF1_MAP]  # type: ignore[arg-type]
        return Df1Unit(driver=Df1Driver("sim://slc504"), items=items, max_read_bytes=236, unit_id=1, name=f"own{i}")

    out: dict[str, float] = {}

    async def measure() -> None:
        now = asyncio.get_running_loop().time()
        for name, build in (("slc", slc), ("df1", df1), ("df1_own", df1_own)):
            build(0)  # imports and caches outside the measurement
            gc.collect()
            tracemalloc.start()
            before = tracemalloc.get_traced_memory()[0]
            kept = []
            for i in range(units):
                unit = build(i + 1)
                for index, block in enumerate(unit.plan.blocks):  # type: ignore[attr-defined]
                    unit.cache.store(index, bytes(block.size), now)  # type: ignore[attr-defined]
                kept.append(unit)
            gc.collect()
            out[name] = (tracemalloc.get_traced_memory()[0] - before) / units
            tracemalloc.stop()
            del kept

    asyncio.run(measure())
    return out


def memory_of_tree(tree: str) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=tree)
    done = subprocess.run([PYTHON, str(BENCH_DIR / "modbus_serving.py"), "--memory-json"], env=env, cwd=tree,
                          capture_output=True, text=True, check=True)
    answer: dict[str, float] = json.loads(done.stdout.strip().splitlines()[-1])
    return answer


# --- main --------------------------------------------------------------------------------


def _start(command: list[str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(command, cwd=str(REPO), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="short windows, one round (CI smoke test)")
    parser.add_argument("--duration", type=float, default=0.0, help="window per measurement, s (default 5; quick 0.4)")
    parser.add_argument("--connections", default="1,10,50")
    parser.add_argument("--maps", default=",".join(MAPS))
    parser.add_argument("--rounds", type=int, default=0, help="rotating rounds (default 3; quick 1)")
    parser.add_argument("--memory", action="store_true", help="only the memory per link")
    parser.add_argument("--memory-tree", default="", help="also measure the memory per link of this checkout")
    parser.add_argument("--memory-json", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--serve-pymodbus", type=int, default=0, help=argparse.SUPPRESS)  # internal: port
    parser.add_argument("--kind", default="context", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_pymodbus:
        asyncio.run(serve_pymodbus(args.serve_pymodbus, args.kind))
        return
    if args.memory_json:
        print(json.dumps(memory_per_link()))
        return
    if args.memory or args.memory_tree:
        memory = memory_per_link()
        line = f"memory per link (tracemalloc, full cache): SLC {memory['slc'] / 1024:.1f} KiB, " \
               f"DF1 {memory['df1'] / 1024:.1f} KiB (shared map), {memory['df1_own'] / 1024:.1f} KiB (map of its own)"
        values: dict[str, object] = {"slc_kib": memory["slc"] / 1024, "df1_kib": memory["df1"] / 1024,
                                     "df1_own_kib": memory["df1_own"] / 1024}
        if args.memory_tree:
            base = memory_of_tree(args.memory_tree)
            line += f"; {args.memory_tree}: SLC {base['slc'] / 1024:.1f} KiB, DF1 {base['df1'] / 1024:.1f} KiB, " \
                    f"{base['df1_own'] / 1024:.1f} KiB"
            values.update(slc_ratio=memory["slc"] / base["slc"], df1_ratio=memory["df1"] / base["df1"],
                          df1_own_ratio=memory["df1_own"] / base["df1_own"])
        print(line)
        result(**values)
        return
    duration = args.duration or (0.4 if args.quick else 5.0)
    rounds = args.rounds or (1 if args.quick else 3)
    warmup = 0.2 if args.quick else 1.0
    connection_counts = [int(c) for c in args.connections.split(",")]
    maps = args.maps.split(",")
    print_machine()
    rows: list[dict[str, object]] = []
    idle: list[dict[str, float]] = []
    processes: list[subprocess.Popen[bytes]] = []
    slc_farm = SimFarm("slc150", 1, paced=True)
    df1_farm = SimFarm("slc504", 1, paced=True)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            gw_port = free_port()
            links = [slc_link("slc", slc_farm.urls()[0], 1), df1_link("df1", df1_farm.urls()[0], 2)]
            config = Path(tmp) / "gateway.toml"
            config.write_text(gateway_config(links, listen=f"{HOST}:{gw_port}"))
            gateway = _start([PYTHON, "-m", "gateway", "run", str(config)])
            processes.append(gateway)
            targets = [("gateway", gw_port, gateway.pid)]
            for kind in ("context", "simdevice"):
                port = free_port()
                bare = _start([PYTHON, str(BENCH_DIR / "modbus_serving.py"), "--serve-pymodbus", str(port),
                               "--kind", kind])
                processes.append(bare)
                targets.append((f"pm-{kind}", port, bare.pid))
            wait_status(gw_port)
            time.sleep(1.0 if args.quick else 3.0)  # both links past their first scans
            for round_number in range(rounds):
                # the links' idle cadence in this round (the gateway otherwise idle)
                idle.append(idle_rates(gw_port, 1.0 if args.quick else max(duration, 3.0)))
                print(f"round {round_number} idle link tx/s: "
                      + ", ".join(f"{k} {v:.2f}" for k, v in idle[-1].items()), flush=True)
                shift = round_number % len(targets)
                order = targets[shift:] + targets[:shift]
                for name_map in maps:
                    unit, function, address, count = MAPS[name_map]
                    for connections in connection_counts:
                        for name, port, pid in order:
                            answer = run_load(port, pid, unit if name == "gateway" else 1, function, address, count,
                                              connections, duration, warmup, gw_port if name == "gateway" else 0)
                            answer.update(server=name, round=round_number, map=name_map, rss=process_rss(pid))
                            rows.append(answer)
                            tx = answer["tx_rates"]
                            line_text = ""
                            if tx:
                                line_text = ", links tx/s " + ", ".join(
                                    f"{k} {v:.2f}" for k, v in tx.items())  # type: ignore[attr-defined]
                            print(f"round {round_number} {name_map:8} {name:12} {connections:3d} conn: "
                                  f"{answer['rps']:.0f} req/s, p50 {answer['p50']:.2f} ms, p99 {answer['p99']:.2f} ms,"
                                  f" server {answer['server_us_per_request']:.0f} us/req, generator CPU "
                                  f"{answer['generator_cpu_per_s']:.2f} s/s{line_text}", flush=True)
        finally:
            for process in processes:
                if process.poll() is None:
                    process.send_signal(signal.SIGTERM)
            for process in processes:
                try:
                    process.wait(5)
                except subprocess.TimeoutExpired:
                    process.kill()
            slc_farm.close()
            df1_farm.close()
    report(rows, idle, maps, connection_counts, duration, rounds, args.quick)


def report(rows: list[dict[str, object]], idle: list[dict[str, float]], maps: list[str],
           connection_counts: list[int], duration: float, rounds: int, quick: bool) -> None:
    def pick(name_map: str, name: str, connections: int) -> list[dict[str, object]]:
        return [r for r in rows if r["map"] == name_map and r["server"] == name and r["connections"] == connections]

    def rps(r: dict[str, object]) -> float:
        return float(r["rps"])  # type: ignore[arg-type]

    headers = ["map", "conn.", "server", "req/s", "p50 ms", "p99 ms", "server us/req", "generator CPU s/s",
               "exceptions", "RSS MiB", "gw / fastest pymodbus, per round", "links loaded/idle (slc, df1)"]
    lines: list[list[object]] = []
    values: dict[str, object] = {}
    faster = {"pm-context": 0, "pm-simdevice": 0}
    worst_line = float("inf")
    for name_map in maps:
        for connections in connection_counts:
            ratios: list[float] = []
            line_ratios: dict[str, list[float]] = {name: [] for name in LINK_UNITS}
            for round_number in range(rounds):
                here = {r["server"]: r for r in rows if r["map"] == name_map and r["connections"] == connections
                        and r["round"] == round_number}
                best = max((here["pm-context"], here["pm-simdevice"]), key=rps)
                faster[str(best["server"])] += 1
                ratios.append(rps(here["gateway"]) / rps(best))
                tx: dict[str, float] = here["gateway"]["tx_rates"]  # type: ignore[assignment]
                for name in LINK_UNITS:
                    if idle[round_number].get(name):
                        line_ratios[name].append(tx[name] / idle[round_number][name])
            for name in SERVERS:
                runs = sorted(pick(name_map, name, connections), key=rps)
                r = runs[len(runs) // 2]
                gw = name == "gateway"
                lines.append([name_map, connections, name, r["rps"], r["p50"], r["p99"], r["server_us_per_request"],
                              r["generator_cpu_per_s"], r["exceptions"], r["rss"],
                              " ".join(f"{x:.2f}" for x in ratios) if gw else "",
                              ", ".join(f"{statistics.median(v):.3f}" for v in line_ratios.values() if v) if gw
                              else ""])
                if gw:
                    key = f"{name_map.replace('-', '_')}_c{connections}"
                    values[f"{key}_ratio"] = statistics.median(ratios)
                    values[f"{key}_gw_p99ms"] = r["p99"]
            if connections == connection_counts[-1]:
                for v in line_ratios.values():
                    if v:
                        worst_line = min(worst_line, statistics.median(v))
    print(f"\n{duration:g} s per window, {rounds} round(s), servers in rotating order; rows: each server's "
          "median round; ratio: gateway / the faster bare pymodbus of the same round")
    print(table(headers, lines))
    print(f"faster bare pymodbus datastore (rounds won): ModbusDeviceContext {faster['pm-context']}, "
          f"SimDevice {faster['pm-simdevice']}")
    print("idle link tx/s per round: " + "; ".join(", ".join(f"{k} {v:.2f}" for k, v in i.items()) for i in idle))
    if not quick:
        memory = memory_per_link()
        print(f"memory per link (tracemalloc, full cache): SLC {memory['slc'] / 1024:.1f} KiB, "
              f"DF1 {memory['df1'] / 1024:.1f} KiB (shared map), {memory['df1_own'] / 1024:.1f} KiB (map of its own)")
        values.update(slc_link_kib=memory["slc"] / 1024, df1_link_kib=memory["df1"] / 1024,
                      df1_own_link_kib=memory["df1_own"] / 1024)
    last = connection_counts[-1]
    first = connection_counts[0]
    values["line_loaded_over_idle_worst"] = worst_line
    values["target_met"] = bool(
        all(float(values[f"{m.replace('-', '_')}_c{last}_ratio"]) >= 1.5  # type: ignore[arg-type]
            and float(values[f"{m.replace('-', '_')}_c{last}_gw_p99ms"]) <= 5.0  # type: ignore[arg-type]
            and float(values[f"{m.replace('-', '_')}_c{first}_ratio"]) >= 1.2  # type: ignore[arg-type]
            for m in maps)
        and worst_line >= 0.95
    )
    result(**values)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
