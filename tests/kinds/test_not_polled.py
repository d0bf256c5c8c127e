"""A kind that is not polled plugs in through the registry alone.

This file is that kind's whole package: a "feed" peer that pushes values to the gateway and asks
it for values, on its own schedule (as a PLC's MSG instructions do).  It has a config model, a
runner that owns the line and fills the unit's image, a simulator and a map; it is registered
with :func:`gateway.kinds.register_link_kind` without editing any module of ``gateway/``, and the
Gateway serves it over Modbus TCP, reads and writes.

The feed protocol (ASCII lines, LF-terminated), the peer speaking first:

* ``P i v``: the peer sets value ``i`` to ``v`` (0-65535); the gateway answers ``K i``.
* ``G i``: the peer asks for value ``i``; the gateway answers ``V i v``, or ``X i`` when nobody
  has set it since start.

Values 0-7 are holding registers 0-7, one block each: a value never set answers 0x0B.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Literal, Unpack

import pytest
from pydantic import Field
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.config.link import LinkBase, Parity, SerialDefaults
from gateway.errors import GatewayError
from gateway.kinds import Built, LinkKind, register_link_kind, unit_options, unregister_link_kind
from gateway.line_driver import LineDriver, LineLease
from gateway.modbus.mapping import Block, Codec, Plan, RegisterPoint, Scan
from gateway.sim import get_simulator, reset_simulators
from gateway.sim.models import SimModel
from gateway.sim.serve import SimDevice
from gateway.streams import SerialSettings
from gateway.unit import Unit, UnitOptions
from tests.waiting import until

# --- the kind's package --------------------------------------------------------------------------

FEED_DEFAULTS = SerialDefaults(baudrate=9600, bytesize=8, parity="N", stopbits=1, timeout=0.5)
VALUES = 8


class FeedLinkConfig(LinkBase):
    serial_defaults: ClassVar[SerialDefaults] = FEED_DEFAULTS
    sim_models: ClassVar[tuple[str, ...]] = ("feed",)

    protocol: Literal["feed"]
    baudrate: int = FEED_DEFAULTS.baudrate
    bytesize: int = FEED_DEFAULTS.bytesize
    parity: Parity = FEED_DEFAULTS.parity
    stopbits: int = FEED_DEFAULTS.stopbits
    timeout: float = Field(FEED_DEFAULTS.timeout, gt=0, le=60)


FEED_WORD = Codec("feed-word", 0, 1)


@dataclass(frozen=True, slots=True)
class ValueTarget:
    index: int


def feed_plan(link: FeedLinkConfig | None = None) -> Plan[ValueTarget, None]:
    """One block per value: each has its own time of last change (never set: stale)."""
    plan: Plan[ValueTarget, None] = Plan()
    for n in range(VALUES):
        plan.blocks.append(Block((0, n), 2, Scan.FAST, f"value {n}"))
        plan.holding[n] = RegisterPoint(n, 0, FEED_WORD, ValueTarget(n))
    return plan


@dataclass(frozen=True, slots=True)
class Line:
    delay: float
    data: bytes


@dataclass
class FeedPeer:
    """The simulated peer: sends its script's lines, one every ``every`` seconds, until ``silent``."""

    script: list[bytes] = field(default_factory=list)
    every: float = 0.01
    silent: bool = False
    answers: list[bytes] = field(default_factory=list)
    _next: float = 0.0
    _pending: bytearray = field(default_factory=bytearray)

    def receive(self, data: bytes, now: float) -> Sequence[Line]:
        self._pending += data
        while b"\n" in self._pending:
            line, _, rest = bytes(self._pending).partition(b"\n")
            self._pending = bytearray(rest)
            self.answers.append(line)
        return []

    def poll(self, now: float) -> Sequence[Line]:
        if now < self._next:
            return []
        self._next = now + self.every
        return [Line(0.0, self.script.pop(0) + b"\n")] if self.script and not self.silent else []

    def next_deadline(self) -> float | None:
        return None if self.silent else self._next


