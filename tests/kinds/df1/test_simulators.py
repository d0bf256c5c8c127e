"""``sim://plc5`` and ``sim://df1line`` in the simulator catalogue, in a config and behind ``simulate``.

* ``sim://df1line?...`` opens a multi-drop line (``gateway.kinds.df1.sim.df1_half_models``): the same URL reaches
  the same line, so several ``[[link]]`` stations with that port and ``duplex = "half"`` share it;
* the line paces itself: ``turnaround`` is its option, ``paced=1`` and a line model are clear errors;
* an unknown option or variant is a clear error naming the choices;
* ``slc-gateway simulate df1line`` / ``simulate plc5`` serve them over TCP (run as a subprocess).
"""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator

import pytest
from cli_support import start_simulator, stop

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.errors import GatewayError, LinkDown, LinkTimeout
from gateway.kinds import link_kind
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.simulators import DF1LINE, PLC5
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead
from gateway.sim import get_simulator, open_sim_stream, parse_sim_url, variants_of
from gateway.sim.models import sim_models
from gateway.sim.serve import serve_tcp
from gateway.streams import SerialSettings

LINE_URL = "sim://df1line?stations=1,2,3,4&dead=4&corrupt=6&ignore=10&checksum=bcc&ladder=0"


pytestmark = pytest.mark.usefixtures("forget_simulators")


def test_the_df1_kind_lists_both_models() -> None:
    kind = link_kind("df1")
    assert {PLC5, DF1LINE} <= set(kind.simulators)
    assert {"plc5", "df1line"} <= set(kind.config_model.sim_models) and DF1LINE.self_paced
    assert sim_models()["df1line"] is DF1LINE


def test_line_url_opens_one_line_with_its_options() -> None:
    line = get_simulator(LINE_URL)
    assert isinstance(line, MultidropLine) and get_simulator(LINE_URL) is line
    options = line.options
    assert options.stations == (1, 2, 3, 4) and options.dead == {4} and sorted(line.slaves) == [1, 2, 3]
    assert (options.corrupt, options.ignore, options.checksum) == (6, 10, Checksum.BCC)
    turned = get_simulator("sim://df1line?turnaround=0.01&model=plc5&variant=typed_logical=accept")
    assert isinstance(turned, MultidropLine) and turned.options.turnaround == 0.01  # the line's own option
    controller = turned.controllers[1]
    assert isinstance(controller, Plc5Simulator) and controller.accept_typed_logical


