"""DF1 target: writes per second a PLC gets through the gateway with ``persist`` on and off.

A PLC's MSG writes N words (SLC protected typed logical write, CMD 0F FNC AA, N7:0) to a DF1
link with ``role = "target"``.  With ``persist`` the gateway commits each write to SQLite (WAL,
``synchronous=FULL``: an fsync) before its reply goes out, so the commit sits in every write's
round trip.  This bench measures how many writes per second get through with and without it,
and sets that against what the line itself allows at 19200 baud 8N1.

Setup: two gateways (``python -m gateway run``, one process each, so the PLC's CPU is not charged
to them), the same config but for ``persist``.  Each connects to a local TCP port of this script
(``socket://``), where the PLC is the gateway's own DF1 master cores
(:class:`~gateway.protocols.df1.full_duplex.datalink.Df1DataLink` +
:class:`~gateway.protocols.df1.full_duplex.transaction.Df1Transactions`, as ``sim://plc-msg`` drives them),
unpaced: the next write goes out in the same write as the DLE ACK of the last reply.  So what is
measured is the gateway's cost per write (and loopback TCP, and the PLC's own work), not a line's.

Runs alternate (on, off, then off, on, ...) so drift of a shared machine hits both alike; each
mode's figure is the median of its runs.  Gateway CPU per write is from /proc/<pid>/stat (10 ms
ticks).  Every write must end ``TransactionDone``; anything else is counted and shown.  At the end
the persisted rows are read back from the database and must be the last values written.

The ceiling: one write's characters on a 19200-baud 8N1 line (10 bits each), from the gateway's
own encoders: the command frame (CRC, no DLE in the data) and its DLE ACK, the reply frame and its
DLE ACK, with no turnaround time.  A PLC cannot get more writes through than 1 / that.

    python bench/target_persist.py [--quick] [--words N] [--runs N] [--seconds S] [--db-dir DIR]

``--db-dir`` puts the database where the real one would be (the fsync cost is the disk's); the
default is a temporary directory, and the file system it is on is printed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import shutil
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from _benchlib import DF1_CHAR_TIME, HOST, PYTHON, REPO, df1_frames, print_machine, result, table

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import NEED_DATA, Checksum
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import Df1Transactions, TransactionDone
from gateway.protocols.df1.pccc import ProtectedTypedLogicalWrite

GATEWAY_NODE, PLC_NODE = 1, 0
FILE, ELEMENTS = 7, 100
BAUD = 19200
CONNECT_TIMEOUT = 20.0  # seconds for a gateway process to start and connect


def config(port: int, persist: Path | None) -> str:
    persist_line = f'persist = "{persist}"\n' if persist else ""
    return (
        f'[modbus]\nlisten = "{HOST}:0"\n\n[logging]\nlevel = "WARNING"\n\n'
        f'[[link]]\nname = "plc"\nprotocol = "df1"\nrole = "target"\nport = "socket://{HOST}:{port}"\nunit = 1\n'
        f'station = {GATEWAY_NODE}\nchecksum = "crc"\n{persist_line}'
        f'[[link.file]]\nfile = {FILE}\ntype = "N"\nelements = {ELEMENTS}\ntable = "holding"\nstart = 0\n'
    )


def values(serial: int, words: int) -> list[int]:
    """The words of write number ``serial``: a counter, each write different."""
    return [(serial * words + k) & 0x7FFF for k in range(words)]


def encode(vals: list[int]) -> bytes:
    return b"".join(v.to_bytes(2, "little") for v in vals)


def wire_time(words: int) -> tuple[int, float]:
    """(characters, seconds at 19200 8N1) of one write of ``words`` words with its ACKs and reply."""
    request = ProtectedTypedLogicalWrite(FileType.INTEGER, FILE, 0, 0, encode([0x0101] * words))  # no DLE
    out, back = df1_frames(request, b"")
    return out + back, (out + back) * DF1_CHAR_TIME


def file_system(path: Path) -> str:
    """``type device`` of the mount ``path`` is on (from /proc/mounts)."""
    real, best = str(path.resolve()), ("?", "?", "")
    try:
        with open("/proc/mounts", encoding="utf-8") as mounts:
            for line in mounts:
                device, point, kind = line.split()[:3]
                inside = real == point or real.startswith(point.rstrip("/") + "/")
                if inside and len(point) >= len(best[2]):
                    best = (kind, device, point)
    except OSError:
        pass
    return f"{best[0]} {best[1]}"


def fsync_ms(directory: Path, count: int = 200) -> float:
    """Median milliseconds of one 100-byte write + fsync of a file in ``directory``: the disk's floor
    under a commit (SQLite in WAL mode with synchronous=FULL syncs the WAL once per commit)."""
    probe = directory / "fsync-probe"
    fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    times = []
    try:
        for _ in range(count):
            start = time.perf_counter()
            os.write(fd, bytes(100))
            os.fsync(fd)
            times.append(time.perf_counter() - start)
    finally:
        os.close(fd)
        probe.unlink()
    return 1000 * statistics.median(times)


def process_cpu(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (from /proc/<pid>/stat)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# --------------------------------------------------------------------------------------------
# the PLC


@dataclass
class Run:
    writes: int = 0
    other: dict[str, int] = field(default_factory=dict)  # outcomes other than TransactionDone
    seconds: float = 0.0
    gateway_cpu: float = 0.0  # CPU seconds of the gateway process during the run
    plc_cpu: float = 0.0  # CPU seconds of this process (the PLC) during the run

    @property
    def rate(self) -> float:
        return self.writes / self.seconds if self.seconds else float("nan")


class Plc(asyncio.Protocol):
    """The initiating station on one gateway's port: one write after another during a run."""

    def __init__(self, words: int) -> None:
        self.words = words
        self.link = Df1DataLink(checksum=Checksum.CRC, ack_timeout=2.0, min_ack_timeout=2.0)
        self.core = Df1Transactions(self.link, station=GATEWAY_NODE, source=PLC_NODE, reply_timeout=2.0, retries=2)
        self.core.min_reply_timeout = 2.0  # a slow commit is waited for, not taken as a lost reply
        self.connected: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self.transport: asyncio.Transport | None = None
        self.serial = 0  # writes started
        self.last_done: list[int] = []  # the values of the last write that ended TransactionDone
        self._pending: list[int] = []  # the values of the write in flight
        self.run: Run | None = None
        self._idle: asyncio.Future[None] | None = None
        self._timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        if not self.connected.done():
            self.connected.set_result(None)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.connected.done():
            self.connected.set_exception(ConnectionError("the gateway closed the port"))
        if self._idle is not None and not self._idle.done():
            self._idle.set_exception(ConnectionError(f"the gateway closed the port ({exc})"))

    async def measure(self, seconds: float, pid: int) -> Run:
        """Writes back to back for ``seconds``; the write in flight then is finished, not counted."""
        self.run = run = Run()
        loop = asyncio.get_running_loop()
        self._idle = loop.create_future()
        cpu, own, start = process_cpu(pid), time.process_time(), time.perf_counter()
        self._start(loop.time())
        self._flush()
        await asyncio.sleep(seconds)
        run.seconds, run.gateway_cpu = time.perf_counter() - start, process_cpu(pid) - cpu
        run.plc_cpu = time.process_time() - own
        counted, self.run = run, None  # from here on: finish the write in flight, count nothing
        try:
            await asyncio.wait_for(self._idle, 10)
        except TimeoutError:
            raise SystemExit(f"the write in flight did not end within 10 s ({counted.writes} writes done in the "
                             f"run, others: {counted.other or 'none'})") from None
        return counted

    def _start(self, now: float) -> None:
        self.serial += 1
        vals = values(self.serial, self.words)
        self._pending = vals
        self.core.start(ProtectedTypedLogicalWrite(FileType.INTEGER, FILE, 0, 0, encode(vals)), now, write=True)

    def data_received(self, data: bytes) -> None:
        now = asyncio.get_running_loop().time()
        self.core.receive_data(data, now)
        self._events(now)
        self._flush()

    def _events(self, now: float) -> None:
        while (event := self.core.next_event()) is not NEED_DATA:
            if isinstance(event, TransactionDone):
                self.last_done = self._pending
            kind = type(event).__name__
            if self.run is not None:
                if kind == "TransactionDone":
                    self.run.writes += 1
                else:
                    self.run.other[kind] = self.run.other.get(kind, 0) + 1
                self._start(now)  # unpaced: the next write rides with the ACK of this reply
            elif self._idle is not None and not self._idle.done():
                self._idle.set_result(None)

    def _flush(self) -> None:
        out = self.core.data_to_send()
        if out and self.transport is not None:
            self.transport.write(out)
        self._arm()

    def _arm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        deadline = self.core.next_deadline()
        if deadline is not None:
            self._timer = asyncio.get_running_loop().call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        now = asyncio.get_running_loop().time()
        self.core.handle_timeout(now)
        self._events(now)
        self._flush()


