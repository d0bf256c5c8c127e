"""Each link as an OPC UA folder: one variable per tag of ``gateway.tags.link_tags`` (the one list).

A variable is named as ``slc-gateway export-tags`` and Sparkplug name the tag (``N7:0``,
``T4:2.ACC``, ``B3:0/5``), in the folder ``Objects/<link>``; the status block's values are in
``Objects/<link>/_Status`` (``link_up``, ``data_age``, ...).  Its NodeId is the string
``<link>.<tag>`` (``press.N7:0``, ``press.status.link_up``) in the namespace ``urn:slc-gateway``:
the same across restarts and reloads.  Data types: the tag's (``bool`` Boolean, ``int16`` Int16,
``uint16`` UInt16, ``int32`` Int32, ``uint32`` UInt32, ``float32`` Float).

:func:`read_point` is a variable's value, status code and read time now, from the unit's image and
the one verdict; no asyncua here.  Generic: knows tags, plans and units, no protocol.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any, Final

from gateway.config.link import LinkBase
from gateway.frozen import frozen
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Table
from gateway.opcua.quality import Reading, point_quality
from gateway.schedule import NEVER
from gateway.tags import link_tags
from gateway.unit import Unit

__all__ = ["DATA_TYPES", "OPCUA_NAMESPACE", "OpcPoint", "PointRun", "link_points", "point_registers", "point_runs",
           "point_value", "read_point"]

#: the namespace of the links' nodes
OPCUA_NAMESPACE: Final = "urn:slc-gateway"
#: tag type -> OPC UA built-in data type name
DATA_TYPES: Final = {"bool": "Boolean", "int16": "Int16", "uint16": "UInt16", "int32": "Int32",
                     "uint32": "UInt32", "float32": "Float"}
_RANGES: Final = {"int16": (-32768, 32767), "uint16": (0, 65535), "int32": (-(2**31), 2**31 - 1),
                  "uint32": (0, 2**32 - 1)}
_FORMATS: Final = {"int32": ">i", "uint32": ">I", "float32": ">f"}


@frozen
class OpcPoint:
    """One variable: ``width`` registers (or one bit) of ``table`` from ``address`` of its link's unit."""

    link: str
    #: the tag's name without its link (``N7:0``; ``status.link_up``)
    name: str
    #: the browse name in its folder (the status block's: the key, without ``status.``)
    browse_name: str
    table: Table
    address: int
    type: str
    low_first: bool
    writable: bool
    #: its block in the unit's plan (None: a status block value)
    block: int | None
    #: the status block's key (``Unit.status_values``); "" for a data point
    status_key: str
    description: str

    @property
    def node_id(self) -> str:
        """The string of its NodeId: ``<link>.<tag>``."""
        return f"{self.link}.{self.name}"

    @property
    def data_type(self) -> str:
        return DATA_TYPES.get(self.type, "UInt16")

    @property
    def width(self) -> int:
        return 2 if self.type in _FORMATS else 1

    @property
    def bits(self) -> bool:
        return self.table in (Table.COIL, Table.DISCRETE)


def link_points(link: LinkBase, unit: Unit[Any, Any]) -> list[OpcPoint]:
    """The variables of one link, in the tag list's order (data points, then the status block)."""
    points: list[OpcPoint] = []
    status_keys = iter(key for key, _ in STATUS_REGISTERS)
    for tag in link_tags(link):
        name = tag.name[len(tag.link) + 1 :]
        if tag.table is Table.INPUT and tag.address >= STATUS_BASE:
            points.append(OpcPoint(link.name, name, name.removeprefix("status."), tag.table, tag.address, tag.type,
                                   False, False, None, next(status_keys), tag.description))
            continue
        plan = unit.plan
        block = (plan.bits(tag.table) if tag.table in (Table.COIL, Table.DISCRETE)
                 else plan.registers(tag.table))[tag.address].block
        points.append(OpcPoint(link.name, name, name, tag.table, tag.address, tag.type,
                               tag.word_order == "low-first", tag.writable, block, "", tag.description))
    return points


def point_value(point: OpcPoint, data: bytes) -> bool | int | float:
    """A point's value from the bytes of a Modbus read of it (registers big-endian, a bit LSB first)."""
    if point.bits:
        return bool(data[0] & 1)
    if point.width == 2:
        raw = data[2:4] + data[0:2] if point.low_first else data[0:4]
        value: int | float = struct.unpack(_FORMATS[point.type], raw)[0]
        return value
    return int.from_bytes(data[:2], "big", signed=point.type == "int16")


