"""One controller served as one Modbus unit: driver + read plan + cache + poller + access rules.

Reads are answered from the register and bit images (``gateway.image``), which the cache fills
when a block is stored; writes go through to the controller and are answered only after it
confirmed them, then patch the cache (never its read times).

A value is stale (exception 0x0B) when its own block was last read longer ago than
``stale_after`` plus the period of its scan class (``fast_interval`` or ``slow_interval``), or when
the controller has answered no poll for ``stale_after`` plus the shortest scan period: a
slow-class value read every 10 s is not stale 5 s after its read while the link is up, and no
value outlives a silent link by more than ``stale_after`` (plus ``fast_interval``).

Error translation (controller -> Modbus exception):

=================================================  =====
unmapped address, read-only point, ``read_only``    0x02
value out of range (e.g. > 9999 on an SLC 100/150)  0x03
controller refused (``;E``, PCCC STS), protected     0x04
no answer, link down, stale data                     0x0B
=================================================  =====
"""

from __future__ import annotations

import asyncio
import struct
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Sequence
from typing import cast

from gateway.cache import BlockCache
from gateway.drivers.base import LinkDriver
from gateway.drivers.slc_ascii import SlcAsciiDriver
from gateway.errors import (
    ControllerRefused,
    GatewayError,
    InvalidRequest,
    LinkError,
    ModbusExceptionReply,
    ProtocolError,
)
from gateway.image import ImageMiss, Images
from gateway.modbus.mapping import (
    STATUS_BASE,
    STATUS_REGISTERS,
    Block,
    Codec,
    Plan,
    RegisterPoint,
    Scan,
    SlcBitWrite,
    SlcWordWrite,
    Table,
    slc_ascii_plan,
)
from gateway.poller import Poller

__all__ = ["SlcAsciiUnit", "Unit", "WritableRange"]

ILLEGAL_ADDRESS = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS
ILLEGAL_VALUE = ModbusExceptionReply.ILLEGAL_DATA_VALUE
DEVICE_FAILURE = ModbusExceptionReply.SERVER_DEVICE_FAILURE
TARGET_FAILED = ModbusExceptionReply.GATEWAY_TARGET_FAILED

WritableRange = tuple[Table, int, int]  # table, first, last


def _pack_registers(values: Sequence[int]) -> bytes:
    return struct.pack(f">{len(values)}H", *values)


