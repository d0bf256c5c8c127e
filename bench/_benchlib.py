"""Shared helpers of the benchmarks (not a benchmark itself).

* ``result(**values)``: the one final ``RESULT key=value ...`` line every script prints.
* ``machine()``: CPU count, CPU model, Python and pymodbus versions, for BENCHMARKS.md.
* ``SimFarm``: simulated controllers served over TCP by ``bench/simfarm.py`` in a *separate
  process*, so that their CPU is not charged to the gateway and their pacing timers are precise.
* config builders (``slc_link``, ``df1_link``, ``gateway_config``) and frame-length arithmetic
  from the protocol encoders (``slc_read_frames``, ``df1_read_frames`` ...).
* CPU and memory probes of the current process (``cpu_seconds``, ``rss_mib``).
* ``Broker``: Debian's mosquitto on a free loopback port, for the Sparkplug figures
  (``mosquitto_path``; a bench without it says so loudly, ``mosquitto_required`` in CI).
"""

from __future__ import annotations

import asyncio
import json
import os
import platform
import resource
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
REPO = BENCH_DIR.parent
PYTHON = sys.executable
HOST = "127.0.0.1"

# --------------------------------------------------------------------------------------------
# output


def fmt(value: object) -> str:
    if isinstance(value, float):
        if value != value:  # NaN
            return "nan"
        if abs(value) >= 100:
            return f"{value:.1f}"
        if abs(value) >= 1:
            return f"{value:.3f}"
        return f"{value:.4f}"
    return str(value).replace(" ", "_")


def result(**values: object) -> None:
    """Print the final ``RESULT key=value ...`` line (flushed)."""
    print("RESULT " + " ".join(f"{key}={fmt(value)}" for key, value in values.items()), flush=True)


def table(headers: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A Markdown table (pasted into BENCHMARKS.md as is)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(fmt(cell).replace("_", " ") if isinstance(cell, str) else fmt(cell)
                                       for cell in row) + " |")
    return "\n".join(lines)


