"""Acceptance (issue 12): a DF1 half-duplex multi-drop line end to end, under BCC and CRC.

The multi-drop simulator (``gateway.kinds.df1.sim.df1_multidrop``) is served over TCP (a device server in raw
mode) and the whole ``Gateway`` (config text -> ``build_df1`` -> one ``Df1HalfDuplexLine`` master per
port, a unit per station, pollers, Modbus TCP server) is driven with pymodbus:

* line A: SLC 5/04 stations 1, 2, 3 live and station 4 configured but absent (``dead=4``);
* line B: one PLC-5 station 5 (``model=plc5``; its ``typed_logical`` variant ``refuse`` under BCC,
  ``accept`` under CRC: the gateway must use word range commands under both);
* both lines: 1 in 6 slave message frames corrupted (``corrupt=6``) and 1 in 10 master frames or
  symbols heard by no station (``ignore=10``).

What SCADA must see:

* every unit reads its own station's values (each station's data table is distinct), never another's;
* every acknowledged write (FC6, FC16, FC5) was applied exactly once on its own station
  (``applied_writes``), nothing on the others, nothing on the absent one;
* the absent station's unit answers 0x0B - reads at once, writes fast once the station is demoted,
  which happens within a few seconds of the start;
* the three live units stay fresh while the absent one is polled: over a polling window, at least
  90 % of their reads are answered with data (not 0x0B).  ``stale_after`` is 1 s here (default 5 s)
  so that a line held up for a second would show; ``demote_after`` is the default (5, see ``TIMING``).

The share and the data ages are printed (``pytest -s``) for the report:
``PYTHONPATH=$PWD python -m pytest -q -s tests/e2e/test_half_duplex_acceptance.py``.
"""

from __future__ import annotations

import asyncio
import statistics
import time
from collections import Counter
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from modbus_support import connect, exception_code
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_half_models import create_line
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.sim.serve import close_tcp, serve_tcp

HOST = "127.0.0.1"
LIVE, ABSENT, PLC5 = (1, 2, 3), 4, 5
TARGET_FAILED = 0x0B
WORDS = 10  # holding 0-9: N7:0-9
COILS = 16  # coils 0-15: B3:0/0-15 (SLC), B3/0-15 (PLC-5)
WINDOW = 5.0  # seconds of the freshness window
FAST = 0.5  # an answer of the absent unit within this is "at once" (a demoted station fails without a poll)
FAULTS = {"corrupt": "6", "ignore": "10"}
#: station keys of every link (seconds); the line keys must agree across a line.  ``demote_after`` is
#: left at its default, 5: with 1 in 10 master frames unheard, 3 answerless polls in a row happen to a live
#: station every few seconds of continuous polling, and a falsely demoted station is stale until its
#: next answered slow poll (2 s or more): measured over 8 s windows, 49-100 % fresh with 3 (seeds 1
#: and 2 below fail the bar), 99-100 % with 5; an absent station is then demoted after 5 x 0.1 s.
TIMING = {
    "timeout": 0.5, "poll_timeout": 0.1, "ack_timeout": 0.1, "poll_interval": 0.5, "slow_poll_interval": 2.0,
    "stale_after": 1.0,
}


def initial_word(station: int, k: int) -> int:
    return 1000 * station + k


def initial_bits(station: int) -> int:
    return (0x0101 * station) ^ 0x8000


def link_text(name: str, unit: int, port: str, station: int, checksum: str, **keys: str) -> str:
    lines = [
        "[[link]]", f'name = "{name}"', 'protocol = "df1"', f'port = "{port}"', 'duplex = "half"',
        f"station = {station}", f"unit = {unit}", f'checksum = "{checksum}"',
    ]
    lines += [f"{key} = {value}" for key, value in TIMING.items()]
    lines += [f'{key} = "{value}"' for key, value in keys.items()]
    bit = "B3/0" if keys.get("processor") == "plc5" else "B3:0/0"
    lines += ["[[link.map]]", 'table = "holding"', "start = 0", 'address = "N7:0"', f"count = {WORDS}"]
    lines += ["[[link.map]]", 'table = "coil"', "start = 0", f'address = "{bit}"', f"count = {COILS}"]
    return "\n".join(lines) + "\n\n"


@dataclass
class Plant:
    gw: Gateway
    slc: MultidropLine
    plc5: MultidropLine
    started: float
    #: the values each station must hold (station -> holding / coils)
    words: dict[int, list[int]] = field(default_factory=dict)
    bits: dict[int, list[bool]] = field(default_factory=dict)
    acked: Counter[int] = field(default_factory=Counter)  # acknowledged writes per station
    failed: Counter[int] = field(default_factory=Counter)  # writes answered with an exception

    def controller(self, station: int) -> Any:
        line = self.plc5 if station == PLC5 else self.slc
        return line.controllers[station]


