"""DF1 target mode with the gateway as a process: an independent PLC, and SIGKILL with ``persist``.

* ``tests/peers/plc_msg_peer.py`` is a PLC written from the manuals alone by an engineer who did not
  read the gateway's code (its README lists its readings).  It runs its MSG script - PLC-5 word
  range, SLC typed logical, ControlLogix PLC-5 typed, floats, longs, masked bits, the error probes -
  under frame corruption, lost ACKs and NAKed replies, and checks every value over Modbus and back.
* The SIGKILL test kills the gateway between writes (a PLC's MSG writes and Modbus writes) and
  checks that every write that was acknowledged is there after a restart.
"""

from __future__ import annotations

import os
import random
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import NEED_DATA, Checksum
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import Df1Transactions, TransactionDone
from gateway.protocols.df1.pccc import ProtectedTypedLogicalWrite
from tests.net import free_port

ROOT = Path(__file__).resolve().parents[2]
PEER = ROOT / "tests" / "peers" / "plc_msg_peer.py"
HOST = "127.0.0.1"


def target_config(path: Path, port: int, modbus: int, extra: str = "") -> Path:
    path.write_text(f"""
[modbus]
listen = "{HOST}:{modbus}"

[[link]]
name = "plc"
protocol = "df1"
role = "target"
port = "socket://{HOST}:{port}"
unit = 1
{extra}

[[link.file]]
file = 7
type = "N"
elements = 100

[[link.file]]
file = 8
type = "F"
elements = 20
start = 200

[[link.file]]
file = 9
type = "L"
elements = 10
start = 300

[[link.file]]
file = 3
type = "B"
elements = 16
table = "coil"
""", encoding="utf-8")
    return path


def gateway(config: Path, log: Path) -> subprocess.Popen[bytes]:
    with log.open("ab") as out:
        return subprocess.Popen([sys.executable, "-m", "gateway", "run", str(config)], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT)


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for process in started:
        if process.poll() is None:
            process.kill()
        process.wait(10)


def test_an_independent_plc_runs_its_msg_script_under_faults(
    tmp_path: Path, processes: list[subprocess.Popen[bytes]]
) -> None:
    port, modbus = free_port(), free_port()
    config = target_config(tmp_path / "target.toml", port, modbus)
    stats = tmp_path / "peer.json"
    peer = subprocess.Popen(
        [sys.executable, str(PEER), "--port", str(port), "--modbus", f"{HOST}:{modbus}", "--unit", "1",
         "--rounds", "1", "--corrupt", "0.1", "--lose-ack", "0.1", "--nak-reply", "0.1", "--seed", "5",
         "--stats", str(stats)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    processes.append(gateway(config, tmp_path / "gateway.log"))
    try:
        output, _ = peer.communicate(timeout=240)
    finally:
        if peer.poll() is None:
            peer.kill()
    assert peer.returncode == 0, output[-4000:] + (tmp_path / "gateway.log").read_text()[-2000:]
    assert "RESULT: PASS" in output and "double applied 0" in output


# --- SIGKILL -------------------------------------------------------------------------------------


class Plc:
    """A PLC on the socket the gateway connects to: the gateway's own DF1 master cores, blocking."""

    def __init__(self, listener: socket.socket) -> None:
        listener.settimeout(30)
        self.sock, _ = listener.accept()
        self.core = Df1Transactions(Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.5), station=1, source=0,
                                    reply_timeout=1.0, retries=0)

    def send_write(self, element: int, value: int) -> int:
        request = ProtectedTypedLogicalWrite(FileType.INTEGER, 7, element, 0, struct.pack("<h", value))
        handle = self.core.start(request, time.monotonic(), write=False)
        try:
            self.sock.sendall(self.core.data_to_send())
        except OSError:
            pass  # the gateway is gone: outcome() says not acknowledged
        return handle

    def outcome(self, handle: int) -> bool:
        """True: the gateway answered STS 0 (acknowledged); False: no answer, or refused."""
        self.sock.settimeout(0.05)
        end = time.monotonic() + 5
        while time.monotonic() < end:
            try:
                data = self.sock.recv(4096)
                if not data:
                    return False  # the gateway is gone
            except TimeoutError:
                data = b""
            except ConnectionResetError:
                # the gateway is gone, its socket reset (a kill with our bytes unread): whatever it had sent is
                # lost with the reset, so this write counts as not acknowledged (it may still have been applied)
                return False
            now = time.monotonic()
            if data:
                self.core.receive_data(data, now)
            self.core.handle_timeout(now)
            out = self.core.data_to_send()
            try:
                if out:
                    self.sock.sendall(out)
            except OSError:
                return False
            while (event := self.core.next_event()) is not NEED_DATA:
                if event.handle == handle:
                    return isinstance(event, TransactionDone)
        return False

    def close(self) -> None:
        self.sock.close()


def modbus_write(port: int, address: int, value: int, tid: int) -> bool:
    """FC6 over a raw socket; True when the gateway answered it (acknowledged)."""
    try:
        with socket.create_connection((HOST, port), timeout=2) as sock:
            sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 6, address, value))
            reply = sock.recv(260)
    except OSError:
        return False
    return len(reply) >= 12 and reply[7] == 6


