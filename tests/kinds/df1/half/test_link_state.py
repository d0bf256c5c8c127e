"""A station on a half-duplex line goes up and down by the rule of every link (``gateway.link_health``).

Down after ``down_after_failures`` failed transactions in a row (not at the first), up at the first
answer, each change logged once; the line's lost port makes every station on it down at once.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

import pytest

from gateway.errors import LinkTimeout
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, Df1Station
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.line_driver import LineDriver
from gateway.link_health import DownAfter, LinkHealth
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.master import StationConfig
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead
from gateway.sim.serve import SimStream
from gateway.transport import ByteStream
from tests.waiting import until

READ = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2)


class CuttableStream(SimStream):
    """A simulator stream whose cable can be pulled (the transport's ``lost`` callback)."""

    lost: Callable[[str], None]

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        self.lost = lost
        return super().start_push(receive, lost)


def make_line(sim: MultidropLine, streams: list[CuttableStream], down_after: dict[int, DownAfter]) -> Df1HalfDuplexLine:
    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        streams.append(CuttableStream(sim))
        return streams[-1]

    configs = [
        StationConfig(n, poll_timeout=0.05, reply_timeout=0.5, demote_after=50, poll_interval=0.2,
                      slow_poll_interval=2.0)
        for n in (1, 2)
    ]
    return Df1HalfDuplexLine(
        "sim://line", configs, name="line", checksum=Checksum.BCC, ack_timeout=0.02, message_retries=1, retries=0,
        opener=opener, first_tns=1, station_names={1: "s1", 2: "s2"}, down_after=down_after,
    )


def link_lines(caplog: pytest.LogCaptureFixture, name: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "gateway.link" and f"link {name}:" in r.getMessage()]


@pytest.mark.looptime
async def test_a_station_goes_down_after_n_failures_in_a_row_not_one(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "gateway.link")
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    line = make_line(sim, [], {2: DownAfter(3, 60.0)})
    s1, s2 = line.station(1), line.station(2)
    changes: list[bool] = []
    s2.add_listener(lambda handle: changes.append(handle.available))
    await s1.start()
    try:
        async with asyncio.timeout(10):
            await s1.execute(READ, "read")
            await s2.execute(READ, "read")
            assert s2.available and s2.state_changes == 1
            slave = sim.slaves.pop(2)  # station 2 stops answering
            for n in range(1, 5):
                with pytest.raises(LinkTimeout):
                    await s2.execute(READ, "read")
                assert s2.available is (n < 3), n
            assert s2.counters.errors == 4 and s2.last_error
            await s1.execute(READ, "read")  # the other station goes on
            assert s1.available
            sim.slaves[2] = slave
            await s2.execute(READ, "read")
            assert s2.available
    finally:
        await s1.close()
    assert s2.state_changes == 3 and changes == [True, False, True]  # up, down, up: each once
    lines = link_lines(caplog, "s2")
    assert sum(": down:" in line for line in lines) == 1, lines
    assert sum(": up (station 2 on " in line for line in lines) == 2, lines
    assert s1.state_changes == 1


@pytest.mark.looptime
async def test_a_lost_port_makes_every_station_down_at_once(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "gateway.link")
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    streams: list[CuttableStream] = []
    line = make_line(sim, streams, {})
    handles = [line.station(1), line.station(2)]
    await handles[0].start()
    try:
        async with asyncio.timeout(10):
            for handle in handles:
                await handle.execute(READ, "read")
                assert handle.available
            streams[-1].lost("cable pulled")
            await until(lambda: not line.connected, step=0.001)
            for handle in handles:
                assert not handle.available and handle.state_changes == 2
                assert handle.last_error == "cable pulled"
            await until(lambda: len(streams) == 2 and line.connected, step=0.001)  # the line reopens the port by itself
            for handle in handles:
                await handle.execute(READ, "read")
                assert handle.available and handle.state_changes == 3
    finally:
        await handles[0].close()
    for name in ("s1", "s2"):
        assert sum(": down: cable pulled" in line for line in link_lines(caplog, name)) == 1


def test_every_driver_uses_the_one_rule() -> None:
    """SLC 100/150, DF1 full duplex and each half-duplex station: one class holds the rule."""
    from gateway.kinds.df1.full.driver import Df1Driver
    from gateway.kinds.slc_ascii.driver import SlcAsciiDriver

    for driver in (SlcAsciiDriver, Df1Driver, Df1HalfDuplexLine, Df1Station):
        assert issubclass(driver, LinkHealth), driver
        for method in ("note_result", "judge", "_report", "add_listener"):
            owner: Any = next(c for c in driver.__mro__ if method in vars(c))
            assert owner is LinkHealth or (driver is Df1HalfDuplexLine and method == "_report"), (driver, method)
    assert issubclass(LineDriver, LinkHealth)
