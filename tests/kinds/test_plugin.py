"""Adding a protocol is one package and one registry entry (issue 11's acceptance).

This file is that package: a tiny "echo" controller kind (config model, codec, plan, driver, unit,
simulator) defined here and registered with :func:`gateway.kinds.register_link_kind` without
editing any module of ``gateway/``.  A config with ``protocol = "echo"`` then loads, the Gateway
polls the simulated controller over ``sim://echo`` and serves it over Modbus TCP, reads and writes.

The echo protocol (bytes, big-endian words):

* ``R a n``: read ``n`` words from word ``a``; the controller answers the ``2n`` bytes.
* ``W a hi lo``: write word ``a``; the controller echoes the 4 bytes.
* ``B a k v``: set bit ``k`` of word ``a`` to ``v``; the controller echoes the 4 bytes.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal, Unpack

import pytest
from pydantic import Field
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway, describe_map
from gateway.config import parse_config
from gateway.config.link import LinkBase, Parity, SerialDefaults
from gateway.errors import ConfigError, GatewayError, LinkTimeout
from gateway.kinds import (
    Built,
    LinkKind,
    kind_names,
    link_kinds,
    register_link_kind,
    unit_options,
    unregister_link_kind,
)
from gateway.line_driver import LineDriver, LineLease
from gateway.modbus.mapping import BitPoint, Block, Codec, Plan, RegisterPoint, Scan
from gateway.sim import get_simulator, model_names, reset_simulators
from gateway.sim.models import SimModel
from gateway.sim.serve import SimDevice
from gateway.streams import SerialSettings
from gateway.unit import Unit, UnitOptions

# --- the kind's package (config, codec, plan, simulator, driver, unit) -------------------------

ECHO_DEFAULTS = SerialDefaults(baudrate=9600, bytesize=8, parity="N", stopbits=1, timeout=0.5)
WORDS = 8  # holding registers 0-7: words 0-7; coils 0-15: the bits of word 8


class EchoLinkConfig(LinkBase):
    serial_defaults: ClassVar[SerialDefaults] = ECHO_DEFAULTS
    sim_models: ClassVar[tuple[str, ...]] = ("echo",)

    protocol: Literal["echo"]
    baudrate: int = ECHO_DEFAULTS.baudrate
    bytesize: int = ECHO_DEFAULTS.bytesize
    parity: Parity = ECHO_DEFAULTS.parity
    stopbits: int = ECHO_DEFAULTS.stopbits
    timeout: float = Field(ECHO_DEFAULTS.timeout, gt=0, le=60)


#: The kind's own codec: a word, MSB first.
ECHO_WORD = Codec("echo-word", 0, 1)


@dataclass(frozen=True, slots=True)
class WordWrite:
    word: int


@dataclass(frozen=True, slots=True)
class BitWrite:
    word: int
    bit: int


def echo_plan(link: EchoLinkConfig | None = None) -> Plan[WordWrite, BitWrite]:
    plan: Plan[WordWrite, BitWrite] = Plan()
    plan.blocks.append(Block((0, WORDS + 1), 2 * (WORDS + 1), Scan.FAST, f"words 0-{WORDS}"))
    for n in range(WORDS):
        plan.holding[n] = RegisterPoint(0, 2 * n, ECHO_WORD, WordWrite(n))
    for k in range(16):
        plan.coils[k] = BitPoint(0, 2 * WORDS + 1 - k // 8, k % 8, BitWrite(WORDS, k))
    return plan


@dataclass(frozen=True, slots=True)
class Reply:
    delay: float
    data: bytes


class EchoSimulator:
    """The simulated echo controller: known words 1000, 1001 ...; writes are echoed."""

    def __init__(self) -> None:
        self.words = [1000 + n for n in range(WORDS)] + [0]
        self.writes: list[bytes] = []
        self._pending = bytearray()

    def receive(self, data: bytes, now: float) -> Sequence[Reply]:
        self._pending += data
        replies: list[Reply] = []
        while self._pending:
            size = 3 if self._pending[0] == ord("R") else 4
            if len(self._pending) < size:
                break
            command, self._pending = bytes(self._pending[:size]), self._pending[size:]
            replies.append(Reply(0.0, self._answer(command)))
        return replies

    def _answer(self, command: bytes) -> bytes:
        kind, a = command[0], command[1]
        if kind == ord("R"):
            return b"".join(word.to_bytes(2, "big") for word in self.words[a : a + command[2]])
        self.writes.append(command)
        if kind == ord("W"):
            self.words[a] = int.from_bytes(command[2:4], "big")
        else:
            mask = 1 << command[2]
            self.words[a] = self.words[a] | mask if command[3] else self.words[a] & ~mask
        return command

    def poll(self, now: float) -> Sequence[Reply]:
        return []

    def next_deadline(self) -> float | None:
        return None


def _make_simulator(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    return EchoSimulator()


class EchoDriver(LineDriver):
    """One transaction at a time: send a command, wait for its ``expect`` bytes."""

    def __init__(self, url: str, *, name: str, settings: SerialSettings, timeout: float) -> None:
        super().__init__(url, name=name, settings=settings, reconnect_min=0.05, reconnect_max=0.1)
        self.timeout = timeout
        self._buffer = bytearray()
        self._reply: asyncio.Future[bytes] | None = None
        self._expect = 0

    def on_connect(self) -> None:
        self._buffer.clear()

    def data_received(self, data: bytes) -> None:
        self._buffer += data
        reply = self._reply
        if reply is not None and not reply.done() and len(self._buffer) >= self._expect:
            reply.set_result(bytes(self._buffer[: self._expect]))
            del self._buffer[: self._expect]

    def abort(self, exc: GatewayError) -> None:
        if self._reply is not None and not self._reply.done():
            self._reply.set_exception(exc)

    async def transact(self, command: bytes, expect: int, line: LineLease | None = None) -> bytes:
        """One command and its answer: a poll, or with ``line`` (a write session's lease) a write."""
        async def op() -> bytes:
            self._buffer.clear()
            self._reply = asyncio.get_running_loop().create_future()
            self._expect = expect
            self.send(command)
            try:
                reply = await asyncio.wait_for(self._reply, self.timeout)
            except TimeoutError:
                self.note_result(False, "no answer")
                raise LinkTimeout(f"link {self.name}: no answer to {command!r}") from None
            self.note_result(True)
            return reply

        return await self.submit(op, line=line)


class EchoUnit(Unit[WordWrite, BitWrite]):
    driver: EchoDriver

    def __init__(self, *, driver: EchoDriver, **common: Unpack[UnitOptions]) -> None:
        super().__init__(driver=driver, plan=echo_plan(), **common)

    async def read_block(self, block: Block) -> bytes:
        return await self.driver.transact(bytes([ord("R"), 0, WORDS + 1]), block.size)

    async def _write_register(self, target: WordWrite, value: int, line: LineLease) -> None:
        command = bytes([ord("W"), target.word]) + value.to_bytes(2, "big")
        if await self.driver.transact(command, 4, line) != command:
            raise GatewayError("the echo differs")

    async def _write_bit(self, target: BitWrite, value: bool, line: LineLease) -> None:
        command = bytes([ord("B"), target.word, target.bit, int(value)])
        if await self.driver.transact(command, 4, line) != command:
            raise GatewayError("the echo differs")

    @property
    def last_fault_number(self) -> int:
        return 0


def build_echo(links: Sequence[EchoLinkConfig]) -> Built:
    units = [
        EchoUnit(driver=EchoDriver(link.port, name=link.name, settings=link.line_settings, timeout=link.timeout),
                 **unit_options(link))
        for link in links
    ]
    return Built(units, [unit.driver for unit in units])


ECHO_SIM = SimModel("echo", _make_simulator, SerialSettings(9600, 8, "N", 1))

KIND: LinkKind[EchoLinkConfig] = LinkKind(
    config_model=EchoLinkConfig,
    build=build_echo,
    plan=echo_plan,
    controllers="echo controllers",
    simulators=(ECHO_SIM,),
)

# --- the acceptance test -----------------------------------------------------------------------


@pytest.fixture
def echo_kind() -> Iterator[LinkKind[EchoLinkConfig]]:
    reset_simulators()
    register_link_kind(KIND)
    try:
        yield KIND
    finally:
        unregister_link_kind("echo")
        reset_simulators()


CONFIG = """
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "echo-1"
protocol = "echo"
port = "sim://echo"
unit = 7
fast_interval = 0.02
"""


@pytest.fixture
async def client(echo_kind: LinkKind[EchoLinkConfig]) -> AsyncIterator[tuple[Gateway, AsyncModbusTcpClient]]:
    async with Gateway(parse_config(CONFIG)) as gw:
        modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
        await modbus.connect()
        try:
            yield gw, modbus
        finally:
            modbus.close()


async def _fresh_holding(modbus: AsyncModbusTcpClient, count: int) -> list[int]:
    for _ in range(200):
        reply = await modbus.read_holding_registers(0, count=count, device_id=7)
        if not reply.isError():
            return list(reply.registers)
        await asyncio.sleep(0.02)
    raise AssertionError("the echo link never served fresh data")


async def test_a_registered_kind_is_served_over_modbus(client: tuple[Gateway, AsyncModbusTcpClient]) -> None:
    gw, modbus = client
    assert await _fresh_holding(modbus, WORDS) == [1000 + n for n in range(WORDS)]

    assert not (await modbus.write_register(3, 4242, device_id=7)).isError()
    controller = get_simulator("sim://echo")
    assert controller.words[3] == 4242
    assert (await _fresh_holding(modbus, WORDS))[3] == 4242  # the write patched the image at once

    assert not (await modbus.write_coil(9, True, device_id=7)).isError()
    assert controller.words[WORDS] == 1 << 9
    coils = await modbus.read_coils(0, count=16, device_id=7)
    assert not coils.isError() and coils.bits[:16] == [k == 9 for k in range(16)]
    assert controller.writes == [b"W\x03" + (4242).to_bytes(2, "big"), b"B\x08\x09\x01"]
    assert [type(unit).__name__ for unit in gw.units] == ["EchoUnit"]


def test_registering_changes_config_cli_and_simulators(echo_kind: LinkKind[EchoLinkConfig]) -> None:
    assert kind_names()[-1] == "echo" and link_kinds()["echo"] is KIND
    assert "echo" in model_names()
    config = parse_config(CONFIG)
    link = config.link[0]
    assert type(link) is EchoLinkConfig and link.baudrate == 9600
    assert "read plan: 1 blocks (1 fast, 0 slow)" in describe_map(config)
    with pytest.raises(ConfigError, match=r"sim://slc150 simulates a controller that speaks slc-ascii"):
        parse_config(CONFIG.replace("sim://echo", "sim://slc150"))
    with pytest.raises(ConfigError, match=r"station: only for df1 links"):
        parse_config(CONFIG + "station = 2\n")


def test_after_unregistering_the_protocol_is_unknown_again() -> None:
    assert "echo" not in kind_names() and "echo" not in model_names()
    with pytest.raises(ConfigError, match=r'unknown protocol: must be "slc-ascii" or "df1" \(got "echo"\)'):
        parse_config(CONFIG)
    register_link_kind(KIND)
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_link_kind(KIND)
    finally:
        unregister_link_kind("echo")
    with pytest.raises(ValueError, match="built-in"):
        unregister_link_kind("df1")