def modbus_read(port: int, address: int, count: int) -> list[int] | None:
    for _ in range(100):
        try:
            with socket.create_connection((HOST, port), timeout=2) as sock:
                sock.sendall(struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, address, count))
                reply = sock.recv(300)
            if len(reply) >= 9 and reply[7] == 3:
                return list(struct.unpack(f">{count}h", reply[9 : 9 + 2 * count]))
            if len(reply) >= 9 and reply[7] == 0x83:
                return None
        except OSError:
            pass
        time.sleep(0.1)
    raise AssertionError(f"the gateway does not answer on Modbus port {port}")


def test_sigkill_loses_no_acknowledged_write(tmp_path: Path, processes: list[subprocess.Popen[bytes]]) -> None:
    rng = random.Random(7)
    port, modbus = free_port(), free_port()
    config = target_config(tmp_path / "target.toml", port, modbus, f'persist = "{tmp_path / "plc.db"}"')
    listener = socket.create_server((HOST, port))
    #: element -> values that may be there: the last acknowledged, then any sent after it
    possible: dict[int, list[int]] = {}
    acknowledged_once: set[int] = set()
    value = 0
    for _cycle in range(4):
        process = gateway(config, tmp_path / "gateway.log")
        processes.append(process)
        plc = Plc(listener)
        kill_after = rng.randrange(20, 60)
        for n in range(kill_after + 1):
            value += 1
            element = rng.randrange(50)
            if n % 3 == 0:  # a Modbus client's write: holding 50-99 are N7:50-99
                element += 50
                sent = [value]
                acknowledged = modbus_write(modbus, element, value, value & 0xFFFF)
            else:
                handle = plc.send_write(element, value)
                if n == kill_after:  # the frame is on its way: kill before (or while) it is answered
                    os.kill(process.pid, signal.SIGKILL)
                    acknowledged = plc.outcome(handle)
                else:
                    acknowledged = plc.outcome(handle)
                sent = [value]
            history = possible.setdefault(element, [])
            if acknowledged:
                history[:] = sent
                acknowledged_once.add(element)
            else:
                history.extend(sent)  # may or may not have been committed
        if process.poll() is None:
            os.kill(process.pid, signal.SIGKILL)
        process.wait(10)
        plc.close()
    process = gateway(config, tmp_path / "gateway.log")
    processes.append(process)
    listener.close()
    words = modbus_read(modbus, 0, 100)
    assert words is None or len(words) == 100
    assert len(acknowledged_once) > 40
    for element, history in possible.items():
        got = modbus_read(modbus, element, 1)
        if element not in acknowledged_once and got is None:
            continue  # only unacknowledged writes went to it, and none was committed
        assert got is not None, f"N7:{element} was acknowledged but is not there after SIGKILL"
        assert got[0] in history, f"N7:{element} = {got[0]}, acknowledged/in flight: {history}"
