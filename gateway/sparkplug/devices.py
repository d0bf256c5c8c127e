"""Each link as a Sparkplug device: its metrics (the tags of ``export-tags``) and how to read them.

A metric is one tag of :func:`gateway.tags.link_tags` (the one place that names a point), named
as the tag without its ``<link>/`` prefix (``N7:0``, ``T4:2.ACC``, ``901.PRE``, ``status.link_up``),
with the Sparkplug datatype of its type (§6.4.16 "Data Types").  Aliases are numbered in the
order of the links and their tags, after ``bdSeq``; they are unique across the node (§6.4.6).

A metric's value is what a peek of its registers or bit answers now (``gateway.freshness``: the
one verdict, no demand unless ``[sparkplug] demand``, no ``offline`` policy): a value, or the
exception that read gets.  0x0B (no fresh data) is quality STALE; any other (the controller
refuses the block: 0x04, or 0x02 for an address it does not have) is BAD; the exception's text is
the reason.  The metrics are read a run at a time (consecutive addresses of
one block: one read, one freshness), and only those whose bytes changed are decoded.  The status
block's values come from :meth:`gateway.unit.Unit.status_values` and are always good.

Generic: knows tags, plans and units, no protocol.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import field
from typing import Any, Final

from gateway.config.link import LinkBase
from gateway.errors import ModbusExceptionReply
from gateway.frozen import frozen
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Table
from gateway.sparkplug.node import BD_SEQ_ALIAS, Device, MetricSpec, Sample
from gateway.sparkplug.payload import BAD, STALE, SparkplugType, Value
from gateway.tags import Tag, link_tags
from gateway.unit import Source, Unit

__all__ = ["DATATYPES", "LinkDevice", "build_devices"]

#: tag type -> Sparkplug datatype
DATATYPES: Final = {
    "bool": SparkplugType.Boolean, "int16": SparkplugType.Int16, "uint16": SparkplugType.UInt16,
    "int32": SparkplugType.Int32, "uint32": SparkplugType.UInt32, "float32": SparkplugType.Float,
}


@frozen
class Point:
    """Where one metric's value is: ``width`` registers (or one bit) of ``table`` from ``address``."""

    table: Table
    address: int
    type: str
    low_first: bool
    #: its block in the unit's plan; None for the status block
    block: int | None
    #: the key of the status block value (``Unit.status_values``); "" for a data point
    status_key: str = ""
    #: registers per value: 2 for a 32-bit type, else 1
    width: int = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "width", 2 if self.type in ("int32", "uint32", "float32") else 1)


def _decode(point: Point, data: bytes) -> Value:
    """A point's value from the bytes of a Modbus read of it (registers big-endian, a bit LSB first)."""
    if point.type == "bool":
        return bool(data[0] & 1)
    if point.width == 2:
        high, low = (data[2:4], data[0:2]) if point.low_first else (data[0:2], data[2:4])
        raw = high + low
        fmt = {"int32": ">i", "uint32": ">I", "float32": ">f"}[point.type]
        value: Value = struct.unpack(fmt, raw)[0]
        return value
    return int.from_bytes(data[:2], "big", signed=point.type == "int16")


