"""What a newcomer trips over on the command line: the protocol of a ``sim://`` URL, a hint when
the answer looks like the other protocol, a probe that gives up within a few tries, and the
``sim://`` program transfer that cannot work in one command."""

from __future__ import annotations

import re
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cli_support import cli, fails, ok_json

from gateway.errors import InvalidRequest, format_seconds
from gateway.tools import resolve_protocol, resolve_retries, wrong_protocol_hint

# ---------------------------------------------------------------------------------------------
# A sim:// URL names its controller, and so its protocol


def test_a_sim_url_sets_the_protocol() -> None:
    assert ok_json("probe", "sim://slc504")["processor"] == "SLC 5/04"  # no --protocol df1
    assert ok_json("probe", "sim://slc150")["controller"] == "SLC150"
    assert ok_json("read", "sim://slc504?ladder=0", "N7:3") == {"N7:3": 3}
    assert ok_json("probe", "sim://slc504", "--protocol", "df1")["processor"] == "SLC 5/04"


def test_a_protocol_that_contradicts_the_sim_url_is_refused_before_anything_runs() -> None:
    reason = fails("probe", "sim://slc150", "--protocol", "df1")
    assert reason == (
        "slc-gateway probe: sim://slc150 simulates an slc150, which speaks slc-ascii, not df1: "
        "leave out --protocol (a sim:// URL names its controller) or give --protocol slc-ascii"
    )
    assert "--protocol df1" in fails("probe", "sim://slc504", "--protocol", "slc-ascii")
    assert "unknown simulator" in fails("probe", "sim://plc9")


def test_resolve_protocol() -> None:
    assert resolve_protocol("/dev/ttyUSB0", None) == "slc-ascii"
    assert resolve_protocol("socket://10.0.0.5:4001", "df1") == "df1"
    assert resolve_protocol("sim://slc100?drop=3", None) == "slc-ascii"
    assert resolve_protocol("SIM://SLC504", None) == "df1"
    with pytest.raises(InvalidRequest):
        resolve_protocol("sim://slc504", "slc-ascii")


def test_a_probe_tries_twice_unless_told_otherwise() -> None:
    assert resolve_retries("probe", None) == 1
    assert resolve_retries("read", None) == 3
    assert resolve_retries("probe", 5) == 5


# ---------------------------------------------------------------------------------------------
# The other protocol's bytes, recognised


def test_hint_for_df1_bytes_on_an_ascii_link() -> None:
    assert "--protocol df1" in wrong_protocol_hint("slc-ascii", b"\x10\x15")  # DLE NAK
    assert "look like DF1" in wrong_protocol_hint("slc-ascii", b"xx\x10\x02\x00\x01\x10\x03\x12\x34")
    assert "nothing came back" in wrong_protocol_hint("slc-ascii", b"")
    assert wrong_protocol_hint("slc-ascii", b":1F\r:1G") == ""  # garbled ASCII: its own protocol


def test_hint_for_ascii_lines_on_a_df1_link() -> None:
    assert "--protocol slc-ascii" in wrong_protocol_hint("df1", b";?\r")
    assert "look like the SLC 100/150 ASCII" in wrong_protocol_hint("df1", b":021FFE1547\r")
    # a 7E1 controller read at 8N1: the parity bit arrives as bit 7 (':' 0x3A has 4 ones -> 0x3A,
    # '1' 0x31 has 3 ones -> 0xB1, CR 0x0D has 3 ones -> 0x8D)
    assert "--protocol slc-ascii" in wrong_protocol_hint("df1", b"\x3a\x30\xb1\x8d")
    assert "nothing came back" in wrong_protocol_hint("df1", b"")
    assert wrong_protocol_hint("df1", b"\x10\x06") == ""  # a DF1 ACK: the right protocol


class FakeController:
    """A TCP "serial device server" whose controller answers every chunk with ``reply``."""

    def __init__(self, reply: bytes) -> None:
        self.reply = reply
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.chunks = 0
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            with conn:
                while conn.recv(256):
                    self.chunks += 1
                    if self.reply:
                        conn.sendall(self.reply)

    def close(self) -> None:
        self.server.close()


MakeFake = Callable[[bytes], FakeController]


@pytest.fixture
def fake() -> Iterator[MakeFake]:
    made: list[FakeController] = []

    def make(reply: bytes) -> FakeController:
        made.append(FakeController(reply))
        return made[-1]

    yield make
    for server in made:
        server.close()


def test_an_ascii_probe_of_a_df1_controller_names_the_flag(fake: MakeFake, tmp_path: Path) -> None:
    controller = fake(b"\x10\x15")  # DLE NAK to everything, as a DF1 node answers a frame it cannot read
    trace = tmp_path / "probe.trace"
    reason = fails("probe", controller.url, "--trace", str(trace))
    assert "look like DF1" in reason and "--protocol df1" in reason
    assert "after 2 tries" in reason  # a probe gives up after one retry per resync ...
    sent = [line for line in trace.read_text().splitlines() if " TX " in line]
    assert len(sent) == 6  # ... and 3 resyncs of a controller that answers: within a few seconds


def test_a_df1_probe_of_an_ascii_controller_names_the_flag(fake: MakeFake, tmp_path: Path) -> None:
    controller = fake(b";?\r")  # what an SLC 100/150 could answer to bytes it cannot read
    trace = tmp_path / "probe.trace"
    reason = fails("probe", "--protocol", "df1", controller.url, "--trace", str(trace))
    assert "look like the SLC 100/150 ASCII protocol" in reason and "--protocol slc-ascii" in reason
    sent = [line.split(" TX ")[1] for line in trace.read_text().splitlines() if " TX " in line]
    frames = [s for s in sent if s.startswith("10 02")]
    enqs = [s for s in sent if s.startswith("10 05")]
    # one retry: 2 frames, each followed by one DLE ENQ (1 s ACK timeout each: about 4 s in all)
    assert (len(frames), len(enqs)) == (2, 2), sent


def test_a_silent_line_says_nothing_came_back_on_either_protocol(fake: MakeFake) -> None:
    silent = fake(b"")
    assert "nothing came back" in fails("probe", silent.url, "--timeout", "0.1")
    assert "nothing came back" in fails("probe", "--protocol", "df1", silent.url, "--timeout", "0.1")


# ---------------------------------------------------------------------------------------------
# Program transfer with sim://, and messages for people


def test_upload_from_a_sim_url_says_why_it_is_refused(tmp_path: Path) -> None:
    reason = fails("upload", "sim://slc150", str(tmp_path / "p.json"))
    assert "refused" in reason
    assert "fresh simulated controller, in run mode, for every command" in reason
    assert "slc-gateway simulate slc150 --listen 127.0.0.1:7001" in reason
    assert not (tmp_path / "p.json").exists()


def test_timeouts_are_rounded_for_people() -> None:
    assert [format_seconds(s) for s in (0.359375, 3.05729, 1.0, 0.3, 20, 0.001)] == [
        "0.36", "3.06", "1", "0.3", "20", "0.001"]
    result = cli("probe", "sim://slc150?drop=1&paced=1", "--retries", "0")
    assert result.returncode == 1
    # the reply time plus the characters' time on a paced 9600 baud line (0.3 s + n x 1.04 ms), to 10 ms
    assert re.search(r"within 0\.3\d s after 1 tries;", result.stderr), result.stderr
