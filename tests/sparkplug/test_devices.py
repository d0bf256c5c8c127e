"""Links as Sparkplug devices (gateway.sparkplug.devices): metric names, datatypes, aliases, access,
deadbands, and reading the image as a Modbus read would, a run at a time.

Names are those ``export-tags`` gives (README "export-tags"); datatypes per Sparkplug 3.0 §6.4.16.
"""

from __future__ import annotations

import asyncio
import struct
import uuid
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.app import build_units
from gateway.config import parse_config
from gateway.modbus.mapping import Table
from gateway.sparkplug.devices import LinkDevice, build_devices
from gateway.sparkplug.payload import BAD, STALE, SparkplugType
from gateway.unit import Unit

CONFIG = """
[[link]]
name = "press"
protocol = "df1"
port = "sim://slc504?ladder=0&instance={one}"
unit = 1
writable = ["holding:0-1", "coil:0-1"]
[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 2
[[link.map]]
table = "holding"
start = 10
address = "F8:0"
count = 1
type = "float32"
deadband = 0.5
[[link.map]]
table = "input"
start = 0
address = "N7:50"
count = 1
[[link.map]]
table = "coil"
start = 0
address = "B3:0/0"
count = 2

[[link]]
name = "oven"
protocol = "df1"
port = "sim://slc504?ladder=0&instance={two}"
unit = 2
[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 1
"""

STATUS = ["status.link_up", "status.data_age", "status.last_fault", "status.transactions", "status.errors",
          "status.retries", "status.kind_counter", "status.state"]


def devices() -> tuple[list[LinkDevice], list[Unit[Any, Any]]]:
    config = parse_config(CONFIG.format(one=uuid.uuid4().hex, two=uuid.uuid4().hex))
    units, _ = build_units(config.link)
    return build_devices(config.link, units), units


def test_metrics_are_the_tags_with_their_datatypes_aliases_and_access() -> None:
    (press, oven), _ = devices()
    specs = press.device.specs
    assert [s.name for s in specs] == ["N7:0", "N7:1", "F8:0", "N7:50", "B3:0/0", "B3:0/1", *STATUS]
    assert [s.datatype for s in specs[:6]] == [SparkplugType.Int16, SparkplugType.Int16, SparkplugType.Float,
                                               SparkplugType.Int16, SparkplugType.Boolean, SparkplugType.Boolean]
    assert all(s.datatype is SparkplugType.UInt16 for s in specs[6:9]) and specs[9].datatype is SparkplugType.UInt32
    # writable: the holding and coil points inside `writable`; inputs and the status block never
    assert [s.writable for s in specs] == [True, True, False, False, True, True] + [False] * 8
    assert [s.deadband for s in specs[:4]] == [0.0, 0.0, 0.5, 0.0]
    # aliases: 1 is bdSeq, then every metric of every device, unique across the node
    aliases = [s.alias for s in specs] + [s.alias for s in oven.device.specs]
    assert aliases == list(range(2, 2 + len(aliases)))


async def test_reading_runs_reports_only_what_changed() -> None:
    (press, _), units = devices()
    unit = units[0]
    holding = next(run for run in press.runs if run.table is Table.HOLDING and run.first == 0)
    # never read: both metrics stale (quality 500) with the gateway's reason
    samples = press.read(holding, 1000)
    assert [m for m, _ in samples] == [0, 1]
    assert all(s.value is None and s.quality == STALE and "no fresh data" in s.reason for _, s in samples)
    assert press.read(holding, 1001) == []  # the same state again: nothing to report
    now = asyncio.get_running_loop().time()
    unit.cache.store(holding.block, struct.pack("<hh", -5, 7), now)  # N7:0-1 as the SLC sends them
    assert [(m, s.value, s.quality, s.timestamp) for m, s in press.read(holding, 2000)] == [
        (0, -5, 192, 2000), (1, 7, 192, 2000)]
    unit.cache.store(holding.block, struct.pack("<hh", -5, 8), now)
    assert [(m, s.value) for m, s in press.read(holding, 2001)] == [(1, 8)]  # only what changed
    assert [(m, s.value) for m, s in press.read(holding, 2002, everything=True)] == [(0, -5), (1, 8)]
    coils = next(run for run in press.runs if run.table is Table.COIL)
    unit.cache.store(coils.block, b"\x02\x00", now)  # B3:0/1 set
    assert [(m, s.value) for m, s in press.read(coils, 3000)] == [(4, False), (5, True)]
    unit.cache.store(coils.block, b"\x03\x00", now)
    assert [(m, s.value) for m, s in press.read(coils, 3001)] == [(4, True)]
    assert press.sample(5, 3002).value is True


