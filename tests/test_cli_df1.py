"""The DF1 command-line tools (``--protocol df1``) against ``slc-gateway simulate slc504`` run as a
real subprocess on 127.0.0.1.

Expected values come from the simulator's documented initial data table (N7:k = k, F8:k = 1.5 k,
T4:1.PRE = 20, B3:0 = 0) with its ladder frozen (``--no-ladder``).
"""

from __future__ import annotations

import json
import re
import selectors
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest

CLI = [sys.executable, "-m", "gateway"]
DF1 = ("--protocol", "df1")
TIMEOUT = 30  # seconds for any one command; each normally takes well under one


def stop(process: subprocess.Popen[str]) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5)
    for stream in (process.stdout, process.stderr):
        if stream is not None:
            stream.close()


def simulate_slc504(*args: str) -> Iterator[str]:
    """Run ``slc-gateway simulate slc504 --listen 127.0.0.1:0 ARGS``; yield its socket:// URL."""
    process = subprocess.Popen(
        [*CLI, "simulate", "slc504", "--listen", "127.0.0.1:0", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(process.stdout, selectors.EVENT_READ)
            assert selector.select(timeout=TIMEOUT), f"simulate slc504 printed nothing within {TIMEOUT} s"
        line = process.stdout.readline().strip()
        match = re.fullmatch(r"simulated slc504 listening on (127\.0\.0\.1):(\d+) \((socket://\S+)\)", line)
        assert match, (line, process.stderr.read() if process.poll() is not None and process.stderr else "")
        assert match.group(3) == f"socket://127.0.0.1:{match.group(2)}" and int(match.group(2)) > 0
        yield match.group(3)
    finally:
        stop(process)


@pytest.fixture
def slc504() -> Iterator[str]:
    """A simulated SLC 5/04 over TCP for one test that changes it."""
    yield from simulate_slc504("--no-ladder")


@pytest.fixture(scope="module")
def shared_slc504() -> Iterator[str]:
    """A simulated SLC 5/04 over TCP shared by the tests that change nothing in it."""
    yield from simulate_slc504("--no-ladder")


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=TIMEOUT, check=False)


def ok(*args: str) -> str:
    result = cli(*args)
    assert result.returncode == 0, f"{args}: exit {result.returncode}: {result.stderr}"
    assert result.stderr == ""
    return result.stdout


def ok_json(*args: str) -> Any:
    lines = ok(*args, "--json").splitlines()
    assert len(lines) == 1, lines  # one object
    return json.loads(lines[0])


def fails(*args: str, status: int = 1) -> str:
    """Run a command that must fail; return its one-line reason."""
    result = cli(*args)
    assert result.returncode == status, f"{args}: exit {result.returncode}: {result.stdout} {result.stderr}"
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, f"{args}: not a one-line reason: {result.stderr!r}"
    assert "Traceback" not in result.stderr
    return lines[0]


# ---------------------------------------------------------------------------------------------


def test_probe_identifies_an_slc_5_04(shared_slc504: str) -> None:
    assert ok_json("probe", *DF1, shared_slc504) == {
        "processor": "SLC 5/04", "catalog": "1747-L542", "series": "C", "frn": 3}


def test_read_items_as_one_json_object(shared_slc504: str) -> None:
    result = ok_json("read", *DF1, shared_slc504, "N7:0", "T4:1.ACC", "F8:2", "B3:0/3", "N7:200", "T4:1", "I:1.2")
    assert result == {
        "N7:0": 0, "T4:1.ACC": 0, "F8:2": 3.0, "B3:0/3": False,
        "N7:200": -1,  # signed
        "T4:1": [0, 20, 0],  # a whole timer: control, PRE, ACC
        "I:1.2": 0x1102,
    }
    assert ok("read", *DF1, shared_slc504, "N7:7", "B3:1/0").splitlines() == ["N7:7 = 7", "B3:1/0 = true"]


def test_write_then_read_back(slc504: str) -> None:
    assert ok("write", *DF1, slc504, "N7:5=1234", "F8:2=2.5", "B3:0/3=1").splitlines() == [
        "N7:5 = 1234", "F8:2 = 2.5", "B3:0/3 = 1"]
    assert ok_json("read", *DF1, slc504, "N7:5", "F8:2", "B3:0/3", "B3:0/2", "B3:0") == {
        "N7:5": 1234, "F8:2": 2.5, "B3:0/3": True, "B3:0/2": False, "B3:0": 8}
    ok("write", *DF1, slc504, "B3:0/3=0", "B3:0/4=1", "N7:6=-5", "T4:2.PRE=77")
    assert ok_json("read", *DF1, slc504, "B3:0", "N7:6", "T4:2.PRE", "N7:5") == {
        "B3:0": 16, "N7:6": -5, "T4:2.PRE": 77, "N7:5": 1234}


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("read", "{url}", "N7:300"), "element 300 out of range"),
        (("read", "{url}", "X7:0"), "not an SLC 500 address"),
        (("read", "{url}", "N7:abc"), "not an SLC 500 address"),
        (("read", "{url}", "N10:150"), "Address doesn't point to something usable"),  # refused by the controller
        (("write", "{url}", "N7:0"), "ADDRESS=VALUE"),
        (("write", "{url}", "N7:0=abc"), "not a whole number"),
        (("write", "{url}", "N7:0=70000"), "-32768..65535"),
        (("write", "{url}", "B3:0/1=2"), "0 or 1"),
        (("write", "{url}", "T4:1=5"), "member"),
    ],
)
def test_bad_items_exit_1_with_a_one_line_reason(shared_slc504: str, args: tuple[str, ...], words: str) -> None:
    command, *rest = args
    reason = fails(command, *DF1, *(a.format(url=shared_slc504) for a in rest))
    assert reason.startswith(f"slc-gateway {command}: ")
    assert words in reason


def test_a_refused_write_changes_nothing(slc504: str) -> None:
    reason = fails("write", *DF1, slc504, "N7:3=9", "N10:150=3")
    assert "Address doesn't point to something usable" in reason
    assert ok_json("read", *DF1, slc504, "N7:3") == {"N7:3": 9}  # the writes before it were done


def test_consecutive_single_writes_are_each_applied(slc504: str) -> None:
    ok("write", *DF1, slc504, "N7:9=1", "--timeout", "0.3")
    ok("write", *DF1, slc504, "N7:9=2", "--timeout", "0.3")  # TNS 1 again, CMD 0F again
    assert ok_json("read", *DF1, slc504, "N7:9") == {"N7:9": 2}


def _hang_up_server() -> tuple[socket.socket, threading.Thread]:
    """A device server that accepts, reads the first bytes and hangs up."""
    listener = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        with listener:
            for _ in range(5):
                try:
                    connection, _ = listener.accept()
                except OSError:
                    return
                with connection:
                    connection.settimeout(5)
                    try:
                        connection.recv(64)
                    except OSError:
                        pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return listener, thread


def test_a_device_server_that_hangs_up_gives_a_one_line_reason() -> None:
    listener, _ = _hang_up_server()
    url = f"socket://127.0.0.1:{listener.getsockname()[1]}"
    try:
        reason = fails("probe", *DF1, url)
        assert reason.startswith("slc-gateway probe: ")
    finally:
        listener.close()


def test_unreachable_port_exit_1() -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    reason = fails("probe", *DF1, f"socket://127.0.0.1:{port}")
    assert reason.startswith("slc-gateway probe: ") and f"127.0.0.1:{port}" in reason