@pytest.fixture(params=[("bcc", "refuse", 2), ("crc", "accept", 1)], ids=["bcc", "crc"])
async def plant(request: pytest.FixtureRequest) -> AsyncIterator[Plant]:
    checksum, typed_logical, seed = request.param
    slc = create_line({"stations": "1,2,3,4", "dead": "4", "checksum": checksum, "seed": str(seed), **FAULTS},
                      ladder=False)
    plc5 = create_line({"stations": "5", "model": "plc5", "checksum": checksum, "seed": "4", **FAULTS},
                       ladder=False, variants={"typed_logical": typed_logical})
    for line in (slc, plc5):
        for station, controller in line.controllers.items():
            for k in range(WORDS):
                controller.set_word("N7", k, initial_word(station, k))
            controller.set_word("B3", 0, initial_bits(station))
    servers = [await serve_tcp(slc, HOST, 0), await serve_tcp(plc5, HOST, 0)]
    a, b = (f"socket://{HOST}:{server.sockets[0].getsockname()[1]}" for server in servers)
    text = '[modbus]\nlisten = "127.0.0.1:0"\n\n'
    text += "".join(link_text(f"slc-{n}", n, a, n, checksum) for n in (*LIVE, ABSENT))
    text += link_text("plc5", PLC5, b, PLC5, checksum, processor="plc5")
    started = time.monotonic()
    try:
        async with Gateway(parse_config(text)) as gw:
            assert sum(isinstance(r, Df1HalfDuplexLine) for r in gw.runners) == 2  # one master per line
            plant = Plant(gw, slc, plc5, started)
            for station in (*LIVE, PLC5):
                plant.words[station] = [initial_word(station, k) for k in range(WORDS)]
                plant.bits[station] = [bool(initial_bits(station) >> k & 1) for k in range(COILS)]
            yield plant
    finally:
        for server in servers:
            await close_tcp(server)


async def read_unit(client: AsyncModbusTcpClient, unit: int) -> tuple[list[int], list[bool]] | int:
    """(holding, coils) of ``unit``, or the exception code of the first that failed."""
    words = await client.read_holding_registers(0, count=WORDS, device_id=unit)
    if words.isError():
        return int(words.exception_code)
    bits = await client.read_coils(0, count=COILS, device_id=unit)
    if bits.isError():
        return int(bits.exception_code)
    return list(words.registers), list(bits.bits[:COILS])


async def until_ready(client: AsyncModbusTcpClient, plant: Plant) -> None:
    async with asyncio.timeout(10):
        while True:
            if not any([isinstance(await read_unit(client, unit), int) for unit in (*LIVE, PLC5)]):
                return
            await asyncio.sleep(0.05)


def check_values(plant: Plant, unit: int, got: tuple[list[int], list[bool]]) -> None:
    words, bits = got
    assert words == plant.words[unit], f"unit {unit} read {words}, its station holds {plant.words[unit]}"
    assert bits == plant.bits[unit], f"unit {unit} coils {bits}, its station holds {plant.bits[unit]}"


async def absent_unit_answers_0x0b(client: AsyncModbusTcpClient, plant: Plant) -> tuple[float, float]:
    """Writes to the absent unit until they fail fast; (seconds from start to demotion, slowest fast answer)."""
    demoted_at = None
    fast: list[float] = []
    async with asyncio.timeout(8):
        while len(fast) < 5:
            t0 = time.monotonic()
            reply = await client.write_register(0, 4242, device_id=ABSENT)
            took = time.monotonic() - t0
            assert exception_code(reply) == TARGET_FAILED
            if took < FAST:
                demoted_at = demoted_at or time.monotonic() - plant.started
                fast.append(took)
            t0 = time.monotonic()
            read = await client.read_holding_registers(0, count=WORDS, device_id=ABSENT)
            assert exception_code(read) == TARGET_FAILED and time.monotonic() - t0 < FAST
    assert demoted_at is not None
    return demoted_at, max(fast)


async def freshness_window(client: AsyncModbusTcpClient, plant: Plant) -> dict[int, tuple[int, int, float, float]]:
    """Reads of the live units for WINDOW seconds; per unit (reads, 0x0B answers, median / max data age)."""
    reads: Counter[int] = Counter()
    stale: Counter[int] = Counter()
    ages: dict[int, list[float]] = {unit: [] for unit in LIVE}
    units = {unit.unit_id: unit for unit in plant.gw.units}
    loop = asyncio.get_running_loop()
    end = time.monotonic() + WINDOW
    absent_writes = 0
    while time.monotonic() < end:
        for unit in LIVE:
            got = await read_unit(client, unit)
            reads[unit] += 1
            if isinstance(got, int):
                assert got == TARGET_FAILED, f"unit {unit}: exception {got:#x}"
                stale[unit] += 1
            else:
                check_values(plant, unit, got)
            ages[unit].append(units[unit].cache.oldest_fast_age(loop.time()))
        if reads[LIVE[0]] % 10 == 0:  # the absent unit is written to meanwhile: it must not hold the others up
            reply = await client.write_register(0, 4242, device_id=ABSENT)
            assert exception_code(reply) == TARGET_FAILED
            absent_writes += 1
        await asyncio.sleep(0.01)
    assert absent_writes > 0
    return {u: (reads[u], stale[u], statistics.median(ages[u]), max(ages[u])) for u in LIVE}


