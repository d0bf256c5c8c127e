"""Reloading the config of a running gateway, while a SCADA client keeps its connection and reads.

In-process: the whole ``Gateway`` on 127.0.0.1 with simulated SLC 5/04s (``sim://slc504``, DF1) and
an SLC 150 (``sim://slc150``), a pymodbus client that keeps one connection open and reads an
unchanged unit every 10 ms through every reload, and ``Gateway.reload()`` re-reading the file as
SIGHUP makes it.  The real process and the signal are in ``tests/test_cli_reload.py``.

What must hold (``gateway.reload``): a line whose links did not change keeps its unit, image, write
queue and port (the same objects, no reconnect, no failed read); a changed or new link starts; a
removed one stops after its queued writes are answered; a file that does not load changes
nothing; the Modbus connection stays open throughout.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import pytest
from modbus_support import connect, exception_code
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.reload import ConfigSource
from gateway.sim import get_simulator
from tests.waiting import until

PATH_UNAVAILABLE = 0x0A  # Modbus: no such unit behind the gateway
A, B, C = 1, 2, 3  # unit ids


def sim_url(model: str = "slc504", **options: Any) -> str:
    return f"sim://{model}?" + urlencode({"ladder": "0", **options, "instance": uuid.uuid4().hex})


def df1_link(name: str, url: str, unit: int, *maps: tuple[int, str, int], **keys: Any) -> str:
    text = f'[[link]]\nname = "{name}"\nprotocol = "df1"\nport = "{url}"\nunit = {unit}\n'
    text += "".join(f"{key} = {value!r}\n".replace("'", '"') for key, value in keys.items())
    for start, address, count in maps:
        text += f'[[link.map]]\ntable = "holding"\nstart = {start}\naddress = "{address}"\ncount = {count}\n'
    return text + "\n"


HEAD = '[modbus]\nlisten = "127.0.0.1:0"\n\n'


@dataclass
class Reader:
    """One client, one connection, reading ``count`` holding registers of ``unit`` every 10 ms."""

    client: AsyncModbusTcpClient
    unit: int
    count: int = 4
    ok: int = 0
    failures: list[object] = field(default_factory=list)

    async def run(self) -> None:
        while True:
            try:
                reply = await self.client.read_holding_registers(0, count=self.count, device_id=self.unit)
            except Exception as exc:  # the connection broke: recorded, the test fails on it
                self.failures.append(exc)
                return
            if reply.isError():
                self.failures.append(f"exception 0x{reply.exception_code:02X}")
            else:
                self.ok += 1
            await asyncio.sleep(0.01)

    async def reads_more(self, reads: int = 5) -> None:
        """Until it has read ``reads`` more times."""
        target = self.ok + reads
        await until(lambda: self.ok >= target or self.failures, 10)


@dataclass
class Plant:
    gw: Gateway
    file: Path
    reader: Reader

    async def reload_with(self, text: str) -> bool:
        self.file.write_text(text)
        return await self.gw.reload()

    def unit(self, name: str) -> Any:
        return next(unit for unit in self.gw.units if unit.name == name)


pytestmark = pytest.mark.usefixtures("forget_simulators")


URL_A, URL_B = sim_url(seed=1), sim_url(seed=2, delay=0.2)  # B: every reply 0.2 s late
FIRST = HEAD + df1_link("a", URL_A, A, (0, "N7:0", 4)) + df1_link("b", URL_B, B, (0, "N7:0", 4), write_timeout=5.0)


@pytest.fixture
async def plant(tmp_path: Path) -> AsyncIterator[Plant]:
    """Links a and b; a client reading unit ``a`` through every reload (a does not change in the
    tests that use this reader)."""
    file = tmp_path / "gateway.toml"
    file.write_text(FIRST)
    source = ConfigSource(file)
    loaded = source.load()
    async with Gateway(loaded.config, source, loaded.sha256) as gw, connect(gw.port) as client:
        await ready(client, A)
        await ready(client, B)
        reader = Reader(client, A)
        task = asyncio.create_task(reader.run())
        try:
            await reader.reads_more()
            yield Plant(gw, file, reader)
            await reader.reads_more()
            assert reader.failures == []  # not one read of the unchanged link failed
            assert client.connected
            assert gw.servers[0].counters.connections_dropped == 0  # the reader's connection, kept
        finally:
            task.cancel()


async def ready(client: AsyncModbusTcpClient, unit: int, address: int = 0, count: int = 4) -> list[int]:
    """The registers once the unit serves them (after its first poll)."""
    async with asyncio.timeout(10):
        while True:
            reply = await client.read_holding_registers(address, count=count, device_id=unit)
            if not reply.isError():
                return list(reply.registers)
            await asyncio.sleep(0.02)


async def test_a_map_added_starts_its_link_again_and_leaves_the_others_running(plant: Plant) -> None:
    gw = plant.gw
    a, b = plant.unit("a"), plant.unit("b")
    more = FIRST.replace(df1_link("b", URL_B, B, (0, "N7:0", 4), write_timeout=5.0),
                         df1_link("b", URL_B, B, (0, "N7:0", 4), (10, "N7:10", 2), write_timeout=5.0))
    assert more != FIRST
    assert await plant.reload_with(more)
    assert plant.unit("a") is a  # untouched: the same unit, image and driver
    assert a.driver.counters.reconnects == 0 and a.driver.connected
    new_b = plant.unit("b")
    assert new_b is not b and not b.driver.connected  # the old one stopped, its port closed
    assert gw.backend.units[B] is new_b
    sim = get_simulator(URL_B)
    async with connect(gw.port) as client:
        assert await ready(client, B, 10, 2) == [sim.word("N7", 10), sim.word("N7", 11)]
    status = gw.config_status
    assert (status.reloads, status.reload_failures, status.restart_needed) == (1, 0, ())
    assert status.sha256 == hashlib.sha256(more.encode()).hexdigest()


async def test_a_changed_link_starts_again_and_an_unchanged_ones_queued_writes_go_on(plant: Plant) -> None:
    """b's writes in its queue (each reply 0.2 s late) are not disturbed by a reload that changes c."""
    gw = plant.gw
    url_c = sim_url(seed=3)
    with_c = FIRST + df1_link("c", url_c, C, (0, "N7:0", 4))
    assert await plant.reload_with(with_c)
    b, c = plant.unit("b"), plant.unit("c")
    async with connect(gw.port) as first, connect(gw.port) as second:
        await ready(first, C)
        writes = [asyncio.create_task(client.write_register(2, value, device_id=B))
                  for client, value in ((first, 1111), (second, 2222))]
        await until(lambda: b.writes.waiting > 0)  # the second write waits behind the first, on the line
        changed = with_c.replace(df1_link("c", url_c, C, (0, "N7:0", 4)),
                                 df1_link("c", url_c, C, (0, "N7:0", 4), stale_after=9.0))
        assert await plant.reload_with(changed)
        assert plant.unit("b") is b and plant.unit("c") is not c
        assert plant.unit("c").stale_after == 9.0
        replies = await asyncio.gather(*writes)
        assert [exception_code(reply) for reply in replies] == [None, None]
        assert get_simulator(URL_B).word("N7", 2) == 2222  # both applied, in order
        assert await ready(first, C) is not None
    assert b.driver.counters.reconnects == 0


