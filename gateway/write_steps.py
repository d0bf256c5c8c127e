r"""The steps of a write request and what every write shares: writable ranges, spans, error translation.

A unit (``gateway.unit``) validates a Modbus write whole, then cuts it into :class:`WriteStep`\ s,
one controller command each, which its write queue (``gateway.writes``) runs in arrival order.

Generic: knows tables and points, no protocol.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from gateway.errors import GatewayError, ModbusExceptionReply, WriteOutcomeUnknown, modbus_exception
from gateway.line_driver import LineLease
from gateway.modbus.mapping import BitPoint, RegisterPoint, Table

__all__ = ["WritableRange", "WriteStep", "WriteTally", "in_writable", "run_step", "span", "spans", "target_of",
           "translated"]

_log = logging.getLogger("gateway.unit")

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
    """Run one command of a write on ``line``; sent again, while ``clock()`` is before ``deadline`` (``write_timeout``),
    as long as its outcome was unknown but a read-back proved it was not applied.

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
                _log.warning("link %s: write of %s: outcome unknown, applied at most once (%s)", link,
                             span(step.first, step.last), cause)
                raise
            if clock() >= deadline:
                raise ModbusExceptionReply(
                    ModbusExceptionReply.GATEWAY_TARGET_FAILED,
                    f"{cause}; a read-back proved it was not applied and write_timeout left no time to send it "
                    "again: nothing written") from cause
            tally.retried += 1
            _log.info("link %s: write of %s not applied (a read-back after it showed the value before it): "
                      "sending it again", link, span(step.first, step.last))