class Unit(ABC):
    """A link as a Modbus unit.  Subclasses: the protocol's plan, block reads and writes."""

    def __init__(
        self,
        *,
        unit_id: int,
        name: str,
        driver: LinkDriver,
        plan: Plan,
        stale_after: float = 5.0,
        read_only: bool = False,
        writable: Sequence[WritableRange] = (),
        fast_interval: float = 0.0,
        slow_interval: float = 10.0,
    ) -> None:
        self.unit_id = unit_id
        self.name = name
        self.driver = driver
        self.plan = plan
        self.stale_after = stale_after
        self.read_only = read_only
        self.writable = tuple(writable)
        period = {Scan.FAST: fast_interval, Scan.SLOW: slow_interval}
        #: per block: the largest age at which its bytes are still served
        self._max_age = [stale_after + period[block.scan] for block in plan.blocks]
        #: the four tables decoded when a block is stored (a read is a slice)
        self.images = Images(plan, self._max_age)
        self.cache = BlockCache(
            [block.size for block in plan.blocks],
            images=self.images,
            fast=[i for i, block in enumerate(plan.blocks) if block.scan is Scan.FAST],
        )
        #: the controller is silent after this long without an answer to a poll (the poller asks
        #: every fast_interval, or only every slow_interval when the plan has no fast class)
        self._silent_after = min(self._max_age, default=stale_after)
        self.poller = Poller(
            name,
            plan.blocks,
            self.cache,
            self.read_block,
            fast_interval=fast_interval,
            slow_interval=slow_interval,
            responding=lambda: driver.available,
        )
        self.write_requests = 0
        self.write_failures = 0

    # --- protocol hooks ---------------------------------------------------------------------

    @abstractmethod
    async def read_block(self, block: Block) -> bytes: ...

    @abstractmethod
    async def _write_register(self, target: object, value: int) -> None: ...

    async def _write_float(self, target: object, raw: int) -> None:
        """Write the 32 bits of a float (both of its registers at once)."""
        raise ModbusExceptionReply(ILLEGAL_ADDRESS, "this unit has no float registers")

    @abstractmethod
    async def _write_bit(self, target: object, value: bool) -> None: ...

    @property
    @abstractmethod
    def last_fault_number(self) -> int: ...

    @property
    def id_resyncs(self) -> int:
        return self.driver.counters.id_resyncs

    # --- reads ------------------------------------------------------------------------------

    def read_register_bytes(self, table: Table, address: int, count: int) -> bytes:
        """Registers ``address``.. (``count``) as the big-endian bytes of a FC3/FC4 reply.

        Served from the image (a slice); the first unmapped or stale register, in address
        order, decides the exception.
        """
        now = self._loop_time()
        if table is Table.INPUT and address >= STATUS_BASE:
            return _pack_registers(self._status(address, count, now))
        if now - self.cache.newest > self._silent_after and self.images.mapped(table, address, count):
            raise self._stale()
        try:
            return self.images.registers(table, address, count, now)
        except ImageMiss as miss:
            raise self._miss(table, miss, f"{table.value} register") from None

    def read_bit_bytes(self, table: Table, address: int, count: int) -> bytes:
        """Bits ``address``.. (``count``) packed LSB first, as the payload of a FC1/FC2 reply."""
        now = self._loop_time()
        if now - self.cache.newest > self._silent_after and self.images.mapped(table, address, count):
            raise self._stale()
        try:
            return self.images.bits(table, address, count, now)
        except ImageMiss as miss:
            raise self._miss(table, miss, table.value) from None

    def read_registers(self, table: Table, address: int, count: int) -> list[int]:
        return list(struct.unpack(f">{count}H", self.read_register_bytes(table, address, count)))

    def read_bits(self, table: Table, address: int, count: int) -> list[bool]:
        bits = int.from_bytes(self.read_bit_bytes(table, address, count), "little")
        return [bool(bits >> k & 1) for k in range(count)]

    def _loop_time(self) -> float:
        return asyncio.get_running_loop().time()

    def _miss(self, table: Table, miss: ImageMiss, what: str) -> ModbusExceptionReply:
        if miss.block is None:
            return ModbusExceptionReply(ILLEGAL_ADDRESS, f"{what} {miss.address} is not mapped")
        return self._stale(miss.block)

    def _silent(self, now: float) -> bool:
        """The controller answered no poll for ``stale_after`` seconds past its scan period."""
        return now - self.cache.newest > self._silent_after

    def _stale(self, block: int | None = None) -> ModbusExceptionReply:
        refused = self.poller.refused.get(block) if block is not None else None
        if refused is not None:
            return self.refusal_exception(refused[0])
        return ModbusExceptionReply(TARGET_FAILED, f"{self.name}: no fresh data (stale after {self.stale_after:g} s)")

    def refusal_exception(self, error: ControllerRefused) -> ModbusExceptionReply:
        """The Modbus answer for data the controller refuses to give (its reason in the message)."""
        return ModbusExceptionReply(DEVICE_FAILURE, f"{self.name}: {error}")

    def status_values(self, now: float) -> dict[str, int]:
        counters = self.driver.counters
        age = self.cache.oldest_fast_age(now)
        return {
            "link_up": 1 if self.driver.available else 0,
            "data_age": min(65535, int(age * 10)) if age != float("inf") else 65535,
            "last_fault": self.last_fault_number,
            "transactions": counters.transactions,
            "errors": counters.errors,
            "retries": counters.retries,
            "id_resyncs": self.id_resyncs,
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

    def _check_writable(self, table: Table, address: int, count: int) -> None:
        if self.read_only:
            raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"{self.name} is read only")
        if self.writable and not any(
            t is table and first <= address and address + count - 1 <= last for t, first, last in self.writable
        ):
            raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"{table.value} {address} is not in a writable range")

    async def _through(self, write: Awaitable[None]) -> None:
        """Await a write coroutine, translating controller errors to Modbus exceptions."""
        self.write_requests += 1
        try:
            await write
        except ModbusExceptionReply:
            self.write_failures += 1
            raise  # already translated (e.g. a PCCC address problem: 0x02)
        except ControllerRefused as exc:
            self.write_failures += 1
            raise ModbusExceptionReply(DEVICE_FAILURE, str(exc)) from exc
        except InvalidRequest as exc:
            self.write_failures += 1
            raise ModbusExceptionReply(ILLEGAL_VALUE, str(exc)) from exc
        except (LinkError, ProtocolError) as exc:
            self.write_failures += 1
            raise ModbusExceptionReply(TARGET_FAILED, str(exc)) from exc
        except GatewayError as exc:
            self.write_failures += 1
            raise ModbusExceptionReply(DEVICE_FAILURE, str(exc)) from exc

    async def write_registers(self, address: int, values: Sequence[int]) -> None:
        self._check_writable(Table.HOLDING, address, len(values))
        points = self.plan.holding
        checked: list[tuple[RegisterPoint, int]] = []
        for i, value in enumerate(values):
            point = points.get(address + i)
            if point is None or point.write is None:
                raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"holding register {address + i} is not writable")
            if value > point.max_value:
                raise ModbusExceptionReply(ILLEGAL_VALUE, f"holding register {address + i}: {value} > "
                                           f"{point.max_value}")
            checked.append((point, value))
        i = 0
        while i < len(checked):
            point, value = checked[i]
            if point.codec in (Codec.F32_HIGH, Codec.F32_LOW):
                if i + 1 >= len(checked) or checked[i + 1][0].write != point.write:
                    raise ModbusExceptionReply(ILLEGAL_ADDRESS, "a float32 takes both of its registers in one write")
                pair = checked[i : i + 2]
                halves = {p.codec: v for p, v in pair}
                if set(halves) != {Codec.F32_HIGH, Codec.F32_LOW}:
                    raise ModbusExceptionReply(ILLEGAL_ADDRESS, "a float32 takes both of its registers in one write")
                raw = halves[Codec.F32_HIGH] << 16 | halves[Codec.F32_LOW]
                await self._through(self._write_float(point.write, raw))
                for p, v in pair:
                    self._patch(p, v)
                i += 2
                continue
            await self._through(self._write_register(point.write, value))
            self._patch(point, value)
            i += 1

    def _patch(self, point: RegisterPoint, value: int) -> None:
        o = point.offset
        if point.codec in (Codec.U16_BE, Codec.U16_BE_MASKED):
            self.cache.patch(point.block, o, value.to_bytes(2, "big"))
        elif point.codec is Codec.U16_LE:
            self.cache.patch(point.block, o, value.to_bytes(2, "little"))
        elif point.codec is Codec.F32_HIGH:
            self.cache.patch(point.block, o + 2, value.to_bytes(2, "little"))
        elif point.codec is Codec.F32_LOW:
            self.cache.patch(point.block, o, value.to_bytes(2, "little"))
        else:
            self.cache.patch(point.block, o, bytes((value & 0xFF,)))

    async def write_bits(self, address: int, values: Sequence[bool]) -> None:
        self._check_writable(Table.COIL, address, len(values))
        points = self.plan.coils
        for i in range(len(values)):
            point = points.get(address + i)
            if point is None or point.write is None:
                raise ModbusExceptionReply(ILLEGAL_ADDRESS, f"coil {address + i} is not writable")
        for i, value in enumerate(values):
            point = points[address + i]
            await self._through(self._write_bit(point.write, value))
            byte = self.cache.data[point.block][point.offset]
            byte = byte | (1 << point.bit) if value else byte & ~(1 << point.bit)
            self.cache.patch(point.block, point.offset, bytes([byte & 0xFF]))


class SlcAsciiUnit(Unit):
    """An SLC 100/150 with the default map."""

    driver: SlcAsciiDriver

    def __init__(self, *, driver: SlcAsciiDriver, **kwargs: object) -> None:
        super().__init__(driver=driver, plan=slc_ascii_plan(), **kwargs)  # type: ignore[arg-type]

    async def read_block(self, block: Block) -> bytes:
        address, count = cast(tuple[int, int], block.request)
        return await self.driver.read(address, count)

    async def _write_register(self, target: object, value: int) -> None:
        assert isinstance(target, SlcWordWrite)
        await self.driver.write_word(target.address, value)

    async def _write_bit(self, target: object, value: bool) -> None:
        assert isinstance(target, SlcBitWrite)
        await self.driver.update_byte(target.address, target.bit, value)

    @property
    def last_fault_number(self) -> int:
        fault = self.driver.last_fault
        return fault.errors[0] if fault is not None and fault.errors else 0