def test_decode_from_the_serving_bytes() -> None:
    from gateway.sparkplug.devices import Point, _decode

    assert _decode(Point(Table.HOLDING, 0, "int16", False, 0), b"\xff\xfb") == -5
    assert _decode(Point(Table.HOLDING, 0, "uint16", False, 0), b"\xff\xfb") == 0xFFFB
    raw = struct.pack(">f", 2.5)
    assert _decode(Point(Table.HOLDING, 0, "float32", False, 0), raw) == 2.5
    assert _decode(Point(Table.HOLDING, 0, "float32", True, 0), raw[2:] + raw[:2]) == 2.5
    assert _decode(Point(Table.HOLDING, 0, "int32", False, 0), b"\xff\xff\xff\xfe") == -2
    assert _decode(Point(Table.COIL, 0, "bool", False, 0), b"\x01") is True
    assert BAD == 0


def test_dcmd_values_as_the_registers_a_modbus_write_sends() -> None:
    from gateway.sparkplug.driver import _registers

    assert _registers("int16", False, -2) == [0xFFFE]
    assert _registers("uint16", False, 65535) == [0xFFFF]
    high, low = struct.unpack(">HH", struct.pack(">f", 2.5))
    assert _registers("float32", False, 2.5) == [high, low]
    assert _registers("float32", True, 2.5) == [low, high]
    assert _registers("int32", False, -2) == [0xFFFF, 0xFFFE]
    for kind, value in (("int16", 32768), ("int16", -32769), ("uint16", -1), ("uint16", 65536)):
        with pytest.raises(ValueError, match="is outside"):
            _registers(kind, False, value)


async def test_a_null_carries_the_time_it_was_found_stale() -> None:
    (press, _), _units = devices()
    holding = next(run for run in press.runs if run.table is Table.HOLDING and run.first == 0)
    samples = press.read(holding, 1000, failed_at=5000)
    assert [s.timestamp for _, s in samples] == [5000, 5000]


WIDTHS = st.lists(st.sampled_from(["int16", "uint16", "int32", "float32"]), min_size=1, max_size=12)


@given(WIDTHS, st.data())
def test_only_the_values_whose_bytes_differ_are_decoded(types: list[str], data: st.DataObject) -> None:
    from gateway.sparkplug.devices import Point, _changed_members, _runs

    points, address = [], 0
    for kind in types:
        points.append(Point(Table.HOLDING, address, kind, False, 0))
        address += points[-1].width
    (run,) = _runs(points)
    size = 2 * address
    before = data.draw(st.binary(min_size=size, max_size=size))
    after = bytearray(before)
    for i in data.draw(st.lists(st.integers(0, size - 1), max_size=4)):  # a few bytes changed, anywhere
        after[i] ^= data.draw(st.integers(1, 255))
    # a value changed when any of its bytes did (its registers, 2 bytes each, from its offset)
    expected = [(m, at) for m, at in run.members
                if before[at : at + 2 * points[m].width] != after[at : at + 2 * points[m].width]]
    assert _changed_members(run, before, bytes(after)) == expected


@given(st.integers(1, 40), st.data())
def test_only_the_bits_that_differ_are_reported(count: int, data: st.DataObject) -> None:
    from gateway.sparkplug.devices import Point, _changed_members, _runs

    (run,) = _runs([Point(Table.COIL, i, "bool", False, 0) for i in range(count)])
    size = (count + 7) // 8
    before = data.draw(st.binary(min_size=size, max_size=size))
    after = data.draw(st.binary(min_size=size, max_size=size))
    # bit k of the read is LSB first in byte k // 8; bits past count (padding) are no member's
    expected = [(m, at) for m, at in run.members if (before[at // 8] ^ after[at // 8]) >> (at % 8) & 1]
    assert _changed_members(run, before, after) == expected
