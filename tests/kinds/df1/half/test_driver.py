"""The half-duplex line driver against the multi-drop simulator over an in-memory stream.

Three live stations and one absent, BCC and CRC, 1 in 6 slave frames corrupted and 1 in 10 master
frames unheard (issue #12 acceptance): values correct and never mixed, writes exactly once on the
right station, the absent station fails promptly while the others go on being read.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import pytest

from gateway.errors import LinkTimeout
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, Df1Station
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.pccc import (
    PcccError,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
)
from gateway.sim.serve import SimStream
from gateway.sim.variants import pairwise_cover, variant_matrix
from gateway.transport import ByteStream

from .lines import N, PullableStream, expected, make_driver, opener_for, seed, stations


@pytest.mark.parametrize("checksum", [Checksum.BCC, Checksum.CRC])
async def test_three_live_one_absent_noisy_line(checksum: Checksum) -> None:
    options = LineOptions(checksum=checksum, stations=(1, 2, 3, 4), dead=frozenset({4}), corrupt=6, ignore=10, seed=11)
    line = MultidropLine(options)
    seed(line)
    driver = make_driver(line, (1, 2, 3, 4))
    handles = [driver.station(n) for n in (1, 2, 3, 4)]
    await handles[0].start()
    reads = {n: 0 for n in (1, 2, 3)}
    failures = {n: 0 for n in (1, 2, 3)}
    stop = asyncio.Event()

    async def reader(handle: Df1Station) -> None:
        while not stop.is_set():
            try:
                reply = await handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10), "read N7:0")
            except LinkTimeout:
                failures[handle.station] += 1
                continue
            assert reply.data == expected(handle.station), (handle.station, reply.data.hex())
            reads[handle.station] += 1

    absent_times: list[float] = []

    async def absent() -> None:
        while not stop.is_set():
            started = time.monotonic()
            with pytest.raises(LinkTimeout, match="station 4"):
                await handles[3].execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2), "read N7:0")
            absent_times.append(time.monotonic() - started)
            await asyncio.sleep(0.05)

    try:
        tasks = [asyncio.create_task(reader(h)) for h in handles[:3]] + [asyncio.create_task(absent())]
        await asyncio.sleep(1.5)
        # writes, exactly once each, on the right station, while the reads go on
        for k in range(3):
            for handle in handles[:3]:
                value = 100 * handle.station + k
                await handle.execute(ProtectedTypedLogicalWrite(N, 7, 50 + k, 0, value.to_bytes(2, "little")))
        await handles[1].execute(ProtectedTypedLogicalMaskedWrite(N, 7, 60, 0, 0x0001, b"\x01\x00"))
        with pytest.raises(LinkTimeout, match="station 4"):
            await handles[3].execute(ProtectedTypedLogicalWrite(N, 7, 50, 0, b"\x01\x00"))
        stop.set()
        await asyncio.gather(*tasks)
    finally:
        stop.set()
        for handle in handles:
            await handle.close()
    for n in (1, 2, 3):
        controller = line.controllers[n]
        assert [controller.word("N7", 50 + k) for k in range(3)] == [100 * n + k for k in range(3)]
        writes = [w for w in controller.applied_writes]
        assert len(writes) == (4 if n == 2 else 3), writes
        assert reads[n] >= 10, (reads, failures)
    assert line.controllers[2].word("N7", 60) == 61  # bit 0 set, the rest of 60 kept
    assert line.controllers[4].applied_writes == []
    assert absent_times and max(absent_times) < 1.5, absent_times
    assert sorted(absent_times)[len(absent_times) // 2] < 0.05  # demoted: the usual failure is at once
    totals = handles[3].totals
    assert totals.demotions >= 1 and totals.polls > 0
    assert handles[0].totals.polls > 0 and handles[0].available is False  # closed
    assert line.counters.corrupted > 0 and line.counters.ignored > 0


async def test_refusal_is_a_pccc_error_and_rts_follows_the_core() -> None:
    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,)))
    rts: list[bool] = []
    driver = make_driver(line, (1,), rts=rts.append, rts_send_delay=0.01, rts_off_delay=0.01)
    handle = driver.station(1)
    await handle.start()
    try:
        with pytest.raises(PcccError, match="EXT STS 0x06"):
            await handle.execute(ProtectedTypedLogicalRead(N, 9, 0, 0, 2), "read N9:0")
        assert handle.last_sts == 0xF0 and handle.available
        async with handle.write_session() as lease:  # the unit's write path (gateway.writes)
            lease.extend_burst()
            await handle.execute(ProtectedTypedLogicalWrite(N, 7, 9, 0, b"\x99\x00"), "write N7:9", lease)
        assert line.controllers[1].word("N7", 9) == 0x99
        await asyncio.sleep(0.1)  # the line goes quiet between polls: RTS off after rts_off_delay
    finally:
        await handle.close()
    assert rts[:2] == [True, False]  # keyed up 10 ms before the first byte, released after the last


async def test_echo_suppression_on_a_two_wire_line() -> None:
    line = MultidropLine(LineOptions(checksum=Checksum.CRC, stations=(1, 2), echo=True))
    seed(line)
    driver = make_driver(line, (1, 2), echo=True)
    handle = driver.station(2)
    await handle.start()
    try:
        reply = await handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10), "read N7:0")
        assert reply.data == expected(2)
        assert driver.core is not None and driver.core.collisions == 0
    finally:
        await handle.close()


async def test_write_without_reply_is_settled_by_a_read_back() -> None:
    """reply_retries=0 and every slave frame corrupted: the write ran, its reply is lost; the read-back
    (whose reply is lost too) cannot prove it, so the outcome is unknown - and the write was sent once."""
    from gateway.kinds.df1.full.driver import WriteOutcomeUnknown

    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,), corrupt=1), variants={"reply_retries": "0"})
    driver = make_driver(line, (1,))
    handle = driver.station(1)
    await handle.start()
    try:
        with pytest.raises(WriteOutcomeUnknown, match="may or may not have been applied"):
            await handle.execute(ProtectedTypedLogicalWrite(N, 7, 70, 0, b"\x2a\x00"), "write N7:70")
    finally:
        await handle.close()
    assert line.controllers[1].applied_writes == [("write", "N7:70", b"\x2a\x00")]
    assert handle.totals.read_backs == 4  # retries (3) + 1, the rule of write_verdict.py


def test_station_numbers_are_checked() -> None:
    line = MultidropLine()
    with pytest.raises(ValueError, match="unique"):
        make_driver(line, (1, 1))
    with pytest.raises(ValueError, match="no station 9"):
        make_driver(line, (1, 2)).station(9)


@pytest.mark.parametrize("typed_logical", ["refuse", "accept"])
async def test_plc5_station_read_and_written_with_word_range_commands(typed_logical: str) -> None:
    """PLC-5 stations on a half-duplex line: word range read / write and the RMW coil write work the
    same whether the PLC-5 refuses or accepts the SLC typed logical commands (it is never sent one)."""
    from gateway.protocols.df1.plc5_commands import plc5_bit_write, plc5_read, plc5_write

    options = LineOptions(checksum=Checksum.CRC, stations=(3, 4), model="plc5", corrupt=6, ignore=10, seed=5)
    line = MultidropLine(options, controller_variants={"typed_logical": typed_logical})
    driver = make_driver(line, (3, 4))
    plc, other = driver.station(3), driver.station(4)
    await plc.start()
    try:
        assert (await plc.execute(plc5_read("N7:30"))).data == bytes.fromhex("1E 00")
        assert (await plc.execute(plc5_read("F8:2"))).data == bytes.fromhex("00 00 40 40")
        await plc.execute(plc5_write("T4:2.ACC", b"\x07\x00"))
        assert (await plc.execute(plc5_read("T4:2"))).data == bytes.fromhex("00 00 32 00 07 00")
        await plc.execute(plc5_bit_write("B3/5", True))
        await plc.execute(plc5_bit_write("B3:1/0", False))
        assert (await plc.execute(plc5_read("B3:0", 2))).data == bytes.fromhex("20 00 A4 A5")
        typed = ProtectedTypedLogicalRead(N, 7, 30, 0, 2)
        if typed_logical == "accept":
            assert (await plc.execute(typed)).data == bytes.fromhex("1E 00")
        else:
            with pytest.raises(PcccError, match="STS 0x10"):
                await plc.execute(typed)
    finally:
        await plc.close()
        await other.close()
    controller = line.controllers[3]
    assert [kind for kind, _, _ in controller.applied_writes] == [
        "word_range_write", "read_modify_write", "read_modify_write"]
    assert line.controllers[4].applied_writes == []


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Every combination of the slave readings with ``--soak``; a pairwise cover otherwise."""
    if "choices" in metafunc.fixturenames:
        every = bool(metafunc.config.getoption("--soak", default=False))
        table = MultidropLine.VARIANTS
        combos = list(variant_matrix(table)) if every else pairwise_cover(table)
        metafunc.parametrize("choices", combos, ids=str)


