"""Helper process of the benchmarks: a Modbus TCP load generator on raw MBAP sockets (not a benchmark).

    python bench/loadgen.py read  --port P [--unit U] [--function 3] [--address A] [--count N] [--connections C]
                                  [--duration S]
    python bench/loadgen.py write --port P [--unit U] [--address A] [--writes N] [--gap-max S]
    python bench/loadgen.py flood --port P [--unit U] [--in-flight K] [--span N] [--duration S]

``read``: C connections, each a closed loop (send one FC3 request (``--function``: 1-4), await its reply, repeat) for
S seconds after a short warm-up (``--rate R``: paced, each connection's next request 1/R s after its last one,
or at once when its reply came later); prints one JSON line: requests, exception replies, latency
percentiles (ms), and this process's CPU seconds per second (to show whether the generator
itself was the limit).  With ``--marks`` it prints ``START`` and ``STOP`` lines around the
measurement window, so a parent can sample the server's CPU time at those moments.

``write``: one connection; N FC6 writes of increasing values to holding register A, each after
a random pause of 0..``gap-max`` seconds (so writes land at random phases of the poll cycle);
prints one JSON line with every latency (ms) and the exception replies.

``flood``: one connection keeping K FC6 writes in flight for S seconds (a new one the moment a
reply comes, 0x06 "busy" replies included: a hostile master), to holding registers 0..N-1;
prints one JSON line with the replies by kind (ok, busy, other).

Before measuring, all wait until the server answers a read of the register range without an
exception (the gateway serves nothing before its first poll completes).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import resource
import struct
import time

HOST = "127.0.0.1"
_READ = struct.Struct(">HHHBBHH")  # MBAP + FC1-FC4 address count
_WRITE = struct.Struct(">HHHBBHH")  # MBAP + FC6 address value


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class ReadLoop(asyncio.Protocol):
    """One closed-loop connection: request, reply, request ..."""

    def __init__(self, unit: int, address: int, count: int, latencies: list[float], function: int = 3,
                 rate: float = 0.0) -> None:
        self.unit, self.address, self.count, self.function = unit, address, count, function
        self.latencies = latencies
        #: requests per second (0: the next request as soon as the reply is in)
        self.period = 1.0 / rate if rate else 0.0
        self.loop = asyncio.get_running_loop()
        self.recording = False
        self.running = True
        self.exceptions = 0
        self.tid = 0
        self.sent_at = 0.0
        self.buffer = b""
        self.transport: asyncio.Transport | None = None
        self.closed = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        if self.period:  # paced connections start at random phases, not in step
            self.loop.call_later(random.uniform(0, self.period), self.send)
        else:
            self.send()

    def send(self) -> None:
        self.tid = (self.tid + 1) & 0xFFFF
        assert self.transport is not None
        self.sent_at = time.perf_counter()
        self.transport.write(_READ.pack(self.tid, 0, 6, self.unit, self.function, self.address, self.count))

    def data_received(self, data: bytes) -> None:
        buffer = self.buffer + data if self.buffer else data
        while len(buffer) >= 8:
            length = (buffer[4] << 8) | buffer[5]
            end = 6 + length
            if len(buffer) < end:
                break
            now = time.perf_counter()
            if self.recording:
                self.latencies.append(now - self.sent_at)
                if buffer[7] & 0x80:
                    self.exceptions += 1
            buffer = buffer[end:]
            if self.running and self.period:
                # paced: the next request one period after the last one went out (at once if late)
                self.loop.call_later(max(0.0, self.sent_at + self.period - time.perf_counter()), self.send)
            elif self.running:
                self.send()
            elif self.transport is not None:
                self.transport.close()
        self.buffer = buffer

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)


async def _request(port: int, frame: bytes) -> bytes:
    reader, writer = await asyncio.open_connection(HOST, port)
    try:
        writer.write(frame)
        header = await reader.readexactly(6)
        body = await reader.readexactly((header[4] << 8) | header[5])
        return header + body
    finally:
        writer.close()


async def wait_ready(port: int, unit: int, address: int, count: int, patience: float = 20.0,
                     function: int = 3) -> None:
    deadline = time.monotonic() + patience
    while True:
        try:
            reply = await asyncio.wait_for(_request(port, _READ.pack(1, 0, 6, unit, function, address, count)), 2.0)
            if not reply[7] & 0x80:
                return
        except (OSError, asyncio.IncompleteReadError, TimeoutError):
            pass
        if time.monotonic() > deadline:
            raise SystemExit(f"server on port {port} did not serve FC{function} {address}+{count} within {patience} s")
        await asyncio.sleep(0.1)


def _pcts(values: list[float]) -> dict[str, float]:
    values = sorted(values)
    if not values:
        return {"p50": float("nan"), "p90": float("nan"), "p99": float("nan"), "max": float("nan")}

    def q(p: float) -> float:
        return values[min(len(values) - 1, max(0, -(-int(p * len(values)) // 100) - 1))] * 1e3

    return {"p50": q(50), "p90": q(90), "p99": q(99), "max": values[-1] * 1e3}


async def read_load(args: argparse.Namespace) -> dict[str, object]:
    await wait_ready(args.port, args.unit, args.address, args.count, function=args.function)
    loop = asyncio.get_running_loop()
    latencies: list[float] = []
    loops: list[ReadLoop] = []
    for _ in range(args.connections):
        _, protocol = await loop.create_connection(
            lambda: ReadLoop(args.unit, args.address, args.count, latencies, args.function, args.rate), HOST, args.port
        )
        loops.append(protocol)
    await asyncio.sleep(args.warmup)
    if args.marks:
        print("START", flush=True)
    for protocol in loops:
        protocol.recording = True
    cpu0, t0 = _cpu(), time.perf_counter()
    await asyncio.sleep(args.duration)
    for protocol in loops:
        protocol.recording = False
    if args.marks:
        print("STOP", flush=True)
    elapsed = time.perf_counter() - t0
    cpu = _cpu() - cpu0
    for protocol in loops:
        protocol.running = False
    await asyncio.wait([p.closed for p in loops], timeout=2.0)
    return {
        "connections": args.connections,
        "requests": len(latencies),
        "seconds": elapsed,
        "rps": len(latencies) / elapsed,
        "exceptions": sum(p.exceptions for p in loops),
        "generator_cpu_per_s": cpu / elapsed,
        **_pcts(latencies),
    }


async def write_load(args: argparse.Namespace) -> dict[str, object]:
    await wait_ready(args.port, args.unit, args.address, 1)
    reader, writer = await asyncio.open_connection(HOST, args.port)
    rng = random.Random(args.seed)
    latencies: list[float] = []
    exceptions = 0
    for n in range(args.writes):
        await asyncio.sleep(rng.uniform(0, args.gap_max))
        value = (n * 7 + 1) % args.modulo
        t0 = time.perf_counter()
        writer.write(_WRITE.pack(n & 0xFFFF, 0, 6, args.unit, 6, args.address, value))
        header = await reader.readexactly(6)
        body = await reader.readexactly((header[4] << 8) | header[5])
        latencies.append(time.perf_counter() - t0)
        if body[1] & 0x80:
            exceptions += 1
    writer.close()
    return {"writes": len(latencies), "exceptions": exceptions, "latencies_ms": [x * 1e3 for x in latencies],
            **_pcts(latencies)}


async def flood_load(args: argparse.Namespace) -> dict[str, object]:
    await wait_ready(args.port, args.unit, 0, 1)
    reader, writer = await asyncio.open_connection(HOST, args.port)
    outcome = {"ok": 0, "busy": 0, "other": 0}
    n = 0

    def send() -> None:
        nonlocal n
        n += 1
        writer.write(_WRITE.pack(n & 0xFFFF, 0, 6, args.unit, 6, n % args.span, n % args.modulo))

    for _ in range(args.in_flight):
        send()
    end = time.monotonic() + args.duration
    while time.monotonic() < end:
        header = await reader.readexactly(6)
        body = await reader.readexactly((header[4] << 8) | header[5])
        kind = "ok" if not body[1] & 0x80 else "busy" if body[2] == 0x06 else "other"
        outcome[kind] += 1
        send()
    writer.close()
    return outcome


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("read", "write", "flood"))
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--unit", type=int, default=1)
    parser.add_argument("--function", type=int, default=3, choices=(1, 2, 3, 4), help="read: function code")
    parser.add_argument("--address", type=int, default=0)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--connections", type=int, default=1)
    parser.add_argument("--rate", type=float, default=0.0,
                        help="read: requests per second per connection (default 0: closed loop, as fast as answered)")
    parser.add_argument("--duration", type=float, default=5.0)
    parser.add_argument("--warmup", type=float, default=0.5)
    parser.add_argument("--writes", type=int, default=100)
    parser.add_argument("--gap-max", type=float, default=0.3)
    parser.add_argument("--modulo", type=int, default=10000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--in-flight", type=int, default=16, help="flood: writes kept in flight")
    parser.add_argument("--span", type=int, default=31, help="flood: holding registers 0..span-1")
    parser.add_argument("--marks", action="store_true", help="read: print START / STOP around the window")
    args = parser.parse_args()
    runner = {"read": read_load, "write": write_load, "flood": flood_load}[args.mode]
    print(json.dumps(asyncio.run(runner(args))), flush=True)


if __name__ == "__main__":
    main()
