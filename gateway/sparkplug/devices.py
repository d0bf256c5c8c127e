"""Each link as a Sparkplug device: its metrics (the tags of ``export-tags``) and how to read them.

A metric is one tag of :func:`gateway.tags.link_tags` (the one place that names a point), named
as the tag without its ``<link>/`` prefix (``N7:0``, ``T4:2.ACC``, ``901.PRE``, ``status.link_up``),
with the Sparkplug datatype of its type (§6.4.16 "Data Types").  Aliases are numbered in the
order of the links and their tags, after ``bdSeq``; they are unique across the node (§6.4.6).

A metric's value is what a Modbus read of its registers or bit answers now, by the unit's own
rule: a value, or the exception that read gets.  0x0B (no fresh data) is quality STALE; any other
(the controller refuses the block: 0x04, or 0x02 for an address it does not have) is BAD; the
exception's text is the reason.  All points of one
block share its read time and its freshness, so a block's state is read from its first metric.
The status block's values come from :meth:`gateway.unit.Unit.status_values` and are always good.

Generic: knows tags, plans and units, no protocol.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any, Final

from gateway.config.link import LinkBase
from gateway.errors import ModbusExceptionReply
from gateway.frozen import frozen
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Table
from gateway.sparkplug.node import BD_SEQ_ALIAS, Device, MetricSpec, Sample
from gateway.sparkplug.payload import BAD, STALE, SparkplugType, Value
from gateway.tags import Tag, link_tags
from gateway.unit import Unit

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

    @property
    def width(self) -> int:
        return 2 if self.type in ("int32", "uint32", "float32") else 1


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

    def __init__(self, link: LinkBase, unit: Unit[Any, Any], first_alias: int) -> None:
        self.unit = unit
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
        #: per block: the metrics in it (their indexes)
        self.by_block: dict[int, list[int]] = {}
        for i, point in enumerate(self.points):
            if point.block is not None:
                self.by_block.setdefault(point.block, []).append(i)
        self.status_metrics = [i for i, point in enumerate(self.points) if point.status_key]
        #: per block: the code of :meth:`block_code` last seen (None: not yet)
        self.block_state: dict[int, int | None] = dict.fromkeys(self.by_block)

    @property
    def next_alias(self) -> int:
        return self.device.specs[-1].alias + 1 if self.device.specs else 0

    def sample(self, index: int, timestamp: int) -> Sample:
        """Metric ``index`` as a Modbus read of it answers now (``timestamp``: its read time, UTC ms)."""
        point = self.points[index]
        try:
            if point.table in (Table.COIL, Table.DISCRETE):
                data = self.unit.read_bit_bytes(point.table, point.address, 1)
            else:
                data = self.unit.read_register_bytes(point.table, point.address, point.width)
        except ModbusExceptionReply as exc:
            quality = STALE if exc.code == ModbusExceptionReply.GATEWAY_TARGET_FAILED else BAD
            return Sample(None, timestamp, quality, str(exc))
        return Sample(_decode(point, data), timestamp)

    def block_code(self, block: int) -> int:
        """0 when the values of ``block`` are served now, else the Modbus exception a read of them gets."""
        point = self.points[self.by_block[block][0]]
        try:
            if point.table in (Table.COIL, Table.DISCRETE):
                self.unit.read_bit_bytes(point.table, point.address, 1)
            else:
                self.unit.read_register_bytes(point.table, point.address, point.width)
        except ModbusExceptionReply as exc:
            return exc.code
        return 0

    def status_samples(self, now: float, timestamp: int) -> list[tuple[int, Sample]]:
        values = self.unit.status_values(now)
        return [(i, Sample(values[self.points[i].status_key], timestamp)) for i in self.status_metrics]


def _metric_name(tag: Tag) -> str:
    """The tag's name without its ``<link>/`` prefix (``N7:0``; ``status.link_up``)."""
    return tag.name[len(tag.link) + 1 :]


def _block_of(unit: Unit[Any, Any], tag: Tag) -> int:
    plan = unit.plan
    if tag.table in (Table.COIL, Table.DISCRETE):
        return plan.bits(tag.table)[tag.address].block
    return plan.registers(tag.table)[tag.address].block


def build_devices(links: Sequence[LinkBase], units: Sequence[Unit[Any, Any]]) -> list[LinkDevice]:
    """A :class:`LinkDevice` per link (``units`` in the same order), aliases numbered after bdSeq."""
    devices: list[LinkDevice] = []
    alias = BD_SEQ_ALIAS + 1
    for link, unit in zip(links, units, strict=True):
        device = LinkDevice(link, unit, alias)
        alias = max(alias, device.next_alias)
        devices.append(device)
    return devices