# --------------------------------------------------------------------------------------------
# the gateways


@dataclass
class Side:
    """One gateway process, the port it connects to, and the PLC on that port."""

    name: str  # "on" / "off": persist
    listener: socket.socket
    process: subprocess.Popen[bytes]
    log: Path
    db: Path | None
    plc: Plc | None = None
    runs: list[Run] = field(default_factory=list)


def start_side(name: str, work: Path, db: Path | None) -> Side:
    listener = socket.create_server((HOST, 0))
    path = work / f"gateway-{name}.toml"
    path.write_text(config(listener.getsockname()[1], db), encoding="utf-8")
    log = work / f"gateway-{name}.log"
    with open(log, "wb") as out:
        process = subprocess.Popen([PYTHON, "-m", "gateway", "run", str(path)], cwd=str(REPO), stdout=out,
                                   stderr=subprocess.STDOUT)
    return Side(name, listener, process, log, db)


def stop(side: Side) -> None:
    if side.process.poll() is None:
        side.process.terminate()
        try:
            side.process.wait(10)
        except subprocess.TimeoutExpired:
            side.process.kill()
            side.process.wait()
    side.listener.close()


async def attach(side: Side, words: int) -> Plc:
    """The PLC on ``side``'s port, once the gateway has connected to it."""
    plc = Plc(words)
    server = await asyncio.get_running_loop().create_server(lambda: plc, sock=side.listener)
    try:
        async with asyncio.timeout(CONNECT_TIMEOUT):
            await asyncio.shield(plc.connected)
    except (TimeoutError, ConnectionError) as exc:
        tail = side.log.read_bytes()[-2000:].decode(errors="replace")
        raise SystemExit(f"gateway (persist {side.name}) did not connect ({exc!r}); exit {side.process.poll()}:\n"
                         f"{tail}") from None
    server.close()  # one connection: the one accepted stays open
    side.plc = plc
    return plc


