"""The half-duplex line driver when a station or the port misbehaves.

A station that never acknowledges the answer to its own message, one that sends replies nobody
asked for, one that stops answering polls and comes back without any request of ours, a port that
never opens and one lost with a request on the line: the counters, up/down states and errors an
integrator sees (docs/guide/df1-half-duplex.md), on the multi-drop simulator over an in-memory stream.
"""

from __future__ import annotations

import asyncio

import pytest

from gateway.errors import LinkDown
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_half_duplex_slave import HalfDuplexSlave
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.link_health import DownAfter
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable
from gateway.protocols.df1.pccc import (
    LogicalBinaryAddress,
    PcccHeader,
    ProtectedTypedLogicalRead,
    WordRangeWrite,
    encode_command,
    encode_reply,
)
from gateway.transport import ByteStream
from tests.waiting import until

from .lines import N, PullableStream, expected, opener_for, seed, stations

COUNTED = ("slave_messages", "slave_writes", "slave_refused", "slave_replies_lost", "stray_replies")


class DeafToMessages(HalfDuplexSlave):
    """A station that answers polls (its own messages, else DLE EOT) but never hears a master message,
    so never sends the DLE ACK of one: the answers to its MSGs are never acknowledged."""

    def _on_message(self, message: bytes, now: float) -> None:
        self.counters.messages += 1


def msg_write(station: int, element: int, value: int, tns: int) -> bytes:
    """The packet of a station's MSG writing ``value`` to N7:``element`` of the gateway (station 0)."""
    write = WordRangeWrite(LogicalBinaryAddress.of(0, 7, element), value.to_bytes(2, "little"))
    return encode_command(write, dst=0, src=station, tns=tns)


async def test_answers_a_station_never_acknowledges_are_counted_lost_and_so_is_one_pending_when_the_port_goes() -> None:
    """``slave_replies_lost``: the answer to a station's MSG that it never acknowledges (sent again
    ``message_retries`` times, then given up), and one still waiting for its DLE ACK when the port is
    lost, counted once; its writes are stored all the same.  The other station's counts stay 0."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    heard = sim.slaves[2]
    sim.slaves[2] = DeafToMessages(heard.station, heard.checksum, heard.handler, heard.variant)
    table = RegisterTable(file_number=7, size=10)
    streams: list[PullableStream] = []

    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        streams.append(PullableStream(sim))
        return streams[-1]

    # the answer is sent 1 + 2 times, 0.2 s apart: 0.6 s to pull the port while it is pending
    driver = Df1HalfDuplexLine("sim://line", stations(1, 2, demote_after=1000), checksum=Checksum.BCC,
                               ack_timeout=0.2, message_retries=2, opener=opener, first_tns=1, link_reset=False,
                               register_tables={2: table}, reconnect_min=0.01, reconnect_max=0.01)
    one, two = driver.station(1), driver.station(2)
    await one.start()
    try:
        sim.slaves[2].initiate(msg_write(2, 1, 41, tns=21))
        await until(lambda: two.metrics()["slave_replies_lost"] >= 1)
        assert table.value(1) == 41
        sim.slaves[2].initiate(msg_write(2, 1, 42, tns=22))
        await until(lambda: table.value(1) == 42)
        streams[-1].lost("cable pulled")  # the answer to the second MSG is waiting for its DLE ACK
        await until(lambda: len(streams) == 2 and driver.connected)
        assert two.metrics()["slave_replies_lost"] == 2
        sim.slaves[2].initiate(msg_write(2, 1, 43, tns=23))  # on the new connection
        await until(lambda: two.metrics()["slave_replies_lost"] >= 3)
        streams[-1].lost("cable pulled again")  # nothing pending now: nothing more is lost
        await until(lambda: len(streams) == 3 and driver.connected)
        assert table.value(1) == 43
        counts = {k: two.metrics()[k] for k in COUNTED}
        others = {k: one.metrics()[k] for k in COUNTED}
    finally:
        await one.close()
        await two.close()
    assert counts == {"slave_messages": 3, "slave_writes": 3, "slave_refused": 0, "slave_replies_lost": 3,
                      "stray_replies": 0}
    assert others == dict.fromkeys(COUNTED, 0)


async def test_replies_nobody_asked_for_are_counted_on_the_line_and_the_station() -> None:
    """A station's message with the reply bit (CMD 0x4F) whose TNS answers no command of ours is a
    stray reply (1770-6.5.16 p. 6-3: a reply carries the command's TNS): counted on the line
    (``stray_replies``) and on the station that sent it, and not taken for a message of its own."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    seed(sim)
    driver = Df1HalfDuplexLine("sim://line", stations(1, 2), checksum=Checksum.BCC, ack_timeout=0.05,
                               opener=opener_for(sim), first_tns=1, link_reset=False)
    one, two = driver.station(1), driver.station(2)
    await one.start()
    try:
        for tns in (0x1234, 0x1235):  # replies (CMD 0x4F) to CMD 0F commands of ours never sent
            sim.slaves[2].initiate(encode_reply(PcccHeader(dst=2, src=0, cmd=0x0F, sts=0, tns=tns)))
        await until(lambda: driver.stray_replies >= 2)
        await asyncio.sleep(0.3)  # a poll cycle more: nothing else is counted
        counts = {k: two.metrics()[k] for k in COUNTED}
        others = {k: one.metrics()[k] for k in COUNTED}
        line_count = driver.stray_replies
        # the line goes on serving both stations
        assert (await two.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10))).data == expected(2)
    finally:
        await one.close()
        await two.close()
    assert line_count == 2
    assert counts == {"slave_messages": 0, "slave_writes": 0, "slave_refused": 0, "slave_replies_lost": 0,
                      "stray_replies": 2}
    assert others == dict.fromkeys(COUNTED, 0)


