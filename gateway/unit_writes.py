r"""The write side of a unit: a Modbus write validated whole, cut into steps, queued, run on the line's lease.

:class:`UnitWrites` is the write half of :class:`gateway.unit.Unit` (its base; ``unit.py`` is the
core and the reads).  A write request (FC5, FC6, FC15, FC16) is validated whole (ranges,
``writable``, value limits, what the image knows the controller will refuse, float pairing) before
anything is queued; then it is cut into :class:`WriteStep`\ s, one controller command each (as few
as the protocol allows), and queued as one job on the link's write queue (``gateway.writes``) in
arrival order.  The queue runs the job with the write session's lease as its argument
(``job(line)``, a ``gateway.line_driver.LineLease``): :meth:`UnitWrites._run_steps` runs the steps
in order on it (:func:`run_step`), each step's command through the kind's write hook
(``_write_register(target, value, line)`` ...) and its driver (``LineDriver.submit(op, line=line)``).
A confirmed step patches the cache (never its read times).

When the controller refuses a step after earlier ones were applied, the request is answered with
the exception, and the registers written are logged and counted (``partial_writes``): never a
success for a partial write, never a silent one.

Every write request is answered within ``write_timeout``.  A write still waiting for the line
then is withdrawn: nothing of it is written.  A write already on the line is answered 0x0B
(outcome unknown) and goes on to its verdict, applied at most once, which the ``gateway.audit``
log reports; a multi-command write sends no further command after the answer.

Generic: knows tables and points, no protocol.
"""

from __future__ import annotations

import asyncio
import logging
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable, Hashable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Generic, TypeVar

from gateway.cache import BlockCache
from gateway.clients import current_client
from gateway.errors import GatewayError, ModbusExceptionReply, WriteOutcomeUnknown, modbus_exception
from gateway.latency import LatencyHistogram
from gateway.line_driver import LineLease, UnitDriver
from gateway.modbus.mapping import BitPoint, Half, Plan, RegisterPoint, Table
from gateway.writes import WriteQueue

__all__ = ["UnitWrites", "WritableRange", "WriteStep", "WriteTally", "in_writable", "run_step", "span", "spans",
           "target_of", "translated"]

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

WritableRange = tuple[Table, int, int]  # table, first, last


def in_writable(writable: Sequence[WritableRange], table: Table, address: int, count: int) -> bool:
    """Whether ``writable`` (empty: everything) lets a write to ``address``.. (``count``) of ``table`` through.

    One range must hold the whole write."""
    return not writable or any(
        t is table and first <= address and address + count - 1 <= last for t, first, last in writable
    )


@dataclass(slots=True)
class WriteStep:
    """One controller command of a write request: Modbus addresses first..last; ``run(line)`` sends
    it on the line of the write session's lease."""

    first: int
    last: int
    run: Callable[[LineLease], Awaitable[None]]
    patches: list[tuple[RegisterPoint[Any], int]] = field(default_factory=list)
    bit_patches: list[tuple[BitPoint[Any], bool]] = field(default_factory=list)


T = TypeVar("T")


def target_of(point: RegisterPoint[T] | BitPoint[T]) -> T:
    """The write target of a point checked writable (``write`` not None)."""
    target = point.write
    if target is None:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_DATA_ADDRESS, "not writable")
    return target


def span(first: int, last: int) -> str:
    return f"{first}" if first == last else f"{first}-{last}"


def spans(steps: list[WriteStep]) -> str:
    runs: list[list[int]] = []
    for step in steps:
        if runs and runs[-1][1] == step.first - 1:
            runs[-1][1] = step.last
        else:
            runs.append([step.first, step.last])
    return ", ".join(span(a, b) for a, b in runs)


async def translated(write: Awaitable[None]) -> None:
    """Await a write, translating its error to the Modbus exception of ``gateway.errors.MODBUS_CODES``."""
    try:
        await write
    except GatewayError as exc:
        reply = modbus_exception(exc)
        if reply is exc:
            raise  # already translated (e.g. a PCCC address problem: 0x02)
        raise reply from exc


@dataclass(slots=True)
class WriteTally:
    """What the one write path counts: commands sent again because a read-back proved them not applied
    (``retried``), and commands whose outcome stayed unknown (``unknown``)."""

    retried: int = 0
    unknown: int = 0


async def run_step(step: WriteStep, line: LineLease, deadline: float, clock: Callable[[], float],
                   not_applied: Callable[[WriteStep, bytes], bool], tally: WriteTally, link: str) -> None:
    """Run one command of a write on ``line`` (the write session's lease); sent again, while ``clock()``
    is before ``deadline`` (``write_timeout``), as long as its outcome was unknown but a read-back
    proved it was not applied.

    A read-back proves that only where it ran after the write and showed the value from before it
    (``WriteOutcomeUnknown.shown`` equal to what the image held: ``not_applied``; DF1 full duplex).  A
    command sent again is then still applied at most once.  An outcome that stays unknown is counted
    and logged (it is answered 0x0B, as before).
    """
    while True:
        try:
            await translated(step.run(line))
            return
        except ModbusExceptionReply as exc:
            cause = exc.__cause__
            if not isinstance(cause, WriteOutcomeUnknown):
                raise
            if cause.shown is None or not not_applied(step, cause.shown):
                tally.unknown += 1
                log.warning("link %s: write of %s: outcome unknown, applied at most once (%s)", link,
                            span(step.first, step.last), cause)
                raise
            if clock() >= deadline:
                raise ModbusExceptionReply(
                    ModbusExceptionReply.GATEWAY_TARGET_FAILED,
                    f"{cause}; a read-back proved it was not applied and write_timeout left no time to send it "
                    "again: nothing written") from cause
            tally.retried += 1
            log.info("link %s: write of %s not applied (a read-back after it showed the value before it): "
                     "sending it again", link, span(step.first, step.last))


class UnitWrites(ABC, Generic[R, B]):
    """The write half of a unit (module docstring): :class:`gateway.unit.Unit` is one.

    Generic in the plan's write targets, as the unit: ``R`` for a holding register, ``B`` for a coil.
    """

    # What the write side reads of the unit's core (set by ``Unit.__init__``).
    unit_id: int
    name: str
    plan: Plan[R, B]
    cache: BlockCache

    def __init__(
        self,
        *,
        name: str,
        driver: UnitDriver,
        writable: Sequence[WritableRange] = (),
        read_only: bool = False,
        write_burst: int = 1,
        poll_burst: int = 2,
        write_queue_per_client: int = 8,
        write_queue_per_link: int = 32,
        write_timeout: float = 0.9,
    ) -> None:
        self.read_only = read_only
        self.writable = tuple(writable)
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

    @abstractmethod
    def _loop_time(self) -> float:
        """The unit's clock (``Unit._loop_time``: the event loop's)."""

    # --- the kind's hooks ---------------------------------------------------------------------
    #
    # The write hooks run one command on ``line``, the write session's lease: they pass it to
    # their driver's request (``LineDriver.submit(op, line=line)``).

    @abstractmethod
    async def _write_register(self, target: R, value: int, line: LineLease) -> None: ...

    async def _write_pair(self, target: R, raw: int, line: LineLease) -> None:
        """Write the 32 bits of a value held in two registers (both at once: a float)."""
        raise ModbusExceptionReply(ILLEGAL_ADDRESS, "this unit has no 32-bit registers")

    @abstractmethod
    async def _write_bit(self, target: B, value: bool, line: LineLease) -> None: ...

    # --- validation and steps ---------------------------------------------------------------

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
