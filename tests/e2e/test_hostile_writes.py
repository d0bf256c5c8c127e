"""End to end: writes on a hostile network (issue 14, the write findings).

* A multi-register write is validated whole before anything is sent; a controller that refuses
  part-way anyway gets an exception, a log line naming the registers written, and a metric.
* Writes apply in arrival order across pipelined requests and connections.
* Bounded write queues (0x06 beyond), and every write in the audit log.

The simulators run with ``ladder=0``, so memory changes only by writes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import struct
import uuid
from collections.abc import AsyncIterator
from typing import Any
from urllib.parse import urlencode

import pytest
from modbus_support import connect, exception_code

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.sim import get_simulator

HOST = "127.0.0.1"
ILLEGAL_ADDRESS, DEVICE_FAILURE, SERVER_BUSY, TARGET_FAILED = 0x02, 0x04, 0x06, 0x0B


pytestmark = pytest.mark.usefixtures("forget_simulators")


def slc_url(**options: Any) -> str:
    return "sim://slc150?" + urlencode({"ladder": "0", **options, "instance": uuid.uuid4().hex})


def df1_url(**options: Any) -> str:
    return "sim://slc504?" + urlencode({"ladder": "0", **options, "instance": uuid.uuid4().hex})


def slc_link(url: str, unit: int = 1, **keys: Any) -> str:
    lines = ["[[link]]", 'name = "slc"', 'protocol = "slc-ascii"', f"port = {json.dumps(url)}", f"unit = {unit}"]
    lines += [f"{key} = {json.dumps(value)}" for key, value in keys.items()]
    return "\n".join(lines) + "\n"


def map_entry(table: str, start: int, address: str, count: int, **keys: str) -> str:
    lines = ["[[link.map]]", f'table = "{table}"', f"start = {start}", f'address = "{address}"', f"count = {count}"]
    lines += [f'{key} = "{value}"' for key, value in keys.items()]
    return "\n".join(lines) + "\n"


#: DF1 map of these tests: holding 0-3 N7:23-26; 4-7 F8:0-1 (float32); 10 N7:99 and 11 N10:100
#: (past the end of N10: the controller refuses it); coils 0-31 B3:0/0-B3:1/15
def df1_link(url: str, unit: int = 1) -> str:
    return (
        f'[[link]]\nname = "df1"\nprotocol = "df1"\nport = "{url}"\nunit = {unit}\ntimeout = 0.2\n'
        + map_entry("holding", 0, "N7:23", 4)
        + map_entry("holding", 4, "F8:0", 2, type="float32")
        + map_entry("holding", 10, "N7:99", 1)
        + map_entry("holding", 11, "N10:100", 1)
        + map_entry("coil", 0, "B3:0/0", 32)
    )


def config(*links: str, modbus: str = "") -> Any:
    return parse_config(f'[modbus]\nlisten = "127.0.0.1:0"\n{modbus}\n' + "\n".join(links))


@contextlib.asynccontextmanager
async def gateway(*links: str, modbus: str = "") -> AsyncIterator[Gateway]:
    async with Gateway(config(*links, modbus=modbus)) as gw:
        yield gw


async def until_ready(gw: Gateway, address: int, count: int, unit: int = 1, deadline: float = 10.0) -> None:
    async with connect(gw.port) as client, asyncio.timeout(deadline):
        while True:
            if not (await client.read_holding_registers(address, count=count, device_id=unit)).isError():
                return
            await asyncio.sleep(0.02)


def slc_holding(sim: SlcAsciiSimulator, address: int) -> int:
    return sim.word(2 * address if address < 32 else 0x40 + 2 * (address - 32)) & 0x7FFF


def word_writes(sim: SlcAsciiSimulator) -> list[tuple[str, int, int]]:
    return [w for w in sim.applied_writes if w[0] == "word"]


# --------------------------------------------------------------------------------------------
# Raw Modbus frames (the pipelining tests need them in one TCP segment)


def fc6(tid: int, address: int, value: int, unit: int = 1) -> bytes:
    return struct.pack(">HHHBBHH", tid, 0, 6, unit, 6, address, value)


def fc16(tid: int, address: int, values: list[int], unit: int = 1) -> bytes:
    pdu = struct.pack(">BHHB", 16, address, len(values), 2 * len(values)) + struct.pack(f">{len(values)}H", *values)
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def read_replies(reader: asyncio.StreamReader, n: int) -> dict[int, bytes]:
    """``n`` reply frames by transaction id (their PDUs)."""
    replies: dict[int, bytes] = {}
    async with asyncio.timeout(10):
        for _ in range(n):
            tid, _, length = struct.unpack(">HHH", await reader.readexactly(6))
            replies[tid] = (await reader.readexactly(length))[1:]
    return replies


# --------------------------------------------------------------------------------------------
# 1. Atomic multi-register writes


async def test_slc_fc16_over_a_protected_preset_writes_nothing() -> None:
    """Holding 63 is the preset of 932, protected in the simulator: FC16 60-63 is refused whole."""
    url = slc_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    before = [slc_holding(sim, a) for a in range(60, 64)]
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 32, 32)
        async with connect(gw.port) as client:
            reply = await client.write_registers(60, [1111, 2222, 3333, 4444], device_id=1)
        assert exception_code(reply) == DEVICE_FAILURE
    assert word_writes(sim) == []
    assert [slc_holding(sim, a) for a in range(60, 64)] == before


async def test_slc_refusal_part_way_is_an_exception_logged_and_counted(caplog: pytest.LogCaptureFixture) -> None:
    """Protected in the controller after the gateway read the presets: the gateway cannot know."""
    url = slc_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 32, 32)
        sim.set_word(0x40 + 2 * (52 - 32), 0x8000 | 5)  # preset 921 (holding 52) protected now
        caplog.set_level(logging.INFO)
        async with connect(gw.port) as client:
            reply = await client.write_registers(50, [1111, 2222, 3333], device_id=1)
        assert exception_code(reply) == DEVICE_FAILURE
        unit = gw.units[0]
        assert unit.partial_writes == 1
    assert [w[1:] for w in word_writes(sim)] == [(0x40 + 2 * 18, 1111), (0x40 + 2 * 19, 2222)]
    partial = [r for r in caplog.records if "partly" in r.getMessage()]
    assert len(partial) == 1 and partial[0].levelno == logging.WARNING
    message = partial[0].getMessage()
    assert "holding 50-51 written" in message and "holding 52" in message, message


async def test_df1_fc16_covering_half_a_float_writes_nothing() -> None:
    url = df1_url()
    sim = get_simulator(url)
    assert isinstance(sim, Slc500Simulator)
    async with gateway(df1_link(url)) as gw:
        await until_ready(gw, 0, 8)
        async with connect(gw.port) as client:
            reply = await client.write_registers(3, [777, 1], device_id=1)  # N7:26 + the high half of F8:0
        assert exception_code(reply) == ILLEGAL_ADDRESS
    assert sim.applied_writes == []


async def test_df1_fc16_of_consecutive_words_and_floats_is_one_command_each() -> None:
    url = df1_url()
    sim = get_simulator(url)
    assert isinstance(sim, Slc500Simulator)
    raw = [struct.unpack("<I", struct.pack("<f", v))[0] for v in (1.5, -2.25)]
    async with gateway(df1_link(url)) as gw:
        await until_ready(gw, 0, 8)
        async with connect(gw.port) as client:
            assert not (await client.write_registers(0, [1, 2, 3, 4], device_id=1)).isError()
            floats = [raw[0] >> 16, raw[0] & 0xFFFF, raw[1] >> 16, raw[1] & 0xFFFF]
            assert not (await client.write_registers(4, floats, device_id=1)).isError()
            assert list((await client.read_holding_registers(0, count=8, device_id=1)).registers) == [
                1, 2, 3, 4, *floats
            ]
    assert sim.applied_writes == [
        ("write", "N7:23", struct.pack("<4H", 1, 2, 3, 4)),
        ("write", "F8:0", struct.pack("<2I", *raw)),
    ]


async def test_df1_fc15_over_one_word_is_one_masked_write() -> None:
    url = df1_url()
    sim = get_simulator(url)
    assert isinstance(sim, Slc500Simulator)
    sim.set_word("B3", 0, 0x00F0)
    sim.set_word("B3", 1, 0xFFFF)
    async with gateway(df1_link(url)) as gw:
        async with connect(gw.port) as client, asyncio.timeout(10):
            while True:
                if not (await client.read_coils(0, count=32, device_id=1)).isError():
                    break
                await asyncio.sleep(0.02)
            bits = [True, False, True, False] + [False] * 10 + [True, True, False, False]  # B3:0/2-15, B3:1/0-3
            assert not (await client.write_coils(2, bits, device_id=1)).isError()
    masked = [w for w in sim.applied_writes if w[0] == "masked_write"]
    assert [w[1] for w in masked] == ["B3:0", "B3:1"], masked  # one command per word touched
    assert sim.word("B3", 0) == 0x0014  # bits 2-15 as written (2 and 4 set), 0-1 kept (clear)
    assert sim.word("B3", 1) == 0xFFF3  # bits 0-3 as written, 4-15 kept (set)


async def test_df1_refusal_part_way_is_an_exception_logged_and_counted(caplog: pytest.LogCaptureFixture) -> None:
    url = df1_url()
    sim = get_simulator(url)
    assert isinstance(sim, Slc500Simulator)
    async with gateway(df1_link(url)) as gw:
        await until_ready(gw, 0, 8)
        caplog.set_level(logging.INFO)
        async with connect(gw.port) as client:
            reply = await client.write_registers(10, [4242, 1], device_id=1)  # N7:99, then N10:100
        assert exception_code(reply) == ILLEGAL_ADDRESS
        assert gw.units[0].partial_writes == 1
    assert sim.applied_writes == [("write", "N7:99", struct.pack("<H", 4242))]
    partial = [r for r in caplog.records if "partly" in r.getMessage()]
    assert len(partial) == 1
    assert "holding 10 written" in partial[0].getMessage() and "holding 11" in partial[0].getMessage()


# --------------------------------------------------------------------------------------------
# 2. Writes apply in arrival order


async def test_pipelined_writes_apply_in_arrival_order() -> None:
    """tid 101 FC16 40-43 = 1111, tid 102 FC6 43 = 9998 in one segment: 43 ends 9998."""
    url = slc_url(paced="1")
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 32, 32)
        reader, writer = await asyncio.open_connection(HOST, gw.port)
        try:
            writer.write(fc16(101, 40, [1111] * 4) + fc6(102, 43, 9998))
            replies = await read_replies(reader, 2)
        finally:
            writer.close()
    assert replies[101][0] == 16 and replies[102][0] == 6, replies
    assert slc_holding(sim, 43) == 9998
    assert [w[1:] for w in word_writes(sim)][-1] == (0x40 + 2 * 11, 9998)


@pytest.mark.parametrize("order", ["fc16-first", "fc6-first"])
async def test_writes_from_two_connections_apply_in_arrival_order(order: str) -> None:
    """Two masters, overlapping registers: the last request to arrive wins, whoever sent it."""
    url = slc_url(paced="1")
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 32, 32)
        first, second = (
            (fc16(1, 40, [1111] * 4), fc6(2, 43, 9998)) if order == "fc16-first"
            else (fc6(2, 43, 9998), fc16(1, 40, [1111] * 4))
        )
        r1, w1 = await asyncio.open_connection(HOST, gw.port)
        r2, w2 = await asyncio.open_connection(HOST, gw.port)
        try:
            w1.write(first)
            await w1.drain()
            await asyncio.sleep(0.01)  # arrived; its first word is on the line (26 ms at 9600 baud)
            w2.write(second)
            replies = {**await read_replies(r1, 1), **await read_replies(r2, 1)}
        finally:
            w1.close()
            w2.close()
    assert replies[1][0] == 16 and replies[2][0] == 6, replies
    assert slc_holding(sim, 43) == (9998 if order == "fc16-first" else 1111)


async def test_many_pipelined_writes_to_one_register_end_with_the_last() -> None:
    url = slc_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 32, 32)
        connections = [await asyncio.open_connection(HOST, gw.port) for _ in range(3)]
        try:
            tid = 0
            for round_ in range(5):
                for _, writer in connections:
                    frames = b""
                    for _ in range(4):
                        tid += 1
                        frames += fc16(tid, 40, [tid] * 4) if tid % 2 else fc6(tid, 42, tid)
                    writer.write(frames)
                    await writer.drain()
                    await asyncio.sleep(0.002 * round_ + 0.005)  # so that the batches arrive in this order
            for reader, _ in connections:
                replies = await read_replies(reader, 20)
                assert all(pdu[0] in (6, 16) for pdu in replies.values()), replies
        finally:
            for _, writer in connections:
                writer.close()
    assert tid == 60
    assert slc_holding(sim, 42) == 60  # the last request to arrive (an FC6 to 42)
    assert [slc_holding(sim, a) for a in (40, 41, 43)] == [59] * 3  # the last FC16


# --------------------------------------------------------------------------------------------
# 3. Bounded queues


async def test_writes_beyond_the_per_connection_bound_answer_0x06_and_are_not_applied() -> None:
    url = slc_url(paced="1")
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    async with gateway(slc_link(url, write_queue_per_client=2)) as gw:
        await until_ready(gw, 32, 32)
        reader, writer = await asyncio.open_connection(HOST, gw.port)
        try:
            writer.write(b"".join(fc6(tid, 40, 100 + tid) for tid in range(8)))
            replies = await read_replies(reader, 8)
        finally:
            writer.close()
    busy = sorted(tid for tid, pdu in replies.items() if pdu[0] == 0x86 and pdu[1] == SERVER_BUSY)
    done = sorted(tid for tid, pdu in replies.items() if pdu[0] == 6)
    assert busy and done and sorted(busy + done) == list(range(8)), replies
    assert [w[2] - 100 for w in word_writes(sim)] == done


# --------------------------------------------------------------------------------------------
# 4. Audit


async def test_every_write_is_audited_with_the_client(caplog: pytest.LogCaptureFixture) -> None:
    url = slc_url()
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 32, 32)
        caplog.set_level(logging.INFO, logger="gateway.audit")
        reader, writer = await asyncio.open_connection(HOST, gw.port)
        try:
            local = writer.get_extra_info("sockname")
            writer.write(fc6(1, 40, 1234))
            assert (await read_replies(reader, 1))[1][0] == 6
            writer.write(fc16(2, 60, [1, 2, 3, 4]))
            assert (await read_replies(reader, 1))[2] == bytes((0x90, DEVICE_FAILURE))
            writer.write(struct.pack(">HHHBBHH", 3, 0, 6, 1, 5, 701, 0xFF00))
            assert (await read_replies(reader, 1))[3][0] == 5
        finally:
            writer.close()
    audit = [r for r in caplog.records if r.name == "gateway.audit"]
    assert [r.levelno for r in audit] == [logging.INFO] * 3, [r.getMessage() for r in audit]
    peer = f"{local[0]}:{local[1]}"
    lines = [r.getMessage() for r in audit]
    assert all(peer in line and "unit 1" in line for line in lines), lines
    assert "FC6 holding 40" in lines[0] and "ok" in lines[0], lines[0]
    assert "FC16 holding 60-63" in lines[1] and "0x04" in lines[1], lines[1]
    assert "FC5 coil 701" in lines[2] and "ok" in lines[2], lines[2]


# --------------------------------------------------------------------------------------------
# 3. Fair line time


async def flood(port: int, stop: asyncio.Event, in_flight: int = 16) -> dict[str, int]:
    """One connection keeping ``in_flight`` FC6 writes outstanding until ``stop`` (0x06 answers too)."""
    reader, writer = await asyncio.open_connection(HOST, port)
    outcome = {"ok": 0, "busy": 0, "late": 0, "other": 0}
    tid = 0
    try:
        for _ in range(in_flight):
            tid = (tid + 1) & 0xFFFF
            writer.write(fc6(tid, tid % 31, tid % 10000))  # accumulators of 901-931 (932 is protected)
        while not stop.is_set():
            pdu = (await read_replies(reader, 1)).popitem()[1]
            key = ("ok" if pdu[0] == 6 else "busy" if pdu[1:2] == bytes((SERVER_BUSY,))
                   else "late" if pdu[1:2] == bytes((TARGET_FAILED,)) else "other")
            outcome[key] += 1
            if key == "busy":
                await asyncio.sleep(0.005)  # a retry a little later, as a master does after 0x06
            tid = (tid + 1) & 0xFFFF
            writer.write(fc6(tid, tid % 31, tid % 10000))  # accumulators of 901-931 (932 is protected)
    finally:
        writer.close()
    return outcome


async def test_a_write_flood_leaves_the_fast_class_fresh() -> None:
    """16 writes in flight on a 9600-baud SLC 150: reads never answer 0x0B, and polls go on.

    Without a bound, writes starve the poller and every read answers 0x0B once ``stale_after``
    (5 s) has passed.  With the defaults (one write, then two polls) a fast round takes
    55 x (37.5 + 26 / 2) ms = 2.8 s plus its share of the slow class.  The flood runs 11 s, past
    the periodic slow scan (due 10 s after the first), which used to hold the fast class up
    for 65 reads at once.
    """
    url = slc_url(paced="1")
    sim = get_simulator(url)
    async with gateway(slc_link(url)) as gw:
        await until_ready(gw, 0, 64)
        async with connect(gw.port) as client, asyncio.timeout(10):
            while True:  # the whole first scan: the block of 951-982 is read last
                if not (await client.read_discrete_inputs(951, count=32, device_id=1)).isError():
                    break
                await asyncio.sleep(0.02)
        unit = gw.units[0]
        stop = asyncio.Event()
        flooder = asyncio.create_task(flood(gw.port, stop))
        codes: list[int | None] = []
        writes = 0
        scans = unit.poller.scans
        async with connect(gw.port) as client:
            loop = asyncio.get_running_loop()
            start = loop.time()
            end, limit = start + 11.0, start + 30.0
            # 11 s at least (past the periodic slow scan); on a loaded machine, until two whole fast scans are
            # done under the flood (a paced line's scan takes longer when the process waits for the CPU)
            while loop.time() < end or (unit.poller.scans - scans < 2 and loop.time() < limit):
                codes.append(exception_code(await client.read_holding_registers(0, count=32, device_id=1)))
                codes.append(exception_code(await client.read_discrete_inputs(701, count=64, device_id=1)))
                writes += not (await client.write_register(33, writes % 10000, device_id=1)).isError()
                await asyncio.sleep(0.1)
        stop.set()
        outcome = await flooder
        scans = unit.poller.scans - scans
        slow = [unit.cache.stamps[i] for i in unit.poller.slow]
    assert codes.count(TARGET_FAILED) == 0 and set(codes) == {None}, codes
    # the flood did reach the line; 16 writes in flight wait longer than write_timeout for it, so
    # many are answered 0x0B (withdrawn, or on the line with the outcome unknown)
    assert outcome["other"] == 0, outcome
    assert sum(1 for kind, _, _ in sim.applied_writes if kind == "word") > 20, outcome
    assert scans >= 2, scans  # whole fast scans completed during the flood
    assert max(slow) > start, "the periodic slow scan did not start during the flood"
    assert writes > 10