async def test_every_slave_reading_values_right_and_writes_once(choices: dict[str, str]) -> None:
    """Each reading of docs/develop/df1-half-duplex-notes.md §5 (bad_frame_reply, reply_retries,
    duplicate_detect, when_busy), a busy and a slow station, lost and corrupted frames and lost slave
    ACKs: reads are right or fail, and no write runs twice (a write whose reply is lost is settled by
    a read-back or reported as possibly applied)."""
    from gateway.kinds.df1.full.driver import WriteOutcomeUnknown

    options = LineOptions(checksum=Checksum.BCC, stations=(1, 2), corrupt=5, ignore=6, lose_symbol=4,
                          busy_polls={2: 1}, slow={1: 0.01}, seed=13)
    line = MultidropLine(options, variants=choices)
    seed(line)
    # with this many lost answers a live station would be demoted after 3 in a row: allow 6
    driver = make_driver(line, (1, 2), duplicate_detect=choices["duplicate_detect"] == "on", demote_after=6,
                         reply_timeout=0.3)
    handles = [driver.station(1), driver.station(2)]
    await handles[0].start()
    outcomes: dict[tuple[int, int], str] = {}
    try:
        for k in range(4):
            for handle in handles:
                try:
                    reply = await handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10), "read")
                    assert reply.data == expected(handle.station)
                except LinkTimeout:
                    pass
                try:
                    await handle.execute(ProtectedTypedLogicalWrite(N, 7, 80 + k, 0, bytes((k + 1, handle.station))))
                    outcomes[handle.station, k] = "done"
                except WriteOutcomeUnknown:
                    outcomes[handle.station, k] = "unknown"
                except LinkTimeout:
                    outcomes[handle.station, k] = "failed"
    finally:
        for handle in handles:
            await handle.close()
    for (station, k), outcome in outcomes.items():
        runs = [w for w in line.controllers[station].applied_writes if w[1] == f"N7:{80 + k}"]
        assert len(runs) <= 1, (station, k, runs)  # never twice
        if outcome == "done":
            assert runs == [("write", f"N7:{80 + k}", bytes((k + 1, station)))]
        if outcome == "failed":
            assert runs == []
    assert sum(o == "done" for o in outcomes.values()) >= 4, outcomes
    assert line.counters.lost_symbols > 0


