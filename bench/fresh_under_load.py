"""Fresh under load: a paced SLC 150 polled at 9600 baud while 50 Modbus connections load the server.

The gateway runs as its own process (``slc-gateway run``) against a controller paced at 9600 baud:
the project's simulator (``slc-gateway simulate slc150 --paced``, answering at the end of its
program scan, 20-60 ms: ``REALISTIC_SCAN``, ``--scan 0`` for at once) and, when
``../shared/interop`` is beside the repository, the independent interop peer
(``slc_ascii_peer.py --baud 9600``, which answers at once).
Windows of ``--seconds`` alternate between no load and load (``bench/loadgen.py read``: 50
closed-loop connections reading the accumulators and presets as fast as the server answers);
meanwhile a monitor reads every mapped table of the unit every 0.1 s and counts the reads
answered 0x0B (stale).  The poll cadence is the controller's transactions per second (status
registers 1003-1004) in each window; loaded / unloaded is taken per pair of windows, the order
alternating, and the median reported.

Target: no read answered 0x0B under load (a healthy line never lets a value go stale), and the
poll cadence kept (ratio near 1).

    python bench/fresh_under_load.py [--seconds 20] [--pairs 3] [--connections 50] [--target sim|peer|both]
                                     [--scan S|MIN-MAX|0]
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _benchlib import print_machine, result, table

from gateway.sim.scan import REALISTIC_SCAN

HOST = "127.0.0.1"
ROOT = Path(__file__).resolve().parent.parent
PEER = ROOT.parent / "shared" / "interop" / "peers" / "slc_ascii_peer.py"
GATEWAY = [sys.executable, "-m", "gateway"]
#: what the monitor reads: (function code, address, count), every mapped table of an SLC 150 unit
MONITOR = [(3, 0, 64), (1, 701, 120), (2, 1, 8), (2, 901, 32), (4, 0, 32)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


def wait_port(port: int, limit: float = 30.0) -> None:
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection((HOST, port), timeout=1):
            return
        time.sleep(0.1)
    raise RuntimeError(f"nothing listens on {port} after {limit} s")


@contextlib.contextmanager
def process(args: list[str], port: int) -> Iterator[subprocess.Popen[bytes]]:
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_port(port)
        yield proc
    finally:
        proc.terminate()
        proc.wait(10)


def controller(target: str, port: int, scan: str = REALISTIC_SCAN.text()) -> list[str]:
    if target == "peer":
        return [sys.executable, str(PEER), "--port", str(port), "--baud", "9600"]
    scan_option = ["--option", f"scan={scan}"] if scan.strip() not in ("", "0") else []
    return [*GATEWAY, "simulate", "slc150", "--paced", "--listen", f"{HOST}:{port}", *scan_option]


class Monitor:
    """One connection reading every mapped table in turn; counts replies and 0x0B answers."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection((HOST, port))
        self.tid = 0

    def call(self, pdu: bytes) -> bytes:
        self.tid = (self.tid + 1) & 0xFFFF
        self.sock.sendall(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, 1) + pdu)
        head = self._recv(7)
        return self._recv(struct.unpack(">H", head[4:6])[0] - 1)

    def _recv(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise RuntimeError("the gateway closed the connection")
            data += chunk
        return data

    def transactions(self) -> int:
        reply = self.call(struct.pack(">BHH", 4, 1003, 2))
        return int.from_bytes(reply[2:6], "big")

    def window(self, seconds: float) -> tuple[int, int, float]:
        """(reads, stale reads, transactions per second) over ``seconds``."""
        reads = stale = 0
        tx0, t0 = self.transactions(), time.monotonic()
        while time.monotonic() < t0 + seconds:
            for fc, address, count in MONITOR:
                reply = self.call(struct.pack(">BHH", fc, address, count))
                reads += 1
                stale += reply[0] & 0x80 and reply[1] == 0x0B
            time.sleep(0.1)
        return reads, stale, (self.transactions() - tx0) / (time.monotonic() - t0)


def measure(target: str, seconds: float, pairs: int, connections: int, scan: str) -> dict[str, object]:
    cport, mport = free_port(), free_port()
    config = Path(tempfile.mkdtemp()) / "gateway.toml"
    config.write_text(f"""
[modbus]
listen = "{HOST}:{mport}"
max_connections = {connections + 16}
max_connections_per_address = {connections + 8}

[logging]
level = "WARNING"

[[link]]
name = "paced"
protocol = "slc-ascii"
port = "socket://{HOST}:{cport}"
unit = 1
""")
    loaded_stale = loaded_reads = idle_stale = idle_reads = 0
    ratios: list[float] = []
    with process(controller(target, cport, scan), cport), process([*GATEWAY, "run", str(config)], mport):
        monitor = Monitor(mport)
        deadline = time.monotonic() + 60
        while monitor.call(struct.pack(">BHH", 4, 0, 32))[0] & 0x80:  # the first scan
            if time.monotonic() > deadline:
                raise RuntimeError(f"{target}: no first scan within 60 s")
            time.sleep(0.2)
        time.sleep(12)  # past the first slow scan
        for pair in range(pairs):
            rates: dict[bool, float] = {}
            for loaded in ((False, True) if pair % 2 == 0 else (True, False)):
                load = None
                if loaded:
                    load = subprocess.Popen(
                        [sys.executable, str(ROOT / "bench" / "loadgen.py"), "read", "--port", str(mport),
                         "--connections", str(connections), "--count", "64", "--duration", str(seconds + 5)],
                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                    time.sleep(2)  # its warm-up
                reads, stale, rate = monitor.window(seconds)
                rates[loaded] = rate
                if loaded:
                    loaded_reads, loaded_stale = loaded_reads + reads, loaded_stale + stale
                    assert load is not None
                    load.terminate()
                    load.wait(10)
                else:
                    idle_reads, idle_stale = idle_reads + reads, idle_stale + stale
            ratios.append(rates[True] / rates[False])
            print(f"  {target} pair {pair + 1}: {rates[False]:.1f} tx/s idle, {rates[True]:.1f} tx/s loaded",
                  flush=True)
    return {"target": target, "idle_reads": idle_reads, "idle_stale": idle_stale, "loaded_reads": loaded_reads,
            "loaded_stale": loaded_stale, "cadence_ratio": statistics.median(ratios)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each window (default 20)")
    parser.add_argument("--pairs", type=int, default=3, help="pairs of windows, idle and loaded (default 3)")
    parser.add_argument("--connections", type=int, default=50)
    parser.add_argument("--target", choices=("sim", "peer", "both"), default="both")
    parser.add_argument("--scan", default=REALISTIC_SCAN.text(),
                        help="the simulator's scan, seconds (default %(default)s; 0: answers at once)")
    args = parser.parse_args()
    print_machine()
    targets = ["sim", "peer"] if args.target == "both" else [args.target]
    if "peer" in targets and not PEER.exists():
        print(f"interop peer not found at {PEER}: measuring the simulator only")
        targets.remove("peer")
    rows = []
    for target in targets:
        figures = measure(target, args.seconds, args.pairs, args.connections, args.scan)
        rows.append([target, figures["idle_reads"], figures["idle_stale"], figures["loaded_reads"],
                     figures["loaded_stale"], figures["cadence_ratio"]])
        result(**{f"{target}_{k}": v for k, v in figures.items() if k != "target"})
    print(table(["controller", "reads idle", "0x0B idle", "reads loaded", "0x0B loaded",
                 "poll cadence loaded / idle (median)"], rows))


if __name__ == "__main__":
    main()
