r"""The steps of a write request and what every write shares: writable ranges, spans, error translation.

A unit (``gateway.unit``) validates a Modbus write whole, then cuts it into :class:`WriteStep`\ s,
one controller command each, which its write queue (``gateway.writes``) runs in arrival order.

Generic: knows tables and points, no protocol.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from gateway.errors import GatewayError, ModbusExceptionReply, modbus_exception
from gateway.modbus.mapping import BitPoint, RegisterPoint, Table

__all__ = ["WritableRange", "WriteStep", "in_writable", "span", "spans", "target_of", "translated"]

WritableRange = tuple[Table, int, int]  # table, first, last


def in_writable(writable: Sequence[WritableRange], table: Table, address: int, count: int) -> bool:
    """Whether ``writable`` (empty: everything) lets a write to ``address``.. (``count``) of ``table`` through.

    One range must hold the whole write."""
    return not writable or any(
        t is table and first <= address and address + count - 1 <= last for t, first, last in writable
    )


@dataclass(slots=True)
class WriteStep:
    """One controller command of a write request: Modbus addresses first..last."""

    first: int
    last: int
    run: Callable[[], Awaitable[None]]
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