async def test_a_station_that_stops_answering_polls_is_down_and_up_again_when_it_answers() -> None:
    """No request needed: a station demoted to slow poll is a failure of its link (down after one here,
    with the reason), and answering a slow poll again brings it back up."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    seed(sim)
    driver = Df1HalfDuplexLine("sim://line", stations(1, 2, demote_after=1, slow_poll_interval=0.3),
                               checksum=Checksum.BCC, ack_timeout=0.05, opener=opener_for(sim), first_tns=1,
                               link_reset=False, down_after={2: DownAfter(failures=1)})
    one, two = driver.station(1), driver.station(2)
    await one.start()
    try:
        assert (await two.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10))).data == expected(2)
        assert two.available
        powered = sim.slaves.pop(2)  # station 2 powered off
        await until(lambda: not two.available)
        reason = two.last_error
        sim.slaves[2] = powered  # and on again
        await until(lambda: two.available)
        assert driver.connected
    finally:
        await one.close()
        await two.close()
    assert reason == "station 2 does not answer polls (demoted to slow poll)"


async def test_a_port_that_never_opens_gives_every_station_its_reason() -> None:
    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        raise LinkDown("/dev/ttyS9: no such device")

    driver = Df1HalfDuplexLine("/dev/ttyS9", stations(1, 2), opener=opener, reconnect_min=0.01, reconnect_max=0.01)
    one, two = driver.station(1), driver.station(2)
    try:
        with pytest.raises(LinkDown, match=r"^/dev/ttyS9: no such device$"):
            await one.start(1.0)
        assert not one.available and not two.available
        assert one.last_error == two.last_error == driver.last_error == "/dev/ttyS9: no such device"
    finally:
        await one.close()
        await two.close()


async def test_a_request_on_a_lost_port_fails_at_once_and_so_does_one_made_while_it_is_down() -> None:
    """The port is lost with a read on the line (station 1 is off, so it waits for a DLE ACK) and does
    not open again: the read fails with LinkDown (Modbus 0x0B) at once, not at its timeouts, and a
    request made while the port is down fails at once too."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,), dead=frozenset({1})))
    streams: list[PullableStream] = []

    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        if streams:
            raise LinkDown("sim://line: port gone")
        streams.append(PullableStream(sim))
        return streams[-1]

    driver = Df1HalfDuplexLine("sim://line", stations(1, demote_after=1000, reply_timeout=30.0),
                               checksum=Checksum.BCC, ack_timeout=10.0, opener=opener, first_tns=1, link_reset=False,
                               reconnect_min=0.01, reconnect_max=0.01)
    handle = driver.station(1)
    await handle.start()
    try:
        pending = asyncio.create_task(handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2)))
        await asyncio.sleep(0.1)
        assert not pending.done()
        streams[-1].lost("cable pulled")
        with pytest.raises(LinkDown):
            await asyncio.wait_for(pending, 2.0)
        with pytest.raises(LinkDown):
            await asyncio.wait_for(handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2)), 2.0)
    finally:
        await handle.close()