async def write_and_check(client: AsyncModbusTcpClient, plant: Plant, unit: int, rounds: int) -> None:
    """FC6, FC16 and FC5 on ``unit``: values unique to the unit and round (so a misdelivery shows)."""
    for r in range(rounds):
        base = 10000 + 1000 * unit + 100 * r
        writes: list[tuple[str, Any]] = [
            ("fc6", (r % WORDS, base + 1)),
            ("fc16", (3, [base + 2, base + 3, base + 4])),
            ("fc5", (r % COILS, not plant.bits[unit][r % COILS])),
        ]
        for kind, (address, value) in writes:
            if kind == "fc6":
                reply = await client.write_register(address, value, device_id=unit)
            elif kind == "fc16":
                reply = await client.write_registers(address, value, device_id=unit)
            else:
                reply = await client.write_coil(address, value, device_id=unit)
            if reply.isError():
                # its outcome may be unknown (0x0B): applied at most once, never elsewhere
                assert exception_code(reply) == TARGET_FAILED
                plant.failed[unit] += 1
                resync(plant, unit)
                continue
            plant.acked[unit] += 1
            if kind == "fc6":
                plant.words[unit][address] = value
            elif kind == "fc16":
                plant.words[unit][address : address + len(value)] = value
            else:
                plant.bits[unit][address] = value


def resync(plant: Plant, unit: int) -> None:
    """After a write with an unknown outcome: the station's memory is the truth (it was applied or not)."""
    controller = plant.controller(unit)
    plant.words[unit] = [controller.word("N7", k) for k in range(WORDS)]
    word = controller.word("B3", 0)
    plant.bits[unit] = [bool(word >> k & 1) for k in range(COILS)]


def check_writes(plant: Plant) -> None:
    for station in (*LIVE, PLC5):
        controller = plant.controller(station)
        assert [controller.word("N7", k) for k in range(WORDS)] == plant.words[station]
        assert [bool(controller.word("B3", 0) >> k & 1) for k in range(COILS)] == plant.bits[station]
        applied = controller.applied_writes
        # exactly once: one applied command per acknowledged write (failed ones at most once)
        assert plant.acked[station] <= len(applied) <= plant.acked[station] + plant.failed[station], applied
        for kind, _, data in applied:  # the values were unique to the station: nothing of another's landed here
            if kind in ("write", "word_range_write"):
                value = int.from_bytes(data[:2], "little")
                assert value < 10000 or (value - 10000) // 1000 == station, (station, applied)
        if station == PLC5:  # word range write / read-modify-write, never SLC typed logical commands
            assert {kind for kind, _, _ in applied} <= {"word_range_write", "read_modify_write"}, applied
            assert {kind for kind, _, _ in applied} == {"word_range_write", "read_modify_write"}
    assert plant.controller(ABSENT).applied_writes == []


async def test_half_duplex_line_acceptance(plant: Plant) -> None:
    async with connect(plant.gw.port, reply_timeout=5) as client:
        demoted_at, slowest = await absent_unit_answers_0x0b(client, plant)
        await until_ready(client, plant)
        for unit in (*LIVE, PLC5):
            got = await read_unit(client, unit)
            assert not isinstance(got, int)
            check_values(plant, unit, got)
        fresh = await freshness_window(client, plant)
        for unit in (*LIVE, PLC5):
            await write_and_check(client, plant, unit, rounds=4)
        await asyncio.sleep(0.5)  # a poll after the writes: reads show the written values
        for unit in (*LIVE, PLC5):
            got = await read_unit(client, unit)
            assert not isinstance(got, int)
            check_values(plant, unit, got)
    check_writes(plant)
    counters = plant.slc.counters
    print(f"\nabsent unit: demoted {demoted_at:.2f} s after start, then 0x0B within {slowest * 1000:.1f} ms")
    print(f"line A faults: corrupted {counters.corrupted}, ignored {counters.ignored}; "
          f"writes acked {dict(plant.acked)}, failed {dict(plant.failed)}")
    for unit, (reads, stale, median_age, max_age) in fresh.items():
        share = 1 - stale / reads
        print(f"unit {unit}: {reads} reads, {stale} x 0x0B, {share:.1%} fresh; data age median "
              f"{median_age * 1000:.0f} ms, max {max_age * 1000:.0f} ms")
        assert share >= 0.9, f"unit {unit}: only {share:.1%} of {reads} reads fresh"
    assert demoted_at < 5.0
    assert counters.corrupted > 0 and counters.ignored > 0  # the faults were on