# --- the line's keys, counters and life cycle (docs/guide/df1-half-duplex.md) -------------------------


def test_line_keys_default_as_the_guide_says() -> None:
    """docs/guide/df1-half-duplex.md "Keys": ack_timeout 0.5 s, message_retries 3, link_reset true,
    rts "toggle", dtr true, no delays, no echo; a line is 19200 8N1 by default (df1-full-duplex.md)."""
    from gateway.protocols.df1.half_duplex.events import LineConfig
    from gateway.streams import SerialSettings

    line = Df1HalfDuplexLine("sim://line", [StationConfig(1)], checksum=Checksum.CRC)
    assert line.tunables == LineConfig(Checksum.CRC, ack_timeout=0.5, message_resends=3, pre_transmit_delay=0.0,
                                       rts_send_delay=0.0, rts_off_delay=0.0, echo=False)
    assert line.link_reset is True and line.dtr is True and line.rts_mode == "toggle"
    assert line.settings == SerialSettings(19200, 8, "N", 1)
    assert line.stray_replies == 0 and line.station_metrics()[1]["stray_replies"] == 0
    given = Df1HalfDuplexLine("sim://line", [StationConfig(1)], checksum=Checksum.BCC, ack_timeout=0.2,
                              message_retries=5, pre_transmit_delay=0.01, rts_send_delay=0.02, rts_off_delay=0.03,
                              echo=True)
    assert given.tunables == LineConfig(Checksum.BCC, ack_timeout=0.2, message_resends=5, pre_transmit_delay=0.01,
                                        rts_send_delay=0.02, rts_off_delay=0.03, echo=True)
    # slaves without duplicate detection: a master frame is never sent again
    no_dd = Df1HalfDuplexLine("sim://line", [StationConfig(1)], message_retries=5, duplicate_detect=False)
    assert no_dd.tunables.message_resends == 0


