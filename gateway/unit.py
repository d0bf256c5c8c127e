"""One controller served as one Modbus unit: driver + read plan + cache + poller + access rules.

A unit is *polled* (the default: its poller reads the plan's blocks from the controller) or not
(its class sets :attr:`Unit.POLLED` False: the kind's runner owns the line and fills the image itself, with
:meth:`Unit.store` when data arrives and :meth:`Unit.heard` when the peer is heard from; a
non-polled value never ages on its own and is stale only once the peer has been silent for
``stale_after``).  Everything else (the image, the status block, writes, access rules) is the same.

Reads are answered from the images (``gateway.image``), which the cache fills when a block is
stored, and note their request as demand (``gateway.schedule``); writes go through to the controller
and are answered only after it confirmed them, then patch the cache (never its read times).  A stale
read on a link that is up may wait ``read_wait`` for its blocks (StaleRead).

A value is stale (exception 0x0B) when its block was last read longer ago than ``stale_after`` plus
the period planned for the block at that read (its class's when demanded, else ``background_interval``
if longer), or when the controller has answered no poll for ``stale_after`` plus the shortest scan
period (the silent limit): a slow-class value read every 10 s is not stale 5 s after its read while
the link is up, and no value outlives a silent link by more than ``stale_after`` (plus
``fast_interval``).  Values read before a link loss are stale from its recovery until read again.

Error translation (controller -> Modbus exception; errors by type: ``gateway.errors.MODBUS_CODES``):

=================================================  =====
unmapped address, read-only point, ``read_only``    0x02
value out of range (e.g. > 9999 on an SLC 100/150)  0x03
controller refused (``;E``, PCCC STS), protected     0x04
no answer, link down, stale data                     0x0B
a write whose outcome is unknown (sent once)         0x0B
a write not done within ``write_timeout``            0x0B
=================================================  =====

The write side (validation, steps, the queue, ``write_timeout``) is the base class
:class:`gateway.unit_writes.UnitWrites`; this module is the unit's core and its reads.
"""

from __future__ import annotations

import asyncio
import struct
from abc import abstractmethod
from collections.abc import Callable, Sequence
from functools import partial
from typing import ClassVar, NotRequired, TypedDict, TypeVar

from gateway.cache import BlockCache
from gateway.errors import ControllerRefused, GatewayError, ModbusExceptionReply, StaleRead
from gateway.freshness import Freshness, LinkVerdict, Offline, Source
from gateway.image import ImageMiss, Images
from gateway.latency import LATENCY_BUCKETS, LatencyHistogram
from gateway.line_driver import UnitDriver
from gateway.modbus.mapping import (
    STATUS_BASE,
    STATUS_REGISTERS,
    Block,
    Plan,
    Scan,
    Table,
)
from gateway.poller import LineShare, Poller
from gateway.schedule import (
    DEFAULT_BACKGROUND_INTERVAL,
    DEFAULT_DEMAND_HOLD,
    DEFAULT_READ_WAIT,
    NEVER,
    DemandLog,
    Schedule,
)
from gateway.unit_writes import UnitWrites, WritableRange

__all__ = ["LATENCY_BUCKETS", "LatencyHistogram", "Source", "Unit", "UnitOptions"]

ILLEGAL_ADDRESS = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS
DEVICE_FAILURE = ModbusExceptionReply.SERVER_DEVICE_FAILURE
TARGET_FAILED = ModbusExceptionReply.GATEWAY_TARGET_FAILED

#: The write target types of a unit's plan: R for a holding register, B for a coil.
R = TypeVar("R")
B = TypeVar("B")


