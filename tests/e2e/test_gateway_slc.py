"""End to end: the gateway against simulated SLC 150s, as SCADA sees it.

Real sockets on 127.0.0.1, the whole ``Gateway`` (driver, poller, cache, unit, Modbus server), and
two independent Modbus clients: pymodbus's ``AsyncModbusTcpClient`` and Debian's ``mbpoll`` (a
libmodbus program) run as a subprocess.  Each controller is a simulator reached either in-process
(``sim://``) or over TCP (``serve_tcp`` + ``socket://``, as a serial device server would be).

Expected values are computed here from the simulator's memory with the manual's tables ("The
Memory Map", "User Address to Controller Address Table"), independently of
``gateway.modbus.mapping``.  The ladder is frozen (``ladder=0``) so memory changes only by writes.

Without ``mbpoll`` its tests are skipped, unless ``SLC_GATEWAY_REQUIRE_MBPOLL=1`` (CI), which makes
them fail instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import re
import struct
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlencode

import pytest
from modbus_support import connect, exception_code, mbpoll_path
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.sim import create_simulator, get_simulator
from gateway.sim.serve import serve_tcp
from tests.net import mbap

HOST = "127.0.0.1"
MAIN, READ_ONLY, SILENT, LIMITED = 1, 2, 3, 4  # the unit ids of the plant fixture
UNKNOWN_UNIT = 9

ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE, PATH_UNAVAILABLE, TARGET_FAILED = 0x02, 0x03, 0x04, 0x0A, 0x0B
#: libmodbus's text for each exception code, as mbpoll prints it
MBPOLL_TEXT = {
    ILLEGAL_ADDRESS: "Illegal data address",
    ILLEGAL_VALUE: "Illegal data value",
    DEVICE_FAILURE: "Slave device or server failure",
    PATH_UNAVAILABLE: "Gateway path unavailable",
    TARGET_FAILED: "Target device failed to respond",
}

STATUS_BASE = 1000
STATUS_COUNT = 12  # 1000-1011 (docs/reference/status-block.md)


# --------------------------------------------------------------------------------------------
# The manual's map, written out again for the test (not imported from the code under test)

#: discrete inputs: contiguous runs of user bit addresses (inputs g01-g10 then outputs g11-g18)
DISCRETE_RUNS = [(g * 100 + 1, g * 100 + 18) for g in range(7)] + [(701, 876), (901, 932), (951, 982)]
COIL_RUN = (701, 868)
WRITABLE_COILS = (701, 820)


def bit_location(user: int) -> tuple[int, int]:
    """(byte address, bit) of a user bit address ("User Address to Controller Address Table")."""
    group, rest = divmod(user, 100)
    if group <= 6:
        if 1 <= rest <= 8:
            return 0x9D + group, rest - 1  # inputs g01-g08: 9DH-A3H
        if rest in (9, 10):
            position = 2 + 2 * group + (rest - 9)  # A4H bits 2-7, then A5H
            return 0xA4 + position // 8, position % 8
        if 11 <= rest <= 18:
            return 0x96 + group, rest - 11  # outputs g11-g18: 96H-9CH
    if 701 <= user <= 876:
        return 0xA6 + (user - 701) // 8, (user - 701) % 8
    if 901 <= user <= 932:
        return 0xDC + (user - 901) // 8, (user - 901) % 8
    if 951 <= user <= 982:
        return 0xE0 + (user - 951) // 8, (user - 951) % 8
    raise ValueError(user)


def expected_bit(sim: SlcAsciiSimulator, user: int) -> bool:
    byte, bit = bit_location(user)
    return bool(sim.memory[byte] >> bit & 1)


def expected_holding(sim: SlcAsciiSimulator, address: int) -> int:
    """0-31 accumulators of 901-932, 32-63 presets; the protect bit (bit 15) masked."""
    word = sim.word(2 * address) if address < 32 else sim.word(0x40 + 2 * (address - 32))
    return word & 0x7FFF


def expected_input(sim: SlcAsciiSimulator, address: int) -> int:
    if address < 32:
        return sim.memory[0xBC + address]  # sequencer step counters
    if address == 66:
        return sim.word(0x84)  # error bits 84H-85H
    if 67 <= address <= 74:
        return sim.word(0x86 + 2 * (address - 67))  # force select table
    if 129 <= address <= 136:
        return sim.word(0x102 + 2 * (address - 129))  # force state table
    raise ValueError(address)


INPUT_RUNS = [(0, 31), (66, 74), (129, 136)]


def seed_memory(sim: SlcAsciiSimulator, seed: int) -> None:
    """Distinct values everywhere the map reaches (the ladder is frozen, so they stay)."""
    rng = random.Random(seed)
    for n in range(31):  # accumulators 901-931 (932 keeps its protected 7)
        sim.set_word(2 * n, rng.randrange(10000))
    for n in range(31):  # presets 901-931 (932 keeps its protected 500)
        sim.set_word(0x40 + 2 * n, rng.randrange(1, 10000))
    for address in [*range(0x84, 0xBC), *range(0xBC, 0xE4), *range(0x102, 0x112)]:
        sim.memory[address] = rng.randrange(256)
    sim.memory[0xA6] = 0  # relays 701-708: known clear, for the coil writes
    sim.memory[0xA7] = 0xF0  # relays 709-716: low half clear, high half set


# --------------------------------------------------------------------------------------------
# Controllers in-process or over TCP, and the gateway in front of them


@dataclass
class Controllers:
    """Simulated SLC 150s reached in-process (``sim://``) or over TCP (``socket://``)."""

    transport: str
    servers: list[asyncio.Server] = field(default_factory=list)

    async def add(self, **options: str) -> tuple[SlcAsciiSimulator, str]:
        options = {"ladder": "0", **options}
        if self.transport == "sim":
            url = "sim://slc150?" + urlencode({**options, "instance": uuid.uuid4().hex})
            sim = get_simulator(url)
        else:
            sim = create_simulator("slc150", options)
            server = await serve_tcp(sim, HOST, 0)
            self.servers.append(server)
            url = f"socket://{HOST}:{server.sockets[0].getsockname()[1]}"
        assert isinstance(sim, SlcAsciiSimulator)
        return sim, url

    async def close(self) -> None:
        for server in self.servers:
            server.close()
            await server.wait_closed()


def link_toml(name: str, port: str, unit: int, **keys: Any) -> str:
    lines = ["[[link]]", f"name = {json.dumps(name)}", 'protocol = "slc-ascii"', f"port = {json.dumps(port)}",
             f"unit = {unit}"]
    for key, value in keys.items():
        lines.append(f"{key} = {json.dumps(value)}")  # JSON scalars and string lists are TOML too
    return "\n".join(lines) + "\n"


def gateway_config(*links: str) -> Any:
    return parse_config('[modbus]\nlisten = "127.0.0.1:0"\n\n' + "\n".join(links))


@dataclass
class Plant:
    gw: Gateway
    sims: dict[int, SlcAsciiSimulator]
    transport: str

    @property
    def port(self) -> int:
        return self.gw.port

    def requests(self, function_code: int) -> int:
        """How many requests of ``function_code`` the gateway's Modbus server received."""
        return self.gw.servers[0].counters.requests.get(function_code, 0)


pytestmark = pytest.mark.usefixtures("forget_simulators")


@pytest.fixture(params=["sim", "tcp"])
async def plant(request: pytest.FixtureRequest) -> AsyncIterator[Plant]:
    """Four controllers: read/write, read-only, silent, and one with writable ranges."""
    controllers = Controllers(request.param)
    sims: dict[int, SlcAsciiSimulator] = {}
    links: list[str] = []
    main, url = await controllers.add()
    sims[MAIN] = main
    # write_timeout: test_read_answered_while_a_write_is_pending slows every reply to 0.4 s, past
    # the default (0.9 s) for a write that waits behind a poll
    links.append(link_toml("main", url, MAIN, write_timeout=3.0))
    read_only, url = await controllers.add()
    sims[READ_ONLY] = read_only
    links.append(link_toml("read-only", url, READ_ONLY, read_only=True))
    silent, url = await controllers.add(drop="1")  # executes commands, never answers
    sims[SILENT] = silent
    links.append(link_toml("silent", url, SILENT, timeout=0.05, retries=1, stale_after=1.0))
    limited, url = await controllers.add()
    sims[LIMITED] = limited
    links.append(link_toml("limited", url, LIMITED, writable=["holding:0-9", "coil:701-708"]))
    for unit, sim in sims.items():
        seed_memory(sim, unit)
    try:
        async with Gateway(gateway_config(*links)) as gw:
            async with connect(gw.port) as client:
                for unit in (MAIN, READ_ONLY, LIMITED):
                    await until_ready(client, unit)
            yield Plant(gw, sims, request.param)
    finally:
        await controllers.close()


# --------------------------------------------------------------------------------------------
# Modbus helpers


async def until_ready(client: AsyncModbusTcpClient, unit: int, deadline: float = 5.0) -> None:
    """Wait until a whole scan is cached: the slow class is read first, the 951-982 block last."""
    async with asyncio.timeout(deadline):
        while True:
            holding = await client.read_holding_registers(0, count=64, device_id=unit)
            bits = await client.read_discrete_inputs(951, count=32, device_id=unit)
            if not holding.isError() and not bits.isError():
                return
            await asyncio.sleep(0.02)


async def eventually(check: Callable[[], Awaitable[bool]], deadline: float, what: str) -> float:
    """Poll ``check`` until true; the seconds it took.  Fails naming ``what`` at the deadline."""
    start = time.monotonic()
    while not await check():
        if time.monotonic() - start > deadline:
            pytest.fail(f"not within {deadline:g} s: {what}")
        await asyncio.sleep(0.02)
    return time.monotonic() - start


async def read_registers(client: AsyncModbusTcpClient, table: str, address: int, count: int, unit: int) -> list[int]:
    read = client.read_holding_registers if table == "holding" else client.read_input_registers
    reply = await read(address, count=count, device_id=unit)
    assert not reply.isError(), f"{table} {address}+{count} unit {unit}: {reply}"
    return list(reply.registers)


async def read_bits(client: AsyncModbusTcpClient, table: str, address: int, count: int, unit: int) -> list[bool]:
    read = client.read_coils if table == "coil" else client.read_discrete_inputs
    reply = await read(address, count=count, device_id=unit)
    assert not reply.isError(), f"{table} {address}+{count} unit {unit}: {reply}"
    return list(reply.bits[:count])


# --------------------------------------------------------------------------------------------
# mbpoll


@dataclass
class MbpollResult:
    returncode: int
    stdout: str
    stderr: str

    @property
    def values(self) -> dict[int, int]:
        """``[reference]: value`` lines (references as printed: 1-based unless -0 was given)."""
        out: dict[int, int] = {}
        for match in re.finditer(r"^\[(\d+)\]:\s+(-?(?:0x)?[0-9A-Fa-f]+)\s*$", self.stdout, re.MULTILINE):
            out[int(match[1])] = int(match[2], 0) & 0xFFFF
        return out


async def mbpoll(port: int, unit: int, *args: str, writes: Sequence[int] = ()) -> MbpollResult:
    """Run mbpoll once (``-1``) against the gateway.  ``writes``: values to write instead of reading."""
    command = [mbpoll_path(), "-m", "tcp", "-p", str(port), "-a", str(unit), "-1", "-o", "3", *args, HOST]
    command += [str(v) for v in writes]
    process = await asyncio.create_subprocess_exec(
        *command, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    async with asyncio.timeout(10):
        stdout, stderr = await process.communicate()
    assert process.returncode is not None
    return MbpollResult(process.returncode, stdout.decode(errors="replace"), stderr.decode(errors="replace"))


async def mbpoll_read(port: int, unit: int, kind: str, address: int, count: int) -> dict[int, int]:
    """Read ``count`` values from protocol address ``address`` with 1-based references (mbpoll's
    default: ``-r address+1``); the result keyed by protocol address."""
    result = await mbpoll(port, unit, "-t", kind, "-r", str(address + 1), "-c", str(count))
    assert result.returncode == 0, result.stderr + result.stdout
    values = {reference - 1: value for reference, value in result.values.items()}
    assert sorted(values) == list(range(address, address + count)), result.stdout
    return values


def assert_mbpoll_exception(result: MbpollResult, code: int) -> None:
    assert result.returncode != 0, result.stdout
    assert MBPOLL_TEXT[code] in result.stderr, (code, result.stderr)


# --------------------------------------------------------------------------------------------
# Raw MBAP (pipelining)


async def read_frame(reader: asyncio.StreamReader) -> tuple[int, int, bytes]:
    """One reply frame: (transaction id, unit, PDU)."""
    async with asyncio.timeout(5):
        header = await reader.readexactly(7)
        tid, protocol, length, unit = struct.unpack(">HHHB", header)
        assert protocol == 0
        pdu = await reader.readexactly(length - 1)
    return tid, unit, pdu


def fc3(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def fc4(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 4, address, count)


def fc6(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, address, value)


def registers_of(pdu: bytes) -> list[int]:
    assert pdu[0] in (3, 4) and pdu[1] == len(pdu) - 2, pdu.hex()
    return list(struct.unpack(f">{pdu[1] // 2}H", pdu[2:]))


# ============================================================================================
# Reads: values equal the controller's memory


async def test_pymodbus_reads_every_mapped_value(plant: Plant) -> None:
    sim = plant.sims[MAIN]
    async with connect(plant.port) as client:
        assert await read_registers(client, "holding", 0, 64, MAIN) == [expected_holding(sim, a) for a in range(64)]
        for first, last in INPUT_RUNS:
            count = last - first + 1
            assert await read_registers(client, "input", first, count, MAIN) == [
                expected_input(sim, a) for a in range(first, last + 1)
            ], (first, last)
        for first, last in DISCRETE_RUNS:
            count = last - first + 1
            assert await read_bits(client, "discrete", first, count, MAIN) == [
                expected_bit(sim, a) for a in range(first, last + 1)
            ], (first, last)
        first, last = COIL_RUN
        assert await read_bits(client, "coil", first, last - first + 1, MAIN) == [
            expected_bit(sim, a) for a in range(first, last + 1)
        ]
        # The protected word 932 is served without its protect bit; the units are independent.
        assert (await read_registers(client, "holding", 31, 1, MAIN)) == [7]
        assert (await read_registers(client, "holding", 63, 1, MAIN)) == [500]
        other = plant.sims[READ_ONLY]
        assert await read_registers(client, "holding", 0, 64, READ_ONLY) == [
            expected_holding(other, a) for a in range(64)
        ]
        assert [expected_holding(other, a) for a in range(8)] != [expected_holding(sim, a) for a in range(8)]
        # The status block: link up, data fresh (age in 100 ms units), no fault, transactions counted.
        status = await read_registers(client, "input", STATUS_BASE, STATUS_COUNT, MAIN)
        assert status[0] == 1
        assert status[1] <= 10
        assert status[2] == 0
        assert (status[3] << 16 | status[4]) > 0
        assert (status[5] << 16 | status[6]) == 0  # errors
        assert status[11] == 0  # 1011: the link's state by the one verdict: up (fresh)


async def test_mbpoll_reads_every_table(plant: Plant) -> None:
    sim = plant.sims[MAIN]
    port = plant.port
    holding = await mbpoll_read(port, MAIN, "4", 0, 64)
    assert holding == {a: expected_holding(sim, a) for a in range(64)}
    for first, last in INPUT_RUNS:
        values = await mbpoll_read(port, MAIN, "3:hex", first, last - first + 1)
        assert values == {a: expected_input(sim, a) for a in range(first, last + 1)}
    for first, last in [*DISCRETE_RUNS[:7], (701, 800), (801, 876), (901, 932), (951, 982)]:
        values = await mbpoll_read(port, MAIN, "1", first, last - first + 1)
        assert values == {a: int(expected_bit(sim, a)) for a in range(first, last + 1)}, (first, last)
    for first, last in [(701, 800), (801, 868)]:
        values = await mbpoll_read(port, MAIN, "0", first, last - first + 1)
        assert values == {a: int(expected_bit(sim, a)) for a in range(first, last + 1)}, (first, last)
    # -0: references are protocol addresses; the status block at 1000.
    result = await mbpoll(port, MAIN, "-0", "-t", "3", "-r", str(STATUS_BASE), "-c", str(STATUS_COUNT))
    assert result.returncode == 0, result.stderr
    status = result.values
    assert sorted(status) == list(range(STATUS_BASE, STATUS_BASE + STATUS_COUNT))
    assert status[STATUS_BASE] == 1


# ============================================================================================
# Writes: through to the controller, exactly once, then read back


async def test_pymodbus_writes_land_once_and_read_back(plant: Plant) -> None:
    sim = plant.sims[MAIN]
    before = {fc: plant.requests(fc) for fc in (5, 6, 15, 16)}
    async with connect(plant.port) as client:
        # FC6: the accumulator of 906
        reply = await client.write_register(5, 4321, device_id=MAIN)
        assert not reply.isError(), reply
        assert sim.applied_writes == [("word", 0x0A, 4321)]
        assert sim.word(0x0A) == 4321
        assert await read_registers(client, "holding", 5, 1, MAIN) == [4321]

        # FC16: the presets of 909-911
        reply = await client.write_registers(40, [1111, 2222, 3333], device_id=MAIN)
        assert not reply.isError(), reply
        assert sim.applied_writes[1:] == [("word", 0x50, 1111), ("word", 0x52, 2222), ("word", 0x54, 3333)]
        assert await read_registers(client, "holding", 40, 3, MAIN) == [1111, 2222, 3333]

        # FC5: relay 703 (byte A6H bit 2), read-modify-write of its byte
        reply = await client.write_coil(703, True, device_id=MAIN)
        assert not reply.isError(), reply
        assert sim.applied_writes[4:] == [("byte", 0xA6, 0b100)]
        assert await read_bits(client, "coil", 701, 8, MAIN) == [False, False, True, False, False, False, False, False]
        assert await read_bits(client, "discrete", 703, 1, MAIN) == [True]  # the same relay
        reply = await client.write_coil(703, False, device_id=MAIN)
        assert not reply.isError(), reply
        assert sim.applied_writes[5:] == [("byte", 0xA6, 0)]

        # FC15: relays 709-712 (byte A7H = F0H: the high half stays set)
        reply = await client.write_coils(709, [True, False, True, True], device_id=MAIN)
        assert not reply.isError(), reply
        assert [w for w in sim.applied_writes[6:]] == [
            ("byte", 0xA7, 0xF1), ("byte", 0xA7, 0xF1), ("byte", 0xA7, 0xF5), ("byte", 0xA7, 0xFD),
        ]
        assert sim.memory[0xA7] == 0xFD
        assert await read_bits(client, "coil", 709, 8, MAIN) == [True, False, True, True, True, True, True, True]

        # Nothing arrives twice later; after fresh polls the controller still has the values.
        writes = list(sim.applied_writes)
        assert len(writes) == 10
        poller = plant.gw.units[0].poller
        scans = poller.scans

        async def two_more_scans() -> bool:
            return poller.scans >= scans + 2

        await eventually(two_more_scans, 5, "two more scans")
        assert sim.applied_writes == writes
        assert await read_registers(client, "holding", 5, 1, MAIN) == [4321]
        assert await read_registers(client, "holding", 40, 3, MAIN) == [1111, 2222, 3333]
        assert sim.memory[0xA7] == 0xFD
        assert plant.sims[LIMITED].applied_writes == []  # other units untouched
    assert {fc: plant.requests(fc) - n for fc, n in before.items()} == {5: 2, 6: 1, 15: 1, 16: 1}


async def test_mbpoll_writes_land_once_and_read_back(plant: Plant) -> None:
    sim = plant.sims[MAIN]
    port = plant.port
    before = {fc: plant.requests(fc) for fc in (5, 6, 15, 16)}
    # One value: FC6 (write single register); reference 13 = holding 12 = accumulator 913.
    result = await mbpoll(port, MAIN, "-t", "4", "-r", "13", writes=[777])
    assert result.returncode == 0, result.stderr
    # Two values: FC16; holding 50-51 = presets 919-920.
    result = await mbpoll(port, MAIN, "-t", "4", "-r", "51", writes=[4000, 5000])
    assert result.returncode == 0, result.stderr
    # Coils with 0-based references: FC5 on 720, FC15 on 730-732.
    result = await mbpoll(port, MAIN, "-0", "-t", "0", "-r", "720", writes=[1])
    assert result.returncode == 0, result.stderr
    result = await mbpoll(port, MAIN, "-0", "-t", "0", "-r", "730", writes=[1, 1, 0])
    assert result.returncode == 0, result.stderr
    assert {fc: plant.requests(fc) - n for fc, n in before.items()} == {5: 1, 6: 1, 15: 1, 16: 1}

    byte720, bit720 = bit_location(720)
    byte730, _ = bit_location(730)
    assert [w[:2] for w in sim.applied_writes] == [
        ("word", 24), ("word", 0x40 + 36), ("word", 0x40 + 38), ("byte", byte720),
        ("byte", byte730), ("byte", byte730), ("byte", byte730),
    ]
    assert sim.word(24) == 777 and sim.word(0x40 + 36) == 4000 and sim.word(0x40 + 38) == 5000
    assert expected_bit(sim, 720) and expected_bit(sim, 730) and expected_bit(sim, 731)
    assert not expected_bit(sim, 732)
    assert sim.memory[byte720] >> bit720 & 1

    assert await mbpoll_read(port, MAIN, "4", 12, 1) == {12: 777}
    assert await mbpoll_read(port, MAIN, "4", 50, 2) == {50: 4000, 51: 5000}
    assert await mbpoll_read(port, MAIN, "0", 729, 4) == {729: int(expected_bit(sim, 729)), 730: 1, 731: 1, 732: 0}
    assert await mbpoll_read(port, MAIN, "0", 720, 1) == {720: 1}


# ============================================================================================
# Exceptions


async def test_exceptions_each_proven_with_pymodbus(plant: Plant) -> None:
    sims = plant.sims
    async with connect(plant.port) as client:
        main = sims[MAIN]

        # 0x02 illegal data address: unmapped, partly unmapped, read-only points, read-only links
        assert exception_code(await client.read_holding_registers(64, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_holding_registers(60, count=8, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_input_registers(32, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_input_registers(1012, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_discrete_inputs(19, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.read_coils(869, count=1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_register(64, 1, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(821, True, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(868, True, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coils(819, [True, True, True], device_id=MAIN)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(700, True, device_id=MAIN)) == ILLEGAL_ADDRESS
        assert main.applied_writes == []  # nothing half-written: checked before the first write
        assert exception_code(await client.write_register(0, 1, device_id=READ_ONLY)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(701, True, device_id=READ_ONLY)) == ILLEGAL_ADDRESS
        assert sims[READ_ONLY].applied_writes == []
        assert exception_code(await client.write_register(20, 1, device_id=LIMITED)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_registers(8, [1, 2, 3], device_id=LIMITED)) == ILLEGAL_ADDRESS
        assert exception_code(await client.write_coil(709, True, device_id=LIMITED)) == ILLEGAL_ADDRESS
        assert sims[LIMITED].applied_writes == []
        assert not (await client.write_register(9, 99, device_id=LIMITED)).isError()
        assert not (await client.write_coil(708, True, device_id=LIMITED)).isError()
        assert sims[LIMITED].applied_writes == [("word", 18, 99), ("byte", 0xA6, 0x80)]

        # 0x03 illegal data value: > 9999 on an SLC 100/150 word; nothing of the request written
        assert exception_code(await client.write_register(0, 10000, device_id=MAIN)) == ILLEGAL_VALUE
        assert exception_code(await client.write_registers(0, [1, 10000, 2], device_id=MAIN)) == ILLEGAL_VALUE
        assert main.applied_writes == []

        # 0x04 server device failure: the controller refuses (;E) the protected preset / accumulator of 932
        assert exception_code(await client.write_register(63, 600, device_id=MAIN)) == DEVICE_FAILURE
        assert exception_code(await client.write_register(31, 8, device_id=MAIN)) == DEVICE_FAILURE
        assert main.applied_writes == []
        assert main.word(0x7E) == 0x8000 | 500 and main.word(0x3E) == 0x8000 | 7
        assert await read_registers(client, "holding", 63, 1, MAIN) == [500]

        # 0x0A gateway path unavailable: no such unit
        assert exception_code(await client.read_holding_registers(0, count=1, device_id=UNKNOWN_UNIT)) == (
            PATH_UNAVAILABLE
        )
        assert exception_code(await client.write_register(0, 1, device_id=UNKNOWN_UNIT)) == PATH_UNAVAILABLE

        # 0x0B gateway target failed to respond: a controller that never answers
        silent = sims[SILENT]
        assert exception_code(await client.read_holding_registers(0, count=1, device_id=SILENT)) == TARGET_FAILED
        assert exception_code(await client.read_coils(701, count=1, device_id=SILENT)) == TARGET_FAILED

        async def silent_link_down() -> bool:
            status = await read_registers(client, "input", STATUS_BASE, STATUS_COUNT, SILENT)
            return status[0] == 0 and (status[5] << 16 | status[6]) > 0  # down, after a failed transaction

        await eventually(silent_link_down, 2.0, "status register 1000 of the silent unit shows link down")
        status = await read_registers(client, "input", STATUS_BASE, STATUS_COUNT, SILENT)
        assert status[0] == 0  # link down
        assert status[1] == 65535  # never read
        assert status[11] == 2  # 1011: down
        assert (status[5] << 16 | status[6]) > 0  # errors counted
        writes_before = len(silent.applied_writes)
        assert exception_code(await client.write_register(3, 42, device_id=SILENT)) == TARGET_FAILED
        # Whether the controller executed it is unknown to the gateway (only replies are lost), so
        # it was never sent again on a guess: applied at most once.
        assert [w for w in silent.applied_writes[writes_before:] if w[0] == "word"] in ([], [("word", 6, 42)])

        # The healthy unit is unaffected.
        assert (await read_registers(client, "input", STATUS_BASE, 1, MAIN)) == [1]


async def test_exceptions_each_proven_with_mbpoll(plant: Plant) -> None:
    port = plant.port
    assert_mbpoll_exception(await mbpoll(port, MAIN, "-t", "4", "-r", "65"), ILLEGAL_ADDRESS)
    assert_mbpoll_exception(await mbpoll(port, MAIN, "-0", "-t", "0", "-r", "821", writes=[1]), ILLEGAL_ADDRESS)
    assert_mbpoll_exception(await mbpoll(port, READ_ONLY, "-t", "4", "-r", "1", writes=[5]), ILLEGAL_ADDRESS)
    assert_mbpoll_exception(await mbpoll(port, MAIN, "-t", "4", "-r", "1", writes=[10000]), ILLEGAL_VALUE)
    assert_mbpoll_exception(await mbpoll(port, MAIN, "-t", "4", "-r", "64", writes=[600]), DEVICE_FAILURE)
    assert_mbpoll_exception(await mbpoll(port, UNKNOWN_UNIT, "-t", "4", "-r", "1"), PATH_UNAVAILABLE)
    assert_mbpoll_exception(await mbpoll(port, SILENT, "-t", "4", "-r", "1"), TARGET_FAILED)
    assert plant.sims[MAIN].applied_writes == []
    assert plant.sims[READ_ONLY].applied_writes == []


# ============================================================================================
# Pipelining on one connection


async def test_two_requests_in_one_segment_both_answered(plant: Plant) -> None:
    sim = plant.sims[MAIN]
    reader, writer = await asyncio.open_connection(HOST, plant.port)
    try:
        writer.write(
            mbap(0x1111, MAIN, fc3(0, 4))
            + mbap(0x2222, MAIN, fc4(66, 1))
            + mbap(0x3333, UNKNOWN_UNIT, fc3(0, 1))
            + mbap(0x4444, MAIN, fc3(64, 1))
        )
        await writer.drain()
        replies = {}
        for _ in range(4):
            tid, unit, pdu = await read_frame(reader)
            replies[tid] = (unit, pdu)
        assert set(replies) == {0x1111, 0x2222, 0x3333, 0x4444}
        assert replies[0x1111][0] == MAIN
        assert registers_of(replies[0x1111][1]) == [expected_holding(sim, a) for a in range(4)]
        assert registers_of(replies[0x2222][1]) == [expected_input(sim, 66)]
        assert replies[0x3333] == (UNKNOWN_UNIT, bytes([0x83, PATH_UNAVAILABLE]))
        assert replies[0x4444] == (MAIN, bytes([0x83, ILLEGAL_ADDRESS]))
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


@pytest.mark.parametrize("same_segment", [False, True], ids=["separate", "same-segment"])
async def test_read_answered_while_a_write_is_pending(plant: Plant, same_segment: bool) -> None:
    sim = plant.sims[MAIN]
    old = [expected_holding(sim, a) for a in range(3)]
    sim.faults.delay = 0.4  # the controller now takes 0.4 s for every reply
    reader, writer = await asyncio.open_connection(HOST, plant.port)
    try:
        write = mbap(0x0A0A, MAIN, fc6(2, 999))
        read = mbap(0x0B0B, MAIN, fc3(0, 3))
        started = time.monotonic()
        if same_segment:
            writer.write(write + read)
        else:
            writer.write(write)
            await writer.drain()
            await asyncio.sleep(0.05)
            writer.write(read)
        await writer.drain()
        first = await read_frame(reader)
        second = await read_frame(reader)
        second_at = time.monotonic() - started
        # The read is served from the cache while the write waits, with its own tid and the value
        # before the write.
        assert first == (0x0B0B, MAIN, bytes([3, 6]) + struct.pack(">3H", *old))
        # The write is answered (an echo) only after the controller confirmed it.
        assert second == (0x0A0A, MAIN, fc6(2, 999))
        assert second_at >= 0.35, second_at
        assert sim.applied_writes == [("word", 4, 999)]
        writer.write(mbap(0x0C0C, MAIN, fc3(2, 1)))
        await writer.drain()
        assert await read_frame(reader) == (0x0C0C, MAIN, bytes([3, 2]) + struct.pack(">H", 999))
    finally:
        sim.faults.delay = 0.0
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


# ============================================================================================
# Many clients


@pytest.mark.parametrize("clients", ["pymodbus", "pymodbus+mbpoll"])
async def test_many_connections_at_once(plant: Plant, clients: str) -> None:
    """20 pymodbus clients at once; and with 5 mbpoll processes among them (skipped loudly without
    mbpoll, a failure in CI), never silently fewer clients than the test's name says."""
    mbpoll_clients = 5 if clients == "pymodbus+mbpoll" else 0
    if mbpoll_clients:
        mbpoll_path()  # skips (or fails under SLC_GATEWAY_REQUIRE_MBPOLL=1) without mbpoll
    sim = plant.sims[MAIN]
    holding = [expected_holding(sim, a) for a in range(64)]
    coils = [expected_bit(sim, a) for a in range(COIL_RUN[0], COIL_RUN[1] + 1)]

    async def one_client(n: int) -> int:
        async with connect(plant.port) as client:
            for _ in range(5):
                assert await read_registers(client, "holding", 0, 64, MAIN) == holding
                assert await read_bits(client, "coil", 701, len(coils), MAIN) == coils
                assert (await read_registers(client, "input", STATUS_BASE, 1, MAIN)) == [1]
        return n

    async def one_mbpoll(n: int) -> int:
        assert await mbpoll_read(plant.port, MAIN, "4", 0, 64) == dict(enumerate(holding))
        return n

    tasks = [one_client(n) for n in range(20)] + [one_mbpoll(n) for n in range(mbpoll_clients)]
    async with asyncio.timeout(20):
        done = await asyncio.gather(*tasks)
    assert len(done) == 20 + mbpoll_clients


# ============================================================================================
# Staleness and link loss


async def test_slow_class_values_served_between_slow_scans() -> None:
    """Presets are read every slow_interval; they must not turn 0x0B between two slow scans
    while the link is up, even when stale_after is shorter than slow_interval."""
    controllers = Controllers("sim")
    sim, url = await controllers.add()
    seed_memory(sim, 5)
    config = gateway_config(link_toml("main", url, MAIN, stale_after=0.5, slow_interval=3.0))
    async with Gateway(config) as gw, connect(gw.port) as client:
        await until_ready(client, MAIN)
        await asyncio.sleep(1.2)
        presets = [expected_holding(sim, a) for a in range(32, 64)]
        assert await read_registers(client, "holding", 32, 32, MAIN) == presets
        assert await read_registers(client, "input", 0, 32, MAIN) == [expected_input(sim, a) for a in range(32)]
        assert await read_registers(client, "holding", 0, 32, MAIN) == [expected_holding(sim, a) for a in range(32)]


async def test_a_plan_with_only_slow_blocks_is_served_between_its_scans() -> None:
    """A DF1 link whose map is all slow class: the controller is asked only every slow_interval,
    which is not silence."""
    url = f"sim://slc504?ladder=0&instance={uuid.uuid4().hex}"
    config = parse_config(f"""
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "slow-only"
protocol = "df1"
port = "{url}"
unit = {MAIN}
stale_after = 0.5
slow_interval = 1.0

[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 10
scan = "slow"
""")
    async with Gateway(config) as gw, connect(gw.port) as client:

        async def ready() -> bool:
            return not (await client.read_holding_registers(0, count=10, device_id=MAIN)).isError()

        await eventually(ready, 5, "the first slow scan")
        end = time.monotonic() + 2.5  # more than two slow scans
        while time.monotonic() < end:
            assert await read_registers(client, "holding", 0, 10, MAIN) == list(range(10))  # N7:k = k
            await asyncio.sleep(0.05)


class DeviceServer:
    """A serial device server in front of a TCP simulator: it can be stopped (listener and every
    connection closed), restarted on the same port, or made silent (bytes dropped both ways)."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.port = 0
        self.silent = False
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, HOST, self.port)
        self.port = self._server.sockets[0].getsockname()[1]

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(HOST, self.upstream_port)
        self._writers |= {writer, up_writer}
        pumps = [asyncio.create_task(self._pump(reader, up_writer)), asyncio.create_task(self._pump(up_reader, writer))]
        self._tasks.update(pumps)
        await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        for w in (writer, up_writer):
            w.close()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError):
            while data := await reader.read(4096):
                if not self.silent:
                    writer.write(data)

    async def stop(self) -> None:
        assert self._server is not None
        self._server.close()
        for writer in self._writers:
            writer.close()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._server.wait_closed()
        self._writers.clear()
        self._tasks.clear()
        self._server = None


@pytest.fixture
async def device_server() -> AsyncIterator[tuple[SlcAsciiSimulator, DeviceServer]]:
    sim = create_simulator("slc150", {"ladder": "0"})
    assert isinstance(sim, SlcAsciiSimulator)
    seed_memory(sim, 7)
    upstream = await serve_tcp(sim, HOST, 0)
    server = DeviceServer(upstream.sockets[0].getsockname()[1])
    await server.start()
    try:
        yield sim, server
    finally:
        if server._server is not None:
            await server.stop()
        upstream.close()
        await upstream.wait_closed()


STALE_AFTER = 1.0


def link_loss_config(port: int) -> Any:
    return gateway_config(
        link_toml("remote", f"socket://{HOST}:{port}", MAIN, stale_after=STALE_AFTER, timeout=0.1, retries=1)
    )


async def test_link_loss_and_recovery(device_server: tuple[SlcAsciiSimulator, DeviceServer]) -> None:
    sim, server = device_server
    async with Gateway(link_loss_config(server.port)) as gw, connect(gw.port) as client:
        await until_ready(client, MAIN)
        assert await read_registers(client, "holding", 0, 4, MAIN) == [expected_holding(sim, a) for a in range(4)]

        # The device server goes away: listener and connection closed.
        await server.stop()
        stopped = time.monotonic()

        async def link_down() -> bool:
            return (await read_registers(client, "input", STATUS_BASE, 1, MAIN)) == [0]

        await eventually(link_down, 1.0, "status register 1000 shows link down")

        async def stale() -> bool:
            return exception_code(await client.read_holding_registers(0, count=4, device_id=MAIN)) == TARGET_FAILED

        await eventually(stale, STALE_AFTER + 0.5, "reads answer 0x0B")
        assert time.monotonic() - stopped <= STALE_AFTER + 0.5
        # Each value ages from its own read; stale_after after the loss every value is stale.
        await asyncio.sleep(max(0.0, stopped + STALE_AFTER + 0.05 - time.monotonic()))
        assert exception_code(await client.read_coils(701, count=8, device_id=MAIN)) == TARGET_FAILED
        assert exception_code(await client.read_discrete_inputs(951, count=32, device_id=MAIN)) == TARGET_FAILED
        assert exception_code(await client.read_holding_registers(32, count=32, device_id=MAIN)) == TARGET_FAILED
        assert exception_code(await client.write_register(0, 5, device_id=MAIN)) == TARGET_FAILED

        # While it is away the controller's values change; then it comes back on the same port.
        sim.set_word(0, 4321)
        sim.set_word(0x40, 1234)
        await asyncio.sleep(0.5)
        await server.start()

        async def served() -> bool:
            return not (await client.read_holding_registers(0, count=64, device_id=MAIN)).isError()

        await eventually(served, 10, "the gateway reconnects (backoff) and serves values again")
        # The first values served after the outage were read after it, slow class (presets) included.
        first = await read_registers(client, "holding", 0, 64, MAIN)
        assert (first[0], first[32]) == (4321, 1234)
        assert (await read_registers(client, "input", STATUS_BASE, 1, MAIN)) == [1]
        assert await read_registers(client, "holding", 0, 64, MAIN) == [expected_holding(sim, a) for a in range(64)]
        assert gw.units[0].driver.counters.reconnects >= 1
        # Writes work again, once.
        assert not (await client.write_register(1, 55, device_id=MAIN)).isError()
        assert sim.applied_writes == [("word", 2, 55)]
        stopping = time.monotonic()
    # Stopping right after a reconnect (docker stop, SIGTERM) does not wait out the reconnect backoff.
    assert time.monotonic() - stopping < 1.5


async def test_silent_device_server_goes_stale_and_recovers(
    device_server: tuple[SlcAsciiSimulator, DeviceServer],
) -> None:
    """The TCP connection stays up but nothing comes back (a cut serial line behind a device server)."""
    sim, server = device_server
    async with Gateway(link_loss_config(server.port)) as gw, connect(gw.port) as client:
        await until_ready(client, MAIN)
        server.silent = True
        silenced = time.monotonic()

        async def stale() -> bool:
            return exception_code(await client.read_holding_registers(0, count=4, device_id=MAIN)) == TARGET_FAILED

        await eventually(stale, STALE_AFTER + 0.5, "reads answer 0x0B")
        assert time.monotonic() - silenced <= STALE_AFTER + 0.5

        async def link_down() -> bool:
            return (await read_registers(client, "input", STATUS_BASE, 1, MAIN)) == [0]

        # down after 3 failed transactions in a row (down_after_failures), not on the first one
        await eventually(link_down, 3.0, "status register 1000 shows link down")

        sim.set_word(2, 2222)
        server.silent = False

        async def fresh() -> bool:
            reply = await client.read_holding_registers(0, count=2, device_id=MAIN)
            return not reply.isError() and reply.registers[1] == 2222

        await eventually(fresh, 5, "fresh values once the controller answers again")
        assert (await read_registers(client, "input", STATUS_BASE, 1, MAIN)) == [1]
