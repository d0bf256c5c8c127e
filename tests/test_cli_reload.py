"""``slc-gateway run`` reloads its config file on SIGHUP (and ``slc-gateway reload``), as a real
process, while one Modbus TCP connection stays open and keeps reading.

The Modbus requests are written here byte by byte (MBAP header + PDU, from the Modbus application
protocol specification), so the connection is one socket the test owns from start to end.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import struct
import subprocess
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_support import CLI, cli, fails

from tests.net import free_port
from tests.waiting import until_sync

PATH_UNAVAILABLE = 0x0A


class ModbusSocket:
    """One Modbus TCP connection: FC3 requests, one at a time."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.tid = 0

    def read_holding(self, unit: int, address: int, count: int) -> list[int] | int:
        """The registers, or the exception code."""
        self.tid += 1
        self.sock.sendall(struct.pack(">HHHBBHH", self.tid, 0, 6, unit, 3, address, count))
        head = self._exactly(7)
        tid, protocol, length, reply_unit = struct.unpack(">HHHB", head)
        assert (tid, protocol, reply_unit) == (self.tid, 0, unit)
        pdu = self._exactly(length - 1)
        if pdu[0] == 0x83:
            return pdu[1]
        assert pdu[0] == 3 and pdu[1] == 2 * count
        return list(struct.unpack(f">{count}H", pdu[2:]))

    def _exactly(self, size: int) -> bytes:
        data = b""
        while len(data) < size:
            more = self.sock.recv(size - len(data))
            assert more, "the gateway closed the connection"
            data += more
        return data


def link(name: str, protocol: str, port: str, unit: int, extra: str = "") -> str:
    return f'[[link]]\nname = "{name}"\nprotocol = "{protocol}"\nport = "{port}"\nunit = {unit}\n{extra}\n'


N7 = '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n'


@pytest.fixture
def gateway(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], Path, Path, int, int]]:
    """``run CONFIG --pid-file FILE`` with one SLC 150; its log goes to a file."""
    modbus, metrics = free_port(), free_port()
    config = tmp_path / "gateway.toml"
    config.write_text(f'[modbus]\nlisten = "127.0.0.1:{modbus}"\n[metrics]\nlisten = "127.0.0.1:{metrics}"\n\n'
                      + link("ascii", "slc-ascii", "sim://slc150?ladder=0", 1))
    pid_file, log = tmp_path / "gateway.pid", tmp_path / "gateway.log"
    with log.open("w") as err:
        process = subprocess.Popen([*CLI, "run", str(config), "--pid-file", str(pid_file)],
                                   stdout=subprocess.DEVNULL, stderr=err, text=True)
    try:
        until_sync(lambda: pid_file.exists() and "serving Modbus TCP" in log.read_text(), 15.0,
                   what="the gateway serving")
        yield process, config, log, modbus, metrics
    finally:
        process.terminate()
        assert process.wait(timeout=15) == 0, log.read_text()
        assert not pid_file.exists()  # removed at exit


def get_json(port: int, path: str) -> dict[str, object]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        document: dict[str, object] = json.load(response)
        return document


def get_text(port: int, path: str) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        text: str = response.read().decode()
        return text


def test_sighup_adds_a_link_and_a_broken_file_changes_nothing(
    gateway: tuple[subprocess.Popen[str], Path, Path, int, int], tmp_path: Path
) -> None:
    process, config, log, modbus, metrics = gateway
    client = ModbusSocket(modbus)
    until_sync(lambda: isinstance(client.read_holding(1, 0, 4), list), 15.0, what="unit 1 served")
    assert client.read_holding(2, 0, 4) == PATH_UNAVAILABLE
    first = config.read_text()

    # a link added, by `slc-gateway reload --pid-file`
    second = first + link("df1", "df1", "sim://slc504?ladder=0", 2, N7)
    config.write_text(second)
    result = cli("reload", "--pid-file", str(tmp_path / "gateway.pid"))
    assert result.returncode == 0, result.stderr
    assert f"asked process {process.pid} to reload its config file" in result.stderr
    until_sync(lambda: isinstance(client.read_holding(2, 0, 4), list), 15.0,
               what="the new unit 2 served on the same connection")
    assert "links: 1 added (df1), 1 line unchanged" in log.read_text()
    short = hashlib.sha256(second.encode()).hexdigest()[:12]

    # a file that does not load: the message check-config gives, logged; nothing changes
    broken = tmp_path / "broken.toml"
    broken.write_text(second.replace("unit = 2\n", "unit = 2\nstale_aftr = 3.0\n"))
    reason = fails("check-config", str(broken)).removeprefix("slc-gateway check-config: ")
    assert f"{broken}:" in reason and 'stale_aftr: unknown key (did you mean "stale_after"?)' in reason
    config.write_text(broken.read_text())
    os.kill(process.pid, signal.SIGHUP)  # as systemctl reload and docker kill -s HUP send it
    reason = reason.replace(str(broken), str(config))
    until_sync(lambda: f"reload: {reason}" in log.read_text(), 15.0, what="the failure logged")
    assert isinstance(client.read_holding(1, 0, 4), list) and isinstance(client.read_holding(2, 0, 4), list)

    status = get_json(metrics, "/api/status")["config"]
    assert isinstance(status, dict)
    assert status["sha256"] == short and status["reloads"] == 1 and status["reload_failures"] == 1
    assert status["last_failure"] == reason and status["restart_needed"] == []
    text = get_text(metrics, "/metrics")
    assert f'slc_gateway_config_info{{sha256="{short}"}} 1.0' in text
    assert 'slc_gateway_config_reloads_total{result="ok"} 1.0' in text
    assert 'slc_gateway_config_reloads_total{result="failed"} 1.0' in text
    rows = get_json(metrics, "/api/status")["links"]
    assert isinstance(rows, list) and [row["name"] for row in rows] == ["ascii", "df1"]


def test_reload_sends_nothing_to_a_process_that_is_not_the_gateway(tmp_path: Path) -> None:
    other = subprocess.Popen(["sleep", "30"])
    try:
        pid_file = tmp_path / "stale.pid"
        pid_file.write_text(f"{other.pid}\n")
        reason = fails("reload", "--pid-file", str(pid_file))
        assert reason.startswith(f"slc-gateway reload: process {other.pid} is not slc-gateway run (sleep 30")
        assert other.poll() is None  # SIGHUP would have ended it
        assert fails("reload", "--pid-file", str(tmp_path / "none.pid")).startswith(
            f"slc-gateway reload: cannot read {tmp_path / 'none.pid'}: No such file or directory")
    finally:
        other.kill()
        other.wait()
