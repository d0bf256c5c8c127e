"""The ``plc5`` and ``df1line`` simulator factories (for the ``sim://`` registry), and the line over TCP."""

from __future__ import annotations

import pytest

from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_half_models import create_half_duplex_model, self_paced
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeRead
from gateway.sim.serve import close_tcp, serve_tcp


def test_plc5_model_with_faults_and_variant() -> None:
    sim = create_half_duplex_model("plc5", {"checksum": "bcc", "drop": "7"}, variants_text="typed_logical=accept")
    assert isinstance(sim, Plc5Simulator) and sim.accept_typed_logical and not self_paced(sim)


def test_line_model_splits_slave_and_controller_variants() -> None:
    line = create_half_duplex_model(
        "df1line", {"stations": "1,2", "model": "plc5", "dead": "2"},
        variants_text="reply_retries=3,typed_logical=accept",
    )
    assert isinstance(line, MultidropLine) and self_paced(line)
    assert line.variant.reply_retries == 3 and list(line.slaves) == [1]
    controller = line.controllers[1]
    assert isinstance(controller, Plc5Simulator) and controller.accept_typed_logical


@pytest.mark.parametrize(
    ("model", "options", "variants", "message"),
    [
        ("df1line", {"stations": "1"}, "typed_logical=accept", "of PLC-5 stations"),  # an SLC line
        ("df1line", {"stations": "1"}, "ack_order=embedded", "unknown variant"),  # a full-duplex link's
        ("df1line", {"stations": "1"}, "reply_retries=9", "not one of"),
        ("df1line", {"bogus": "1"}, "", "unknown multi-drop line option"),
        ("plc5", {}, "typed_logical=maybe", "not one of"),
        ("slc9", {}, "", "unknown half-duplex simulator model"),
    ],
)
def test_bad_options_and_variants_are_named(model: str, options: dict[str, str], variants: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        create_half_duplex_model(model, options, variants_text=variants)


async def test_line_model_over_tcp() -> None:
    line = create_half_duplex_model("df1line", {"stations": "4,5", "model": "plc5", "checksum": "bcc"})
    assert isinstance(line, MultidropLine)
    line.controllers[5].set_word("N7", 0, 4242)
    server = await serve_tcp(line, "127.0.0.1", 0)
    url = f"socket://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    driver = Df1HalfDuplexLine(url, [StationConfig(4, poll_timeout=0.1), StationConfig(5, poll_timeout=0.1)],
                               checksum=Checksum.BCC, ack_timeout=0.1)
    station = driver.station(5)
    await station.start()
    try:
        reply = await station.execute(WordRangeRead(LogicalBinaryAddress.of(0, 7, 0), 2), "read N7:0")
    finally:
        await station.close()
        await close_tcp(server)
    assert reply.data == (4242).to_bytes(2, "little")
