"""Every mapped point of a configuration as a tag, for SCADA tag lists (``slc-gateway export-tags``).

The points are the links' plans, the same ones ``check-config`` prints and the units serve; the
link kind names what each point is in the controller (``LinkKind.point_labels``: its address, data
type and a description).  A tag is one value: a 32-bit value (two registers whose points are the
two halves of one value) is one tag at its first register, with its word order.  Every unit's
status block (input registers from 1000) is listed too.

Access follows the unit's own rules: a point with a write target, outside ``read_only``, inside
``writable`` (:func:`gateway.unit_writes.in_writable`) is read-write; everything else is read-only.

Formats (:data:`FORMATS`): ``csv`` (header :data:`CSV_HEADER`), ``json`` (a list of objects) and
``kepware``, the Kepware tag CSV layout (:func:`kepware_rows`): one file is one Kepware device, so
one unit (:func:`kepware_devices`), with the word order its 32-bit values need.

Generic: knows plans, points and the kind registry, no protocol.
"""

from __future__ import annotations

import csv
import io
import json
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Final

from gateway.config.link import LinkBase
from gateway.errors import GatewayError
from gateway.frozen import frozen
from gateway.kinds import link_kind, unit_options
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Half, PointLabel, RegisterPoint, Table
from gateway.unit_writes import in_writable

__all__ = ["CSV_HEADER", "FORMATS", "KepwareDevice", "Tag", "config_tags", "kepware_devices", "link_tags", "reference",
           "render"]

CSV_HEADER: Final = ("name", "unit", "table", "address", "reference", "type", "access", "description")

#: the first digit of a table's 1-based reference (the classic 0xxxx / 1xxxx / 3xxxx / 4xxxx notation)
_REFERENCE_PREFIX: Final = {Table.COIL: 0, Table.DISCRETE: 1, Table.INPUT: 3, Table.HOLDING: 4}

_STATUS_TEXT: Final = {
    "link_up": "link up (1) / down (0)",
    "data_age": "age of the oldest fast-class value, 0.1 s (65535: never read)",
    "last_fault": "last controller fault number",
    "transactions": "transactions the controller answered",
    "errors": "failed transactions",
    "retries": "protocol retries",
    "state": "link state: 0 up (fresh), 1 stale, 2 down",
}


def reference(table: Table, address: int) -> str:
    """The 1-based six-digit reference of a 0-based protocol address: holding 0 -> ``400001``.

    Six digits for every address (``465536`` is holding 65535), as the Kepware Modbus drivers take them.
    """
    return f"{_REFERENCE_PREFIX[table]}{address + 1:05d}"


@frozen
class Tag:
    """One value of one unit: ``width`` registers (or one bit) from ``address`` of ``table``."""

    name: str
    link: str
    unit: int
    table: Table
    address: int
    type: str
    word_order: str  # "high-first" / "low-first" for a 32-bit value, "" otherwise
    writable: bool
    description: str

    @property
    def width(self) -> int:
        return 2 if self.word_order else 1

    @property
    def reference(self) -> str:
        return reference(self.table, self.address)

    @property
    def type_text(self) -> str:
        """``int16``; ``float32 high-first`` for a 32-bit value."""
        return f"{self.type} {self.word_order}" if self.word_order else self.type

    @property
    def access(self) -> str:
        return "read-write" if self.writable else "read"


def link_tags(link: LinkBase) -> list[Tag]:
    """The tags of one ``[[link]]``: its plan's points by table and address, then its status block."""
    kind = link_kind(link.protocol)
    plan = kind.plan_of(link)
    labels: Mapping[tuple[Table, int], PointLabel] = kind.point_labels(link) if kind.point_labels else {}
    writable = unit_options(link).get("writable", ())
    tags: list[Tag] = []
    names: set[str] = set()

    def add(table: Table, address: int, can_write: bool, word_order: str = "") -> None:
        label = labels.get((table, address))
        if label is None:
            bits = table in (Table.COIL, Table.DISCRETE)
            label = PointLabel(f"{table.value}:{address}", "bool" if bits else "uint32" if word_order else "uint16")
        width = 2 if word_order else 1
        can_write = can_write and not link.read_only and in_writable(writable, table, address, width)
        name = f"{link.name}/{label.address}"
        if name in names:  # the same controller bit as a coil and as a discrete input
            name += f"@{table.value}"
        names.add(name)
        tags.append(Tag(name, link.name, link.unit, table, address, label.type,
                        word_order, can_write, label.description))

    for table in (Table.HOLDING, Table.INPUT):
        points = plan.registers(table)
        paired: set[int] = set()
        for address in sorted(points):
            if address in paired:
                continue
            point = points[address]
            partner = points.get(address + 1)
            if _halves(point, partner):
                paired.add(address + 1)
                order = "high-first" if point.codec.half is Half.HIGH else "low-first"
                add(table, address, point.write is not None, order)
            else:
                add(table, address, point.write is not None)
    for table in (Table.COIL, Table.DISCRETE):
        bits = plan.bits(table)
        for address in sorted(bits):
            add(table, address, bits[address].write is not None)
    address = STATUS_BASE
    kind_key, kind_text = link_kind(link.protocol).status_counter
    for key, width in STATUS_REGISTERS:
        name, text = (kind_key, kind_text) if key == "kind_counter" else (key, _STATUS_TEXT.get(key, key))
        tags.append(Tag(f"{link.name}/status.{name}", link.name, link.unit, Table.INPUT, address,
                        "uint32" if width == 2 else "uint16", "high-first" if width == 2 else "", False,
                        f"status: {text}"))
        address += width
    return tags