def check_persisted(side: Side) -> str:
    """The rows of N7:0.. in the database are the last write the PLC saw done."""
    assert side.db is not None and side.plc is not None
    want = side.plc.last_done
    with contextlib.closing(sqlite3.connect(f"file:{side.db}?mode=ro", uri=True)) as db:
        rows = dict(db.execute("SELECT element, value FROM element WHERE file = ? AND element < ?",
                               (FILE, len(want))).fetchall())
    got = [int.from_bytes(rows[k], "little") if k in rows else None for k in range(len(want))]
    if got != want:
        raise SystemExit(f"persisted N7:0-{len(want) - 1} are {got}, the last acknowledged write was {want}")
    return f"persisted N7:0-{len(want) - 1} = the last acknowledged write ({want[0]}..{want[-1]})"


async def bench(args: argparse.Namespace, sides: dict[str, Side]) -> None:
    plcs = {name: await attach(side, args.words) for name, side in sides.items()}
    for name, plc in plcs.items():  # warm-up: imports, the database's first pages, the loops
        await plc.measure(args.seconds / 3, sides[name].process.pid)
    for i in range(args.runs):
        for name in ("on", "off") if i % 2 == 0 else ("off", "on"):
            sides[name].runs.append(await plcs[name].measure(args.seconds, sides[name].process.pid))


def remove_db(db: Path) -> None:
    for suffix in ("", "-wal", "-shm"):
        Path(f"{db}{suffix}").unlink(missing_ok=True)