class LinkDevice:
    """One link (unit) as a device: the core's :class:`Device`, and each metric's :class:`Point`."""

    def __init__(self, link: LinkBase, unit: Unit[Any, Any], first_alias: int, *, demand: bool = False) -> None:
        self.unit = unit
        #: the node's reads count as client demand (``[sparkplug] demand``); they peek all the same
        self.demand = demand
        self.name = link.name
        deadbands = link.deadbands()
        specs: list[MetricSpec] = []
        self.points: list[Point] = []
        tags = link_tags(link)
        status_keys = [key for key, _ in STATUS_REGISTERS]
        status_index = 0
        for tag in tags:
            is_status = tag.table is Table.INPUT and tag.address >= STATUS_BASE
            datatype = DATATYPES.get(tag.type, SparkplugType.UInt16)
            writable = tag.writable and not is_status
            specs.append(MetricSpec(_metric_name(tag), first_alias + len(specs), datatype, writable,
                                    deadbands.get((tag.table.value, tag.address), 0.0)))
            if is_status:
                self.points.append(Point(tag.table, tag.address, tag.type, False, None, status_keys[status_index]))
                status_index += 1
            else:
                self.points.append(Point(tag.table, tag.address, tag.type, tag.word_order == "low-first",
                                         _block_of(unit, tag)))
        self.device = Device(link.name, specs)
        #: the data points as runs of consecutive addresses of one block and table, each read at once
        self.runs = _runs(self.points)
        #: per block: its runs
        self.by_block: dict[int, list[_Run]] = {}
        for run in self.runs:
            self.by_block.setdefault(run.block, []).append(run)
        self.status_metrics = [i for i, point in enumerate(self.points) if point.status_key]

    @property
    def next_alias(self) -> int:
        return self.device.specs[-1].alias + 1 if self.device.specs else 0

    def read(self, run: _Run, timestamp: int, *, failed_at: int | None = None,
             everything: bool = False) -> list[tuple[int, Sample]]:
        """The metrics of ``run`` whose value or state changed since its last read (``everything``: all),
        as a Modbus read of the run answers now; ``timestamp``: their read time (UTC ms); ``failed_at``:
        the time of a null (stale or refused: when it was found so; default ``timestamp``).

        One read per run: a run is one block, so its values share one freshness and one answer.
        """
        try:
            data = self._bytes(run)
        except ModbusExceptionReply as exc:
            reason = str(exc)
            if run.last is None and run.reason == reason and not everything:
                return []
            run.last, run.reason = None, reason
            at = timestamp if failed_at is None else failed_at
            return [(metric, _failed(exc, at)) for metric, _ in run.members]
        previous, run.last, run.reason = run.last, data, ""
        if previous == data and not everything:
            return []
        points = self.points
        out: list[tuple[int, Sample]] = []
        members = run.members if previous is None or everything else _changed_members(run, previous, data)
        if run.bits:
            bits = int.from_bytes(data, "little")
            for metric, at in members:
                out.append((metric, Sample(bool(bits >> at & 1), timestamp)))
            return out
        for metric, at in members:
            point = points[metric]
            out.append((metric, Sample(_decode(point, data[at : at + 2 * point.width]), timestamp)))
        return out

    def _bytes(self, run: _Run) -> bytes:
        """The run's bytes as a peek (``Source.PEEK``): the node's reads are no client's demand, and
        it publishes the truth whatever the link's ``offline`` policy serves Modbus.  With ``demand``
        the run is noted as demand all the same (``Unit.note_demand``)."""
        if self.demand:
            self.unit.note_demand(run.table, run.first, run.count)
        if run.bits:
            return self.unit.read_bit_bytes(run.table, run.first, run.count, Source.PEEK)
        return self.unit.read_register_bytes(run.table, run.first, run.count, Source.PEEK)

    def sample(self, metric: int, timestamp: int) -> Sample:
        """Metric ``metric`` as a Modbus read of it answers now (its run's last read is left alone)."""
        run, at = next((run, at) for run in self.runs for m, at in run.members if m == metric)
        try:
            data = self._bytes(run)
        except ModbusExceptionReply as exc:
            return _failed(exc, timestamp)
        if run.bits:
            return Sample(bool(int.from_bytes(data, "little") >> at & 1), timestamp)
        point = self.points[metric]
        return Sample(_decode(point, data[at : at + 2 * point.width]), timestamp)

    def status_samples(self, now: float, timestamp: int) -> list[tuple[int, Sample]]:
        values = self.unit.status_values(now)
        return [(i, Sample(values[self.points[i].status_key], timestamp)) for i in self.status_metrics]


def _changed_members(run: _Run, previous: bytes, data: bytes) -> list[tuple[int, int]]:
    """The members of ``run`` whose bits or bytes differ between two reads of it, in their order: found
    from the bits that differ, so an unchanged value costs nothing (a 100-register run with one
    counter changing is one step, not a hundred comparisons)."""
    members, owner = run.members, run.owner
    found: list[tuple[int, int]] = []
    if run.bits:
        diff = (int.from_bytes(data, "little") ^ int.from_bytes(previous, "little")) & ((1 << run.count) - 1)
        while diff:
            low = diff & -diff  # the lowest bit that differs: members are in bit order
            found.append(members[owner[low.bit_length() - 1]])
            diff ^= low
        return found
    size = len(data)
    diff = int.from_bytes(data, "big") ^ int.from_bytes(previous, "big")
    while diff:
        byte = size - 1 - (diff.bit_length() - 1) // 8  # the first byte that differs: members are in byte order
        member = members[owner[byte]]
        found.append(member)
        end = member[1] + 2 * run.widths[owner[byte]]
        diff &= (1 << (8 * (size - end))) - 1  # on past this member's bytes
    return found


def _failed(exc: ModbusExceptionReply, timestamp: int) -> Sample:
    quality = STALE if exc.code == ModbusExceptionReply.GATEWAY_TARGET_FAILED else BAD
    return Sample(None, timestamp, quality, str(exc))


class _Run:
    """Consecutive addresses ``first``.. (``count``) of ``table`` in block ``block``: the metrics in it
    (index, where it starts: a byte offset in the read's registers, or a bit number), the last read."""

    __slots__ = ("bits", "block", "count", "first", "last", "members", "owner", "reason", "table", "widths")

    def __init__(self, table: Table, block: int, first: int) -> None:
        self.table = table
        self.block = block
        self.first = first
        self.count = 0
        self.bits = table in (Table.COIL, Table.DISCRETE)
        self.members: list[tuple[int, int]] = []
        #: per member: its registers (1 or 2; 1 for a bit)
        self.widths: list[int] = []
        #: per byte of a register read (per bit of a bit read): the position in ``members`` of its member
        self.owner: list[int] = []
        #: the bytes of the last read (None: not read yet, or it failed with ``reason``)
        self.last: bytes | None = None
        self.reason = ""


def _runs(points: Sequence[Point]) -> list[_Run]:
    by_key: dict[tuple[int, Table], list[int]] = {}
    for i, point in enumerate(points):
        if point.block is not None:
            by_key.setdefault((point.block, point.table), []).append(i)
    runs: list[_Run] = []
    for (block, table), members in by_key.items():
        run: _Run | None = None
        for i in sorted(members, key=lambda m: points[m].address):
            point = points[i]
            if run is None or point.address != run.first + run.count:
                run = _Run(table, block, point.address)
                runs.append(run)
            offset = point.address - run.first
            run.owner += [len(run.members)] * (1 if run.bits else 2 * point.width)
            run.members.append((i, offset if run.bits else 2 * offset))
            run.widths.append(1 if run.bits else point.width)
            run.count += 1 if run.bits else point.width
    return runs


def _metric_name(tag: Tag) -> str:
    """The tag's name without its ``<link>/`` prefix (``N7:0``; ``status.link_up``)."""
    return tag.name[len(tag.link) + 1 :]


def _block_of(unit: Unit[Any, Any], tag: Tag) -> int:
    plan = unit.plan
    if tag.table in (Table.COIL, Table.DISCRETE):
        return plan.bits(tag.table)[tag.address].block
    return plan.registers(tag.table)[tag.address].block


def build_devices(links: Sequence[LinkBase], units: Sequence[Unit[Any, Any]], *,
                  demand: bool = False) -> list[LinkDevice]:
    """A :class:`LinkDevice` per link (``units`` in the same order), aliases numbered after bdSeq;
    ``demand``: the node's reads count as client demand (``[sparkplug] demand``)."""
    devices: list[LinkDevice] = []
    alias = BD_SEQ_ALIAS + 1
    for link, unit in zip(links, units, strict=True):
        device = LinkDevice(link, unit, alias, demand=demand)
        alias = max(alias, device.next_alias)
        devices.append(device)
    return devices

