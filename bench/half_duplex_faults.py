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

``--mode gateway`` runs the whole gateway instead (``gateway.app.Gateway``, one ``[[link]]`` per
station on one ``sim://df1line`` line, each station's program scan ``--scan`` seconds): an HMI reads
each live station's N7:0-19 every ``--read-every`` s (FC3) and writes N7:10 (FC6, a new value each
time) to the stations in turn, one write at a time with a pause of ``--write-every`` s between.
Reported per checksum: the writes acknowledged within ``write_timeout`` (the unit's, 0.9 s), those
answered 0x0B, those applied twice and those acknowledged but lost (both from the simulated
controllers' record of applied writes), and the slowest answer.

    python bench/half_duplex_faults.py [--target sim|peer|both] [--seconds S] [--runs N]
    python bench/half_duplex_faults.py --mode gateway [--scan S] [--seconds S] [--runs N]
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import struct
import subprocess
import sys
from pathlib import Path
from typing import Final

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import percentile, print_machine, result, table

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.errors import GatewayError
from gateway.kinds.df1.build import build_line
from gateway.kinds.df1.config import Df1LinkConfig, group_lines
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, Df1Station
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite
from gateway.sim import get_simulator
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


# ------------------------------------------------------------------- the whole gateway (--mode gateway)

#: the register each write goes to (N7:10) and the words the HMI reads (N7:0-19)
WRITE_REGISTER = 10
READ_WORDS = 20
CLIENT_TIMEOUT = 3.0
EXCEPTION_0B = 0x0B


class ModbusClient:
    """One Modbus TCP connection: FC3 and FC6, answered with data (code 0), an exception code or
    ``None`` (no answer within ``CLIENT_TIMEOUT``)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer, self.tid = reader, writer, 0

    @classmethod
    async def connect(cls, port: int) -> ModbusClient:
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def request(self, unit: int, fc: int, address: int, value: int) -> int | None:
        self.tid = (self.tid + 1) & 0xFFFF
        self.writer.write(struct.pack(">HHHBBHH", self.tid, 0, 6, unit, fc, address, value))
        try:
            async with asyncio.timeout(CLIENT_TIMEOUT):
                head = await self.reader.readexactly(7)
                body = await self.reader.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
        except TimeoutError:
            return None
        return int(body[1]) if body[0] & 0x80 else 0

    def close(self) -> None:
        self.writer.close()


def gateway_config(url: str, checksum: str) -> str:
    links = "".join(f"""
[[link]]
name = "drop-{st}"
protocol = "df1"
duplex = "half"
port = "{url}"
baudrate = 19200
checksum = "{checksum}"
station = {st}
unit = {10 + st}
  [[link.map]]
  table = "holding"
  start = 0
  address = "N7:0"
  count = {READ_WORDS}
""" for st in (*LIVE, ABSENT))
    return f'[modbus]\nlisten = "127.0.0.1:0"\n\n[logging]\nlevel = "ERROR"\n{links}'


async def run_gateway(checksum: str, seconds: float, write_every: float, read_every: float, scan: float,
                      seed: int) -> dict[str, float]:
    """The whole gateway under the fault mix: an HMI's writes and reads (module docstring)."""
    url = (f"sim://df1line?checksum={checksum}&stations={','.join(map(str, (*LIVE, ABSENT)))}&dead={ABSENT}"
           f"&corrupt=6&ignore=10&seed={seed}&char_time={SerialSettings(19200, 8, 'N', 1).char_time:.9f}"
           f"{f'&scan={scan:g}' if scan > 0 else ''}&instance=bench-{checksum}-{seed}")
    line = get_simulator(url)
    config = parse_config(gateway_config(url, checksum))
    write_timeout = config.links[0].write_timeout
    writes: list[tuple[int, int, int | None, float]] = []  # (station, value, code, seconds to the answer)
    stop = asyncio.Event()

    async def hmi_reader(port: int, station: int) -> None:
        client = await ModbusClient.connect(port)
        try:
            while not stop.is_set():
                if await client.request(10 + station, 3, 0, READ_WORDS) is None:
                    client.close()
                    client = await ModbusClient.connect(port)
                await asyncio.sleep(read_every)
        finally:
            client.close()

    async with Gateway(config) as gw:
        loop = asyncio.get_running_loop()
        readers = [asyncio.create_task(hmi_reader(gw.port, st)) for st in LIVE] if read_every > 0 else []
        client = await ModbusClient.connect(gw.port)
        try:
            end = loop.time() + seconds
            k = 0
            while loop.time() < end:
                await asyncio.sleep(write_every)
                station = LIVE[k % len(LIVE)]
                value = 1000 + k
                k += 1
                t0 = loop.time()
                code = await client.request(10 + station, 6, WRITE_REGISTER, value)
                writes.append((station, value, code, loop.time() - t0))
                if code is None:
                    client.close()
                    client = await ModbusClient.connect(gw.port)
        finally:
            client.close()
            stop.set()
            await asyncio.gather(*readers, return_exceptions=True)
            await asyncio.sleep(2 * write_timeout)  # writes answered 0x0B reach their verdict on the line
    applied: dict[tuple[int, int], int] = {}
    for station in LIVE:
        for kind, address, data in line.controllers[station].applied_writes:
            if kind in ("write", "typed_write") and address == f"N7:{WRITE_REGISTER}":
                key = (station, int.from_bytes(data[:2], "little"))
                applied[key] = applied.get(key, 0) + 1
    acked = [(st, v, t) for st, v, code, t in writes if code == 0]
    return {
        "writes": len(writes),
        "acked": sum(t <= write_timeout + 0.1 for _, _, t in acked),  # (0.1 s: the server's turnaround)
        "0x0B": sum(code == EXCEPTION_0B for _, _, code, _ in writes),
        "other": sum(code not in (0, EXCEPTION_0B) for _, _, code, _ in writes),
        "twice": sum(n > 1 for n in applied.values()),
        "lost": sum(applied.get((st, v), 0) == 0 for st, v, _ in acked),
        "worst": max((t for *_, t in writes), default=float("nan")),
        "write_timeout": write_timeout,
    }


async def main_gateway(args: argparse.Namespace) -> None:
    print_machine()
    print(f"the whole gateway; {len(LIVE)} live stations + 1 absent, 19200 baud, scan {args.scan:g} s, 1/6 slave "
          f"frames corrupted, 1/10 master frames unheard; {args.seconds:g} s per run; an HMI writes (FC6) with "
          f"{args.write_every:g} s between writes and reads each station every {args.read_every:g} s\n")
    rows = []
    summary: dict[str, float] = {}
    for checksum in ("bcc", "crc"):
        share = []
        for k in range(args.runs):
            seed = 33 + k
            got = await run_gateway(checksum, args.seconds, args.write_every, args.read_every, args.scan, seed)
            share.append(got["acked"] / got["writes"] if got["writes"] else float("nan"))
            rows.append((checksum, seed, f"{got['acked']:g}/{got['writes']:g}", f"{100 * share[-1]:.0f} %",
                         got["0x0B"], got["other"], got["twice"], got["lost"], got["worst"]))
        summary[f"gateway_{checksum}_acked_share_min"] = min(share)
    print(table(["check", "seed", "acked within write_timeout", "share", "0x0B", "other / none", "applied twice",
                 "acked and lost", "worst answer s"], rows))
    result(**summary)


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", choices=("sim", "peer", "both"), default="both")
    parser.add_argument("--peer", type=Path, default=DEFAULT_PEER, help="df1_halfduplex_peer.py")
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--runs", type=int, default=2, help="runs per target and checksum (seeds 33, 34, ...)")
    parser.add_argument("--write-every", type=float, default=0.4)
    parser.add_argument("--mode", choices=("line", "gateway"), default="line",
                        help="line: the line driver alone; gateway: the whole gateway, an HMI writing (FC6)")
    parser.add_argument("--scan", type=float, default=0.06,
                        help="--mode gateway: each station's program scan, s (0: answers at once)")
    parser.add_argument("--read-every", type=float, default=0.5,
                        help="--mode gateway: seconds between the HMI's reads of a station (0: no reads)")
    args = parser.parse_args()
    if args.mode == "gateway":
        await main_gateway(args)
        return
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
