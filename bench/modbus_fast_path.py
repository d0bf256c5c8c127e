"""The Modbus server's read fast path in-process: CPU per request, this checkout against another.

What is timed: one connection's ``data_received`` given 64 pipelined requests at once (the server's
budget per loop turn), against a backend whose ``read_now`` answers from memory (as the gateway's
register images do) and a transport that only counts its writes; the loop turns once between two
batches, as it does between two segments.  Nothing else runs: no socket, no links, no client, so
the figure is the server's own work per request (framing, checks, reply frame, one write).

Each measurement runs in its own process; with ``--tree DIR`` the other checkout (e.g. made with
``git archive <rev> | tar -x -C DIR``) is measured in the same rounds, in alternated order, and
the ratio of the medians is reported (1.00 = as fast).  Absolute figures move with the machine's
load; the ratio measured side by side is what counts.

    python bench/modbus_fast_path.py [--quick] [--rounds N] [--registers 10,125] [--tree DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import struct
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from _benchlib import BENCH_DIR, PYTHON, REPO, print_machine, result, table

BATCH = 64  # requests per data_received: the server's _FRAMES_PER_TURN


class _Backend:
    """Every unit-1 read answered from memory (zeros)."""

    def has_unit(self, unit: int) -> bool:
        return unit == 1

    def read_now(self, unit: int, function_code: int, address: int, count: int) -> bytes:
        return bytes(2 * count) if function_code in (3, 4) else bytes((count + 7) // 8)

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        raise AssertionError("served by read_now")

    read_discrete_inputs = read_coils

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        raise AssertionError("served by read_now")

    read_input_registers = read_holding_registers

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None: ...

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None: ...


class _Transport:
    """Counts the replies written."""

    def __init__(self) -> None:
        self.writes = 0

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return ("127.0.0.1", 50000) if name == "peername" else default

    def write(self, data: bytes) -> None:
        self.writes += 1

    def is_closing(self) -> bool:
        return False

    def pause_reading(self) -> None: ...

    def resume_reading(self) -> None: ...

    def close(self) -> None: ...

    def abort(self) -> None: ...


def _connection_class(server: Any) -> Any:
    """The connection protocol class, wherever the measured checkout keeps it."""
    try:
        from gateway.modbus.connection import Connection  # since the split of server.py (issue 11)

        return Connection
    except ImportError:
        return sys.modules[type(server).__module__]._Connection


async def _measure(registers: int, batches: int) -> float:
    """Microseconds per request, in this process (the checkout on sys.path)."""
    from gateway.modbus.server import ModbusTcpServer

    server = ModbusTcpServer(_Backend(), "127.0.0.1", 0, idle_timeout=None, frame_timeout=None)
    connection = _connection_class(server)(server)
    transport = _Transport()
    connection.connection_made(transport)
    batch = b"".join(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0, registers) for tid in range(BATCH))
    for _ in range(max(20, batches // 10)):  # warm-up (specialisation of the bytecode)
        connection.data_received(batch)
        await asyncio.sleep(0)
    before = transport.writes
    start = time.perf_counter()
    for _ in range(batches):
        connection.data_received(batch)
        await asyncio.sleep(0)
    elapsed = time.perf_counter() - start
    if transport.writes - before != batches * BATCH:
        raise SystemExit(f"expected {batches * BATCH} replies, got {transport.writes - before}")
    return elapsed / (batches * BATCH) * 1e6


def _run_one(tree: Path, registers: int, batches: int) -> float:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join((str(tree), str(BENCH_DIR)))}
    done = subprocess.run(
        [PYTHON, str(BENCH_DIR / "modbus_fast_path.py"), "--measure-one", str(registers), str(batches)],
        env=env, cwd=tree, capture_output=True, text=True, check=False,
    )
    if done.returncode != 0:
        raise SystemExit(f"measurement in {tree} failed:\n{done.stdout}\n{done.stderr}")
    value: float = json.loads(done.stdout.strip().splitlines()[-1])["us_per_request"]
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="few batches, one round (CI smoke test)")
    parser.add_argument("--rounds", type=int, default=None, help="alternated rounds (default 9; quick 1)")
    parser.add_argument("--registers", default="10,125", help="registers per FC3 request, comma-separated")
    parser.add_argument("--tree", type=Path, default=None, help="another checkout to measure side by side")
    parser.add_argument("--measure-one", nargs=2, type=int, metavar=("REGISTERS", "BATCHES"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure_one:
        registers, batches = args.measure_one
        print(json.dumps({"us_per_request": asyncio.run(_measure(registers, batches))}))
        return

    rounds = args.rounds or (1 if args.quick else 9)
    batches = 100 if args.quick else 3000
    trees = {"this": REPO} | ({"other": args.tree.resolve()} if args.tree else {})
    counts = [int(text) for text in args.registers.split(",")]
    print_machine()
    samples: dict[tuple[str, int], list[float]] = {(name, n): [] for name in trees for n in counts}
    for round_number in range(rounds):
        order = list(trees.items())
        if round_number % 2:
            order.reverse()
        for n in counts:
            for name, tree in order:
                samples[name, n].append(_run_one(tree, n, batches))
    rows = []
    summary: dict[str, object] = {}
    for n in counts:
        this = statistics.median(samples["this", n])
        row: list[object] = [f"FC3 x {n} registers", this]
        summary[f"us_{n}"] = this
        if args.tree:
            other = statistics.median(samples["other", n])
            row += [other, this / other]
            summary[f"ratio_{n}"] = this / other
        rows.append(row)
    headers = ["request", "this checkout, us/request"]
    if args.tree:
        headers += [f"{args.tree}, us/request", "ratio this/other"]
    print(f"median of {rounds} round(s), {batches} batches of {BATCH} requests each")
    print(table(headers, rows))
    result(rounds=rounds, **summary)


if __name__ == "__main__":
    main()