async def test_a_removed_link_answers_its_queued_writes_then_stops(plant: Plant) -> None:
    gw = plant.gw
    b = plant.unit("b")
    async with connect(gw.port) as first, connect(gw.port) as second:
        writes = [asyncio.create_task(client.write_register(3, value, device_id=B))
                  for client, value in ((first, 3333), (second, 4444))]
        await until(lambda: b.writes.waiting > 0)  # the second write waits behind the first, on the line
        assert await plant.reload_with(HEAD + df1_link("a", URL_A, A, (0, "N7:0", 4)))
        async with asyncio.timeout(1):  # answered before b stopped, and applied
            replies = await asyncio.gather(*writes)
        assert [exception_code(reply) for reply in replies] == [None, None]
        assert get_simulator(URL_B).word("N7", 3) == 4444
        assert not b.driver.connected
        reply = await first.read_holding_registers(0, count=4, device_id=B)
        assert exception_code(reply) == PATH_UNAVAILABLE
    assert [unit.name for unit in gw.units] == ["a"]


async def test_a_file_that_does_not_load_changes_nothing(plant: Plant, caplog: pytest.LogCaptureFixture) -> None:
    gw = plant.gw
    units, runners, config = list(gw.units), list(gw.runners), gw.config
    broken = FIRST.replace('unit = 2\n', 'unit = 2\nstale_aftr = 3.0\n')
    line = broken.splitlines().index("stale_aftr = 3.0") + 1
    with caplog.at_level(logging.ERROR, logger="gateway"):
        assert not await plant.reload_with(broken)
    message = (f'{plant.file}:{line}: link "b" (link[1]).stale_aftr: unknown key (did you mean "stale_after"?)')
    assert gw.config_status.last_failure == message
    assert f"reload: {message}" in caplog.messages
    assert gw.units == units and gw.runners == runners and gw.config is config
    assert (gw.config_status.reloads, gw.config_status.reload_failures) == (0, 1)
    assert gw.config_status.sha256 == hashlib.sha256(FIRST.encode()).hexdigest()
    assert all(unit.driver.connected for unit in gw.units)
    # not even a part of a file that fails is applied
    bad_unit = FIRST.replace('name = "b"', 'name = "b2"').replace("unit = 1\n", "unit = 2\n")
    assert not await plant.reload_with(bad_unit)
    assert gw.units == units and gw.config_status.reload_failures == 2
    async with connect(gw.port) as client:
        assert await ready(client, B) == [get_simulator(URL_B).word("N7", k) for k in range(4)]


