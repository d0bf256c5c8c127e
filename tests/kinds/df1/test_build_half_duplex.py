"""Half-duplex lines built from ``[[link]]`` configs, end to end over TCP against the multi-drop simulator.

Two lines, as the DF1 link kind builds them (``gateway.kinds.df1.build.build_df1``): SLC 5/04 stations 1-3 (BCC)
behind one device server port, PLC-5 stations 5 and 6 (CRC) behind another; station 3 absent.  Every
unit reads its own station's values (never another's), the absent one fails with 0x0B promptly,
a write lands once on the right station, and an MSG of station 2 lands in its register table.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from gateway.errors import LinkTimeout
from gateway.kinds.df1.build import build_df1
from gateway.kinds.df1.config import Df1LinkConfig, line_problems
from gateway.kinds.df1.half.driver import Df1Station
from gateway.kinds.df1.plc5_unit import Plc5Unit
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.kinds.df1.unit import Df1Unit
from gateway.modbus.mapping import Table
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeWrite, encode_command
from gateway.sim.serve import close_tcp, serve_tcp
from gateway.unit import Unit

HOST = "127.0.0.1"


def link(name: str, unit: int, port: str, station: int, **keys: Any) -> Df1LinkConfig:
    return Df1LinkConfig.model_validate({
        "name": name, "protocol": "df1", "port": port, "unit": unit, "duplex": "half", "station": station,
        "timeout": 1.0, "poll_timeout": 0.05, "ack_timeout": 0.05, "poll_interval": 0.05, "slow_poll_interval": 2.0,
        "map": [{"table": "holding", "start": 0, "address": "N7:0", "count": 4}], **keys,
    })


async def refresh(unit: Unit) -> None:
    for index, block in enumerate(unit.plan.blocks):
        unit.cache.store(index, await unit.read_block(block), unit._loop_time())


async def test_two_lines_from_config_over_tcp() -> None:
    slc = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2, 3), dead=frozenset({3})))
    plc5 = MultidropLine(LineOptions(checksum=Checksum.CRC, stations=(5, 6), model="plc5"))
    for sim in (slc, plc5):
        for number, controller in sim.controllers.items():
            for k in range(4):
                controller.set_word("N7", k, 100 * number + k)
    servers = [await serve_tcp(slc, HOST, 0), await serve_tcp(plc5, HOST, 0)]
    ports = [f"socket://{HOST}:{server.sockets[0].getsockname()[1]}" for server in servers]
    links = [
        link("s1", 1, ports[0], 1, checksum="bcc"),
        link("s2", 2, ports[0], 2, checksum="bcc", receive_words=4),
        link("s3", 3, ports[0], 3, checksum="bcc", demote_after=2),
        link("p5", 5, ports[1], 5, processor="plc5"),
        link("p6", 6, ports[1], 6, processor="plc5"),
    ]
    assert line_problems(links) == []
    built = build_df1(links)
    units = {link.name: unit for link, unit in zip(links, built.units, strict=True)}
    assert len(built.runners) == 2  # one line master per port
    assert [type(units[n]) for n in ("s1", "p5")] == [Df1Unit, Plc5Unit]
    lines = {id(u.driver.line) for u in units.values() if isinstance(u.driver, Df1Station)}
    assert len(lines) == 2  # one master per port
    msg = encode_command(WordRangeWrite(LogicalBinaryAddress.of(0, 7, 1), b"\x2a\x00"), dst=0, src=2, tns=77)
    tasks = [asyncio.create_task(runner.run()) for runner in built.runners]
    try:
        await asyncio.sleep(0.3)  # after the line's link reset (DLE NAK empties slave queues)
        slc.slaves[2].initiate(msg)
        for name in ("s1", "s2", "p5", "p6"):
            await refresh(units[name])
        for name, number in (("s1", 1), ("s2", 2), ("p5", 5), ("p6", 6)):
            assert units[name].read_registers(Table.HOLDING, 0, 4) == [100 * number + k for k in range(4)]
        started = time.monotonic()
        for _ in range(3):
            with pytest.raises(LinkTimeout, match="station 3"):
                await refresh(units["s3"])
        assert time.monotonic() - started < 2.0
        for name in ("s2", "p6"):
            unit = units[name]
            async with unit.driver.write_session() as line:
                for step in unit._register_steps(unit.check_register_write(3, [999])):
                    await step.run(line)
        for _ in range(100):
            driver = units["s2"].driver
            assert isinstance(driver, Df1Station)
            if driver.line.register_tables[2].writes:
                break
            await asyncio.sleep(0.02)
    finally:
        for task in tasks:
            task.cancel()
        for runner in built.runners:
            await runner.close()
        for server in servers:
            await close_tcp(server)
    assert slc.controllers[2].word("N7", 3) == 999 and slc.controllers[1].word("N7", 3) == 103
    assert plc5.controllers[6].word("N7", 3) == 999 and plc5.controllers[5].word("N7", 3) == 503
    assert [len(slc.controllers[n].applied_writes) for n in (1, 2, 3)] == [0, 1, 0]
    assert [len(plc5.controllers[n].applied_writes) for n in (5, 6)] == [0, 1]
    driver = units["s2"].driver
    assert isinstance(driver, Df1Station)
    assert driver.line.register_tables[2].values() == [0, 42, 0, 0]


def test_the_stations_of_one_line_share_their_pollers_line_and_other_links_do_not() -> None:
    """One station's background must wait for another's demanded blocks (``gateway.poller.LineShare``):
    the pollers of one half-duplex line share one, a full-duplex link has its own line."""
    links = [
        link("a1", 1, "socket://127.0.0.1:1", 1),
        link("a2", 2, "socket://127.0.0.1:1", 2),
        link("b1", 3, "socket://127.0.0.1:2", 1),
        Df1LinkConfig.model_validate({"name": "f", "protocol": "df1", "port": "socket://127.0.0.1:3", "unit": 4,
                                      "map": [{"table": "holding", "start": 0, "address": "N7:0", "count": 4}]}),
    ]
    units = build_df1(links).units
    shares = [unit.poller._share if unit.poller is not None else None for unit in units]
    assert shares[0] is not None and shares[0] is shares[1]
    assert shares[2] is not None and shares[2] is not shares[0]
    assert shares[3] is None
