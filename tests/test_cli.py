"""The command-line tools against ``slc-gateway simulate`` run as a real subprocess.

Over TCP (``socket://127.0.0.1:PORT``, a serial device server in raw mode) and over a
pseudo-terminal (the simulator prints its ``/dev/pts/N``; the CLI opens it as a serial port).
Everything stays on this machine: 127.0.0.1 and a pty.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_support import cli, fails, ok, ok_json, start_simulator, stop

from tests.net import free_port


def tcp_simulator(model: str) -> Iterator[str]:
    process, line = start_simulator(model, "--listen", "127.0.0.1:0", "--no-ladder")
    try:
        match = re.fullmatch(rf"simulated {model} listening on (127\.0\.0\.1):(\d+) \((socket://\S+)\)", line)
        assert match, line
        assert match.group(3) == f"socket://127.0.0.1:{match.group(2)}"
        assert int(match.group(2)) > 0
        yield match.group(3)
    finally:
        stop(process)


@pytest.fixture
def slc150() -> Iterator[str]:
    """URL of a simulated SLC 150 over TCP, for one test that changes it."""
    yield from tcp_simulator("slc150")


@pytest.fixture(scope="module")
def shared_slc150() -> Iterator[str]:
    """URL of a simulated SLC 150 over TCP, shared by the tests that change nothing in it."""
    yield from tcp_simulator("slc150")


@pytest.fixture
def slc100() -> Iterator[str]:
    """URL of a simulated SLC 100 over TCP."""
    yield from tcp_simulator("slc100")


@pytest.fixture
def pty_slc150() -> Iterator[str]:
    """Path of a pseudo-terminal with a simulated SLC 150 behind it."""
    process, line = start_simulator("slc150", "--pty", "--no-ladder")
    try:
        match = re.fullmatch(r"simulated slc150 on (/dev/\S+)", line)
        assert match, line
        assert os.path.exists(match.group(1))
        yield match.group(1)
    finally:
        stop(process)


# ---------------------------------------------------------------------------------------------
# Over TCP


def test_probe(shared_slc150: str) -> None:
    assert ok_json("probe", shared_slc150) == {"controller": "SLC150", "device_type": 0x15, "frn": 47}
    text = ok("probe", shared_slc150)
    assert text.splitlines() == ["controller = SLC150", "device_type = 21", "frn = 47"]


def test_read_json_gives_one_object(shared_slc150: str) -> None:
    result = ok_json("read", shared_slc150, "901.PRE", "701", "932.PRE", "932.PROTECTED", "@0x84", "901.STEP")
    assert result == {"901.PRE": 100, "701": False, "932.PRE": 500, "932.PROTECTED": True, "@0x84": 0, "901.STEP": 0}


def test_write_then_read_back(slc150: str) -> None:
    assert ok("write", slc150, "905.PRE=1234", "701=1", "903.ACC=0x10").splitlines() == [
        "905.PRE = 1234", "701 = 1", "903.ACC = 16"]
    assert ok_json("read", slc150, "905.PRE", "701", "702", "903.ACC") == {
        "905.PRE": 1234, "701": True, "702": False, "903.ACC": 16}
    assert ok("read", slc150, "701", "905.PRE").splitlines() == ["701 = true", "905.PRE = 1234"]
    ok("write", slc150, "701=0", "708=1")
    assert ok_json("read", slc150, "701", "708", "@A6") == {"701": False, "708": True, "@A6": 0x80}


def test_mode_upload_and_download_back(slc150: str, tmp_path: Path) -> None:
    backup = tmp_path / "slc150.json"
    assert ok_json("mode", slc150, "program") == {"mode": "program"}
    assert ok_json("upload", slc150, str(backup)) == {"file": str(backup), "controller": "SLC150", "blocks": 0xA5}
    document = json.loads(backup.read_text())
    assert document["format"] == "slc-gateway-program/1"
    assert document["controller"] == "SLC150"
    assert len(document["blocks"]) == 0xA5
    assert all(len(block) == 30 for block in document["blocks"])
    assert document["blocks"][0] == bytes((i * 7 + 3) & 0xFF for i in range(15)).hex().upper()
    assert document["blocks"][-1].endswith("00" * 8)  # fill
    assert ok_json("download", slc150, str(backup))["blocks"] == 0xA5
    # the program read back is the same
    again = tmp_path / "again.json"
    ok("upload", slc150, str(again))
    assert json.loads(again.read_text())["blocks"] == document["blocks"]
    # reads are refused in program mode; back to run mode they work
    assert "refused" in fails("read", slc150, "901.PRE")
    ok("mode", slc150, "run")
    assert ok_json("read", slc150, "901.PRE") == {"901.PRE": 100}


def test_upload_outside_program_mode_is_refused(shared_slc150: str, tmp_path: Path) -> None:
    reason = fails("upload", shared_slc150, str(tmp_path / "x.json"))
    assert reason.startswith("slc-gateway upload: ")
    assert "refused" in reason
    assert not (tmp_path / "x.json").exists()


def test_download_refuses_a_program_for_another_controller(slc100: str, slc150: str, tmp_path: Path) -> None:
    backup = tmp_path / "slc100.json"
    ok("mode", slc100, "program")
    ok("upload", slc100, str(backup))
    assert json.loads(backup.read_text())["controller"] == "SLC100"
    assert len(json.loads(backup.read_text())["blocks"]) == 0x7B
    ok("mode", slc150, "program")
    reason = fails("download", slc150, str(backup))
    assert reason.startswith("slc-gateway download: ")
    assert "SLC100" in reason and "SLC150" in reason
    # nothing was downloaded: the SLC 150 still has its own program
    after = tmp_path / "after.json"
    ok("upload", slc150, str(after))
    assert json.loads(after.read_text())["blocks"][0] == bytes((i * 7 + 3) & 0xFF for i in range(15)).hex().upper()


def test_download_refuses_a_damaged_file(slc150: str, tmp_path: Path) -> None:
    backup = tmp_path / "p.json"
    ok("mode", slc150, "program")
    ok("upload", slc150, str(backup))
    document = json.loads(backup.read_text())
    document["blocks"][3] = "FF" * 15
    backup.write_text(json.dumps(document))
    assert "checksum" in fails("download", slc150, str(backup))
    backup.write_text("not json")
    assert "not a program backup file" in fails("download", slc150, str(backup))


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("read", "{url}", "999.FOO"), "999"),
        (("read", "{url}", "901.FOO"), "suffix"),
        (("read", "{url}", "@0x80"), "0x80"),
        (("write", "{url}", "901.PRE"), "ITEM=VALUE"),
        (("write", "{url}", "901.PRE=abc"), "not a whole number"),
        (("write", "{url}", "901.PRE=10000"), "0-9999"),
        (("write", "{url}", "11=1"), "read only"),  # an output
        (("write", "{url}", "701=2"), "0 or 1"),
        (("write", "{url}", "932.PRE=5"), "refused"),  # protected preset: the controller says ;E
    ],
)
def test_failures_exit_non_zero_with_a_one_line_reason(shared_slc150: str, args: tuple[str, ...], words: str) -> None:
    reason = fails(*(a.format(url=shared_slc150) for a in args))
    assert reason.startswith(f"slc-gateway {args[0]}: ")
    assert words in reason


def test_a_refused_write_changes_nothing(shared_slc150: str) -> None:
    fails("write", shared_slc150, "932.PRE=5")
    assert ok_json("read", shared_slc150, "932.PRE", "932.PROTECTED") == {"932.PRE": 500, "932.PROTECTED": True}


def test_unreachable_port() -> None:
    url = f"socket://127.0.0.1:{free_port()}"
    reason = fails("probe", url)
    assert reason.startswith("slc-gateway probe: ")
    assert f"127.0.0.1:{url.rsplit(':', 1)[1]}" in reason
    assert fails("read", "/dev/does-not-exist", "901.PRE").startswith("slc-gateway read: ")


def test_usage_errors_exit_2() -> None:
    result = cli("read", "socket://127.0.0.1:1")  # no items
    assert result.returncode == 2
    result = cli("mode", "socket://127.0.0.1:1", "sideways")
    assert result.returncode == 2


def test_simulate_stops_on_sigterm_with_a_client_connected() -> None:
    process, line = start_simulator("slc150", "--listen", "127.0.0.1:0")
    try:
        match = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        assert match, line
        with socket.create_connection(("127.0.0.1", int(match.group(1))), timeout=5) as client:
            client.sendall(b"#010800A3\r")
            assert client.recv(64).startswith(b":021FFE1547")
            process.terminate()
            assert process.wait(timeout=5) == 0
            assert client.recv(64) == b""  # the simulator closed the connection
    finally:
        stop(process)


# ---------------------------------------------------------------------------------------------
# Over a pseudo-terminal, as over a serial port


#: 8N1 with the parity bit sent as bit 7 by the driver: the same bits on a real wire as 7E1.
PTY_LINE = ("--bytesize", "8", "--parity", "N")


def test_over_a_pty_as_the_guide_says(pty_slc150: str, tmp_path: Path) -> None:
    """The guide's example (docs/guide/command-line.md): ``simulate slc150 --pty``, then the CLI on
    the path it printed, with the protocol's own 7E1.  Ports that refuse 7E1 (this machine's ptys
    do) fall back to 8N1 with the parity bit computed in software, by themselves."""
    assert ok_json("probe", pty_slc150) == {"controller": "SLC150", "device_type": 0x15, "frn": 47}
    ok("write", pty_slc150, "910.PRE=4321", "720=1")
    assert ok_json("read", pty_slc150, "910.PRE", "720", "901.PRE") == {"910.PRE": 4321, "720": True, "901.PRE": 100}
    assert "refused" in fails("write", pty_slc150, "932.PRE=5")
    backup = tmp_path / "pty.json"
    ok("mode", pty_slc150, "program")
    ok("upload", pty_slc150, str(backup))
    ok("download", pty_slc150, str(backup))
    ok("mode", pty_slc150, "run")
    assert len(json.loads(backup.read_text())["blocks"]) == 0xA5
    assert fails("probe", "/dev/pts/999999").startswith("slc-gateway probe: ")
    # -v shows the fallback, once per port per process
    result = cli("-v", "probe", pty_slc150)
    assert result.returncode == 0, result.stderr
    fallback = [line for line in result.stderr.splitlines() if "parity bit computed in software" in line]
    if fallback:  # not on ports that take 7E1
        assert len(fallback) == 1 and f"{pty_slc150} refuses 7E1: using 8N1" in fallback[0]


def test_over_a_pty_with_8n1_and_the_drivers_parity(pty_slc150: str) -> None:
    """The explicit form for a port that cannot do 7E1: ``--bytesize 8 --parity N``."""
    assert ok_json("probe", pty_slc150, *PTY_LINE) == {"controller": "SLC150", "device_type": 0x15, "frn": 47}
    ok("write", pty_slc150, *PTY_LINE, "910.PRE=4321")
    assert ok_json("read", pty_slc150, *PTY_LINE, "910.PRE") == {"910.PRE": 4321}


def test_run_trace_records_every_byte_of_every_link(tmp_path: Path) -> None:
    config = tmp_path / "gateway.toml"
    config.write_text(
        '[modbus]\nlisten = "127.0.0.1:0"\n'
        '[[link]]\nname = "ascii"\nprotocol = "slc-ascii"\nport = "sim://slc150?ladder=0"\nunit = 1\n'
        '[[link]]\nname = "df1"\nprotocol = "df1"\nport = "sim://slc504?ladder=0"\nunit = 2\n'
        '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n'
    )
    trace = tmp_path / "links.trace"
    process = subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", str(config), "--trace", str(trace)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    def traced() -> bool:
        text = trace.read_text() if trace.exists() else ""
        return " df1 RX " in text and " ascii RX " in text

    try:
        deadline = time.monotonic() + 10
        while not traced() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        process.terminate()
        _, err = process.communicate(timeout=10)
    assert process.returncode == 0, err
    lines = trace.read_text().splitlines()
    # "<unix time> <link> <TX|RX> <hex bytes>  |<printable>|"
    pattern = re.compile(r"^\d+\.\d{6} (ascii|df1) (TX|RX) [0-9a-f]{2}( [0-9a-f]{2})*  \|.*\|$")
    assert lines and all(pattern.match(line) for line in lines), lines[:3]
    assert any(line.split()[1:3] == ["ascii", "TX"] and "|#010800A3.|" in line for line in lines)  # ID 00 resync
    directions = {tuple(line.split()[1:3]) for line in lines}
    assert directions == {("ascii", "TX"), ("ascii", "RX"), ("df1", "TX"), ("df1", "RX")}
