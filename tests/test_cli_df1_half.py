"""The DF1 command-line tools on a half-duplex multi-drop line (``--duplex half --station N``) and on
a PLC-5 (``--processor plc5``: word range commands, PLC-5 addresses) - issue #12.

The line is the in-process multi-drop simulator (:class:`gateway.kinds.df1.sim.df1_multidrop.MultidropLine`)
served over TCP (``serve_tcp``, as a serial device server would be) from an event loop in a thread
of its own; the CLI (``gateway.cli.main``) runs in the test's thread with its own loop, as a
subprocess would, and talks to it through a ``socket://`` URL.  Stations hold ``N7:k = 100 n + k``
(n: the station number), so a value read from the wrong station shows.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from gateway.cli import main
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.slc500_options import Slc500Options
from gateway.protocols.df1.framing import Checksum
from gateway.sim.serve import close_tcp, serve_tcp

HOST = "127.0.0.1"
FAST = ("--poll-timeout", "0.1", "--ack-timeout", "0.1", "--timeout", "1")


class ServedLine:
    """A simulator served on a free TCP port by an event loop in a thread."""

    def __init__(self, sim: Any) -> None:
        self.sim = sim
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server = asyncio.run_coroutine_threadsafe(serve_tcp(sim, HOST, 0), self.loop).result(10)
        self.url = f"socket://{HOST}:{self.server.sockets[0].getsockname()[1]}"

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(close_tcp(self.server), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


def served(options: LineOptions, **keys: Any) -> Iterator[ServedLine]:
    sim = MultidropLine(options, **keys)
    for number, controller in sim.controllers.items():
        for k in range(8):
            controller.set_word("N7", k, 100 * number + k)
    line = ServedLine(sim)
    try:
        yield line
    finally:
        line.close()


@pytest.fixture
def slc_line() -> Iterator[ServedLine]:
    """SLC 5/04 stations 1, 2, 3 (BCC); station 4 configured on the line but absent."""
    yield from served(LineOptions(checksum=Checksum.BCC, stations=(1, 2, 3, 4), dead=frozenset({4})))


@pytest.fixture(params=["refuse", "accept"])
def plc5_line(request: pytest.FixtureRequest) -> Iterator[ServedLine]:
    """PLC-5 stations 5, 6 (CRC), in both readings of the SLC typed logical commands."""
    yield from served(LineOptions(checksum=Checksum.CRC, stations=(5, 6), model="plc5"),
                      controller_variants={"typed_logical": request.param})


def run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    status = main(list(args))
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def ok_json(capsys: pytest.CaptureFixture[str], *args: str) -> Any:
    status, out, err = run(capsys, *args, "--json")
    assert status == 0, err
    return json.loads(out)


def half(url: str, station: int, *more: str) -> tuple[str, ...]:
    return (url, "--protocol", "df1", "--duplex", "half", "--station", str(station), *FAST, *more)


# ---------------------------------------------------------------------------------------------


def test_probe_and_read_each_station_of_the_line(slc_line: ServedLine, capsys: pytest.CaptureFixture[str]) -> None:
    assert ok_json(capsys, "probe", *half(slc_line.url, 2, "--checksum", "bcc"))["processor"] == "SLC 5/04"
    for number in (1, 3):
        found = ok_json(capsys, "read", *half(slc_line.url, number, "--checksum", "bcc"), "N7:0", "N7:7", "F8:2",
                        "T4:1.PRE", "B3:0/3")
        assert found == {"N7:0": 100 * number, "N7:7": 100 * number + 7, "F8:2": 3.0, "T4:1.PRE": 20,
                         "B3:0/3": False}


def test_write_lands_once_on_the_right_station(slc_line: ServedLine, capsys: pytest.CaptureFixture[str]) -> None:
    status, out, err = run(capsys, "write", *half(slc_line.url, 2, "--checksum", "bcc"), "N7:3=-7", "B3:0/3=1")
    assert (status, err) == (0, "")
    assert out.splitlines() == ["N7:3 = -7", "B3:0/3 = 1"]
    controllers = slc_line.sim.controllers
    assert controllers[2].word("N7", 3) == 0xFFF9 or controllers[2].word("N7", 3) == -7
    assert [controllers[n].word("N7", 3) for n in (1, 3)] == [103, 303]
    assert [len(controllers[n].applied_writes) for n in (1, 2, 3)] == [0, 2, 0]
    assert ok_json(capsys, "read", *half(slc_line.url, 2, "--checksum", "bcc"), "N7:3", "B3:0") == {
        "N7:3": -7, "B3:0": 8}


def test_absent_station_fails_promptly_with_a_reason(slc_line: ServedLine, capsys: pytest.CaptureFixture[str]) -> None:
    started = time.monotonic()
    status, out, err = run(capsys, "read", *half(slc_line.url, 4, "--checksum", "bcc"), "N7:0")
    assert status == 1 and out == ""
    assert "station 4" in err and err.startswith("slc-gateway read: ")
    assert time.monotonic() - started < 10


def test_wrong_checksum_on_the_line_says_what_to_check(slc_line: ServedLine,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    status, _, err = run(capsys, "read", *half(slc_line.url, 1, "--checksum", "crc"), "N7:0")
    assert status == 1 and "station 1 does not answer" in err and "--checksum (bcc or crc)" in err


def test_plc5_read_and_write_with_word_range_commands(plc5_line: ServedLine,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    url = plc5_line.url
    plc5 = ("--processor", "plc5")
    found = ok_json(capsys, "read", *half(url, 6, *plc5), "N7:0", "N7:7", "F8:2", "T4:1.PRE", "T4:1", "B3/5", "N7:1/0")
    assert found == {"N7:0": 600, "N7:7": 607, "F8:2": 3.0, "T4:1.PRE": 20, "T4:1": [0, 20, 0], "B3/5": False,
                     "N7:1/0": True}
    controller = plc5_line.sim.controllers[6]
    before = controller.word("B3", 1)
    assert before & 0x30 == 0x20  # B3/20 clear, B3/21 set (B3:1 bits 4 and 5)
    status, _, err = run(capsys, "write", *half(url, 6, *plc5), "N7:3=999", "B3/20=1", "F8:2=2.5", "T4:1.PRE=77")
    assert (status, err) == (0, "")
    assert [kind for kind, _, _ in controller.applied_writes] == [
        "word_range_write", "read_modify_write", "word_range_write", "word_range_write"]
    assert controller.word("N7", 3) == 999 and controller.word("B3", 1) == before | 0x10
    assert plc5_line.sim.controllers[5].applied_writes == []
    assert ok_json(capsys, "read", *half(url, 6, *plc5), "F8:2", "T4:1.PRE", "B3/20", "B3/21", "B3:1") == {
        "F8:2": 2.5, "T4:1.PRE": 77, "B3/20": True, "B3/21": True, "B3:1": before | 0x10}
    assert ok_json(capsys, "write", *half(url, 6, *plc5), "B3/21=0") == {"B3/21": "0"}
    assert controller.word("B3", 1) == (before | 0x10) & ~0x20  # only the written bits changed


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("read", "N7:abc"), "not a PLC-5 address"),
        (("read", "I:018"), "octal"),
        (("write", "N7:0"), "expected ADDRESS=VALUE, e.g. N7:0=5 or B3/5=1"),
        (("write", "B3/5=2"), "a bit takes 0 or 1"),
        (("write", "T4:1=5"), "write a member"),
        (("write", "N7:0=70000"), "-32768..65535"),
        (("mode", "program"), "a PLC-5 has no SLC change-mode command"),
    ],
)
def test_plc5_bad_input_is_refused_before_the_line_opens(args: tuple[str, str], words: str,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    command, item = args
    status, out, err = run(capsys, command, "socket://127.0.0.1:1", "--protocol", "df1", "--processor", "plc5",
                           "--duplex", "half", item)
    assert status == 1 and out == ""
    assert words in err and err.startswith(f"slc-gateway {command}: ")


def test_station_equal_to_source_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    status, _, err = run(capsys, "probe", "socket://127.0.0.1:1", "--protocol", "df1", "--duplex", "half",
                         "--station", "0")
    assert status == 1 and "our own address" in err


@pytest.mark.parametrize("typed_logical", ["refuse", "accept"])
def test_plc5_on_a_full_duplex_link_uses_word_range_commands(typed_logical: str,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    plc5 = Plc5Simulator(Slc500Options(station=1), ladder=False, variants={"typed_logical": typed_logical})
    line = ServedLine(plc5)
    try:
        args = (line.url, "--protocol", "df1", "--processor", "plc5")
        found = ok_json(capsys, "read", *args, "N7:255", "N7:7", "F8:2")
        assert found == {"N7:255": plc5.word("N7", 255), "N7:7": 7, "F8:2": 3.0}
        assert ok_json(capsys, "write", *args, "N7:7=-2", "B3/3=1") == {"N7:7": "-2", "B3/3": "1"}
        assert [kind for kind, _, _ in plc5.applied_writes] == ["word_range_write", "read_modify_write"]
        assert ok_json(capsys, "read", *args, "N7:7", "B3/3") == {"N7:7": -2, "B3/3": True}
    finally:
        line.close()
