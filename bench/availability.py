"""Availability: the share of Modbus reads answered fresh on a bad line, per controller variant.

A SCADA client reads all 31 presets of an SLC 150 (holding registers 32-62, presets of 901-931)
over and over through the whole gateway (driver, poller, cache, unit, Modbus server) while the
simulated controller (in-process, unpaced, where the line's faults dominate) garbles, drops and
power-cycles.  It answers at the end of its program scan, 20-60 ms (``REALISTIC_SCAN``,
``docs/develop/controller-variants.md`` "Answer time"), as a real one does; ``--scan 0`` answers at once.
A read is *fresh* when it is answered with values (not exception 0x0B).  Counted after the first
scan has completed.  Meanwhile a writer changes one preset every ``--write-every`` seconds (1); at
the end every acknowledged write must have been applied exactly once, no write twice, and every
value read must be one that preset held.

Fault mixes (1 in N replies garbled / dropped, a power cycle every N commands):

* ``clean``: none;
* ``realistic``: garble 30, drop 50, power cycle every 500;
* ``harsh``: garble 4, drop 6, power cycle every 25.

Variants: the simulator's default reading, then each other reading of
``SlcAsciiSimulator.VARIANTS`` alone (``docs/develop/controller-variants.md``), then all of them at once.
Goodput is the driver's completed transactions per second, relative to the clean line of the
same variant.  A second part measures recovery: a device server in front of the controller
goes away for ``--outage`` seconds (10 by default); the time from its return to the first
fresh read of all 31 presets is reported (the target is 2 s or less).

    python bench/availability.py [--quick] [--seconds S] [--outage S] [--scan S|MIN-MAX|0]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import time
import uuid
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import percentile, print_machine, result, table
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.sim import create_simulator, get_simulator, reset_simulators
from gateway.sim.scan import REALISTIC_SCAN
from gateway.sim.serve import serve_tcp

HOST = "127.0.0.1"
MIXES: dict[str, dict[str, int]] = {
    "clean": {},
    "realistic": {"garble": 30, "drop": 50, "power_cycle_every": 500},
    "harsh": {"garble": 4, "drop": 6, "power_cycle_every": 25},
}
PRESETS = range(32, 63)  # holding registers: presets of 901-931


def variant_list(everything: bool = True) -> list[dict[str, str]]:
    """The default reading, each other reading alone, and all non-default readings together."""
    table_ = SlcAsciiSimulator.VARIANTS
    out: list[dict[str, str]] = [{}]
    for name, values in table_.items():
        out += [{name: value} for value in values[1:]]
    if everything:
        out.append({name: values[-1] for name, values in table_.items()})
    return out


def describe(variants: dict[str, str]) -> str:
    if not variants:
        return "default"
    if len(variants) > 1:
        return "all non-default"
    return ",".join(f"{k}={v}" for k, v in variants.items())


#: the controller's scan (``scan=`` of the sim:// URL): every answer at the end of the scan in progress
SCAN = REALISTIC_SCAN.text()


def scan_options(scan: str) -> dict[str, str]:
    """The ``scan`` option of a simulator (none when ``scan`` is 0 or empty: answers at once)."""
    return {"scan": scan} if scan.strip() not in ("", "0") else {}


def sim_url(mix: dict[str, int], variants: dict[str, str], seed: int, extra: str = "", scan: str = SCAN) -> str:
    query = [f"{k}={v}" for k, v in mix.items()] + [f"variant={k}={v}" for k, v in variants.items()]
    query += [f"{k}={v}" for k, v in scan_options(scan).items()]
    query += [extra] if extra else []
    query += ["ladder=0", f"seed={seed}", f"instance={uuid.uuid4().hex}"]
    return "sim://slc150?" + "&".join(query)


def config(port: str) -> Any:
    return parse_config(f"""
[modbus]
listen = "{HOST}:0"

[logging]
level = "ERROR"

