"""The DF1 command-line tools (``--protocol df1``) against ``slc-gateway simulate slc504`` run as a
real subprocess on 127.0.0.1.

Expected values come from the simulator's documented initial data table (N7:k = k, F8:k = 1.5 k,
T4:1.PRE = 20, B3:0 = 0) with its ladder frozen (``--no-ladder``).
"""

from __future__ import annotations

import re
import socket
import threading
from collections.abc import Iterator

import pytest
from cli_support import fails, ok, ok_json, start_simulator, stop

DF1 = ("--protocol", "df1")


def simulate_slc504(*args: str) -> Iterator[str]:
    """Run ``slc-gateway simulate slc504 --listen 127.0.0.1:0 ARGS``; yield its socket:// URL."""
    process, line = start_simulator("slc504", "--listen", "127.0.0.1:0", *args)
    try:
        match = re.fullmatch(r"simulated slc504 listening on (127\.0\.0\.1):(\d+) \((socket://\S+)\)", line)
        assert match, line
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
