"""Half-duplex line driver: PLC-5 stations served by ``Plc5Unit``, and the per-station metrics.

PLC-5 stations on the multi-drop simulator (``model="plc5"``), both ``typed_logical`` variants, a
noisy line (1 in 6 slave frames corrupted, 1 in 10 master frames unheard): reads are word range reads,
register writes word range writes, coil writes read-modify-writes, each applied exactly once on the
right station (``applied_writes`` of each simulated controller).
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from gateway.errors import LinkTimeout
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.plc5_unit import Plc5Unit
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.modbus.mapping import Table
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeRead
from gateway.sim.serve import SimStream
from gateway.transport import ByteStream

MAP = [MapItem("holding", 0, "N7:0", 4), MapItem("coil", 0, "B3/0", 16)]


def make_line(line: MultidropLine, numbers: tuple[int, ...], **kwargs: Any) -> Df1HalfDuplexLine:
    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        return SimStream(line)

    configs = [StationConfig(n, poll_timeout=0.05, reply_timeout=1.0, demote_after=3, poll_interval=0.2,
                             slow_poll_interval=2.0) for n in numbers]
    return Df1HalfDuplexLine("sim://line", configs, name="line", checksum=line.options.checksum, ack_timeout=0.05,
                             message_retries=3, retries=3, opener=opener, first_tns=1, **kwargs)


async def refresh(unit: Plc5Unit) -> None:
    for index, block in enumerate(unit.plan.blocks):
        unit.cache.store(index, await unit.read_block(block), unit._loop_time())


@pytest.mark.parametrize("variant", ["refuse", "accept"])
@pytest.mark.parametrize("checksum", [Checksum.BCC, Checksum.CRC])
async def test_plc5_stations_on_a_noisy_half_duplex_line(variant: str, checksum: Checksum) -> None:
    options = LineOptions(checksum=checksum, stations=(1, 2, 3), corrupt=6, ignore=10, seed=5, model="plc5")
    line = MultidropLine(options, controller_variants={"typed_logical": variant})
    for n, controller in line.controllers.items():
        for k in range(4):
            controller.set_word("N7", k, 1000 * n + k)
        controller.set_word("B3", 0, 0x8000)
    driver = make_line(line, (1, 2, 3))
    units = {n: Plc5Unit(driver=driver.station(n), items=MAP, unit_id=n, name=f"plc5-{n}") for n in (1, 2, 3)}
    await driver.station(1).start()
    try:
        for _ in range(3):
            await asyncio.gather(*(refresh(u) for u in units.values()))
            for n, unit in units.items():
                assert unit.read_registers(Table.HOLDING, 0, 4) == [1000 * n + k for k in range(4)]
        for n, unit in units.items():
            points = unit.plan.coils
            async with unit.driver.write_session() as lease:
                for step in unit._register_steps(unit.check_register_write(1, [n, n + 1])):
                    await step.run(lease)
                for step in unit._bit_steps([(n, points[n], True), (n + 1, points[n + 1], True)]):
                    await step.run(lease)
    finally:
        await driver.station(1).close()
    for n in (1, 2, 3):
        controller = line.controllers[n]
        assert isinstance(controller, Plc5Simulator)
        assert [controller.word("N7", k) for k in range(4)] == [1000 * n, n, n + 1, 1000 * n + 3]
        assert controller.word("B3", 0) == 0x8000 | 3 << n
        kinds = [kind for kind, _where, _data in controller.applied_writes]
        assert kinds == ["word_range_write", "read_modify_write"], (n, controller.applied_writes)
        assert set(controller.counters.commands) <= {"word_range_read", "word_range_write", "read_modify_write"}
    assert line.counters.corrupted > 0 and line.counters.ignored > 0


async def test_station_metrics_polls_eots_retries_demotions_data_age() -> None:
    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2), dead=frozenset({2}), ignore=4, seed=3,
                                     model="plc5"))
    driver = make_line(line, (1, 2))
    handle, dead = driver.station(1), driver.station(2)
    assert handle.metrics()["data_age"] == -1.0
    await handle.start()
    try:
        for _ in range(10):
            await handle.execute(WordRangeRead(LogicalBinaryAddress.of(0, 7, 0), 2), "read N7:0")
        with pytest.raises(LinkTimeout):
            for _ in range(5):
                await dead.execute(WordRangeRead(LogicalBinaryAddress.of(0, 7, 0), 2), "read N7:0")
        now = asyncio.get_running_loop().time()
        live, gone = handle.metrics(now), dead.metrics(now)
        await asyncio.sleep(0.05)
        assert handle.metrics()["data_age"] >= live["data_age"] + 0.04  # it ages while nothing is read
    finally:
        await handle.close()
        await dead.close()
    assert live["polls"] >= 10 and live["eots"] >= 1 and live["messages_received"] >= 10
    assert live["retries"] + live["read_retries"] >= 1  # 1 in 4 master frames unheard
    assert live["active"] == 1.0 and 0 <= live["data_age"] < 1.0 and live["demotions"] == 0
    assert gone["demotions"] >= 1 and gone["active"] == 0.0 and gone["data_age"] == -1.0 and gone["eots"] == 0
    assert set(driver.station_metrics()) == {1, 2}