async def test_a_new_listen_address_waits_for_a_restart(plant: Plant, caplog: pytest.LogCaptureFixture) -> None:
    gw = plant.gw
    moved = FIRST.replace('listen = "127.0.0.1:0"', 'listen = "127.0.0.1:0"\nallow = ["127.0.0.0/8"]')
    moved = moved.replace('[modbus]\nlisten = "127.0.0.1:0"', '[modbus]\nlisten = "127.0.0.2:0"')
    with caplog.at_level(logging.WARNING, logger="gateway"):
        assert await plant.reload_with(moved)
    needed = '[modbus] listen ("127.0.0.1:0" -> "127.0.0.2:0")'
    assert gw.config_status.restart_needed == (needed,)
    assert f"reload: {needed}: a restart is needed to apply it" in caplog.messages
    assert [str(net) for net in gw.servers[0].allow or ()] == ["127.0.0.0/8"]  # applied at once
    assert gw.servers[0].host == "127.0.0.1"  # still serving where it was


def half_duplex_station(url: str, number: int, extra: str = "") -> str:
    return (f'[[link]]\nname = "s{number}"\nprotocol = "df1"\nport = "{url}"\nduplex = "half"\nchecksum = "bcc"\n'
            f"station = {number}\nunit = {10 + number}\npoll_timeout = 0.05\nack_timeout = 0.05\ntimeout = 0.5\n"
            f"poll_interval = 0.05\n{extra}"
            '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n\n')


async def test_a_change_to_one_station_restarts_its_half_duplex_line_whole(plant: Plant) -> None:
    """One master per line: a station changed means a new line with both stations, the old master
    closed; the links on other ports go on."""
    gw = plant.gw
    url = "sim://df1line?" + urlencode({"stations": "1,2", "checksum": "bcc", "ladder": "0",
                                        "instance": uuid.uuid4().hex})
    line = FIRST + half_duplex_station(url, 1) + half_duplex_station(url, 2)
    assert await plant.reload_with(line)
    a, b, s1, s2 = (plant.unit(name) for name in ("a", "b", "s1", "s2"))
    master = s1.driver.line
    assert s2.driver.line is master and master in gw.runners
    async with connect(gw.port) as client:
        await ready(client, 11)
        await ready(client, 12)
        assert await plant.reload_with(line.replace("station = 2\n", "station = 2\nstale_after = 9.0\n"))
        new_s1, new_s2 = plant.unit("s1"), plant.unit("s2")
        assert new_s1 is not s1 and new_s2 is not s2 and new_s2.stale_after == 9.0
        assert new_s1.driver.line is new_s2.driver.line is not master
        assert master not in gw.runners and not master.connected  # the old master stopped, its port closed
        assert sum(runner is new_s1.driver.line for runner in gw.runners) == 1
        await ready(client, 11)
        await ready(client, 12)
    assert plant.unit("a") is a and plant.unit("b") is b


async def test_signals_during_a_reload_make_one_more_reload_after_it(plant: Plant) -> None:
    """SIGHUP calls ``request_reload``.  Signals before a reload reads the file are that reload;
    signals while it runs make one more after it (which reads the file as it is by then), never two
    reloads at once."""
    gw = plant.gw
    b = plant.unit("b")
    for _ in range(3):
        gw.request_reload()
    await until(lambda: gw.config_status.reloads == 1)
    async with connect(gw.port) as client:
        write = asyncio.create_task(client.write_register(1, 5555, device_id=B))  # 0.2 s on b's line
        await until(lambda: b.write_requests == 1)
        plant.file.write_text(FIRST.replace("write_timeout = 5.0", "write_timeout = 4.0"))
        gw.request_reload()
        await until(lambda: plant.unit("b") is not b)  # b's old line is stopping: its write runs first
        assert not write.done()
        gw.request_reload()
        gw.request_reload()
        assert exception_code(await write) is None
    await until(lambda: gw.config_status.reloads == 3, 10)
    await asyncio.sleep(0.3)
    assert gw.config_status.reloads == 3 and gw.config_status.reload_failures == 0