def _halves(point: RegisterPoint[Any], partner: RegisterPoint[Any] | None) -> bool:
    """Whether two neighbouring registers are the two halves of one 32-bit value."""
    if point.codec.half is None or partner is None or partner.codec.half is None:
        return False
    return (point.block, point.write) == (partner.block, partner.write) and point.codec.half is not partner.codec.half


def config_tags(links: Iterable[LinkBase], unit: int | None = None) -> list[Tag]:
    """The tags of every link in file order (of unit ``unit`` only, when given)."""
    return [tag for link in links if unit is None or link.unit == unit for tag in link_tags(link)]


# --- formats --------------------------------------------------------------------------------


def _csv(tags: Sequence[Tag]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    for tag in tags:
        writer.writerow((tag.name, tag.unit, tag.table.value, tag.address, tag.reference, tag.type_text,
                         tag.access, tag.description))
    return out.getvalue()


def _json(tags: Sequence[Tag]) -> str:
    return json.dumps([
        {"name": tag.name, "link": tag.link, "unit": tag.unit, "table": tag.table.value, "address": tag.address,
         "reference": tag.reference, "type": tag.type, "word_order": tag.word_order or None,
         "registers": tag.width if tag.table in (Table.HOLDING, Table.INPUT) else None,
         "access": tag.access, "description": tag.description}
        for tag in tags
    ], indent=1) + "\n"


# The Kepware tag CSV layout: the heading record of a server tag list as the Kepware server documents
# it for CSV import / export ("CSV Import/Export", http://www.kepware.com/Products/feature-csvimportexport.htm):
# Tag Name, Address, Data Type, Respect Data Type (1, 0), Client Access (RO, RW, WO), Scan Rate (ms),
# Scaling, Raw Low, Raw High, Scaled Low, Scaled High, Scaled Data Type, Clamp Low, Clamp High,
# Eng Units, Description; a blank column takes the server's default.  The file is imported under one
# device or tag group (the same page: "The CSV functions are only available when a Device or Tag
# Group is selected"), and the device holds the Modbus unit id: one file per unit.  Addresses and
# data types are the Modbus Ethernet driver's ("Modbus Ethernet Driver", PTC/Kepware 2016, "Modbus
# Addressing", "Data Types Description"): six-digit 000001 coils, 100001 discrete inputs, 300001
# input registers, 400001 holding registers; Boolean, Word, Short, DWord, Float.
KEPWARE_HEADER: Final = (
    "Tag Name", "Address", "Data Type", "Respect Data Type", "Client Access", "Scan Rate", "Scaling",
    "Raw Low", "Raw High", "Scaled Low", "Scaled High", "Scaled Data Type", "Clamp Low", "Clamp High",
    "Eng Units", "Description",
)
_KEPWARE_TYPES: Final = {"bool": "Boolean", "uint16": "Word", "int16": "Short", "uint32": "DWord",
                         "int32": "Long", "float32": "Float"}
_KEPWARE_NAME: Final = re.compile(r"[^A-Za-z0-9_]")
#: The Modbus driver reads every 32-bit value of a device in one word order, the device's "First
#: word low" setting (Data Encoding), on by default: the low word at the lower address.  There is
#: no per-tag word order in the tag CSV.
KEPWARE_DEFAULT_ORDER: Final = "low-first"
#: the tags named one by one in a word-order warning (the rest are counted)
_NAMED: Final = 12


def _kepware_name(text: str) -> str:
    """A Kepware tag name: letters, digits and underscores (``N7:10`` -> ``N7_10``)."""
    return _KEPWARE_NAME.sub("_", text).strip("_") or "tag"


def first_word_low(word_order: str) -> str:
    """The Kepware device setting for a word order: ``'First word low' on`` / ``off``."""
    return f"'First word low' {'on' if word_order == 'low-first' else 'off'}"


def _status(tag: Tag) -> bool:
    return tag.table is Table.INPUT and tag.address >= STATUS_BASE


@frozen
class KepwareDevice:
    """One Kepware device: one Modbus unit, its tags and the word order its 32-bit values need.

    ``word_order`` is the order of most of the unit's own 32-bit values (the status block's counters
    decide only when it has none; a tie takes Kepware's default); ``misread`` are the 32-bit tags in
    the other order, which this device reads wrong.
    """

    unit: int
    links: tuple[str, ...]
    word_order: str
    tags: tuple[Tag, ...]
    misread: tuple[Tag, ...]

    @property
    def setting(self) -> str:
        return first_word_low(self.word_order)

    def warning(self) -> str:
        """The word-order warning for ``misread`` ("" when every 32-bit value is in the device's order)."""
        if not self.misread:
            return ""
        names = ", ".join(kepware_name(tag) for tag in self.misread[:_NAMED])
        more = f" and {len(self.misread) - _NAMED} more" if len(self.misread) > _NAMED else ""
        other = "low-first" if self.word_order == "high-first" else "high-first"
        return (f"unit {self.unit}: 32-bit values in both word orders, but a Kepware device reads all of them in "
                f"one: this one is {self.word_order} ({self.setting}), so these {len(self.misread)} {other} "
                f"values read wrong: {names}{more}; give the map's 32-bit values one word order (the status "
                f"block's counters are high-first), or read these as two Words each")


def kepware_devices(tags: Sequence[Tag]) -> list[KepwareDevice]:
    """``tags`` as Kepware devices, one per unit, in the order the units first appear."""
    by_unit: dict[int, list[Tag]] = {}
    for tag in tags:
        by_unit.setdefault(tag.unit, []).append(tag)
    devices = []
    for unit, unit_tags in by_unit.items():
        wide = [tag for tag in unit_tags if tag.word_order]
        own = [tag for tag in wide if not _status(tag)] or wide
        high = sum(tag.word_order == "high-first" for tag in own)
        low = len(own) - high
        order = KEPWARE_DEFAULT_ORDER if high == low else "high-first" if high > low else "low-first"
        links = tuple(dict.fromkeys(tag.link for tag in unit_tags))
        devices.append(KepwareDevice(unit, links, order, tuple(unit_tags),
                                     tuple(tag for tag in wide if tag.word_order != order)))
    return devices


def kepware_name(tag: Tag) -> str:
    """``<link>.<address>``: the link is the tag group (the name before any de-duplication)."""
    return f"{_kepware_name(tag.link)}.{_kepware_name(tag.name[len(tag.link) + 1 :])}"


def kepware_rows(tags: Sequence[Tag]) -> list[tuple[str, ...]]:
    """The Kepware rows of ``tags`` (one unit: one device, :func:`kepware_devices`): names unique.

    The description of a 32-bit value says its word order and whether the device reads it so.
    """
    rows: list[tuple[str, ...]] = []
    seen: set[str] = set()
    for device in kepware_devices(tags):
        for tag in device.tags:
            base = kepware_name(tag)
            name = base if base not in seen else f"{base}_{tag.table.value}"
            seen.add(name)
            description = tag.description
            if tag.word_order == device.word_order:
                description += f" ({tag.word_order} words: {device.setting})"
            elif tag.word_order:
                description += f" ({tag.word_order} words: reads wrong with {device.setting})"
            rows.append((name, tag.reference, _KEPWARE_TYPES.get(tag.type, "Word"), "1",
                         "RW" if tag.writable else "RO", "", "", "", "", "", "", "", "", "", "", description))
    return rows


def _kepware(tags: Sequence[Tag]) -> str:
    units = sorted({tag.unit for tag in tags})
    if len(units) > 1:
        raise GatewayError(f"a Kepware file is one device, one unit: these tags are of units "
                         f"{', '.join(map(str, units))} (export-tags --unit N, or -o DIR for one file per unit)")
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\r\n")
    writer.writerow(KEPWARE_HEADER)
    writer.writerows(kepware_rows(tags))
    return out.getvalue()


FORMATS: Final[Mapping[str, Callable[[Sequence[Tag]], str]]] = {"csv": _csv, "kepware": _kepware, "json": _json}


def render(tags: Sequence[Tag], format_name: str) -> str:
    """``tags`` as text in one of :data:`FORMATS`."""
    return FORMATS[format_name](tags)
