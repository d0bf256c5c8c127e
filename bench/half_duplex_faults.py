"""Half-duplex DF1 line under the interop fault mix: time to the first fresh value and write latency.

Three live SLC 5/0x stations (1, 2, 5) and one absent (9) on one line at 19200 baud; 1 in 6 slave
frames corrupted, 1 in 10 master frames unheard by their station.  The line master is built from
the same ``[[link]]`` keys (defaults) as ``slc-gateway run`` uses (``gateway.kinds.df1.build``).
Each live station is read (N7:0-19, one protected typed logical read) over and over; every
``--write-every`` s a one-word write (N7:10) goes to the next live station in turn, as the interop
check's FC6 does.  Reported per checksum:

* ``first fresh``: seconds from the line's start to the first good read of station 1;
* write latency p50 / p99 / worst, and how many writes succeeded.

Two targets, each named in the output:

* ``--target sim``: the project's multi-drop line simulator (``gateway.kinds.df1.sim.df1_multidrop``),
  paced at the baud rate;
* ``--target peer``: the independent peer ``../shared/interop/peers/df1_halfduplex_peer.py``
  (``--peer PATH``), over TCP, paced by itself.

    python bench/half_duplex_faults.py [--target sim|peer|both] [--seconds S] [--runs N]
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import subprocess
import sys
from pathlib import Path
from typing import Final

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import percentile, print_machine, result, table

from gateway.errors import GatewayError
from gateway.kinds.df1.build import build_line
from gateway.kinds.df1.config import Df1LinkConfig, group_lines
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, Df1Station
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite
from gateway.sim.serve import SimStream
from gateway.streams import SerialSettings
from gateway.transport import ByteStream

LIVE = (1, 2, 5)
ABSENT = 9
READ = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 40)
#: ``../shared`` beside the checkout (a worktree under ``wt/`` has it one level further up)
_PEER: Final = "shared/interop/peers/df1_halfduplex_peer.py"
DEFAULT_PEER = next((path for up in (2, 3) if (path := Path(__file__).resolve().parents[up] / _PEER).exists()),
                    Path("..", _PEER))


class PacedSimStream(SimStream):
    def char_time(self, settings: SerialSettings) -> float:
        return settings.char_time


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def line_for(port: str, checksum: str) -> Df1HalfDuplexLine:
    links = [Df1LinkConfig.model_validate({
        "name": f"drop-{st}", "protocol": "df1", "duplex": "half", "port": port, "baudrate": 19200,
        "checksum": checksum, "station": st, "unit": 10 + st,
        "map": [{"table": "holding", "start": 0, "address": "N7:0", "count": 20}],
    }) for st in (*LIVE, ABSENT)]
    return build_line(group_lines(links)[0])


async def measure(line: Df1HalfDuplexLine, seconds: float, write_every: float) -> dict[str, float]:
    loop = asyncio.get_running_loop()
    handles = {n: line.station(n) for n in (*LIVE, ABSENT)}
    stop = asyncio.Event()
    first_fresh: list[float] = []
    writes: list[float] = []
    failed = 0

    async def reader(handle: Df1Station) -> None:
        while not stop.is_set():
            try:
                await handle.execute(READ, "read N7:0")
            except GatewayError:
                await asyncio.sleep(0.05)
                continue
            if handle.station == LIVE[0] and not first_fresh:
                first_fresh.append(loop.time() - started)

    await handles[LIVE[0]].start()
    started = loop.time()
    tasks = [asyncio.create_task(reader(h)) for h in handles.values()]
    try:
        end = started + seconds
        k = 0
        while loop.time() < end:
            await asyncio.sleep(write_every)
            station = LIVE[k % len(LIVE)]
            k += 1
            request = ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 10, 0, (7100 + k).to_bytes(2, "little"))
            t0 = loop.time()
            try:
                await handles[station].execute(request, "write N7:10")
            except GatewayError:
                failed += 1
            writes.append(loop.time() - t0)
    finally:
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        for handle in handles.values():
            await handle.close()
    writes.sort()
    return {
        "first_fresh": first_fresh[0] if first_fresh else float("nan"),
        "write_p50": percentile(writes, 50), "write_p99": percentile(writes, 99),
        "write_worst": writes[-1] if writes else float("nan"), "writes": len(writes), "failed": failed,
    }


async def run_sim(checksum: str, seconds: float, write_every: float, seed: int) -> dict[str, float]:
    settings = SerialSettings(19200, 8, "N", 1)
    sim = MultidropLine.from_options({
        "checksum": checksum, "stations": ",".join(map(str, (*LIVE, ABSENT))), "dead": str(ABSENT),
        "corrupt": "6", "ignore": "10", "seed": str(seed), "char_time": str(settings.char_time),
    })
    line = line_for("sim://df1line", checksum)

    async def opener(url: str, _settings: object, **_: object) -> ByteStream:
        return PacedSimStream(sim)

    line._opener = opener
    return await measure(line, seconds, write_every)


async def run_peer(peer: Path, checksum: str, seconds: float, write_every: float, seed: int) -> dict[str, float]:
    port = free_port()
    args = [sys.executable, str(peer), "--port", str(port), "--stations", ",".join(map(str, LIVE)), "--baud",
            "19200", "--corrupt", "6", "--no-reply", "10", "--seed", str(seed)]
    args += ["--crc"] if checksum == "crc" else []
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # noqa: ASYNC220
    try:
        assert proc.stdout is not None
        if not proc.stdout.readline():  # "halfduplex peer listening on ..."
            raise SystemExit(f"the peer {peer} did not start")
        return await measure(line_for(f"socket://127.0.0.1:{port}", checksum), seconds, write_every)
    finally:
        proc.terminate()
        proc.wait(5)


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", choices=("sim", "peer", "both"), default="both")
    parser.add_argument("--peer", type=Path, default=DEFAULT_PEER, help="df1_halfduplex_peer.py")
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--runs", type=int, default=2, help="runs per target and checksum (seeds 33, 34, ...)")
    parser.add_argument("--write-every", type=float, default=0.4)
    args = parser.parse_args()
    print_machine()
    print(f"3 live stations + 1 absent, 19200 baud, 1/6 slave frames corrupted, 1/10 master frames unheard; "
          f"{args.seconds:g} s per run, a write every {args.write_every:g} s\n")
    targets = ("sim", "peer") if args.target == "both" else (args.target,)
    rows = []
    summary: dict[str, float] = {}
    for target in targets:
        for checksum in ("bcc", "crc"):
            runs = []
            for k in range(args.runs):
                seed = 33 + k
                if target == "sim":
                    got = await run_sim(checksum, args.seconds, args.write_every, seed)
                else:
                    got = await run_peer(args.peer, checksum, args.seconds, args.write_every, seed)
                runs.append(got)
                rows.append((target, checksum, seed, got["first_fresh"], got["write_p50"], got["write_p99"],
                             got["write_worst"], f"{got['writes'] - got['failed']:g}/{got['writes']:g}"))
            summary[f"{target}_{checksum}_first_fresh_max"] = max(r["first_fresh"] for r in runs)
            summary[f"{target}_{checksum}_write_p99_max"] = max(r["write_p99"] for r in runs)
            summary[f"{target}_{checksum}_write_worst"] = max(r["write_worst"] for r in runs)
    print(table(["target", "check", "seed", "first fresh s", "write p50 s", "write p99 s", "worst s", "writes ok"],
                rows))
    result(**summary)


if __name__ == "__main__":
    asyncio.run(main())