async def test_the_line_is_opened_with_its_serial_settings_and_down_after_rule_per_station() -> None:
    from gateway.link_health import DownAfter
    from gateway.streams import SerialSettings

    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    opened: list[object] = []

    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        opened.append(settings)
        return SimStream(sim)

    driver = Df1HalfDuplexLine("sim://line", stations(1, 2), checksum=Checksum.BCC, opener=opener,
                               down_after={2: DownAfter(failures=7, seconds=9.0)})
    assert (driver.station(2).down_after_failures, driver.station(2).down_after_seconds) == (7, 9.0)
    assert (driver.station(1).down_after_failures, driver.station(1).down_after_seconds) == (3, 5.0)  # defaults
    handle = driver.station(1)
    await handle.start()
    try:
        assert opened == [SerialSettings(19200, 8, "N", 1)]
    finally:
        await handle.close()


async def test_commands_carry_the_first_tns_and_the_source_address() -> None:
    """The TNS of the first command is ``first_tns`` when given, else a random one in 1..65535 (never 0);
    the reply comes back addressed to the gateway's own station (``source``)."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,)))
    seed(sim)
    driver = make_driver(sim, (1,), source=9, first_tns=0x2345)  # not the transaction layer's own first TNS
    driver_random = Df1HalfDuplexLine("sim://line", stations(1), checksum=Checksum.BCC, opener=opener_for(sim))
    read = ProtectedTypedLogicalRead(N, 7, 0, 0, 2)
    for line, tns in ((driver, 0x2345), (driver_random, None)):
        handle = line.station(1)
        await handle.start()
        try:
            reply = await handle.execute(read)
        finally:
            await handle.close()
        assert reply.data == expected(1)[:2]
        if tns is None:
            assert 1 <= reply.tns <= 0xFFFF
        else:
            assert (reply.tns, reply.dst) == (tns, 9)


async def test_a_read_is_tried_retries_plus_one_times() -> None:
    """``retries`` (the link key): a read without an answer is sent again with a new TNS that many times."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,), dead=frozenset({1})))
    driver = Df1HalfDuplexLine("sim://line", stations(1, demote_after=50), checksum=Checksum.BCC, ack_timeout=0.02,
                               message_retries=0, retries=1, opener=opener_for(sim), link_reset=False)
    handle = driver.station(1)
    await handle.start()
    try:
        # the error names the command: its given name, else its type
        with pytest.raises(LinkTimeout, match="ProtectedTypedLogicalRead"):
            await handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2))
        totals = handle.totals
        quality = handle.line_quality()
        with pytest.raises(LinkTimeout, match=": diagnostic status: "):  # "link <name>: <command>: <reason>"
            await handle.probe()
    finally:
        await handle.close()
    assert totals.read_retries == 1 and totals.resends == 0
    # line quality: the master frames sent again and the timeouts of this station, no DLE NAK count
    assert quality.retransmits == 1 and quality.timeouts == totals.timeouts >= 2 and quality.check_errors == 0