def report(args: argparse.Namespace, sides: dict[str, Side], db_dir: Path, fsync: float) -> None:
    chars, seconds = wire_time(args.words)
    ceiling = 1 / seconds
    print(f"\none write of {args.words} words on the line: {chars} characters (command + ACK, ACK + reply) = "
          f"{seconds * 1000:.2f} ms at {BAUD} 8N1: ceiling {ceiling:.1f} writes/s")
    print(f"persist: {db_dir} ({file_system(db_dir)}; write + fsync there: {fsync:.3f} ms, median); "
          f"{args.runs} alternating runs of {args.seconds:g} s, median; gateway and PLC in separate processes\n")
    rows, median = [], {}
    for name, title in (("off", "persist off"), ("on", "persist on")):
        runs = sides[name].runs
        rates = sorted(run.rate for run in runs)
        median[name] = statistics.median(rates)
        writes = sum(run.writes for run in runs)
        cpu_ms = 1000 * sum(run.gateway_cpu for run in runs) / writes if writes else float("nan")
        plc_ms = 1000 * sum(run.plc_cpu for run in runs) / writes if writes else float("nan")
        other = {k: sum(run.other.get(k, 0) for run in runs) for run in runs for k in run.other}
        rows.append([title, median[name], f"{rates[0]:.0f}-{rates[-1]:.0f}", 1000 / median[name], cpu_ms, plc_ms,
                     median[name] / ceiling, ", ".join(f"{k} {v}" for k, v in other.items()) or "none"])
        if other:
            print(f"WARNING: persist {name}: writes that did not end TransactionDone: {other}")
    rows.append([f"the line, {BAUD} 8N1", ceiling, "-", seconds * 1000, "-", "-", 1.0, "-"])
    print(table(["", "writes/s", "range of runs", "ms per write", "gateway CPU ms/write", "PLC CPU ms/write",
                 "x the line's ceiling", "not done"], rows))
    ratio = median["on"] / median["off"]
    commit_ms = 1000 / median["on"] - 1000 / median["off"]
    print(f"\npersist on / off: {ratio:.3f}; the commit adds {commit_ms:.2f} ms per write, "
          f"{commit_ms / (seconds * 1000):.1%} of the write's {seconds * 1000:.1f} ms on the line")
    result(words=args.words, runs=args.runs, persist_on_per_s=median["on"], persist_off_per_s=median["off"],
           ratio=ratio, commit_ms=commit_ms, fsync_ms=fsync, ceiling_19200_per_s=ceiling,
           on_x_ceiling=median["on"] / ceiling)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="0.3 s runs (CI smoke test, under 20 s)")
    parser.add_argument("--words", type=int, default=10, help="words per write (default 10; at most 117)")
    parser.add_argument("--runs", type=int, default=5, help="alternating runs per mode (default 5)")
    parser.add_argument("--seconds", type=float, default=0.0, help="seconds per run (default 3; quick 0.3)")
    parser.add_argument("--db-dir", type=Path, help="directory of the persist database (default: a temporary one)")
    args = parser.parse_args()
    args.seconds = args.seconds or (0.3 if args.quick else 3.0)
    if not 1 <= args.words <= 117:
        parser.error("--words: 1 to 117 (234 data bytes, an SLC typed logical write's most on DF1)")
    print_machine()
    work = Path(tempfile.mkdtemp(prefix="target-persist-"))
    db_dir = args.db_dir or work
    db_dir.mkdir(parents=True, exist_ok=True)
    db = db_dir / "target-persist-bench.db"
    remove_db(db)
    fsync = fsync_ms(db_dir)
    sides: dict[str, Side] = {}
    try:
        sides["on"] = start_side("on", work, db)
        sides["off"] = start_side("off", work, None)
        asyncio.run(bench(args, sides))
        print(check_persisted(sides["on"]))
    finally:
        for side in sides.values():
            stop(side)
        remove_db(db)
        shutil.rmtree(work, ignore_errors=True)
    report(args, sides, db_dir, fsync)

if __name__ == "__main__":
    main()
