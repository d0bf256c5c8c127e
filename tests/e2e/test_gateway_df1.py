"""Acceptance (issue 4): the gateway end to end against a simulated SLC 5/04 on a faulty DF1 link.

Real sockets on 127.0.0.1, the whole ``Gateway`` (Df1Driver, poller, cache, Df1Unit, Modbus
server) and two independent Modbus clients: pymodbus's ``AsyncModbusTcpClient`` and Debian's
``mbpoll`` run as a subprocess.  The controller is ``gateway.kinds.df1.sim.slc500`` with its ladder frozen
(``ladder=0``: memory changes only by writes) and these faults on the link: 1 in 10 frames
corrupted, 1 in 15 replies dropped (the command is executed), 1 in 10 ACKs withheld, 1 in 10
frames duplicated, noise before 1 in 10 outputs.

What SCADA must see, whatever the line does:

* a read returns the last value SCADA had acknowledged, or the value of a write that failed with
  0x0B and was in fact applied (the controller executed it, its reply was lost) - nothing else;
* every acknowledged write was applied exactly once (``sim.applied_writes``); a write answered
  with an exception was applied at most once;
* nothing hangs (``asyncio.timeout``).

Expected values come from the simulator's memory and its documented initial data table, not
from ``gateway.kinds.df1.plan``.  Without ``mbpoll`` its test is skipped, unless
``SLC_GATEWAY_REQUIRE_MBPOLL=1``, which makes it fail instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import re
import struct
import uuid
from collections import Counter
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlencode

import pytest
from modbus_support import connect, exception_code, mbpoll_path
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.sim import get_simulator

HOST = "127.0.0.1"
MAIN, READ_ONLY = 1, 2
ILLEGAL_ADDRESS, DEVICE_FAILURE, TARGET_FAILED = 0x02, 0x04, 0x0B
FAULTS = {"corrupt": 10, "drop": 15, "withhold_ack": 10, "duplicate": 10, "noise": 10}

# The map of unit MAIN (Modbus address -> SLC address), written out for the test.
N7_FIRST, N7_COUNT = 0, 100  # holding 0-99: N7:0-99
F8_FIRST, F8_COUNT = 200, 16  # holding 200-231: F8:0-15, float32 high word first
B3_BITS = 64  # coils 0-63: B3:0/0 - B3:3/15
INPUT_WORDS = 8  # input 0-7: I:1.0-7
HOLDING_OF_INPUTS = 150  # holding 150-151 are not mapped; input 150-151 are N7:50-51 (read only)
PAST_END = 300  # holding 300-303: N10:100-103, past the end of N10 (100 words in the simulator)
VALID_THEN_PAST_END = 310  # holding 310-317: N10:96-103, the first four valid


def map_entry(table: str, start: int, address: str, count: int, **keys: str) -> str:
    lines = ["[[link.map]]", f'table = "{table}"', f"start = {start}", f'address = "{address}"', f"count = {count}"]
    lines += [f'{key} = "{value}"' for key, value in keys.items()]
    return "\n".join(lines) + "\n"


def config_text(main_url: str, read_only_url: str) -> str:
    return (
        '[modbus]\nlisten = "127.0.0.1:0"\n\n'
        f'[[link]]\nname = "slc504"\nprotocol = "df1"\nport = "{main_url}"\nunit = {MAIN}\ntimeout = 0.05\n'
        + map_entry("holding", N7_FIRST, "N7:0", N7_COUNT)
        + map_entry("holding", F8_FIRST, "F8:0", F8_COUNT, type="float32")
        + map_entry("coil", 0, "B3:0/0", B3_BITS)
        + map_entry("input", 0, "I:1.0", INPUT_WORDS)
        + map_entry("input", HOLDING_OF_INPUTS, "N7:50", 2)
        + map_entry("discrete", 0, "T4:0/DN", 10)
        + map_entry("holding", PAST_END, "N10:100", 4)
        + map_entry("holding", VALID_THEN_PAST_END, "N10:96", 8)
        + f'\n[[link]]\nname = "read-only"\nprotocol = "df1"\nport = "{read_only_url}"\nunit = {READ_ONLY}\n'
        "read_only = true\n"
        + map_entry("holding", 0, "N7:0", 10)
        + map_entry("coil", 0, "B3:0/0", 16)
    )


@dataclass
class Plant:
    gw: Gateway
    sim: Slc500Simulator  # behind unit MAIN, on the faulty link
    read_only_sim: Slc500Simulator

    @property
    def port(self) -> int:
        return self.gw.port


pytestmark = pytest.mark.usefixtures("forget_simulators")


def sim_url(**options: Any) -> str:
    return "sim://slc504?" + urlencode({"ladder": "0", **options, "instance": uuid.uuid4().hex})


@pytest.fixture
async def plant() -> AsyncIterator[Plant]:
    main_url = sim_url(**FAULTS, seed=4)
    read_only_url = sim_url(seed=5)
    sim, read_only_sim = get_simulator(main_url), get_simulator(read_only_url)
    assert isinstance(sim, Slc500Simulator) and isinstance(read_only_sim, Slc500Simulator)
    async with Gateway(parse_config(config_text(main_url, read_only_url))) as gw:
        async with connect(gw.port, reply_timeout=5) as client:
            await until_ready(client)
        yield Plant(gw, sim, read_only_sim)


# --------------------------------------------------------------------------------------------
# Modbus helpers


async def until_ready(client: AsyncModbusTcpClient, deadline: float = 10.0) -> None:
    """Every block of both units read at least once."""
    async with asyncio.timeout(deadline):
        while True:
            replies = [
                await client.read_holding_registers(N7_FIRST, count=N7_COUNT, device_id=MAIN),
                await client.read_holding_registers(F8_FIRST, count=2 * F8_COUNT, device_id=MAIN),
                await client.read_coils(0, count=B3_BITS, device_id=MAIN),
                await client.read_input_registers(0, count=INPUT_WORDS, device_id=MAIN),
                await client.read_discrete_inputs(0, count=10, device_id=MAIN),
                await client.read_holding_registers(0, count=10, device_id=READ_ONLY),
            ]
            if not any(reply.isError() for reply in replies):
                return
            await asyncio.sleep(0.02)


def float_registers(value: float) -> list[int]:
    raw = struct.unpack("<I", struct.pack("<f", value))[0]
    return [raw >> 16, raw & 0xFFFF]  # high word first


def float_bits(sim: Slc500Simulator, element: int) -> int:
    raw: int = struct.unpack("<I", struct.pack("<f", sim.float_value("F8", element)))[0]
    return raw


# --------------------------------------------------------------------------------------------
# The model SCADA may rely on


@dataclass
class Model:
    """Per Modbus point, the values a read may return; the writes by outcome."""

    sim: Slc500Simulator
    registers: dict[int, set[int]] = field(default_factory=dict)  # N7 holding -> allowed values
    floats: dict[int, set[int]] = field(default_factory=dict)  # F8 element -> allowed raw 32-bit values
    coils: dict[int, set[bool]] = field(default_factory=dict)
    acked: list[tuple[str, str, bytes]] = field(default_factory=list)
    failed: list[tuple[str, str, bytes]] = field(default_factory=list)
    coil_acked: Counter[int] = field(default_factory=Counter)  # per B3 word
    coil_failures: Counter[int] = field(default_factory=Counter)
    coil_failed_applied: Counter[int] = field(default_factory=Counter)
    exceptions: Counter[int] = field(default_factory=Counter)
    reads = 0

    def __post_init__(self) -> None:
        sim = self.sim
        self.registers = {a: {sim.word("N7", a)} for a in range(N7_COUNT)}
        self.floats = {k: {float_bits(sim, k)} for k in range(F8_COUNT)}
        self.coils = {n: {bool(sim.word("B3", n // 16) >> n % 16 & 1)} for n in range(B3_BITS)}

    def word_written(self, address: int, value: int, ok: bool) -> None:
        entry = ("write", f"N7:{address}", value.to_bytes(2, "little"))
        if ok:
            self.acked.append(entry)
            self.registers[address] = {value}
            return
        self.failed.append(entry)
        if self.sim.word("N7", address) == value:  # applied: its reply was lost (unique values)
            self.registers[address].add(value)

    def words_written(self, first: int, values: list[int], ok: bool) -> None:
        """An FC16 of consecutive N7 words: one command, so applied whole or not at all."""
        entry = ("write", f"N7:{first}", b"".join(v.to_bytes(2, "little") for v in values))
        if ok:
            self.acked.append(entry)
            for k, value in enumerate(values):
                self.registers[first + k] = {value}
            return
        self.failed.append(entry)
        if all(self.sim.word("N7", first + k) == value for k, value in enumerate(values)):
            for k, value in enumerate(values):
                self.registers[first + k].add(value)

    def float_written(self, element: int, raw: int, ok: bool) -> None:
        entry = ("write", f"F8:{element}", struct.pack("<I", raw))
        if ok:
            self.acked.append(entry)
            self.floats[element] = {raw}
            return
        self.failed.append(entry)
        if float_bits(self.sim, element) == raw:
            self.floats[element].add(raw)

    def coil_written(self, coil: int, value: bool, ok: bool) -> None:
        """Coil writes always toggle, so whether a failed one was applied shows in the bit."""
        word = coil // 16
        if ok:
            self.coil_acked[word] += 1
            self.coils[coil] = {value}
            return
        self.coil_failures[word] += 1
        if self.known_coil(coil) == value:
            self.coil_failed_applied[word] += 1
            self.coils[coil].add(value)

    def known_coil(self, coil: int) -> bool:
        """The coil's value in the controller (after a failed write the simulator says which)."""
        return bool(self.sim.word("B3", coil // 16) >> coil % 16 & 1)


async def worker(
    client: AsyncModbusTcpClient, model: Model, number: int, operations: int, values: Iterator[int]
) -> None:
    """One SCADA client, sequential, owning N7 words, F8 floats and B3 bits of its own."""
    rng = random.Random(number)
    own_words = list(range(number * 25, number * 25 + 25))
    own_floats = list(range(number * 4, number * 4 + 4))
    own_coils = list(range(number * 16, number * 16 + 16))  # B3:number, a word of its own
    for _ in range(operations):
        op = rng.random()
        if op < 0.30:  # FC3: a run of N7 words
            first = rng.choice(own_words)
            count = rng.randint(1, own_words[-1] - first + 1)
            reply = await client.read_holding_registers(N7_FIRST + first, count=count, device_id=MAIN)
            assert not reply.isError(), reply
            for k, value in enumerate(reply.registers):
                assert value in model.registers[first + k], (first + k, value, model.registers[first + k])
            model.reads += 1
        elif op < 0.45:  # FC3: floats
            element = rng.choice(own_floats)
            count = rng.randint(1, own_floats[-1] - element + 1)
            reply = await client.read_holding_registers(F8_FIRST + 2 * element, count=2 * count, device_id=MAIN)
            assert not reply.isError(), reply
            for k in range(count):
                high, low = reply.registers[2 * k : 2 * k + 2]
                assert (high << 16 | low) in model.floats[element + k], (element + k, high, low)
            model.reads += 1
        elif op < 0.50:  # FC1: coils
            reply = await client.read_coils(own_coils[0], count=16, device_id=MAIN)
            assert not reply.isError(), reply
            for k, bit in enumerate(reply.bits[:16]):
                assert bit in model.coils[own_coils[k]], (own_coils[k], bit)
            model.reads += 1
        elif op < 0.70:  # FC6: one N7 word
            address, value = rng.choice(own_words), next(values)
            reply = await client.write_register(N7_FIRST + address, value, device_id=MAIN)
            code = exception_code(reply)
            model.exceptions[code or 0] += 1
            model.word_written(address, value, code is None)
        elif op < 0.80:  # FC16: two or three N7 words
            first = rng.choice(own_words[:-2])
            new = [next(values) for _ in range(rng.randint(2, 3))]
            reply = await client.write_registers(N7_FIRST + first, new, device_id=MAIN)
            code = exception_code(reply)
            model.exceptions[code or 0] += 1
            model.words_written(first, new, code is None)  # one typed logical write of all the words
        elif op < 0.88:  # FC16: a float, both of its registers
            element = rng.choice(own_floats)
            number_written = next(values) + 0.5
            registers = float_registers(number_written)
            reply = await client.write_registers(F8_FIRST + 2 * element, registers, device_id=MAIN)
            code = exception_code(reply)
            model.exceptions[code or 0] += 1
            model.float_written(element, registers[0] << 16 | registers[1], code is None)
        else:  # FC5: toggle a B3 bit
            coil = rng.choice(own_coils)
            value = not model.known_coil(coil)
            reply = await client.write_coil(coil, value, device_id=MAIN)
            code = exception_code(reply)
            model.exceptions[code or 0] += 1
            model.coil_written(coil, value, code is None)


# ============================================================================================
# The acceptance test


WORKERS, OPERATIONS = 4, 500  # 2,000 Modbus requests


async def test_2000_requests_through_a_faulty_link_values_right_writes_exactly_once(plant: Plant) -> None:
    sim = plant.sim
    model = Model(sim)
    values = iter(range(1000, 60000))  # unique values: each write is recognisable in applied_writes
    async with asyncio.timeout(60), contextlib.AsyncExitStack() as stack:
        clients = [await stack.enter_async_context(connect(plant.port, reply_timeout=5)) for _ in range(WORKERS)]
        await asyncio.gather(*(worker(client, model, n, OPERATIONS, values) for n, client in enumerate(clients)))

    # Writes: only successes and 0x0B (the outcome of a write whose reply was lost is unknown).
    assert set(model.exceptions) <= {0, TARGET_FAILED}, model.exceptions
    applied = Counter(entry for entry in sim.applied_writes if entry[0] == "write")
    for entry in model.acked:
        assert applied[entry] == 1, (entry, applied[entry])
    for entry in model.failed:
        assert applied[entry] <= 1, (entry, applied[entry])
    assert set(applied) <= set(model.acked) | set(model.failed)
    masked = Counter(entry[1] for entry in sim.applied_writes if entry[0] == "masked_write")
    for word in range(B3_BITS // 16):
        # each acknowledged coil write once, plus the failed ones the bit shows were applied
        assert masked[f"B3:{word}"] == model.coil_acked[word] + model.coil_failed_applied[word], word
        assert model.coil_failed_applied[word] <= model.coil_failures[word]
    assert set(masked) <= {f"B3:{word}" for word in range(B3_BITS // 16)}
    # The controller ends with what SCADA was told, or a failed write that was applied.
    for address in range(N7_COUNT):
        assert sim.word("N7", address) in model.registers[address], address
    for element in range(F8_COUNT):
        assert float_bits(sim, element) in model.floats[element], element
    for coil in range(B3_BITS):
        assert model.known_coil(coil) in model.coils[coil], coil

    # The faults did happen, and the run exercised what it claims to.
    total = sum(model.exceptions.values()) + model.reads
    assert total == WORKERS * OPERATIONS
    assert model.reads > 800 and len(model.acked) > 500
    counters = sim.counters
    assert counters.corrupted > 50 and counters.dropped > 30 and counters.withheld_acks > 50
    assert counters.duplicates > 0 and counters.noise > 0
    driver = plant.gw.units[0].driver
    assert driver.counters.crc_errors > 0 and driver.counters.retries_by_kind.get("enq", 0) > 0


# ============================================================================================
# mbpoll, through the same faulty link


async def mbpoll_read(port: int, unit: int, kind: str, address: int, count: int) -> dict[int, int]:
    """``mbpoll -1`` read of ``count`` values from protocol address ``address`` (``-0``: 0-based
    references); the values keyed by protocol address."""
    command = [mbpoll_path(), "-m", "tcp", "-p", str(port), "-a", str(unit), "-1", "-o", "3", "-0",
               "-t", kind, "-r", str(address), "-c", str(count), HOST]
    process = await asyncio.create_subprocess_exec(
        *command, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    async with asyncio.timeout(10):
        stdout, stderr = await process.communicate()
    text = stdout.decode(errors="replace")
    assert process.returncode == 0, stderr.decode(errors="replace") + text
    values = {int(m[1]): int(m[2], 0) & 0xFFFF
              for m in re.finditer(r"^\[(\d+)\]:\s+(-?(?:0x)?[0-9A-Fa-f]+)\s*$", text, re.MULTILINE)}
    assert sorted(values) == list(range(address, address + count)), text
    return values


async def test_mbpoll_reads_the_simulators_values_through_the_faulty_link(plant: Plant) -> None:
    sim = plant.sim
    for _ in range(3):
        assert await mbpoll_read(plant.port, MAIN, "4", 0, 50) == {a: sim.word("N7", a) for a in range(50)}
        assert await mbpoll_read(plant.port, MAIN, "3", 0, INPUT_WORDS) == {
            w: sim.word("I1", 1, w) for w in range(INPUT_WORDS)}  # I:1.w = 0x1100 + w
        floats = await mbpoll_read(plant.port, MAIN, "4", F8_FIRST, 8)
        for k in range(4):
            assert (floats[F8_FIRST + 2 * k] << 16 | floats[F8_FIRST + 2 * k + 1]) == float_bits(sim, k)
            assert sim.float_value("F8", k) == 1.5 * k
        bits = await mbpoll_read(plant.port, MAIN, "0", 0, 32)
        assert bits == {n: sim.word("B3", n // 16) >> n % 16 & 1 for n in range(32)}
    assert sim.counters.corrupted + sim.counters.dropped + sim.counters.withheld_acks > 0


# ============================================================================================
# Exceptions


async def test_unmapped_addresses_answer_0x02(plant: Plant) -> None:
    async with connect(plant.port, reply_timeout=5) as client:
        assert exception_code(await client.read_holding_registers(100, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_holding_registers(150, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_register(120, 1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_coils(64, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(64, True, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_input_registers(8, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
    assert plant.sim.applied_writes == []


async def test_a_read_running_off_the_end_of_a_mapped_run_answers_0x02(plant: Plant) -> None:
    async with connect(plant.port, reply_timeout=5) as client:
        # input 0-7 are I:1.0-7; 8-149 are not mapped; 150-151 are N7:50-51
        reply = await client.read_input_registers(INPUT_WORDS - 2, count=4, device_id=MAIN)
        assert exception_code(reply) == ILLEGAL_ADDRESS, reply.registers
        # holding 98-99 are N7:98-99; 100-199 are not mapped; 200- are F8 floats
        assert exception_code(await client.read_holding_registers(98, count=4, device_id=MAIN)) == ILLEGAL_ADDRESS


async def test_writes_to_read_only_points_answer_0x02(plant: Plant) -> None:
    async with connect(plant.port, reply_timeout=5) as client:
        # input registers 150-151 are N7:50-51; holding 150 is not mapped: the input table is not writable
        assert await client.read_input_registers(HOLDING_OF_INPUTS, count=2, device_id=MAIN) is not None
        assert exception_code(await client.write_register(HOLDING_OF_INPUTS, 7, device_id=MAIN)) == ILLEGAL_ADDRESS
        # discrete inputs (T4:n/DN) are not coils
        assert exception_code(await client.write_coil(70, True, device_id=MAIN)) == ILLEGAL_ADDRESS
        # a read_only link refuses every write, holding and coil
        assert (await client.read_holding_registers(0, count=10, device_id=READ_ONLY)).registers == list(range(10))
        assert exception_code(await client.write_register(0, 7, device_id=READ_ONLY)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_registers(0, [7, 8], device_id=READ_ONLY)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(0, True, device_id=READ_ONLY)) == ILLEGAL_ADDRESS
    assert plant.sim.applied_writes == []
    assert plant.read_only_sim.applied_writes == []


async def test_pccc_address_error_reads_never_return_data(plant: Plant) -> None:
    """Holding 300-303 map N10:100-103, past the end of the simulator's N10 (100 words): the
    controller refuses every read (STS F0, EXT STS 06).  The gateway never invents values."""
    async with connect(plant.port, reply_timeout=5) as client:
        for address in (PAST_END, PAST_END + 3, VALID_THEN_PAST_END + 5):
            code = exception_code(await client.read_holding_registers(address, count=1, device_id=MAIN))
            assert code in (ILLEGAL_ADDRESS, TARGET_FAILED), (address, code)
    assert plant.gw.units[0].poller.block_errors > 0


async def test_write_to_an_address_the_controller_refuses_answers_0x02(plant: Plant) -> None:
    async with connect(plant.port, reply_timeout=5) as client:
        code = exception_code(await client.write_register(PAST_END, 7, device_id=MAIN))  # N10:100: F0/06
    assert plant.sim.applied_writes == []
    assert code == ILLEGAL_ADDRESS


async def test_read_of_an_address_the_controller_refuses_answers_0x02(plant: Plant) -> None:
    async with connect(plant.port, reply_timeout=5) as client:
        code = exception_code(await client.read_holding_registers(PAST_END, count=4, device_id=MAIN))
    assert code == ILLEGAL_ADDRESS


# ============================================================================================
# The verdict of a write whose reply never came: read back, success only when proved


@contextlib.asynccontextmanager
async def gateway_with(**faults: Any) -> AsyncIterator[tuple[Gateway, Slc500Simulator]]:
    url = sim_url(**faults, seed=6)
    sim = get_simulator(url)
    assert isinstance(sim, Slc500Simulator)
    text = (
        '[modbus]\nlisten = "127.0.0.1:0"\n\n'
        f'[[link]]\nname = "slc504"\nprotocol = "df1"\nport = "{url}"\nunit = {MAIN}\ntimeout = 0.05\n'
        + map_entry("holding", N7_FIRST, "N7:0", 20)
        + map_entry("coil", 0, "B3:0/0", 16)
    )
    async with Gateway(parse_config(text)) as gw:
        yield gw, sim


async def test_a_write_whose_reply_was_lost_after_it_ran_is_a_success() -> None:
    """Every write's reply is lost after execution: the read-back proves it, SCADA gets success."""
    async with gateway_with(drop=1, faults_on="writes") as (gw, sim), connect(gw.port, reply_timeout=5) as client:
        async with asyncio.timeout(20):
            assert exception_code(await client.write_register(7, 4321, device_id=MAIN)) is None
            assert exception_code(await client.write_coil(3, True, device_id=MAIN)) is None
            assert exception_code(await client.write_registers(10, [11, 12], device_id=MAIN)) is None
        assert sim.word("N7", 7) == 4321 and sim.word("B3", 0) & 0x0008
        assert [sim.word("N7", k) for k in (10, 11)] == [11, 12]
        # each applied once (a two-register write is two word writes), none resent
        writes = Counter(kind for kind, _, _ in sim.applied_writes)
        assert writes["masked_write"] == 1 and writes["write"] in (2, 3)
        assert sim.counters.dropped == len(sim.applied_writes)
        assert len(set(sim.applied_writes)) == len(sim.applied_writes)


async def test_a_write_the_controller_never_ran_is_0x0b_and_the_value_is_unchanged() -> None:
    """Every write frame is lost on the way in; the ENQ gets the previous frame's ACK: 0x0B.

    Where the read-back shows the value the gateway read before the write, the write was proven not
    applied and is sent again while ``write_timeout`` lasts (issue 43, 6b): every copy is lost here too."""
    async with gateway_with(lose_in=1, faults_on="writes") as (gw, sim), connect(gw.port, reply_timeout=5) as client:
        async with asyncio.timeout(20):
            assert exception_code(await client.write_register(7, 4321, device_id=MAIN)) == TARGET_FAILED
            assert exception_code(await client.write_coil(3, True, device_id=MAIN)) == TARGET_FAILED
            await gw.units[0].writes.drain()
        assert sim.applied_writes == []
        assert sim.word("N7", 7) == 7 and not sim.word("B3", 0) & 0x0008
        # each write's first frame, and one more for every time it was sent again
        assert sim.counters.lost_in == 2 + gw.units[0].write_tally.retried