async def test_the_last_station_closing_closes_the_line_and_run_shares_one_line_task() -> None:
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    seed(sim)
    driver = make_driver(sim, (1, 2))
    one, two = driver.station(1), driver.station(2)
    runs = [asyncio.create_task(one.run()), asyncio.create_task(two.run())]
    try:
        for _ in range(200):
            if driver.connected:
                break
            await asyncio.sleep(0.01)
        assert (await two.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10))).data == expected(2)
        await one.close()
        await one.close()  # a second close of one handle does not release the line again
        assert driver.connected  # station 2 still uses it
        assert (await two.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10))).data == expected(2)
        await two.close()
        assert not driver.connected
    finally:
        for task in runs:
            task.cancel()
        await asyncio.gather(*runs, return_exceptions=True)


async def test_a_started_station_alone_owns_the_line() -> None:
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,)))
    seed(sim)
    driver = make_driver(sim, (1,))
    handle = driver.station(1)
    await handle.start()
    assert driver.connected and driver.last_error == ""  # coming up gives no error
    assert handle.last_sts == 0 and handle.metrics()["data_age"] == -1.0  # nothing answered yet
    info = await handle.probe()
    now = asyncio.get_running_loop().time() + 100.0
    ages = (handle.metrics(now)["data_age"], driver.station_metrics(now)[1]["data_age"])
    await handle.close()
    assert not driver.connected
    assert info.raw  # the diagnostic status reply's data (1770-6.5.16 ch. 7 "diagnostic status")
    assert ages[0] == ages[1] and 100.0 <= ages[0] < 101.0  # the age at the given time, for every station


@pytest.mark.parametrize("link_reset", [None, False])
async def test_the_link_reset_at_start_empties_the_slaves_queued_messages(link_reset: bool | None) -> None:
    """``link_reset`` (default true): a DLE NAK when the line starts empties the messages the slaves had
    queued (docs/guide/df1-half-duplex.md); without it they are delivered at the first poll."""
    from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable
    from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeWrite, encode_command

    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,)))
    table = RegisterTable(file_number=7, size=10)
    kwargs: dict[str, Any] = {} if link_reset is None else {"link_reset": link_reset}
    driver = make_driver(sim, (1,), register_tables={1: table}, **kwargs)
    handle = driver.station(1)
    write = WordRangeWrite(LogicalBinaryAddress.of(0, 7, 0), (7).to_bytes(2, "little"))
    sim.slaves[1].initiate(encode_command(write, dst=0, src=1, tns=5))
    await handle.start()
    try:
        await asyncio.sleep(0.5)  # polled every 0.2 s
        received = handle.metrics()["slave_messages"]
    finally:
        await handle.close()
    assert (received, table.value(0)) == ((0, 0) if link_reset is None else (1, 7))


async def test_messages_a_station_initiates_are_counted_stored_or_refused() -> None:
    """A station's MSG write to the gateway's own station lands in its register table (STS 00); a read
    is refused with STS 10 (1770-6.5.16 p. 8-3): counted per station as slave_messages / slave_writes /
    slave_refused, the other station's counts untouched."""
    from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable
    from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeWrite, encode_command

    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    table = RegisterTable(file_number=7, size=10)
    driver = make_driver(sim, (1, 2), register_tables={2: table}, link_reset=False)
    one, two = driver.station(1), driver.station(2)
    await one.start()
    write = WordRangeWrite(LogicalBinaryAddress.of(0, 7, 1), (42).to_bytes(2, "little"))
    try:
        sim.slaves[2].initiate(encode_command(write, dst=0, src=2, tns=21))
        for _ in range(300):
            if table.value(1) == 42 and two.metrics()["slave_writes"] >= 1:
                break
            await asyncio.sleep(0.01)
        sim.slaves[2].initiate(encode_command(ProtectedTypedLogicalRead(N, 7, 0, 0, 2), dst=0, src=2, tns=22))
        sim.slaves[2].initiate(encode_command(ProtectedTypedLogicalRead(N, 7, 0, 0, 2), dst=0, src=2, tns=23))
        for _ in range(300):
            if two.metrics()["slave_refused"] >= 2:
                break
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.3)  # the replies are delivered
        counted = ("slave_messages", "slave_writes", "slave_refused", "slave_replies_lost", "stray_replies")
        counts = {k: two.metrics()[k] for k in counted}
        others = {k: one.metrics()[k] for k in counted}
    finally:
        await one.close()
        await two.close()
    assert table.value(1) == 42
    assert counts == {"slave_messages": 3, "slave_writes": 1, "slave_refused": 2, "slave_replies_lost": 0,
                      "stray_replies": 0}
    assert others == dict.fromkeys(counted, 0)