[[link]]
name = "slc"
protocol = "slc-ascii"
port = "{port}"
unit = 1
writable = ["holding:32-62"]
""")


async def measure(variants: dict[str, str], mix: dict[str, int], seconds: float, *, seed: int = 1,
                  write_every: float = 5.0, extra: str = "", scan: str = SCAN) -> dict[str, Any]:
    """Read the presets for ``seconds`` after the first scan; the figures and the correctness checks."""
    url = sim_url(mix, variants, seed, extra, scan)
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    held = {reg: {sim.word(0x40 + 2 * (reg - 32)) & 0x7FFF} for reg in PRESETS}
    wrong: list[str] = []
    acknowledged: list[tuple[int, int]] = []
    attempted: list[tuple[int, int]] = []
    fresh = stale = 0
    write_times: list[float] = []
    async with Gateway(config(url)) as gw:
        client = AsyncModbusTcpClient(HOST, port=gw.port, timeout=5, retries=0)
        assert await client.connect()
        try:
            first_deadline = time.monotonic() + 60
            while time.monotonic() < first_deadline:
                reply = await client.read_holding_registers(32, count=31, device_id=1)
                if not reply.isError():
                    break
                await asyncio.sleep(0.02)
            else:
                raise RuntimeError(f"{describe(variants)}: no first scan within 60 s")
            driver = gw.units[0].driver
            transactions0 = driver.counters.transactions
            started = time.monotonic()
            next_write = started + write_every
            value = 1
            while (now := time.monotonic()) < started + seconds:
                if now >= next_write:
                    next_write += write_every
                    reg = 32 + value % 31
                    value += 1
                    attempted.append((reg, value))
                    held[reg].add(value)  # it may be applied from now on
                    t0 = time.monotonic()
                    w = await client.write_register(reg, value, device_id=1)
                    write_times.append(time.monotonic() - t0)
                    if not w.isError():
                        acknowledged.append((reg, value))
                    continue
                reply = await client.read_holding_registers(32, count=31, device_id=1)
                if reply.isError():
                    stale += 1
                else:
                    fresh += 1
                    for reg, got in zip(PRESETS, reply.registers, strict=True):
                        if got not in held[reg]:
                            wrong.append(f"holding {reg} = {got}, never held")
                await asyncio.sleep(0.01)
            elapsed = time.monotonic() - started
            transactions = driver.counters.transactions - transactions0
        finally:
            client.close()
    applied = [(0x40, a, v) for kind, a, v in sim.applied_writes if kind == "word"]
    counts: dict[tuple[int, int], int] = {}
    for _, address, v in applied:
        counts[(32 + (address - 0x40) // 2, v)] = counts.get((32 + (address - 0x40) // 2, v), 0) + 1
    doubles = sum(1 for n in counts.values() if n > 1)
    lost = sum(1 for w in acknowledged if counts.get(w, 0) != 1)
    reads = fresh + stale
    return {
        "variant": describe(variants),
        "fresh": fresh / reads if reads else 0.0,
        "reads": reads,
        "goodput": transactions / elapsed,
        "wrong": len(wrong),
        "wrong_examples": wrong[:3],
        "writes": len(attempted),
        "acknowledged": len(acknowledged),
        "double_writes": doubles,
        "lost_writes": lost,
        "power_cycles": sim.counters.power_cycles,
        "write_p99": percentile(sorted(write_times), 99) if write_times else float("nan"),
        "write_worst": max(write_times, default=float("nan")),
    }


class DeviceServer:
    """A TCP device server in front of the simulator: stopped and restarted on the same port."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.port = 0
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, HOST, self.port)
        self.port = self._server.sockets[0].getsockname()[1]

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(HOST, self.upstream_port)
        self._writers |= {writer, up_writer}
        pumps = [asyncio.create_task(self._pump(reader, up_writer)), asyncio.create_task(self._pump(up_reader, writer))]
        self._tasks.update(pumps)
        await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        for w in (writer, up_writer):
            w.close()

    @staticmethod
    async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError):
            while data := await reader.read(4096):
                writer.write(data)

    async def stop(self) -> None:
        assert self._server is not None
        self._server.close()
        for writer in self._writers:
            writer.close()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._server.wait_closed()
        self._writers.clear()
        self._tasks.clear()
        self._server = None


async def until_fresh(client: AsyncModbusTcpClient, limit: float, what: str) -> None:
    """Read all 31 presets every 10 ms until they are answered with values."""
    for _ in range(int(limit / 0.01)):
        if not (await client.read_holding_registers(32, count=31, device_id=1)).isError():
            return
        await asyncio.sleep(0.01)
    raise RuntimeError(f"no {what} within {limit:g} s")


async def recovery(outage: float, scan: str = SCAN) -> float:
    """Seconds from the device server's return to the first fresh read of all 31 presets."""
    sim = create_simulator("slc150", {"ladder": "0", **scan_options(scan)})
    upstream = await serve_tcp(sim, HOST, 0)
    server = DeviceServer(upstream.sockets[0].getsockname()[1])
    await server.start()
    try:
        async with Gateway(config(f"socket://{HOST}:{server.port}")) as gw:
            client = AsyncModbusTcpClient(HOST, port=gw.port, timeout=5, retries=0)
            assert await client.connect()
            try:
                await until_fresh(client, 30, "the first scan")
                await server.stop()
                stopped = time.monotonic()
                stale_after = gw.units[0].stale_after
                # wait until the values have gone stale, then out the rest of the outage
                while not (await client.read_holding_registers(32, count=31, device_id=1)).isError():
                    if time.monotonic() - stopped > stale_after + 20:
                        raise RuntimeError("values never went stale during the outage")
                    await asyncio.sleep(0.05)
                await asyncio.sleep(max(0.0, stopped + outage - time.monotonic()))
                await server.start()
                back = time.monotonic()
                await until_fresh(client, 60, "a fresh read after the device server's return")
                return time.monotonic() - back
            finally:
                client.close()
    finally:
        if server._server is not None:
            await server.stop()
        upstream.close()
        await upstream.wait_closed()


async def run(args: argparse.Namespace) -> None:
    variants = variant_list(everything=True)
    if args.quick:
        variants = [variants[0], variants[-1]]
    if args.only:
        variants = [v for v in variants if args.only in describe(v)]
    mixes = ["clean", "harsh"] if args.quick else list(MIXES)
    if args.mix:
        mixes = [m for m in mixes if m in args.mix.split(",")]
    rows = []
    worst_harsh = 1.0
    worst_write = 0.0
    wrong = doubles = lost = 0
    for variant in variants:
        clean_goodput = 0.0
        for mix in mixes:
            reset_simulators()
            figures = await measure(variant, MIXES[mix], args.seconds, seed=args.seed, extra=args.sim_option,
                                    write_every=args.write_every, scan=args.scan)
            if mix == "clean":
                clean_goodput = figures["goodput"]
            relative = figures["goodput"] / clean_goodput if clean_goodput else float("nan")
            rows.append([figures["variant"], mix, 100 * figures["fresh"], figures["reads"], figures["goodput"],
                         relative, figures["wrong"], f"{figures['acknowledged']}/{figures['writes']}",
                         f"{figures['write_p99']:.2f}", f"{figures['write_worst']:.2f}",
                         figures["double_writes"], figures["lost_writes"]])
            worst_write = max(worst_write, figures["write_worst"])
            print(f"{figures['variant']:>40} {mix:>9}: fresh {100 * figures['fresh']:5.1f} % of "
                  f"{figures['reads']} reads, {figures['goodput']:.0f} tx/s", flush=True)
            if figures["wrong_examples"]:
                print("   wrong:", figures["wrong_examples"])
            if mix == "harsh":
                worst_harsh = min(worst_harsh, figures["fresh"])
            wrong += figures["wrong"]
            doubles += figures["double_writes"]
            lost += figures["lost_writes"]
    print()
    print(table(["variant", "mix", "fresh %", "reads", "goodput tx/s", "goodput vs clean", "wrong values",
                 "writes acked/sent", "write p99 s", "worst write s", "double writes", "acked writes lost"],
                rows))
    recovered = await recovery(args.outage, args.scan) if not args.no_recovery else float("nan")
    print(f"\nrecovery after a {args.outage:g} s outage: first fresh read of all 31 presets "
          f"{recovered:.2f} s after the device server returned (target <= 2 s)")
    result(worst_harsh_fresh_pct=100 * worst_harsh, worst_write_s=worst_write, wrong_values=wrong,
           double_writes=doubles, acked_writes_lost=lost, recovery_s=recovered, variants=len(variants),
           seconds=args.seconds, scan=args.scan)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="default and all-non-default readings, clean and "
                                                              "harsh, short (CI smoke test)")
    parser.add_argument("--seconds", type=float, default=0.0, help="reading time per cell (default 20; quick 3)")
    parser.add_argument("--outage", type=float, default=0.0, help="outage for the recovery part (default 10; "
                                                                   "quick 2)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--only", default="", help="only the variants whose description contains this")
    parser.add_argument("--mix", default="", help="only these mixes (comma separated)")
    parser.add_argument("--sim-option", default="", help="one more sim:// option, e.g. late_every=20")
    parser.add_argument("--write-every", type=float, default=1.0, help="seconds between writes (default 1)")
    parser.add_argument("--no-recovery", action="store_true", help="skip the recovery part")
    parser.add_argument("--scan", default=SCAN, help=f"the controller's scan, seconds (default {SCAN}; 0: answers "
                                                      "at once)")
    args = parser.parse_args()
    args.seconds = args.seconds or (3.0 if args.quick else 20.0)
    args.outage = args.outage or (2.0 if args.quick else 10.0)
    print_machine()
    asyncio.run(run(args))


if __name__ == "__main__":
    main()