def _make_peer(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    return FeedPeer()


class FeedRunner(LineDriver):
    """Owns the line: answers the peer and fills the unit's image (no read plan, no poller)."""

    def __init__(self, url: str, *, name: str, settings: SerialSettings) -> None:
        super().__init__(url, name=name, settings=settings, reconnect_min=0.05, reconnect_max=0.1)
        self.values: list[int | None] = [None] * VALUES
        self.unit: FeedUnit | None = None
        self._buffer = bytearray()

    def on_connect(self) -> None:
        self._buffer.clear()

    def abort(self, exc: GatewayError) -> None:
        pass

    def data_received(self, data: bytes) -> None:
        self._buffer += data
        while b"\n" in self._buffer:
            line, _, rest = bytes(self._buffer).partition(b"\n")
            self._buffer = bytearray(rest)
            self.send(self._answer(line.split()))

    def _answer(self, words: list[bytes]) -> bytes:
        now = asyncio.get_running_loop().time()
        unit = self.unit
        assert unit is not None
        unit.heard(now)
        self.note_result(True)
        index = int(words[1])
        if words[0] == b"P":
            value = int(words[2])
            self.values[index] = value
            unit.store(index, value.to_bytes(2, "big"), now)
            return b"K %d\n" % index
        value_now = self.values[index]
        return b"X %d\n" % index if value_now is None else b"V %d %d\n" % (index, value_now)


class FeedUnit(Unit[ValueTarget, None]):
    driver: FeedRunner
    POLLED = False

    def __init__(self, *, driver: FeedRunner, **common: Unpack[UnitOptions]) -> None:
        super().__init__(driver=driver, plan=feed_plan(), **common)
        driver.unit = self

    async def read_block(self, block: Block) -> bytes:
        raise AssertionError("a unit that is not polled is never asked to read")

    async def _write_register(self, target: ValueTarget, value: int, line: LineLease) -> None:
        # the peer's next G gets it; the image is patched by the generic write path
        self.driver.values[target.index] = value
        self.store(target.index, value.to_bytes(2, "big"), asyncio.get_running_loop().time())

    async def _write_bit(self, target: None, value: bool, line: LineLease) -> None:
        raise AssertionError("the feed map has no coils")

    @property
    def last_fault_number(self) -> int:
        return 0


def build_feed(links: Sequence[FeedLinkConfig]) -> Built:
    units = [FeedUnit(driver=FeedRunner(link.port, name=link.name, settings=link.line_settings),
                      **unit_options(link)) for link in links]
    return Built(units, [unit.driver for unit in units])


FEED_SIM = SimModel("feed", _make_peer, SerialSettings(9600, 8, "N", 1))

KIND: LinkKind[FeedLinkConfig] = LinkKind(
    config_model=FeedLinkConfig,
    build=build_feed,
    plan=feed_plan,
    controllers="feed peers",
    simulators=(FEED_SIM,),
    unit_class=lambda link: FeedUnit,
)

# --- the acceptance test -------------------------------------------------------------------------

CONFIG = """
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "feed-1"
protocol = "feed"
port = "sim://feed"
unit = 9
stale_after = 0.5
"""


@pytest.fixture
def feed_kind() -> Iterator[LinkKind[FeedLinkConfig]]:
    reset_simulators()
    register_link_kind(KIND)
    try:
        yield KIND
    finally:
        unregister_link_kind("feed")
        reset_simulators()


@pytest.fixture
async def client(feed_kind: LinkKind[FeedLinkConfig]) -> AsyncIterator[tuple[Gateway, AsyncModbusTcpClient]]:
    peer = get_simulator("sim://feed")
    peer.script[:] = [b"P 0 111", b"P 3 333"]
    async with Gateway(parse_config(CONFIG)) as gw:
        modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
        await modbus.connect()
        try:
            yield gw, modbus
        finally:
            modbus.close()


async def test_a_kind_that_is_not_polled_is_served_over_modbus(client: tuple[Gateway, AsyncModbusTcpClient]) -> None:
    gw, modbus = client
    peer = get_simulator("sim://feed")
    (unit,) = gw.units
    assert unit.poller is None  # nothing polls: the runner fills the image

    async def pushed() -> bool:
        reply = await modbus.read_holding_registers(3, count=1, device_id=9)
        return not reply.isError() and list(reply.registers) == [333]

    await until(pushed, 3.0, step=0.01, what="the value the peer set never reached Modbus")
    first = await modbus.read_holding_registers(0, count=1, device_id=9)
    assert list(first.registers) == [111]
    never = await modbus.read_holding_registers(1, count=1, device_id=9)
    assert never.isError() and never.exception_code == 0x0B  # nobody set it: no invented zero

    assert not (await modbus.write_register(5, 555, device_id=9)).isError()
    written = await modbus.read_holding_registers(5, count=1, device_id=9)
    assert list(written.registers) == [555]
    peer.script[:] = [b"G 5", b"G 1"]

    async def answered() -> bool:
        return len(peer.answers) >= 4

    await until(answered, 3.0, step=0.01, what="the peer's gets were not answered")
    assert peer.answers == [b"K 0", b"K 3", b"V 5 555", b"X 1"]
    peer.silent = True

    async def stale() -> bool:
        reply = await modbus.read_holding_registers(0, count=1, device_id=9)
        return reply.isError() and reply.exception_code == 0x0B

    await until(stale, 3.0, step=0.01, what="values did not go stale after the peer fell silent for stale_after")
    status = await modbus.read_input_registers(1000, count=11, device_id=9)
    assert status.registers[0] == 1 and status.registers[3:5] == [0, 4]  # link up, 4 messages