def test_plc5_url_opens_a_plc5() -> None:
    sim = get_simulator("sim://plc5?checksum=bcc&variant=typed_logical=accept")
    assert isinstance(sim, Plc5Simulator) and sim.accept_typed_logical
    assert variants_of("plc5", {})["typed_logical"] == "refuse"


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("sim://df1line?bogus=1", "unknown multi-drop line option"),
        ("sim://df1line?garble=3", "unknown multi-drop line option"),  # the full-duplex fault is not the line's
        ("sim://df1line?dead=9", "not on the line"),
        ("sim://df1line?variant=reply_retries=9", "not one of"),
        ("sim://df1line?variant=ack_order=embedded", "unknown variant"),
        ("sim://df1line?variant=typed_logical=accept", "of PLC-5 stations"),
        ("sim://df1line?paced=1", "paces itself"),
        ("sim://plc5?variant=typed_logical=maybe", "not one of"),
        ("sim://plc5?stations=1", "unknown"),
    ],
)
def test_bad_option_or_variant_is_a_clear_error(url: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        get_simulator(url)


async def test_bad_line_url_is_link_down_naming_it() -> None:
    with pytest.raises(LinkDown, match="unknown multi-drop line option"):
        open_sim_stream("sim://df1line?bogus=1", SerialSettings())


async def test_a_line_refuses_a_line_model() -> None:
    line = get_simulator("sim://df1line")
    with pytest.raises(GatewayError, match="paces its own bytes"):
        await serve_tcp(line, "127.0.0.1", 0, settings=SerialSettings())


def test_parse_sim_url_validates_line_variants_early() -> None:
    assert parse_sim_url("sim://df1line?variant=when_busy=silent")[0] == "df1line"
    with pytest.raises(ValueError, match="unknown variant"):
        parse_sim_url("sim://df1line?variant=nope=1")


def _config(url: str) -> str:
    text = '[modbus]\nlisten = "127.0.0.1:0"\n'
    for station in (1, 2, 3, 4):
        text += (
            f'\n[[link]]\nname = "s{station}"\nprotocol = "df1"\nport = "{url}"\nduplex = "half"\n'
            f'checksum = "bcc"\nstation = {station}\nunit = {station}\npoll_timeout = 0.05\nack_timeout = 0.05\n'
            f'timeout = 0.5\npoll_interval = 0.05\nslow_poll_interval = 2.0\ndemote_after = 5\n'
            '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 2\n'
        )
    return text


async def test_stations_with_one_sim_url_share_one_line() -> None:
    config = parse_config(_config(LINE_URL))
    line = get_simulator(LINE_URL)
    assert isinstance(line, MultidropLine)
    for number, controller in line.controllers.items():
        controller.set_word("N7", 0, 1000 + number)
    async with Gateway(config) as gw:
        masters = [runner for runner in gw.runners if isinstance(runner, Df1HalfDuplexLine)]
        assert len(masters) == 1
        units = {unit.unit_id: unit for unit in gw.units}
        for number in (1, 2, 3):
            unit = units[number]
            block = unit.plan.blocks[0]
            data = await unit.read_block(block)
            assert int.from_bytes(bytes(data)[:2], "little") == 1000 + number
    assert line.counters.master_bytes > 0


def _served(model: str, *args: str) -> Iterator[str]:
    process, first = start_simulator(model, "--listen", "127.0.0.1:0", *args)
    try:
        match = re.fullmatch(rf"simulated {model} listening on (127\.0\.0\.1):(\d+) \((socket://\S+)\)", first)
        assert match, first
        yield match.group(3)
    finally:
        stop(process)


async def test_simulate_df1line_serves_the_line_over_tcp() -> None:
    for url in _served("df1line", "--checksum", "bcc", "--no-ladder"):
        master = Df1HalfDuplexLine(url, [StationConfig(2, poll_timeout=0.2)], checksum=Checksum.BCC,
                                   ack_timeout=0.2)
        station = master.station(2)
        await station.start()
        try:
            reply = await station.execute(ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2), "read N7:0")
        finally:
            await station.close()
        assert reply.src == 2 and len(reply.data) == 2  # station 2 (of the default 1, 2, 3) answered


def test_simulate_plc5_serves_a_plc5() -> None:
    for url in _served("plc5", "--checksum", "bcc", "--variant", "typed_logical=accept"):
        assert url.startswith("socket://127.0.0.1:")


async def test_simulate_df1line_takes_the_url_options() -> None:
    """``--option stations=5,6 --option dead=6``: station 5 answers, the dead 6 and the absent 2 do not."""
    for url in _served("df1line", "--checksum", "bcc", "--option", "stations=5,6", "--option", "dead=6"):
        configs = [StationConfig(n, poll_timeout=0.1, reply_timeout=0.5, demote_after=2) for n in (2, 5, 6)]
        master = Df1HalfDuplexLine(url, configs, checksum=Checksum.BCC, ack_timeout=0.1)
        stations = {n: master.station(n) for n in (2, 5, 6)}
        await stations[5].start()
        try:
            reply = await stations[5].execute(ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2), "read N7:0")
            assert reply.src == 5
            for number in (2, 6):
                with pytest.raises(LinkTimeout):
                    await stations[number].execute(ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2), "read")
        finally:
            await stations[5].close()


def test_simulate_option_needs_key_and_value() -> None:
    process = subprocess.run([sys.executable, "-m", "gateway", "simulate", "df1line", "--option", "dead"],
                             capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert process.returncode != 0 and "give KEY=VALUE" in process.stderr