class UnitOptions(TypedDict):
    """The keyword arguments of :class:`Unit` every link has, whatever its kind."""

    unit_id: int
    name: str
    stale_after: NotRequired[float]
    read_only: NotRequired[bool]
    writable: NotRequired[Sequence[WritableRange]]
    fast_interval: NotRequired[float]
    slow_interval: NotRequired[float]
    demand_hold: NotRequired[float]
    background_interval: NotRequired[float]
    read_wait: NotRequired[float]
    #: the pollers of units that share one line (not a config key: the kind's build gives it)
    line_share: NotRequired[LineShare | None]
    write_burst: NotRequired[int]
    poll_burst: NotRequired[int]
    write_queue_per_client: NotRequired[int]
    write_queue_per_link: NotRequired[int]
    write_timeout: NotRequired[float]
    stagger: NotRequired[float | None]
    offline: NotRequired[Offline]


def _pack_registers(values: Sequence[int]) -> bytes:
    return struct.pack(f">{len(values)}H", *values)


class Unit(UnitWrites[R, B]):
    """A link as a Modbus unit.  Subclasses: the link kind's plan, block reads and writes (the write
    hooks and steps of its base, :class:`~gateway.unit_writes.UnitWrites`).

    Generic in the plan's write targets: ``R`` for a holding register, ``B`` for a coil (a
    link kind's own types, e.g. a file address and a bit), so that a subclass's write hooks take
    exactly the targets its plan holds.
    """

    POLLED: ClassVar[bool] = True  #: False: the kind's runner fills the image (module doc; LinkKind.is_polled)

    def __init__(
        self,
        *,
        unit_id: int,
        name: str,
        driver: UnitDriver,
        plan: Plan[R, B],
        stale_after: float = 5.0,
        writable: Sequence[WritableRange] = (),
        fast_interval: float = 0.0,
        slow_interval: float = 10.0,
        demand_hold: float = DEFAULT_DEMAND_HOLD,
        background_interval: float = DEFAULT_BACKGROUND_INTERVAL,
        read_wait: float = DEFAULT_READ_WAIT,
        line_share: LineShare | None = None,
        write_burst: int = 1,
        poll_burst: int = 2,
        write_queue_per_client: int = 8,
        write_queue_per_link: int = 32,
        write_timeout: float = 0.9,
        stagger: float | None = None,
        read_only: bool = False,
        offline: Offline = Offline.EXCEPTION,
    ) -> None:
        super().__init__(
            name=name, driver=driver, writable=writable, read_only=read_only, write_burst=write_burst,
            poll_burst=poll_burst, write_queue_per_client=write_queue_per_client,
            write_queue_per_link=write_queue_per_link, write_timeout=write_timeout,
        )
        self.unit_id = unit_id
        self.name = name
        self.driver = driver
        self.plan = plan
        self.stale_after = stale_after
        #: seconds a read of data not read yet or stale may wait for its block (0: answer at once)
        self.read_wait = read_wait
        #: the requests clients read from the image (folded into demand by the poller)
        self.demand = DemandLog()
        #: the read order and the stale limits of a polled unit (None: not polled)
        self.schedule = Schedule(
            [block.scan for block in plan.blocks], fast_interval=fast_interval, slow_interval=slow_interval,
            stale_after=stale_after, demand_hold=demand_hold, background_interval=background_interval,
        ) if self.POLLED else None
        #: the one verdict on the unit's data and link (``gateway.freshness``): every face reads it
        self.freshness = Freshness(stale_after=stale_after, schedule=self.schedule, link=driver,
                                   blocks=len(plan.blocks))
        #: what a client's read of data that is not fresh gets (``gateway.freshness.Offline``)
        self.offline = Offline(offline)
        #: the four tables decoded when a block is stored (a read is a slice)
        self.images = Images(plan, self.freshness.deadline)
        self.cache = BlockCache([block.size for block in plan.blocks], images=self.images,
                                fast=[i for i, block in enumerate(plan.blocks) if block.scan is Scan.FAST])
        self.freshness.watch(self.cache, self.images)
        #: None: not polled (the kind's runner fills the image)
        self.poller = Poller(
            name, plan.blocks, self.cache, self.read_block, fast_interval=fast_interval, slow_interval=slow_interval,
            responding=lambda: self.freshness.link.available,
            ready=driver.first_attempt,
            stagger=stagger,  # None: a share of fast_interval from the name (gateway.poller.default_stagger)
            schedule=self.schedule, demand=self.demand, share=line_share,
        ) if self.schedule is not None else None

    # --- what runs, and what fills the image ---------------------------------------------------

    async def run(self) -> None:
        """Poll until cancelled; a unit that is not polled has nothing to run (its runner fills it)."""
        if self.poller is not None:
            await self.poller.run()

    def store(self, block: int, data: bytes, now: float) -> None:
        """New bytes of block ``block`` (its index in the plan), read or received at loop time ``now``."""
        self.cache.store(block, data, now)

    def heard(self, now: float) -> None:
        """The peer was heard from at ``now`` without new data (a non-polled unit is not silent)."""
        self.cache.newest = max(self.cache.newest, now)

    def data_age(self, now: float) -> float:
        """Polled: seconds since the oldest fast-class block was read.  Not polled: since the peer was
        last heard.  +Inf: never (``gateway.freshness.Freshness.data_age``)."""
        return self.freshness.data_age(now)

    def verdict(self, now: float) -> LinkVerdict:
        """The link's state at ``now``: up, stale or down (``gateway.freshness``, the one verdict)."""
        return self.freshness.verdict(now)

    @property
    def last_error(self) -> GatewayError | None:
        """The error of the last failed poll (None: the last poll succeeded, or none ran)."""
        return self.poller.last_error if self.poller is not None else None

    @property
    def last_error_at(self) -> float | None:
        return self.poller.last_error_at if self.poller is not None else None

    # --- protocol hooks ---------------------------------------------------------------------

    @abstractmethod
    async def read_block(self, block: Block) -> bytes: ...

    @property
    @abstractmethod
    def last_fault_number(self) -> int: ...

    @property
    def kind_counter(self) -> int:
        """The status block's kind counter (1009-1010): what it counts is the kind's ``status_counter``."""
        return 0

    # --- reads ------------------------------------------------------------------------------

    def read_register_bytes(self, table: Table, address: int, count: int, source: Source = Source.SERVE) -> bytes:
        """Registers ``address``.. (``count``) as the big-endian bytes of a FC3/FC4 reply: a slice of the
        image; the first unmapped or stale register, in address order, decides the exception.
        ``source``: who reads (``gateway.freshness.Source``: a client's read is demand and gets the
        ``offline`` policy; a peek is neither)."""
        now = self._loop_time()
        if table is Table.INPUT and address >= STATUS_BASE:
            return _pack_registers(self._status(address, count, now))
        return self._read(table, address, count, now, source, self.images.registers, f"{table.value} register")

    def read_bit_bytes(self, table: Table, address: int, count: int, source: Source = Source.SERVE) -> bytes:
        """Bits ``address``.. (``count``) packed LSB first, as the payload of a FC1/FC2 reply."""
        return self._read(table, address, count, self._loop_time(), source, self.images.bits, table.value)

    def _read(self, table: Table, address: int, count: int, now: float, source: Source,
              read: Callable[[Table, int, int, float], bytes], what: str) -> bytes:
        serve = source is Source.SERVE
        if serve:
            self.demand.keys[(table, address, count)] = now  # demand: one dict store (note_demand)
        if self.freshness.silent(now) and self.images.mapped(table, address, count):
            miss = ImageMiss(address, self.images.blocks_in(table, address, 1)[0])
            answer = self._stale()
        else:
            try:
                return read(table, address, count, now)
            except ImageMiss as found:
                miss = found
            answer = self._miss(table, miss, what, address, count, now, serve)
        if serve and answer.code == TARGET_FAILED and miss.block is not None:
            held = self._offline_bytes(table, address, count, now)
            if held is not None:
                if isinstance(answer, StaleRead):
                    answer.held = held  # served after the read's wait if the data is still not fresh
                else:
                    return held
        raise answer

    def note_demand(self, table: Table, address: int, count: int) -> None:
        """Count a read of ``address``.. (``count``) as demand without reading (a face that demands
        but peeks, as the Sparkplug node with ``demand = true``)."""
        self.demand.keys[(table, address, count)] = self._loop_time()

    def _offline_bytes(self, table: Table, address: int, count: int, now: float) -> bytes | None:
        """What the ``offline`` policy serves for data that is not fresh (None: the exception)."""
        policy = self.offline
        if policy is Offline.EXCEPTION:
            return None
        images, stamps = self.images, self.cache.stamps
        if policy is Offline.HOLD and any(stamps[b] == NEVER for b in images.blocks_in(table, address, count)):
            return None  # nothing read yet to hold
        return images.held(table, address, count, None if policy is Offline.HOLD else now)

    def read_registers(self, table: Table, address: int, count: int) -> list[int]:
        return list(struct.unpack(f">{count}H", self.read_register_bytes(table, address, count)))

    def read_bits(self, table: Table, address: int, count: int) -> list[bool]:
        bits = int.from_bytes(self.read_bit_bytes(table, address, count), "little")
        return [bool(bits >> k & 1) for k in range(count)]

    def _loop_time(self) -> float:
        return asyncio.get_running_loop().time()

    def _miss(self, table: Table, miss: ImageMiss, what: str, address: int, count: int,
              now: float, serve: bool = True) -> ModbusExceptionReply:
        if miss.block is None:
            return ModbusExceptionReply(ILLEGAL_ADDRESS, f"{what} {miss.address} is not mapped")
        stale = self._stale(miss.block)
        poller = self.poller
        if (not serve or stale.code != TARGET_FAILED or poller is None or not poller.running or self.read_wait <= 0
                or not self.freshness.link.available):
            return stale
        # The link is up: the reader may wait for an immediate read of the stale blocks.
        blocks = self.images.stale_blocks(table, address, count, now)
        return StaleRead(str(stale), partial(poller.wait_for, blocks), self.read_wait)

    def _stale(self, block: int | None = None) -> ModbusExceptionReply:
        refused = self.poller.refused.get(block) if block is not None and self.poller is not None else None
        if refused is not None:
            return self.refusal_exception(refused[0])
        return ModbusExceptionReply(TARGET_FAILED, f"{self.name}: no fresh data (stale after {self.stale_after:g} s)")

    def refusal_exception(self, error: ControllerRefused) -> ModbusExceptionReply:
        """The Modbus answer for data the controller refuses to give (its reason in the message)."""
        return ModbusExceptionReply(DEVICE_FAILURE, f"{self.name}: {error}")

    def status_values(self, now: float) -> dict[str, int]:
        counters = self.driver.counters
        verdict = self.freshness.verdict(now)
        age = verdict.age
        return {
            "link_up": 1 if verdict.up else 0,
            "data_age": min(65535, int(age * 10)) if age != float("inf") else 65535,
            "last_fault": self.last_fault_number,
            "transactions": counters.transactions,
            "errors": counters.errors,
            "retries": counters.retries,
            "kind_counter": self.kind_counter,
            "state": verdict.state.number,
        }

    def _status(self, address: int, count: int, now: float) -> list[int]:
        values = self.status_values(now)
        registers: list[int] = []
        for key, width in STATUS_REGISTERS:
            value = values[key] & 0xFFFFFFFF
            registers.extend([value >> 16, value & 0xFFFF] if width == 2 else [min(value, 0xFFFF)])
        first = address - STATUS_BASE
        if first + count > len(registers):
            raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"status block is input registers {STATUS_BASE}-"
                                       f"{STATUS_BASE + len(registers) - 1}")
        return registers[first : first + count]
