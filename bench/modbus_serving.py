"""Modbus serving: FC3 reads of 100 holding registers, the gateway against a bare pymodbus server.

Four processes, so nobody's CPU is charged to anybody else:

* the gateway (``python -m gateway run CONFIG``, the production entry point) with one DF1 link
  (SLC 5/04, 19200 8N1, paced) polling N7:0-99 as holding registers 0-99 (and T4 / F8 / B3),
  so it serves reads from its cache *while it polls*;
* the paced simulator for that link (``bench/simfarm.py``);
* a bare pymodbus 3.16.1 TCP server (``StartAsyncTcpServer``, a ``ModbusDeviceContext`` with a
  sequential block of holding registers) in its own process;
* the load generator (``bench/loadgen.py``): C raw MBAP connections, each a closed loop
  (send one request, await its reply, repeat) for a fixed duration.

For C = 1, 10 and 50 connections both servers are measured in one run, one after the other,
in alternating order, for several rounds; the table shows each server's median round and the
gateway/pymodbus ratio of every round (the RESULT ratio is their median).
Reported: requests/s, latency p50 / p99, the server process's CPU per request (from
``/proc/PID/stat`` sampled at the generator's START/STOP marks) and the generator's own CPU
(if it is near 1.0 s/s the generator, not the server, is the limit).

Without the DF1 simulator (``gateway/sim/slc500.py``) the gateway link is an SLC 150 and the
read is 64 registers (its whole holding table), for both servers.

    python bench/modbus_serving.py [--quick] [--duration S] [--connections 1,10,50]

Full mode then runs the gateway once more, in a child process under cProfile, at the largest
connection count, and prints its top 20 functions by own time.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import statistics
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
    df1_simulator_available,
    gateway_config,
    print_machine,
    result,
    slc_link,
    table,
)

_TICKS = os.sysconf("SC_CLK_TCK")


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


async def serve_pymodbus(port: int, registers: int) -> None:
    from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
    from pymodbus.server import StartAsyncTcpServer

    # pymodbus numbers data block addresses from 1: block address 1 is protocol address 0.
    block = ModbusSequentialDataBlock(1, list(range(registers)))
    context = ModbusServerContext(devices=ModbusDeviceContext(hr=block), single=True)
    await StartAsyncTcpServer(context=context, address=(HOST, port))


async def serve_gateway_profiled(config_path: str) -> None:
    """The gateway in this process under cProfile (CPU time), until stdin closes; then the top 20."""
    import cProfile
    import io
    import pstats
    import threading

    from gateway.app import Gateway
    from gateway.config import load_config

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), loop.call_soon_threadsafe(stop.set)), daemon=True).start()
    profile = cProfile.Profile(time.process_time)  # CPU time: waiting in epoll is not a cost
    async with Gateway(load_config(config_path)):
        print("READY", flush=True)
        profile.enable()
        await stop.wait()
        profile.disable()
    out = io.StringIO()
    pstats.Stats(profile, stream=out).sort_stats("tottime").print_stats(20)
    text = out.getvalue()
    print(text[text.find("   ncalls"):].rstrip(), flush=True)


def profile_gateway(config: Path, count: int, connections: int, duration: float) -> str:
    """Run the gateway under cProfile in a child process while the generator loads it."""
    child = subprocess.Popen([PYTHON, str(BENCH_DIR / "modbus_serving.py"), "--profile-gateway", str(config)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(REPO))
    assert child.stdout is not None and child.stdin is not None
    if child.stdout.readline().strip() != "READY":
        raise SystemExit("profiled gateway did not start")
    port = int(config.read_text().split('listen = "', 1)[1].split('"', 1)[0].rsplit(":", 1)[1])
    answer = run_load(port, child.pid, count, connections, duration, 0.5)
    child.stdin.close()
    text = child.stdout.read()
    child.wait()
    return f"profiled run: {answer['rps']:.0f} req/s (cProfile slows it down)\n{text}"


def backend_read_cost(count: int) -> float:
    """Seconds of one ``Unit.read_registers(HOLDING, 0, count)`` from a fresh cache (no I/O)."""
    import timeit

    from gateway.drivers.df1 import Df1Driver
    from gateway.modbus.mapping import Table
    from gateway.modbus.mapping_df1 import MapItem
    from gateway.unit_df1 import Df1Unit

    async def measure() -> float:
        unit = Df1Unit(driver=Df1Driver("sim://slc504"), items=[MapItem(**e) for e in DF1_MAP],  # type: ignore[arg-type]
                       max_read_bytes=236, unit_id=1, name="timing")
        now = asyncio.get_running_loop().time()
        for index in range(len(unit.plan.blocks)):
            unit.cache.store(index, bytes(unit.plan.blocks[index].size), now)
        def read() -> object:
            return unit.read_registers(Table.HOLDING, 0, count)

        number, _ = timeit.Timer(read).autorange()
        return min(timeit.repeat(read, number=number, repeat=5)) / number

    return asyncio.run(measure())


def run_load(port: int, pid: int, count: int, connections: int, duration: float, warmup: float) -> dict[str, object]:
    command = [PYTHON, str(BENCH_DIR / "loadgen.py"), "read", "--port", str(port), "--count", str(count),
               "--connections", str(connections), "--duration", str(duration), "--warmup", str(warmup), "--marks"]
    generator = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, cwd=str(REPO))
    assert generator.stdout is not None
    cpu0 = cpu1 = 0.0
    t0 = t1 = 0.0
    answer: dict[str, object] = {}
    for line in generator.stdout:
        line = line.strip()
        if line == "START":
            cpu0, t0 = process_cpu(pid), time.perf_counter()
        elif line == "STOP":
            cpu1, t1 = process_cpu(pid), time.perf_counter()
        elif line.startswith("{"):
            answer = json.loads(line)
    if generator.wait() != 0 or not answer:
        raise SystemExit(f"load generator failed against port {port}")
    answer["server_cpu_per_s"] = (cpu1 - cpu0) / (t1 - t0)
    requests = int(answer["requests"])  # type: ignore[call-overload]
    answer["server_us_per_request"] = (cpu1 - cpu0) / requests * 1e6 if requests else float("nan")
    return answer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="short windows (CI smoke test)")
    parser.add_argument("--duration", type=float, default=0.0, help="window per measurement, s (default 10; quick 1)")
    parser.add_argument("--connections", default="1,10,50")
    parser.add_argument("--rounds", type=int, default=0, help="alternating rounds per pair (default 3; quick 1)")
    parser.add_argument("--serve-pymodbus", type=int, default=0, help=argparse.SUPPRESS)  # internal: port
    parser.add_argument("--registers", type=int, default=100, help=argparse.SUPPRESS)
    parser.add_argument("--profile-gateway", default="", help=argparse.SUPPRESS)  # internal: config path
    args = parser.parse_args()
    if args.serve_pymodbus:
        asyncio.run(serve_pymodbus(args.serve_pymodbus, args.registers))
        return
    if args.profile_gateway:
        asyncio.run(serve_gateway_profiled(args.profile_gateway))
        return
    duration = args.duration or (1.0 if args.quick else 8.0)
    rounds = args.rounds or (1 if args.quick else 3)
    warmup = 0.3 if args.quick else 1.0
    connection_counts = [int(c) for c in args.connections.split(",")]
    print_machine()
    have_df1 = df1_simulator_available()
    count = 100 if have_df1 else 64
    if not have_df1:
        print("DF1 simulator not there yet: gateway link is an SLC 150; reading 64 registers from both servers")
    processes: list[subprocess.Popen[bytes]] = []
    farm = SimFarm("slc504" if have_df1 else "slc150", 1, paced=True)
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        try:
            gw_port, pm_port = free_port(), free_port()
            link = df1_link("df1", farm.urls()[0], 1) if have_df1 else slc_link("slc", farm.urls()[0], 1)
            config = Path(tmp) / "gateway.toml"
            config.write_text(gateway_config([link], listen=f"{HOST}:{gw_port}"))
            gateway = subprocess.Popen([PYTHON, "-m", "gateway", "run", str(config)], cwd=str(REPO),
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            processes.append(gateway)
            bare = subprocess.Popen([PYTHON, str(BENCH_DIR / "modbus_serving.py"), "--serve-pymodbus", str(pm_port),
                                     "--registers", str(count)], cwd=str(REPO),
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            processes.append(bare)
            targets = [("gateway", gw_port, gateway.pid), ("pymodbus", pm_port, bare.pid)]
            for round_number in range(rounds):
                for connections in connection_counts:
                    # alternate which server goes first, so a drift of the machine does not favour one
                    for name, port, pid in targets if round_number % 2 == 0 else targets[::-1]:
                        answer = run_load(port, pid, count, connections, duration, warmup)
                        answer["server"] = name
                        answer["round"] = round_number
                        answer["rss"] = process_rss(pid)
                        rows.append(answer)
                        print(f"round {round_number} {name:8} {connections:3d} conn: {answer['rps']:.0f} req/s, "
                              f"p50 {answer['p50']:.2f} ms, p99 {answer['p99']:.2f} ms, "
                              f"server {answer['server_us_per_request']:.0f} us/req, "
                              f"generator CPU {answer['generator_cpu_per_s']:.2f} s/s", flush=True)
            profile_text = ""
            for process in processes:
                process.send_signal(signal.SIGTERM)
                process.wait(5)
            if not args.quick:
                profile_config = Path(tmp) / "profiled.toml"
                profile_config.write_text(gateway_config([link], listen=f"{HOST}:{free_port()}"))
                profile_text = profile_gateway(profile_config, count, connection_counts[-1], duration)
        finally:
            for process in processes:
                if process.poll() is None:
                    process.send_signal(signal.SIGTERM)
            for process in processes:
                try:
                    process.wait(5)
                except subprocess.TimeoutExpired:
                    process.kill()
            farm.close()
    # per server and connection count: the round with the median req/s (its latencies go with it)
    by: dict[tuple[object, object], dict[str, object]] = {}
    ratios: dict[int, list[float]] = {}
    for connections in connection_counts:
        for name in ("gateway", "pymodbus"):
            runs = sorted((r for r in rows if r["server"] == name and r["connections"] == connections),
                          key=lambda r: float(r["rps"]))  # type: ignore[arg-type]
            by[(name, connections)] = runs[len(runs) // 2]
        ratios[connections] = [
            float(g["rps"]) / float(p["rps"])  # type: ignore[arg-type]
            for g in rows for p in rows
            if g["server"] == "gateway" and p["server"] == "pymodbus"
            and g["connections"] == p["connections"] == connections and g["round"] == p["round"]
        ]
    headers = ["connections", "server", "req/s", "p50 ms", "p99 ms", "max ms", "server CPU s/s", "server us/req",
               "generator CPU s/s", "exceptions", "RSS MiB", "gw/pymodbus req/s, per round"]
    lines = []
    for connections in connection_counts:
        gw, pm = by[("gateway", connections)], by[("pymodbus", connections)]
        for r in (gw, pm):
            lines.append([connections, r["server"], r["rps"], r["p50"], r["p99"], r["max"], r["server_cpu_per_s"],
                          r["server_us_per_request"], r["generator_cpu_per_s"], r["exceptions"], r["rss"],
                          " ".join(f"{x:.2f}" for x in ratios[connections]) if r is gw else ""])
    print(f"reading {count} holding registers per request, {duration:g} s per measurement, {rounds} round(s); "
          "rows: the median round of each server")
    print(table(headers, lines))
    if not args.quick and have_df1:
        cost = backend_read_cost(count)
        print(f"\nin-process, no I/O: Unit.read_registers(HOLDING, 0, {count}) = {cost * 1e6:.1f} us per call")
    if profile_text:
        print(f"\n--- cProfile of the gateway process serving {connection_counts[-1]} connections: "
              "top 20 by own time ---")
        print(profile_text)
    values: dict[str, object] = {"registers": count}
    for connections in connection_counts:
        gw, pm = by[("gateway", connections)], by[("pymodbus", connections)]
        values[f"c{connections}_gw_rps"] = gw["rps"]
        values[f"c{connections}_pm_rps"] = pm["rps"]
        values[f"c{connections}_ratio"] = statistics.median(ratios[connections])
        values[f"c{connections}_gw_p99ms"] = gw["p99"]
        values[f"c{connections}_cpu_ratio"] = (float(pm["server_us_per_request"])  # type: ignore[arg-type]
                                               / float(gw["server_us_per_request"]))  # type: ignore[arg-type]
    last = connection_counts[-1]
    values["target_met"] = bool(values[f"c{last}_ratio"] >= 1.0 and float(by[("gateway", last)]["p99"]) <= 5.0)  # type: ignore[arg-type, operator]
    result(**values)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