async def test_start_waits_as_long_as_asked_for_the_first_connection() -> None:
    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        await asyncio.sleep(3600)  # a port that never opens
        raise AssertionError

    driver = Df1HalfDuplexLine("sim://line", stations(1), opener=opener, connect_timeout=30.0)
    handle = driver.station(1)
    started = time.monotonic()
    try:
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(handle.start(0.1), 3.0)
        assert time.monotonic() - started < 2.0  # the 0.1 s asked, not the 30 s connect timeout
    finally:
        await handle.close()


async def test_two_started_stations_share_the_line_until_both_close() -> None:
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    seed(sim)
    driver = make_driver(sim, (1, 2))
    one, two = driver.station(1), driver.station(2)
    await one.start()
    await two.start()  # the line is running: the second start only takes a share of it
    try:
        await one.close()
        assert driver.connected
        assert (await two.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10))).data == expected(2)
    finally:
        await one.close()
        await two.close()
    assert not driver.connected


async def test_counters_are_totals_over_reconnects() -> None:
    """Df1Station.metrics: "Counters are totals since the line was created (reconnects included)"."""
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1,)))
    seed(sim)
    streams: list[PullableStream] = []

    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        streams.append(PullableStream(sim))
        return streams[-1]

    driver = Df1HalfDuplexLine("sim://line", stations(1), checksum=Checksum.BCC, opener=opener, first_tns=1,
                               reconnect_min=0.01, reconnect_max=0.01)
    handle = driver.station(1)
    await handle.start()
    try:
        for _ in range(3):
            await handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2))
        before = handle.metrics()
        streams[-1].lost("cable pulled")
        for _ in range(500):
            if len(streams) == 2 and driver.connected:
                break
            await asyncio.sleep(0.01)
        await handle.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2))
        after = handle.metrics()
    finally:
        await handle.close()
    assert before["messages_sent"] >= 3 and before["messages_received"] >= 3
    assert after["messages_sent"] >= before["messages_sent"] + 1
    assert after["messages_received"] >= before["messages_received"] + 1
    assert after["polls"] >= before["polls"]


async def test_a_demoted_station_is_down_and_an_abandoned_request_harms_no_other(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A station demoted to slow poll counts as a failed link (down after ``down_after_failures``, here 1);
    a caller that gives up on its request leaves the line serving the others, and the verdict that
    comes for it later is dropped without an error."""
    from gateway.link_health import DownAfter

    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2), dead=frozenset({2})))
    seed(sim)
    driver = make_driver(sim, (1, 2), demote_after=1, down_after={2: DownAfter(failures=1)})
    one, two = driver.station(1), driver.station(2)
    await one.start()
    try:
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(two.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 2)), 0.01)
        for _ in range(300):
            if not two.available:
                break
            await asyncio.sleep(0.01)
        assert not two.available  # demoted: down after its one allowed failure
        await asyncio.sleep(0.3)  # the abandoned request's verdict comes and goes
        assert (await one.execute(ProtectedTypedLogicalRead(N, 7, 0, 0, 10))).data == expected(1)
        assert one.available and driver.connected
    finally:
        await one.close()
        await two.close()
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []
