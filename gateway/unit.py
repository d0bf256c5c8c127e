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

Every write request is answered within ``write_timeout``.  A write still waiting for the line
then is withdrawn: nothing of it is written.  A write already on the line is answered 0x0B
(outcome unknown) and goes on to its verdict, applied at most once, which the ``gateway.audit``
log reports; a multi-command write sends no further command after the answer.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Sequence
from functools import partial
from typing import ClassVar, Generic, NotRequired, TypedDict, TypeVar

from gateway.cache import BlockCache
from gateway.clients import current_client
from gateway.errors import ControllerRefused, GatewayError, ModbusExceptionReply, StaleRead
from gateway.freshness import Freshness, LinkVerdict, Offline, Source
from gateway.image import ImageMiss, Images
from gateway.latency import LATENCY_BUCKETS, LatencyHistogram
from gateway.line_driver import LineLease, UnitDriver
from gateway.modbus.mapping import (
    STATUS_BASE,
    STATUS_REGISTERS,
    BitPoint,
    Block,
    Half,
    Plan,
    RegisterPoint,
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
from gateway.write_steps import WritableRange, WriteStep, WriteTally, in_writable, run_step, span, spans, target_of
from gateway.write_steps import translated as translated
from gateway.writes import WriteQueue

__all__ = [
    "LATENCY_BUCKETS", "LatencyHistogram", "Source", "Unit", "UnitOptions", "WritableRange", "WriteStep", "in_writable",
    "translated",
]

log = logging.getLogger("gateway.unit")
audit = logging.getLogger("gateway.audit")

ILLEGAL_ADDRESS = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS
ILLEGAL_VALUE = ModbusExceptionReply.ILLEGAL_DATA_VALUE
DEVICE_FAILURE = ModbusExceptionReply.SERVER_DEVICE_FAILURE
TARGET_FAILED = ModbusExceptionReply.GATEWAY_TARGET_FAILED


#: The write target types of a unit's plan: R for a holding register, B for a coil.
R = TypeVar("R")
B = TypeVar("B")

#: Seconds a 0x06 (busy) answer to a write is held before it is sent.
BUSY_HOLD = 0.1


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


class Unit(ABC, Generic[R, B]):
    """A link as a Modbus unit.  Subclasses: the link kind's plan, block reads and writes.

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
        self.unit_id = unit_id
        self.name = name
        self.driver = driver
        self.plan = plan
        self.stale_after = stale_after
        self.read_only = read_only
        self.writable = tuple(writable)
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
        self.write_requests = 0
        self.write_failures = 0
        #: seconds from a write request's arrival to its answer, success or exception
        self.write_latency = LatencyHistogram()
        #: write requests the controller refused after part of them was applied
        self.partial_writes = 0
        #: write commands sent again (proved not applied) and whose outcome stayed unknown
        self.write_tally = WriteTally()
        driver.write_burst = write_burst
        driver.poll_burst = poll_burst
        self.writes = WriteQueue(driver, name, per_client=write_queue_per_client, per_link=write_queue_per_link)
        #: every write request is answered within this many seconds (see _queue_write)
        self.write_timeout = write_timeout

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

    # The write hooks run one command on ``line``, the write session's lease: they pass it to
    # their driver's request (``LineDriver.submit(op, line=line)``).

    @abstractmethod
    async def _write_register(self, target: R, value: int, line: LineLease) -> None: ...

    async def _write_pair(self, target: R, raw: int, line: LineLease) -> None:
        """Write the 32 bits of a value held in two registers (both at once: a float)."""
        raise ModbusExceptionReply(ILLEGAL_ADDRESS, "this unit has no 32-bit registers")

    @abstractmethod
    async def _write_bit(self, target: B, value: bool, line: LineLease) -> None: ...

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

    # --- writes -----------------------------------------------------------------------------
    #
    # A write request is validated whole (ranges, ``writable``, value limits, what the image
    # knows the controller will refuse, float pairing) before anything is queued; then it is
    # cut into steps, one controller command each (as few as the protocol allows), queued on
    # the link's write queue in arrival order and run there.  When the controller refuses a
    # step after earlier ones were applied, the request is answered with the exception, and
    # the registers written are logged and counted (``partial_writes``): never a success for a
    # partial write, never a silent one.

    def _check_writable(self, table: Table, address: int, count: int) -> None:
        if self.read_only:
            raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"{self.name} is read only")
        if not in_writable(self.writable, table, address, count):
            raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"{table.value} {address} is not in a writable range")

    def _refused_by_image(self, point: RegisterPoint[R]) -> str | None:
        """Why the controller is known (from the image) to refuse a write to ``point``, or None."""
        return None

    def _footprint(self, target: R | B) -> Hashable:
        """The controller word a write target changes (writes to one word stay in arrival order)."""
        address: Hashable = getattr(target, "address", target)
        return address

    def _register_steps(self, checked: list[tuple[int, RegisterPoint[R], int]]) -> list[WriteStep]:
        """One step per word, one per 32-bit pair (its two registers); protocols may merge more."""
        steps: list[WriteStep] = []
        i = 0
        while i < len(checked):
            address, point, value = checked[i]
            target = target_of(point)
            if point.codec.half is not None:
                pair = checked[i : i + 2]
                halves = {p.codec.half: v for _, p, v in pair}
                raw = halves[Half.HIGH] << 16 | halves[Half.LOW]
                steps.append(WriteStep(address, address + 1, partial(self._write_pair, target, raw),
                                   [(p, v) for _, p, v in pair]))
                i += 2
                continue
            write = partial(self._write_register, target, value)
            steps.append(WriteStep(address, address, write, [(point, value)]))
            i += 1
        return steps

    def _bit_steps(self, checked: list[tuple[int, BitPoint[B], bool]]) -> list[WriteStep]:
        """One step per coil; protocols may merge more."""
        return [WriteStep(a, a, partial(self._write_bit, target_of(bit), value), bit_patches=[(bit, value)])
                for a, bit, value in checked]

    def check_register_write(self, address: int, values: Sequence[int]) -> list[tuple[int, RegisterPoint[R], int]]:
        """Validate a whole FC6/FC16: (address, point, value) per register, or the exception."""
        self._check_writable(Table.HOLDING, address, len(values))
        points = self.plan.holding
        checked: list[tuple[int, RegisterPoint[R], int]] = []
        for i, value in enumerate(values):
            point = points.get(address + i)
            if point is None or point.write is None:
                raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"holding register {address + i} is not writable")
            if value > point.max_value:
                raise ModbusExceptionReply(ILLEGAL_VALUE, f"holding register {address + i}: {value} > "
                                           f"{point.max_value}")
            refused = self._refused_by_image(point)
            if refused is not None:
                raise ModbusExceptionReply(DEVICE_FAILURE, f"holding register {address + i}: {refused}; "
                                           "nothing written")
            checked.append((address + i, point, value))
        i = 0
        while i < len(checked):
            point = checked[i][1]
            if point.codec.half is not None:
                pair = checked[i : i + 2]
                if len(pair) < 2 or pair[1][1].write != point.write or {p.codec.half for _, p, _ in pair} != {
                    Half.HIGH, Half.LOW
                }:
                    raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"holding register {checked[i][0]} is half of a "
                                               "32-bit value: write both of its registers in one request")
                i += 2
            else:
                i += 1
        return checked

    async def write_registers(self, address: int, values: Sequence[int]) -> None:
        checked = self.check_register_write(address, values)
        steps = self._register_steps(checked)
        footprint = frozenset(self._footprint(target_of(p)) for _, p, _ in checked)
        await self._queue_write(Table.HOLDING, steps, footprint)

    async def write_bits(self, address: int, values: Sequence[bool]) -> None:
        self._check_writable(Table.COIL, address, len(values))
        points = self.plan.coils
        for i in range(len(values)):
            point = points.get(address + i)
            if point is None or point.write is None:
                raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"coil {address + i} is not writable")
        steps = self._bit_steps([(address + i, points[address + i], value) for i, value in enumerate(values)])
        footprint = frozenset(self._footprint(target_of(points[address + i])) for i in range(len(values)))
        await self._queue_write(Table.COIL, steps, footprint)

    async def _queue_write(self, table: Table, steps: list[WriteStep], footprint: frozenset[Hashable]) -> None:
        """Queue the steps now (arrival order) and wait for them, at most ``write_timeout``;
        errors as Modbus exceptions."""
        self.write_requests += 1
        started = self._loop_time()
        deadline = started + self.write_timeout
        try:
            try:
                future = self.writes.submit(current_client.get(), footprint,
                                            partial(self._run_steps, table, steps, deadline))
            except ModbusExceptionReply:
                # Busy: the answer is held a moment, so that a master re-sending at once costs
                # at most a few answers per second per request it keeps in flight, not a spin.
                await asyncio.sleep(BUSY_HOLD)
                raise
            try:
                async with asyncio.timeout_at(deadline):
                    await asyncio.shield(future)
            except TimeoutError:
                raise self._late_write(table, steps, future) from None
        except ModbusExceptionReply:
            self.write_failures += 1
            raise
        finally:
            self.write_latency.observe(self._loop_time() - started)

    def _late_write(self, table: Table, steps: list[WriteStep],
                    future: asyncio.Future[None]) -> ModbusExceptionReply:
        """The answer to a write not done within ``write_timeout``."""
        what = f"{table.value} {span(steps[0].first, steps[-1].last)}"
        seconds = f"{self.write_timeout:g} s"
        if self.writes.withdraw(future):
            audit.info("unit %d: %s not sent within write_timeout %s: withdrawn, nothing written",
                       self.unit_id, what, seconds)
            return ModbusExceptionReply(
                TARGET_FAILED,
                f"link {self.name}: the line was busy for write_timeout ({seconds}): the write was withdrawn, "
                "nothing was written; send it again")

        def outcome(done: asyncio.Future[None]) -> None:
            if done.cancelled():  # the gateway stopped while it was on the line
                verdict: object = "not known (the gateway stopped before its verdict)"
            else:
                verdict = done.exception() or "applied"
            audit.info("unit %d: %s answered 0x0B at write_timeout %s, then: %s", self.unit_id, what, seconds, verdict)

        future.add_done_callback(outcome)
        return ModbusExceptionReply(
            TARGET_FAILED,
            f"link {self.name}: no verdict within write_timeout ({seconds}): outcome unknown, applied at most "
            "once (the audit log gives the outcome)")

    async def _run_steps(self, table: Table, steps: list[WriteStep], deadline: float, line: LineLease) -> None:
        """The write job (``gateway.writes``): the steps in order on ``line``, the session's lease."""
        done: list[WriteStep] = []
        for step in steps:
            if done and self._loop_time() >= deadline:
                # answered 0x0B already: send nothing more of it
                exc = ModbusExceptionReply(TARGET_FAILED, "write_timeout passed before this command")
                self._partial_write(table, done, step, exc)
                raise exc
            try:
                await run_step(step, line, deadline, self._loop_time, self.proves_not_applied, self.write_tally,
                               self.name)
            except ModbusExceptionReply as exc:
                if done:
                    self._partial_write(table, done, step, exc)
                raise
            for point, value in step.patches:
                self._patch(point, value)
            for bit, on in step.bit_patches:
                byte = self.cache.data[bit.block][bit.offset]
                byte = byte | (1 << bit.bit) if on else byte & ~(1 << bit.bit)
                self.cache.patch(bit.block, bit.offset, bytes([byte & 0xFF]))
            done.append(step)

    def proves_not_applied(self, step: WriteStep, shown: bytes) -> bool:
        """Whether ``shown`` (what a read-back after the step's command gave) proves it was not applied: the
        kind decides (DF1 full duplex: the value from before the write); by default never."""
        return False

    def _partial_write(self, table: Table, done: list[WriteStep], failed: WriteStep, exc: ModbusExceptionReply) -> None:
        self.partial_writes += 1
        written = spans(done)
        log.warning(
            "link %s: write partly applied: %s %s written, %s %s and after not (%s); answered 0x%02X",
            self.name, table.value, written, table.value, span(failed.first, failed.last), exc, exc.code,
        )

    def _patch(self, point: RegisterPoint[R], value: int) -> None:
        """Put a confirmed register value into its block's bytes where its codec reads them."""
        codec = point.codec
        lsb = point.offset + codec.lsb
        if codec.msb is None:
            self.cache.patch(point.block, lsb, bytes((value & 0xFF,)))
            return
        msb = point.offset + codec.msb
        if msb == lsb - 1:
            self.cache.patch(point.block, msb, value.to_bytes(2, "big"))
        elif msb == lsb + 1:
            self.cache.patch(point.block, lsb, value.to_bytes(2, "little"))
        else:
            self.cache.patch(point.block, msb, bytes((value >> 8 & 0xFF,)))
            self.cache.patch(point.block, lsb, bytes((value & 0xFF,)))