def percentile(sorted_values: Sequence[float], q: float) -> float:
    """Nearest-rank percentile of already sorted values (q in 0..100); NaN when empty."""
    if not sorted_values:
        return float("nan")
    rank = max(1, min(len(sorted_values), int(-(-q * len(sorted_values) // 100))))
    return sorted_values[rank - 1]


def machine() -> dict[str, str]:
    model = "?"
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout.splitlines():
            if line.startswith("Model name:"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import pymodbus

        pymodbus_version = pymodbus.__version__
    except Exception:  # pragma: no cover - informational only
        pymodbus_version = "?"
    return {
        "nproc": str(os.cpu_count()),
        "cpu": model,
        "python": platform.python_version(),
        "pymodbus": pymodbus_version,
        "kernel": platform.release(),
    }


def print_machine() -> None:
    info = machine()
    print("machine: " + ", ".join(f"{k}={v}" for k, v in info.items()), flush=True)


# --------------------------------------------------------------------------------------------
# process probes


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (all threads)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def rss_mib() -> float:
    """Resident set size of this process now, MiB (from /proc/self/status)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def df1_simulator_available() -> bool:
    """The SLC 5/04 simulator (``gateway/sim/slc500.py``) is being written separately."""
    try:
        import gateway.kinds.df1.sim.slc500  # noqa: F401
    except ImportError:
        return False
    return True


# --------------------------------------------------------------------------------------------
# line arithmetic

SLC_CHAR_TIME = 10 / 9600  # 7E1: start + 7 data + parity + stop
DF1_CHAR_TIME = 10 / 19200  # 8N1: start + 8 data + stop


def slc_read_frames(address: int, count: int) -> tuple[int, int]:
    """(request, reply) characters of one SLC 100/150 read, from the protocol's own encoders."""
    from gateway.protocols.slc_ascii import commands as cmds
    from gateway.protocols.slc_ascii.framing import encode_data_reply, frame_command

    request = frame_command(cmds.read_bytes(address, count), 1)
    body = f"{count:04X}{address:04X}" + "00" * count  # count, address, data (the simulator's form)
    return len(request), len(encode_data_reply(body, 1))


def slc_write_word_frames(address: int = 0, value: int = 1234) -> tuple[int, int]:
    """(request, reply) characters of one SLC 100/150 write word (``;R`` acknowledge)."""
    from gateway.protocols.slc_ascii import commands as cmds
    from gateway.protocols.slc_ascii.framing import encode_ack, frame_command

    return len(frame_command(cmds.write_word(address, value), 1)), len(encode_ack(1))


def df1_frames(request: Any, reply_data: bytes, *, tns: int = 0x1234) -> tuple[int, int]:
    """(host -> controller, controller -> host) bytes of one DF1 transaction, ACKs included.

    Host: command frame + DLE ACK of the reply.  Controller: DLE ACK of the command + reply frame.
    CRC checksum; DLE doubling included (it depends on the data: zeros in a simulator's memory).
    """
    from gateway.protocols.df1.framing import Checksum, encode_frame
    from gateway.protocols.df1.pccc import PcccHeader, encode_command, encode_reply

    command = encode_command(request, dst=1, src=0, tns=tns)
    reply = encode_reply(PcccHeader.decode(command), data=reply_data)
    return len(encode_frame(command, Checksum.CRC)) + 2, 2 + len(encode_frame(reply, Checksum.CRC))


# --------------------------------------------------------------------------------------------
# configurations

#: A realistic SLC 5/04 map: N7:0-99 (holding), T4:0-9 ACC (input), F8:0-9 (input, float32),
#: B3:0-3 as 64 coils; all fast class.
DF1_MAP = [
    dict(table="holding", start=0, address="N7:0", count=100),
    dict(table="input", start=0, address="T4:0.ACC", count=10),
    dict(table="input", start=100, address="F8:0", count=10, type="float32"),
    dict(table="coil", start=0, address="B3:0/0", count=64),
]


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return json.dumps(str(value))


def slc_link(name: str, port: str, unit: int, **extra: object) -> str:
    lines = ["[[link]]", f'name = "{name}"', 'protocol = "slc-ascii"', f'port = "{port}"', f"unit = {unit}"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in extra.items()]
    return "\n".join(lines) + "\n"


def df1_link(name: str, port: str, unit: int, entries: Sequence[dict[str, object]] = DF1_MAP, **extra: object) -> str:
    lines = ["[[link]]", f'name = "{name}"', 'protocol = "df1"', f'port = "{port}"', f"unit = {unit}"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in extra.items()]
    for entry in entries:
        lines.append("  [[link.map]]")
        lines += [f"  {k} = {_toml_value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"


def gateway_config(links: Sequence[str], listen: str = f"{HOST}:0", max_connections: int = 256) -> str:
    # Every load-generator connection comes from 127.0.0.1: the per-address cap is the total one.
    head = (
        f'[modbus]\nlisten = "{listen}"\nmax_connections = {max_connections}\n'
        f"max_connections_per_address = {max_connections}\n\n[logging]\nlevel = \"WARNING\"\n\n"
    )
    return head + "\n".join(links)


# --------------------------------------------------------------------------------------------
# the simulator farm (bench/simfarm.py in its own process)


@dataclass
class FarmStats:
    cpu: float  # CPU seconds of the farm process so far
    lateness_p50: float  # the farm loop's timer lateness (seconds): the pacing error
    lateness_p99: float
    gaps: list[dict[str, float]]  # per connection: gateway reaction (reply out -> next request in)


class SimFarm:
    """``count`` simulators of ``model`` on ``count`` TCP ports, in a helper process.

    The helper uses a ``select()``-based event loop: ``epoll`` rounds its timeout up to a whole
    millisecond, which makes every paced character burst arrive about 0.5 ms late on average;
    ``select()`` takes microseconds, and the loop spins the last ``spin`` seconds before a timer.
    ``ports`` lists the ports; ``stats()`` returns the farm's
    CPU, its timer lateness and per-connection gateway reaction times since the last call.
    """

    def __init__(
        self,
        model: str,
        count: int = 1,
        *,
        paced: bool = True,
        turnaround: float = 0.0,
        baudrate: int | None = None,
        selector: str = "select",
        trace: str = "",
        spin: float = 0.0003,
        jitter: float = 0.0,
        ladder: bool = False,
    ) -> None:
        command = [
            PYTHON,
            str(BENCH_DIR / "simfarm.py"),
            "--model", model,
            "--count", str(count),
            "--turnaround", str(turnaround),
            "--selector", selector,
            "--spin", str(spin),
            "--jitter", str(jitter),
        ]
        if paced:
            command.append("--paced")
        if ladder:
            command.append("--ladder")
        if baudrate:
            command += ["--baudrate", str(baudrate)]
        if trace:
            command += ["--trace", trace]
        self.process = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(REPO), bufsize=1
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"simfarm for {model} did not start (exit {self.process.wait()})")
        self.ports: list[int] = json.loads(line)["ports"]
        self.model = model

    def urls(self) -> list[str]:
        return [f"socket://{HOST}:{port}" for port in self.ports]

    def _ask(self, command: str) -> dict[str, Any]:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()
        answer: dict[str, Any] = json.loads(self.process.stdout.readline())
        return answer

    def stats(self) -> FarmStats:
        data = self._ask("stats")
        return FarmStats(data["cpu"], data["lateness_p50"], data["lateness_p99"], data["gaps"])

    def close(self) -> None:
        if self.process.poll() is None:
            try:
                assert self.process.stdin is not None
                self.process.stdin.close()
                self.process.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                self.process.kill()
                self.process.wait()

    def __enter__(self) -> SimFarm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_until(predicate: Any, timeout: float, step: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


# --------------------------------------------------------------------------------------------
# the MQTT broker of the Sparkplug benchmarks


def free_port() -> int:
    """A loopback TCP port free now."""
    with socket.socket() as sock:
        sock.bind((HOST, 0))
        return int(sock.getsockname()[1])


def mosquitto_path() -> str | None:
    """Debian's mosquitto (``apt-get install mosquitto``), or None: the caller says so loudly."""
    return shutil.which("mosquitto") or next(
        (p for p in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto") if os.access(p, os.X_OK)), None)


def mosquitto_required() -> bool:
    """CI (``.ci/run``) sets SLC_GATEWAY_REQUIRE_MOSQUITTO=1: a missing broker is a failure there."""
    return os.environ.get("SLC_GATEWAY_REQUIRE_MOSQUITTO") == "1"


class Broker:
    """mosquitto on a free loopback port (``port``); ``start()`` waits until it listens, ``stop()`` ends it."""

    def __init__(self, path: str, directory: Path) -> None:
        self.path = path
        self.port = free_port()
        self.config = directory / "mosquitto.conf"
        self.config.write_text(f"listener {self.port} {HOST}\nallow_anonymous true\npersistence false\n"
                               "log_dest none\n", encoding="utf-8")
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, patience: float = 10.0) -> None:
        if self.process is None:
            self.process = subprocess.Popen([self.path, "-c", str(self.config)], stdout=subprocess.DEVNULL,
                                            stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + patience
        while time.monotonic() < deadline and self.process.poll() is None:
            try:
                socket.create_connection((HOST, self.port), timeout=0.5).close()
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"mosquitto did not listen on {HOST}:{self.port} (exit {self.process.poll()})")

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            self.process.wait(5)
            self.process = None


# --------------------------------------------------------------------------------------------
# completion-aligned windows


@dataclass
class Window:
    """Counter deltas between two completed poll blocks of one link."""

    seconds: float = 0.0
    transactions: int = 0
    sent: int = 0
    received: int = 0
    data: int = 0
    errors: int = 0

    def ideal(self, char_time: float, turnaround: float = 0.0) -> float:
        """Seconds the same frames need on the line, serialized (one request outstanding)."""
        return (self.sent + self.received) * char_time + self.transactions * turnaround

    def efficiency(self, char_time: float, turnaround: float = 0.0) -> float:
        return self.ideal(char_time, turnaround) / self.seconds if self.seconds > 0 else float("nan")


class CompletionLog:
    """Snapshots of a unit's link counters each time its poller completes a block.

    At that moment the counters hold whole transactions only (the reply and, for DF1, our ACK
    of it; not yet the next request), so a window between two snapshots has no partial
    transaction at either end: a plain time window would be off by up to one frame (a 213-byte
    DF1 reply is 110 ms, 4 % of a 3 s window).
    """

    def __init__(self, unit: Any) -> None:
        self.samples: list[tuple[float, int, int, int, int, int]] = []
        self._data = 0
        counters = unit.driver.counters
        inner = unit.poller._read_block  # the unit's read_block, as the poller calls it

        async def logged(block: Any) -> bytes:
            data: bytes = await inner(block)
            self._data += len(data)
            self.samples.append((time.perf_counter(), counters.transactions, counters.bytes_sent,
                                 counters.bytes_received, self._data, counters.errors))
            return data

        unit.poller._read_block = logged

    def window(self, start: float, end: float) -> Window:
        inside = [s for s in self.samples if start <= s[0] <= end]
        if len(inside) < 2:
            return Window()
        a, b = inside[0], inside[-1]
        return Window(b[0] - a[0], b[1] - a[1], b[2] - a[2], b[3] - a[3], b[4] - a[4], b[5] - a[5])


# --------------------------------------------------------------------------------------------
# the reference host: the least any asyncio program can do per transaction


def slc_bare_frames() -> list[bytes]:
    """SLC 100/150 read requests of the default map's fast class, IDs 00, 01..7F, 01..7F ..."""
    from gateway.kinds.slc_ascii.plan import slc_ascii_plan
    from gateway.modbus.mapping import Scan
    from gateway.protocols.slc_ascii import commands as cmds
    from gateway.protocols.slc_ascii.framing import frame_command

    blocks = [b for b in slc_ascii_plan().blocks if b.scan is Scan.FAST]
    frames = []
    for i in range(127 * len(blocks)):  # a whole number of ID cycles and of scans
        msg_id = 0 if i == 0 else (i - 1) % 0x7F + 1
        address, count = blocks[i % len(blocks)].request  # type: ignore[misc]
        frames.append(frame_command(cmds.read_bytes(address, count), msg_id))
    return frames  # after the last (ID 7E) comes ID 00 again, always accepted


def df1_bare_frames(
    entries: Sequence[dict[str, object]] = DF1_MAP, count: int = 4000, first_tns: int = 30000
) -> list[bytes]:
    """DF1 command frames (CRC) of the map's read plan, consecutive TNS from ``first_tns``."""
    from gateway.kinds.df1.plan import MapItem, plan_df1
    from gateway.protocols.df1.framing import Checksum, encode_frame
    from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, encode_command

    items = [MapItem(**entry) for entry in entries]  # type: ignore[arg-type]
    blocks = plan_df1(items, 236).blocks
    frames = []
    for i in range(count):
        r = blocks[i % len(blocks)].request
        request = ProtectedTypedLogicalRead(r.file_type, r.file_number, r.element, r.sub_element, r.size)  # type: ignore[attr-defined]
        packet = encode_command(request, dst=1, src=0, tns=(first_tns + i) & 0xFFFF)
        frames.append(encode_frame(packet, Checksum.CRC))
    return frames


def _slc_reply_end(buffer: bytearray) -> int:
    return buffer.find(b"\r") + 1


def _df1_reply_end(buffer: bytearray) -> int:
    """End of ``DLE ACK`` + one CRC frame in ``buffer``, or 0 (the ACK may come first alone)."""
    start = buffer.find(b"\x10\x02")
    if start < 0:
        return 0
    position = start + 2
    while True:
        position = buffer.find(b"\x10", position)
        if position < 0 or position + 1 >= len(buffer):
            return 0
        following = buffer[position + 1]
        if following == 0x10:  # a doubled DLE: data
            position += 2
            continue
        if following == 0x03:
            end = position + 4  # DLE ETX CRC CRC
            return end if end <= len(buffer) else 0
        position += 2


class BareHost(asyncio.Protocol):
    """Polls a simulator with precomputed frames and no logic: the reference for the gateway.

    Each reply completes a transaction: the next request (DF1: our DLE ACK and the next command
    in one write) goes out from ``data_received`` at once.  What is left between this host's
    efficiency and 1 is the machine (process wake-up, loopback TCP) and the simulator's pacing.
    """

    def __init__(self, frames: Sequence[bytes], df1: bool) -> None:
        self.frames = frames
        self.df1 = df1
        self.end_of_reply = _df1_reply_end if df1 else _slc_reply_end
        self.buffer = bytearray()
        self.index = 0
        self.transport: asyncio.Transport | None = None
        self.transactions = self.sent = self.received = 0
        self.samples: list[tuple[float, int, int, int, int, int]] = []

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        self._send(b"")

    def _send(self, prefix: bytes) -> None:
        frame = prefix + self.frames[self.index % len(self.frames)]
        self.index += 1
        self.sent += len(frame)
        assert self.transport is not None
        self.transport.write(frame)

    def data_received(self, data: bytes) -> None:
        self.received += len(data)
        self.buffer += data
        end = self.end_of_reply(self.buffer)
        if end:
            del self.buffer[:end]
            self.transactions += 1
            # counters as of the completed transaction (our ACK counted, the next request not)
            self.samples.append((time.perf_counter(), self.transactions, self.sent + (2 if self.df1 else 0),
                                 self.received, 0, 0))
            self._send(b"\x10\x06" if self.df1 else b"")

    def window(self, start: float, end: float) -> Window:
        inside = [s for s in self.samples if start <= s[0] <= end]
        if len(inside) < 2:
            return Window()
        a, b = inside[0], inside[-1]
        return Window(b[0] - a[0], b[1] - a[1], b[2] - a[2], b[3] - a[3])


async def run_bare_host(port: int, df1: bool, warmup: float, duration: float) -> Window:
    loop = asyncio.get_running_loop()
    frames = df1_bare_frames() if df1 else slc_bare_frames()
    transport, host = await loop.create_connection(lambda: BareHost(frames, df1), HOST, port)
    await asyncio.sleep(warmup)
    start = time.perf_counter()
    await asyncio.sleep(duration)
    end = time.perf_counter()
    transport.close()
    return host.window(start, end)


def fetch(port: int, path: str) -> str:
    """The text of ``http://127.0.0.1:<port><path>`` (the gateway's /metrics or /api/status)."""
    with urllib.request.urlopen(f"http://{HOST}:{port}{path}", timeout=5) as reply:
        text: str = reply.read().decode()
        return text


def wait_for(predicate: Callable[[], object], timeout: float, what: str, step: float = 0.2) -> None:
    """Poll ``predicate`` every ``step`` seconds until it holds; exit the bench naming ``what`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit(f"{what} did not reach the expected state in time")
        time.sleep(step)