def point_registers(point: OpcPoint, value: object) -> list[int]:
    """The registers a Modbus write of ``value`` to ``point`` sends.

    TypeError: not a value of the point's type; ValueError: outside its range (a Float that is not
    finite, or too large for 32 bits, included)."""
    if point.type == "float32":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"{value!r} is not a number")
        if not math.isfinite(value) or abs(value) > 3.4028234663852886e38:
            raise ValueError(f"{value} is outside Float")
        raw = struct.pack(">f", value)
    else:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{value!r} is not an integer")
        low, high = _RANGES.get(point.type, (0, 65535))
        if not low <= value <= high:
            raise ValueError(f"{value} is outside {point.type} ({low}..{high})")
        if point.width == 1:
            return [value & 0xFFFF]
        raw = struct.pack(_FORMATS[point.type], value)
    words = [int.from_bytes(raw[0:2], "big"), int.from_bytes(raw[2:4], "big")]
    return words[::-1] if point.low_first else words


def read_point(unit: Unit[Any, Any], point: OpcPoint, now: float) -> tuple[Reading, bool | int | float | None, float]:
    """A data point's status code, value (None without one) and read time (loop seconds; ``now`` when
    never read) at ``now``: the truth (a peek: no demand), under the link's ``offline`` policy."""
    block = point.block
    if block is None:
        raise ValueError(f"{point.node_id} is a status value")
    verdict = unit.verdict(now)
    read_at = unit.cache.stamps[block]
    poller = unit.poller
    reading = point_quality(
        state=verdict.state, known=verdict.since is not None, fresh=unit.freshness.block_fresh(block, now),
        read=read_at != NEVER, refused=poller is not None and block in poller.refused, offline=unit.offline)
    if not reading.carries_value:
        return reading, None, now if read_at == NEVER else read_at
    data = unit.images.held(point.table, point.address, 1 if point.bits else point.width, None)
    return reading, point_value(point, data), read_at


def status_point_value(unit: Unit[Any, Any], point: OpcPoint, now: float) -> int:
    """A status block value now (always good)."""
    return unit.status_values(now)[point.status_key]


def points_by_block(points: Sequence[OpcPoint]) -> dict[int, list[int]]:
    """Per block: the indices of its points in ``points``."""
    found: dict[int, list[int]] = {}
    for index, point in enumerate(points):
        if point.block is not None:
            found.setdefault(point.block, []).append(index)
    return found


class PointRun:
    """Consecutive addresses ``first``.. (``count``) of one table of one block, and its points: (index, where
    its value starts in a read of the run: a byte offset, or a bit number, and how many bytes)."""

    __slots__ = ("bits", "count", "first", "members", "owner", "table")

    def __init__(self, point: OpcPoint) -> None:
        self.table, self.first, self.count, self.bits = point.table, point.address, 0, point.bits
        self.members: list[tuple[int, int, int]] = []
        #: per byte of a register run's read (per bit of a bit run's): the position of its member in ``members``
        self.owner: list[int] = []

    def changed(self, old: bytes, new: bytes) -> list[int]:
        """The positions in ``members`` of the points whose bytes differ between two reads of the run, in
        order: one integer comparison for the run, then a step per changed point (not per point)."""
        owner, found = self.owner, []
        if self.bits:
            diff = int.from_bytes(old, "little") ^ int.from_bytes(new, "little")
            while diff:
                low = diff & -diff
                found.append(owner[low.bit_length() - 1])
                diff ^= low
            return found
        size = len(new)
        diff = int.from_bytes(old, "big") ^ int.from_bytes(new, "big")
        members = self.members
        while diff:
            position = owner[size - 1 - (diff.bit_length() - 1) // 8]
            found.append(position)
            _, at, width = members[position]
            diff &= (1 << 8 * (size - at - width)) - 1  # this point and those before it are done
        return found


def point_runs(points: Sequence[OpcPoint], members: Sequence[int]) -> list[PointRun]:
    """The points ``members`` of ``points`` (one block) as runs of consecutive addresses, each read at once."""
    runs: list[PointRun] = []
    run: PointRun | None = None
    for index in sorted(members, key=lambda i: (points[i].table.value, points[i].address)):
        point = points[index]
        if run is None or point.table is not run.table or point.address != run.first + run.count:
            run = PointRun(point)
            runs.append(run)
        offset = point.address - run.first
        run.members.append((index, offset if run.bits else 2 * offset, 0 if run.bits else 2 * point.width))
        run.owner.extend([len(run.members) - 1] * (1 if run.bits else 2 * point.width))
        run.count += 1 if run.bits else point.width
    return runs
